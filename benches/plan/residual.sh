#!/usr/bin/env bash
# Planning with and without the residual network: dm-synth scenes with a
# hidden plasticity, fitted with the residual (the tasks' short fit, the
# network kept when it earns its place), each goal planned physics only
# and with `--residual`, carried out in the truth world re-planning every
# 20 frames (docs/plan.md "With the residual network").
#   bash benches/plan/residual.sh OUT_DIR
set -euo pipefail
OUT=${1:?usage: residual.sh OUT_DIR}
BIN=${BIN:-target/release}
FIT="--iters 3 --stage2-iters 1 --gain-evals 4 --rgb-iters 0"
PLAN="--horizon 60 --knots 4 --replan-every 20 --replan-iterations 2 --no-video"
mkdir -p "$OUT"
for spec in rope-plastic:rope:32:u-shape toy-plastic:toy:32:squash; do
  IFS=: read -r name preset seed goal <<< "$spec"
  if [ ! -f "$OUT/$name/model/model.json" ]; then
    "$BIN/dm-synth" --preset "$preset" --seed "$seed" --effect plasticity \
      --out "$OUT/$name/scene" --truth "$OUT/$name/truth.json" > "$OUT/$name.synth.log" 2>&1
    "$BIN/dm-fit" "$OUT/$name/scene" --out "$OUT/$name/model" $FIT > "$OUT/$name.fit.log" 2>&1
  fi
  grep "residual network" "$OUT/$name.fit.log" || true
  for residual in off on; do
    dir="$OUT/$name-$goal-$residual"
    [ -f "$dir/plan.json" ] ||
      "$BIN/dm-plan" "$OUT/$name/model" --bundle "$OUT/$name/scene" --goal "$goal" \
        --plant "$OUT/$name/truth.json" --out "$dir" $PLAN $([ "$residual" = on ] && echo --residual) > "$dir.log" 2>&1
    python3 - "$dir/plan.json" "$name-$goal" "$residual" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
mm = lambda o, k: f"{1000 * o[k]:.1f}"
print(f"{sys.argv[2]} residual {sys.argv[3]}: planned symmetric {mm(d['planned'], 'final_symmetric_chamfer_m')} mm; "
      f"executed Chamfer / symmetric / Track {mm(d['executed'], 'final_chamfer_m')} / "
      f"{mm(d['executed'], 'final_symmetric_chamfer_m')} / {mm(d['executed'], 'final_track_m')} mm; {d['seconds']:.0f} s")
PY
  done
done
