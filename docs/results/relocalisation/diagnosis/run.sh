#!/usr/bin/env bash
# Where each far query is lost: the validation scenes' far-map protocol (map: the first half of the posed
# frames; 100k distractor observations of two training scenes; castle as the foreign scene) with the shipped
# pipeline, every method (SConE, FREAK on the same keypoints, SIFT), each query's diagnosis in the report and its
# matches written for pictures. Then table.py prints, per query that SIFT places and SConE does not, the stage
# that lost it.
#   docs/results/relocalisation/diagnosis/run.sh      (reports to $OUT, default $SCONE_PREFIX/work/reloc-diagnosis)
# Extra flags for every run (an estimator, say) go in $EXTRA.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="${OUT:-$SCONE_PREFIX/work/reloc-diagnosis}"
mkdir -p "$out"
read -r -a extra <<< "${EXTRA:-}"
for sc in ${SCENES:-llff-goldcape kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office}; do
  f="$out/far--$sc.json"
  [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --map-block 0:0.5 --methods scone,freak,sift \
    --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000 --distractor-stride 5 \
    --foreign "$D/strecha-castle-P30" --foreign-stride 3 --opencv-threads 1 --embed-threads 1 \
    --dump-matches "$out/matches/$sc" "${extra[@]}" --json "$f" > "$out/far--$sc.md" 2> "$out/far--$sc.log" \
    || echo "FAILED far $sc"
done
echo "$out"
