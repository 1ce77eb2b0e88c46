#!/usr/bin/env bash
# Gradient refinement alone against MPPI alone on the planning tasks of
# tasks.sh (run it first): the same first plan, open loop, 66 gradient
# steps (67 rollouts, a third of MPPI's 201); benches/plan/compare.py
# reads both.
#   bash benches/plan/gradient.sh OUT_DIR
set -euo pipefail
OUT=${1:?usage: gradient.sh OUT_DIR}
BIN=${BIN:-target/release}
TASKS="rope-null:u-shape rope-bent:straighten:70 rope-drag:move cloth-null:fold cloth-null:flatten cloth-tilt:move toy-null:place toy-null:squash toy-friction:rotate"
for spec in $TASKS; do
  IFS=: read -r name goal start <<< "$spec"
  dir="$OUT/tasks/$name-$goal/gradient"
  [ -f "$dir/plan.json" ] && continue
  mkdir -p "$(dirname "$dir")"
  "$BIN/dm-plan" "$OUT/$name/model" --bundle "$OUT/$name/scene" --goal "$goal" \
    --plant "$OUT/$name/truth.json" --out "$dir" ${start:+--start-frame $start} --horizon 60 --knots 4 --no-video \
    --optimizer gradient --gradient-iters 66 > "$dir.log" 2>&1 || echo "failed: see $dir.log"
done
python3 "$(dirname "$0")/compare.py" "$OUT/tasks"
