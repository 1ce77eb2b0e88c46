#!/usr/bin/env bash
# GPU checks of the CUDA world (docs/gpu.md), run from prebuilt binaries:
#   bash benches/gpu/check.sh [BIN_DIR]
# 1. parity against the CPU world (f64 and f32, two scenes);
# 2. substep throughput, 1e5 particles on a 32³ grid and 1e6 on 128³,
#    Neo-Hookean and the expert mixture, with the CPU figure beside it.
# Every step runs even when an earlier one fails; the exit status is the
# first failure's.
set -u
BIN=${1:-target/release}
status=0
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
run "$BIN/dm-bench" cuda-parity --particles 20000 --frames 10
for setup in "100000 32" "1000000 128"; do
    set -- $setup
    for experts in nh moce; do
        run "$BIN/dm-bench" mpm --device cuda --particles "$1" --grid "$2" --experts "$experts" --substeps 400 --repeats 5
    done
done
run "$BIN/dm-bench" mpm --particles 100000 --grid 32 --experts nh --substeps 100
exit $status
