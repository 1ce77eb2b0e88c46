#!/usr/bin/env bash
# The planning tasks of docs/plan.md: three goals per preset on dm-synth
# scenes with and without a hidden effect, each planned with the fitted
# model and with the untrained one, carried out in the scene's truth world
# with re-planning; then a table (benches/plan/table.py).
#   bash benches/plan/tasks.sh OUT_DIR [EXTRA dm-plan ARGS...]
# ENGINE=mujoco makes the scenes foreign-physics ones (MuJoCo is then the
# plant too); SCENES and TASKS replace the lists below.
set -euo pipefail
OUT=${1:?usage: tasks.sh OUT_DIR [dm-plan args]}
shift
BIN=${BIN:-target/release}
FIT="--iters 3 --stage2-iters 1 --gain-evals 4 --residual none --rgb-iters 0"
PLAN="--horizon 60 --knots 4 --replan-every 20 --replan-iterations 2 --no-video $*"
mkdir -p "$OUT"
# scene: preset seed effect [action]; rope-bent is pushed on a rough floor,
# which keeps it bent once let go (an elastic rope on the default floor
# springs back straight).
SCENES=${SCENES:-"rope-null:rope:31: rope-bent:rope:31:floor_friction:0.8:push rope-drag:rope:32:air_drag cloth-null:cloth:31: cloth-tilt:cloth:32:ground_tilt toy-null:toy:31: toy-friction:toy:32:floor_friction"}
for spec in $SCENES; do
  IFS=: read -r name preset seed effect magnitude action <<< "$spec"
  if [ ! -f "$OUT/$name/model/model.json" ]; then
    "$BIN/dm-synth" ${ENGINE:+--engine $ENGINE} --preset "$preset" --seed "$seed" ${effect:+--effect $effect${magnitude:+:$magnitude}} ${action:+--action $action} \
      --out "$OUT/$name/scene" --truth "$OUT/$name/truth.json" > "$OUT/$name.synth.log" 2>&1
    "$BIN/dm-fit" "$OUT/$name/scene" --out "$OUT/$name/model" $FIT > "$OUT/$name.fit.log" 2>&1
  fi
done
# task: scene goal [start frame]; the bent rope is straightened from where
# its clip leaves it (frame 70, let go, settled).
TASKS=${TASKS:-"rope-null:u-shape rope-bent:straighten:70 rope-drag:move cloth-null:fold cloth-null:flatten cloth-tilt:move toy-null:place toy-null:squash toy-friction:rotate"}
for spec in $TASKS; do
  IFS=: read -r name goal start <<< "$spec"
  for model in fitted untrained; do
    dir="$OUT/tasks/$name-$goal/$model"
    [ -f "$dir/plan.json" ] && continue
    mkdir -p "$(dirname "$dir")"
    "$BIN/dm-plan" "$OUT/$name/model" --bundle "$OUT/$name/scene" --goal "$goal" \
      --plant "$OUT/$name/truth.json" --out "$dir" ${start:+--start-frame $start} $PLAN $([ "$model" = untrained ] && echo --untrained) \
      > "$dir.log" 2>&1 || { mkdir -p "$dir"; echo "failed: see $dir.log"; }
  done
done
python3 "$(dirname "$0")/table.py" "$OUT/tasks"
