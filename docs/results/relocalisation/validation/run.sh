#!/usr/bin/env bash
# The validation scenes once with the stages the selection rule chose (BENCHMARKS.md, "Relocalisation on the
# validation scenes"), every method (SConE, FREAK on the same keypoints, SIFT):
# far-map protocol (map: the first half of the posed frames; 100k distractor observations of the two distractor
# scenes; castle as the foreign scene) and the sparse protocol (every 10th frame, scenes of at least 30 frames).
# Each query's diagnosis is in the reports and its matches under $OUT/matches (../diagnosis/ reads them).
#   STAGES=candidates docs/results/relocalisation/validation/run.sh   (reports to $OUT, default $SCONE_PREFIX/work/reloc-val)
# Extra flags for every run (the estimator the selection chose, say) go in $EXTRA; $SCENES and $SPARSE_SCENES
# narrow the scenes (two shells can share the scenes between both cores).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="${OUT:-$SCONE_PREFIX/work/reloc-val}"
mkdir -p "$out"
stages=(--stages "${STAGES:?the configuration the rule chose, e.g. candidates}")
read -r -a extra <<< "${EXTRA:-}"
methods="scone,freak,sift"
common=(--methods "$methods" --foreign "$D/strecha-castle-P30" --foreign-stride 3 --opencv-threads 1
  --embed-threads 1 "${stages[@]}" "${extra[@]}")
for sc in ${SCENES-llff-goldcape kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office}; do
  f="$out/far--$sc.json"
  [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --map-block 0:0.5 --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" \
    --distractor-observations 100000 --distractor-stride 5 "${common[@]}" --dump-matches "$out/matches/$sc" \
    --json "$f" > "$out/far--$sc.md" \
    2> "$out/far--$sc.log" || echo "FAILED far $sc"
done
for sc in ${SPARSE_SCENES-llff-goldcape kitti-clip2 middlebury-dino48 tum-fr3-long-office}; do
  f="$out/sparse--$sc.json"
  [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --map-stride 10 "${common[@]}" --json "$f" > "$out/sparse--$sc.md" \
    2> "$out/sparse--$sc.log" || echo "FAILED sparse $sc"
done
echo "$out"
