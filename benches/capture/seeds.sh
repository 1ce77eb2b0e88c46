#!/bin/bash
# Capture accuracy on fresh seeds: for each preset and each action, a
# dm-synth RGB-D capture (exact skin tracks as the reference), `dm-prep all`
# on it, and `dm-prep score` (docs/RESULTS.md "Capture → bundle").
#
#   bash benches/capture/seeds.sh OUT [FIRST_SEED]      # seeds FIRST_SEED+1 .. +12
set -euo pipefail
out=${1:?usage: seeds.sh OUT [FIRST_SEED]}
first=${2:-60000}
bin=${DM_BIN_DIR:-target/release}
i=0
for preset in rope cloth toy; do
  for action in lift push stretch twist; do
    i=$((i + 1))
    seed=$((first + i))
    dir=$out/$preset-$action-s$seed
    [ -f "$dir/capture/calibration.json" ] ||
      "$bin/dm-synth" --preset "$preset" --seed "$seed" --action "$action" --exact-tracks --tracks 3000 \
        --out "$dir/truth" --capture-out "$dir/capture" > /dev/null
    "$bin/dm-prep" all --capture "$dir/capture" --out "$dir/scene" --work "$dir/work" --overwrite > "$dir/prep.log" 2>&1
    echo "$preset $action $seed $("$bin/dm-prep" score "$dir/scene" --reference "$dir/truth" | tr '\n' ' ')"
  done
done
