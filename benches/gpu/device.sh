#!/usr/bin/env bash
# gpu-check on a GPU machine without a Rust toolchain or OpenCV, from the
# pack `make gpu-bin` writes (docs/gpu.md, "Checks"):
#   bash benches/gpu/device.sh [PACK [WORK]]
# unpacks the tools into WORK/bin, makes gpu-check's inputs with them in
# WORK/inputs (once: a later call with the same WORK reuses them), then
# runs benches/gpu/check.sh on them, writing to WORK/check. PARTS,
# CPU_REFERENCE, GRAPHS_AB and FIT_DEFAULTS are check.sh's.
set -euo pipefail
PACK=${1:-.devbin}
WORK=${2:-out/gpu-device}
[ -f "$PACK/bin.tar.xz" ] && [ -f "$PACK/inputs.sh" ] || {
    echo "error: $PACK holds no pack of make gpu-bin (bin.tar.xz, inputs.sh)" >&2
    exit 2
}
export GPU_BIN=$WORK/bin GPU_INPUTS=$WORK/inputs
mkdir -p "$WORK"
tar -C "$WORK" -xJf "$PACK/bin.tar.xz"
if [ ! -f "$GPU_INPUTS/complete" ]; then
    rm -rf "$GPU_INPUTS" && mkdir -p "$GPU_INPUTS"
    SECONDS=0
    bash -ex "$PACK/inputs.sh"
    echo "inputs made in $SECONDS s"
    touch "$GPU_INPUTS/complete"
fi
export FIT_SCENE=$GPU_INPUTS/scene
export DIAGNOSE_MODEL=$GPU_INPUTS/diag_model DIAGNOSE_SCENE=$GPU_INPUTS/diag_scene
exec bash benches/gpu/check.sh "$GPU_BIN" "$GPU_INPUTS/scene100k" "$GPU_INPUTS/model100k" "$WORK/check"
