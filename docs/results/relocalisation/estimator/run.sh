#!/usr/bin/env bash
# The PnP estimator's selection runs (RULE.md beside this file): far-map protocol, 100k distractor observations,
# every method, every candidate estimator on the same map, on four training scenes. Then score.py applies the rule.
# STAGES=candidates,build builds the maps with the keyframes' poses (../map-building/).
#   docs/results/relocalisation/estimator/run.sh     (reports to $OUT, default $SCONE_PREFIX/work/reloc-estimator)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="${OUT:-$SCONE_PREFIX/work/reloc-estimator}"
mkdir -p "$out"
# Each report's own rows are EPnP's (the default the rule compared against; score.py reads them as epnp:2000).
candidates=${CANDIDATES:-p3p:2000,usac:2000,usac-prosac:2000,usac-magsac:2000,usac-prosac-magsac:2000}
for sc in ${SCENES:-llff-ethiopianhead llff-blowtorch llff-lemontea-office turntable-squirrel}; do
  foreign=$D/strecha-castle-P30
  f="$out/far--$sc.json"
  [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --map-block 0:0.5 --methods scone,freak,sift \
    --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000 --distractor-stride 5 \
    --foreign "$foreign" --foreign-stride 3 --opencv-threads 1 --embed-threads 1 --stages "${STAGES:-candidates}" --pnp epnp --also-pnp "$candidates" \
    --json "$f" > "$out/far--$sc.md" 2> "$out/far--$sc.log" || echo "FAILED far $sc"
done
echo "$out"
