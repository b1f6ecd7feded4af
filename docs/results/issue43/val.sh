#!/usr/bin/env bash
# Issue 43: the validation scenes once, far-map protocol (map: the first half of the posed frames; 100k
# distractor observations of the two distractor scenes; a foreign scene), with the shipped model and defaults:
# SConE and SIFT single frames, then SConE with 3-frame tracks (tracker error 1 % of the distance and 0.5 degrees
# per frame, seeded). Nothing was tuned for it: the track estimator's constants are those of src/pose/track.rs.
#   docs/results/issue43/val.sh            (reports to $OUT, default $SCONE_PREFIX/work/i43/val)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="${OUT:-$SCONE_PREFIX/work/i43/val}"
mkdir -p "$out"
common=(--map-block 0:0.5 --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000
  --distractor-stride 5 --foreign-stride 3 --opencv-threads 1 --embed-threads 1)
for sc in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
  for run in single track3; do
    methods=scone,sift; extra=()
    [ "$run" = track3 ] && methods=scone && extra=(--track 3)
    f="$out/$sc-$run.json"
    [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --methods "$methods" --foreign "$D/strecha-castle-P30" \
      "${common[@]}" "${extra[@]}" --json "$f" > "$out/$sc-$run.md" 2> "$out/$sc-$run.log"
  done
done
echo "$out"
