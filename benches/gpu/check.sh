#!/usr/bin/env bash
# GPU checks of the CUDA world (docs/gpu.md), run from prebuilt binaries:
#   bash benches/gpu/check.sh [BIN_DIR [SCENE MODEL_DIR [OUT]]]
# 1. parity against the CPU world (f64 and f32, two scenes): positions
#    after frames, and every group of one substep's adjoint; the residual
#    network (both kinds) against the CPU's: Δv and every gradient;
# 2. substep throughput, 1e5 particles on a 32³ grid and 1e6 on 128³,
#    Neo-Hookean and the expert mixture, with the CPU figure beside it;
#    one truncated window (20 substeps, forward and backward) at 1e5
#    particles, with its gradients against the CPU's; one frame of the
#    residual network (forward and VJP, 8 000 particles) on both; the
#    splat renderer on the host's cores;
# 3. with a scene and a fitted model: dm-sim's rollout on the CPU and on
#    the GPU (times and largest position difference), the playground's
#    frame with all the model's particles at its substeps on both, and
#    dm-eval's metrics of the rollout on both;
# 4. with FIT_SCENE set (the demo's scene): the demo's fit on the GPU and
#    on the CPU, their times and results; then, with the scene's truth file
#    beside it (FIT_SCENE.truth.json), a 120-frame plan (dm-plan's
#    defaults, goal place, carried out in the truth world) with the
#    GPU-fitted model on both devices; with FIT_DEFAULTS=1 also dm-fit's
#    defaults (the pgnd residual included) on the GPU;
# 5. with DIAGNOSE_MODEL and DIAGNOSE_SCENE set (the demo's diag_model and
#    diag_scene): dm-diagnose on both devices, its time and named cause.
# PARTS picks some of them (default every one): a space-separated subset
# of `parity throughput sim fit defaults plan diagnose`; PLAN_MODEL is the
# model the plan uses (default the GPU fit of part `fit`). CPU_REFERENCE=0
# leaves out the runs on the host's cores beside the GPU's; GRAPHS_AB=1
# also runs the demo's fit and the plan with DM_CUDA_GRAPHS=off (every
# substep launched kernel by kernel); PLAN_SCALING=1 adds MPPI alone with
# 2 and with 20 samples side by side (10 iterations each).
# Every step runs even when an earlier one fails; the exit status is the
# first failure's.
set -u
BIN=${1:-target/release}
SCENE=${2:-}
MODEL=${3:-}
OUT_DIR=${4:-out/gpu-check}
status=0
ALL_PARTS="parity throughput sim fit defaults plan diagnose"
PARTS=" ${PARTS:-$ALL_PARTS} "
for name in $PARTS; do
    [[ " $ALL_PARTS " == *" $name "* ]] || { echo "error: PARTS: unknown part '$name' (parts: $ALL_PARTS)" >&2; exit 2; }
done
part() { [[ $PARTS == *" $1 "* ]]; }
if [ "${CPU_REFERENCE:-1}" = 0 ]; then CPU_DEVICE=""; else CPU_DEVICE=cpu; fi
# The GPU runs, then (GRAPHS_AB=1) the same without graphs, then the CPU's.
GPU_VARIANTS="cuda"
[ "${GRAPHS_AB:-0}" = 1 ] && GPU_VARIANTS="cuda cuda-nographs"
variant_env() { [ "$1" = cuda-nographs ] && echo DM_CUDA_GRAPHS=off || echo "DM_CUDA_GRAPHS=${DM_CUDA_GRAPHS:-on}"; }
variant_device() { [ "$1" = cpu ] && echo cpu || echo cuda; }
run() {
    echo "\$ $*"
    "$@" || { rc=$?; echo "FAILED ($rc): $*"; [ $status -ne 0 ] || status=$rc; }
}
# NVRTC of the CUDA toolkit, or of a PyPI nvidia-cuda-nvrtc.
if [ -z "${DM_NVRTC_DIR:-}" ]; then
    for candidate in /usr/local/cuda/lib64 /usr/local/cuda/targets/x86_64-linux/lib \
        $(python3 -c 'import nvidia, os; print(os.path.join(nvidia.__path__[0], "cu13", "lib"))' 2>/dev/null); do
        if [ -e "$candidate/libnvrtc.so.13" ]; then DM_NVRTC_DIR=$candidate; break; fi
    done
