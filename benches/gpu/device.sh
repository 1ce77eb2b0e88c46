#!/usr/bin/env bash
# gpu-check on a GPU machine without a Rust toolchain or OpenCV, from the
# pack `make gpu-bin` writes (docs/gpu.md, "Checks"):
#   bash benches/gpu/device.sh [PACK [WORK]]
# unpacks the tools into WORK/bin, makes the inputs the chosen parts need
# in WORK/inputs (each once: a later call with the same WORK reuses them),
# then runs benches/gpu/check.sh on them, writing to WORK/check. PARTS,
# CPU_REFERENCE, GRAPHS_AB, FIT_DEFAULTS and PLAN_SCALING are check.sh's.
set -euo pipefail
PACK=${1:-.devbin}
WORK=${2:-out/gpu-device}
[ -f "$PACK/bin.tar.xz" ] && [ -f "$PACK/inputs.sh" ] || {
    echo "error: $PACK holds no pack of make gpu-bin (bin.tar.xz, inputs.sh)" >&2
    exit 2
}
PARTS=" ${PARTS:-parity throughput sim fit defaults plan diagnose} "
export GPU_BIN=$WORK/bin GPU_INPUTS=$WORK/inputs
mkdir -p "$WORK" "$GPU_INPUTS"
tar -C "$WORK" -xJf "$PACK/bin.tar.xz"
# The commands of `make gpu-inputs` that write `name`'s inputs (their
# outputs' names say which), run unless an earlier call finished them.
make_inputs() {
    local name=$1 pattern=$2
    [ -f "$GPU_INPUTS/$name.complete" ] && return 0
    SECONDS=0
    grep -E "$pattern" "$PACK/inputs.sh" | while read -r line; do
        out=$(sed -E 's/.*--out ([^ ]+).*/\1/' <<<"$line")
        out=$(eval echo "$out")
        rm -rf "$out" "$out.truth.json"
        echo "+ $line"
        eval "$line"
    done
    echo "inputs ($name) made in $SECONDS s"
    touch "$GPU_INPUTS/$name.complete"
}
if [[ $PARTS == *" sim "* ]]; then make_inputs scene100k '(scene|model)100k'; fi
if [[ $PARTS =~ \ (fit|defaults|plan)\  ]]; then make_inputs scene '/scene( |$)'; fi
if [[ $PARTS == *" diagnose "* ]]; then make_inputs diag 'diag_(scene|model)'; fi
export PARTS
[ -f "$GPU_INPUTS/scene.complete" ] && export FIT_SCENE=$GPU_INPUTS/scene
if [ -f "$GPU_INPUTS/diag.complete" ]; then
    export DIAGNOSE_MODEL=$GPU_INPUTS/diag_model DIAGNOSE_SCENE=$GPU_INPUTS/diag_scene
fi
if [ -f "$GPU_INPUTS/scene100k.complete" ]; then
    exec bash benches/gpu/check.sh "$GPU_BIN" "$GPU_INPUTS/scene100k" "$GPU_INPUTS/model100k" "$WORK/check"
fi
exec bash benches/gpu/check.sh "$GPU_BIN" "" "" "$WORK/check"