fi
if [ -n "${DM_NVRTC_DIR:-}" ]; then
    export LD_LIBRARY_PATH=$DM_NVRTC_DIR${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
fi
echo "NVRTC from ${DM_NVRTC_DIR:-the library path}"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
part parity && run "$BIN/dm-bench" cuda-parity --particles 20000 --frames 10
if part throughput; then
    for setup in "100000 32" "1000000 128"; do
        set -- $setup
        for experts in nh moce; do
            run "$BIN/dm-bench" mpm --device cuda --particles "$1" --grid "$2" --experts "$experts" --substeps 400 --repeats 5
        done
    done
    run "$BIN/dm-bench" grad --device cuda --particles 100000 --window 20 --grid 32 --repeats 5
    [ -n "$CPU_DEVICE" ] && run "$BIN/dm-bench" mpm --particles 100000 --grid 32 --experts nh --substeps 100
    for device in cuda $CPU_DEVICE; do
        run "$BIN/dm-bench" residual --device "$device" --particles 8000 --repeats 9
    done
    # Stage 3's splats stay on the CPU: the renderer on the host's cores.
    run "$BIN/dm-bench" render --gaussians 50000 --width 640 --height 480
fi
if part sim && [ -n "$SCENE" ] && [ -n "$MODEL" ]; then
    mkdir -p "$OUT_DIR"
    for device in $CPU_DEVICE cuda; do
        run "$BIN/dm-sim" "$SCENE" --model-dir "$MODEL" --out "$OUT_DIR/sim-$device" --device "$device"
        python3 -c "import json,sys; s=json.load(open(sys.argv[1])); print('dm-sim $device: %d frames, %d particles, %.2f s, held-out track %.2f mm' % (s['frames'], s['particles'], s['seconds'], 1e3*s['track_error_m']['test']))" "$OUT_DIR/sim-$device/summary.json"
    done
    [ -n "$CPU_DEVICE" ] && python3 -c "import numpy as np,sys; a=np.load(sys.argv[1]); b=np.load(sys.argv[2]); d=np.abs(a-b).max(axis=(1,2)); print('rollout cpu vs cuda: largest position difference %.3e m (frame 1: %.3e m, last: %.3e m)' % (d.max(), d[1], d[-1]))" "$OUT_DIR/sim-cpu/rollout.npy" "$OUT_DIR/sim-cuda/rollout.npy"
    for device in cuda $CPU_DEVICE; do
        run "$BIN/dm-bench" play --model "$MODEL" --exact --device "$device" --frames 40
    done
    # The metrics of the same rollout (LPIPS left out: its network is not carried).
    for device in $CPU_DEVICE cuda; do
        run "$BIN/dm-eval" "$MODEL" "$SCENE" --out "$OUT_DIR/eval-$device" --skip-lpips --lpips-dir "$OUT_DIR/no-lpips" --device "$device"
        python3 -c "import json,sys; m=json.load(open(sys.argv[1])); print('dm-eval $device: %.2f s, held-out track %.2f mm, chamfer %.2f mm' % (m['run']['rollout_and_metrics_seconds'], 1e3*m['test']['track'], 1e3*m['test']['chamfer']))" "$OUT_DIR/eval-$device/metrics.json"
    done
fi
if [ -n "${FIT_SCENE:-}" ]; then
    mkdir -p "$OUT_DIR"
    # One line per fit: its time, where the time went, and the result.
    FIT_SUMMARY='import json,sys; r=json.load(open(sys.argv[2])); print("%s: %.1f s (%s; material steps by phase: %s), E %.4g Pa, final loss %.5g, residual %s" % (sys.argv[1], r["seconds"], ", ".join("%s %.1f" % kv for kv in r.get("seconds_by_stage", {}).items()), ", ".join("%s %.1f" % kv for kv in r.get("seconds_by_phase", {}).items()), r["material"]["E_median_pa"], r["loss"]["final"], r["residual"]["kind"]))'
    if part fit; then
        for variant in $GPU_VARIANTS $CPU_DEVICE; do
            run env "$(variant_env "$variant")" "$BIN/dm-fit" "$FIT_SCENE" --out "$OUT_DIR/fit-$variant" --iters 3 --stage2-iters 1 --gain-evals 4 --residual none --rgb-iters 1 --device "$(variant_device "$variant")"
            python3 -c "$FIT_SUMMARY" "dm-fit $variant" "$OUT_DIR/fit-$variant/fit_report.json"
        done
    fi
    if part defaults && [ "${FIT_DEFAULTS:-0}" = 1 ]; then
        started=$(date +%s.%N)
        run "$BIN/dm-fit" "$FIT_SCENE" --out "$OUT_DIR/fit-defaults-cuda" --device cuda
        echo "dm-fit defaults cuda: the whole command took $(python3 -c "import sys; print('%.1f' % (float(sys.argv[2]) - float(sys.argv[1])))" "$started" "$(date +%s.%N)") s"
        python3 -c "$FIT_SUMMARY" "dm-fit defaults cuda" "$OUT_DIR/fit-defaults-cuda/fit_report.json"
    fi
    PLAN_SUMMARY='import json,sys; r=json.load(open(sys.argv[1])); st=r["seconds_by_stage"]; print("%s: %.1f s (MPPI %.1f, gradient %.1f, execute %.1f), %d rollouts, Chamfer start %.1f, planned %.1f, executed %.1f mm" % (sys.argv[2], r["seconds"], st["mppi"], st["gradient"], st["execute"], r["rollouts"], 1e3*r["start"]["final_chamfer_m"], 1e3*r["planned"]["final_chamfer_m"], 1e3*r["executed"]["final_chamfer_m"]))'
    if part plan && [ -e "$FIT_SCENE.truth.json" ]; then
        for variant in $GPU_VARIANTS $CPU_DEVICE; do
            run env "$(variant_env "$variant")" "$BIN/dm-plan" "${PLAN_MODEL:-$OUT_DIR/fit-cuda}" --bundle "$FIT_SCENE" --goal place \
                --plant "$FIT_SCENE.truth.json" --no-video --device "$(variant_device "$variant")" --out "$OUT_DIR/plan-$variant"
            python3 -c "$PLAN_SUMMARY" "$OUT_DIR/plan-$variant/plan.json" "dm-plan $variant"
        done
        if [ "${PLAN_SCALING:-0}" = 1 ]; then
            # MPPI alone, 2 and 20 samples side by side over 10 iterations:
            # per rollout, how far the samples' streams overlap on the GPU.
            for samples in 2 20; do
                iterations=10
                run "$BIN/dm-plan" "${PLAN_MODEL:-$OUT_DIR/fit-cuda}" --bundle "$FIT_SCENE" --goal place \
                    --samples "$samples" --iterations "$iterations" --gradient-iters 0 --no-video --device cuda \
                    --out "$OUT_DIR/plan-mppi-$samples"
                python3 -c "$PLAN_SUMMARY" "$OUT_DIR/plan-mppi-$samples/plan.json" "dm-plan MPPI $samples x $iterations"
            done
        fi
    fi
fi
if part diagnose && [ -n "${DIAGNOSE_MODEL:-}" ] && [ -n "${DIAGNOSE_SCENE:-}" ]; then
    mkdir -p "$OUT_DIR"
    for device in cuda $CPU_DEVICE; do
        SECONDS=0
        run "$BIN/dm-diagnose" "$DIAGNOSE_MODEL" "$DIAGNOSE_SCENE" --out "$OUT_DIR/diagnose-$device" --device "$device"
        python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print('dm-diagnose $device: %.1f s, cause %s (confidence %.2f)' % (float(sys.argv[2]), d['cause'], d['confidence']))" "$OUT_DIR/diagnose-$device/diagnosis.json" "$SECONDS"
    done
fi
exit $status
