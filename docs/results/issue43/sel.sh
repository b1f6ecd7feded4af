#!/usr/bin/env bash
# Issue 43: the selection scenes (issue 27's five, far-map protocol, map = first half of the posed frames, a
# foreign scene), SConE one frame against SConE with 3-frame tracks: success and how often the 95 % ellipsoid
# holds the truth. A check of the track estimator and its covariance on scenes that are not validation scenes.
#   docs/results/issue43/sel.sh     (reports to $OUT, default $SCONE_PREFIX/work/i43/sel)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
S=$SCONE_PREFIX/work/sel
out="${OUT:-$SCONE_PREFIX/work/i43/sel}"
mkdir -p "$out"
for sc in "$D/strecha-castle-P30" "$SCONE_PREFIX/work/cal/templeRing-1-31" "$S/7scenes-redkitchen-sel" \
  "$S/sun3d-studyroom-sel" "$S/liberty-internet-sel"; do
  name=$(basename "$sc")
  foreign=$S/7scenes-redkitchen-sel
  [ "$name" = 7scenes-redkitchen-sel ] && foreign=$S/strecha-castle-P30-sel
  for run in single track3; do
    extra=(); [ "$run" = track3 ] && extra=(--track 3)
    f="$out/$name-$run.json"
    [ -s "$f" ] || "$B" eval reloc --scene "$sc" --methods scone --map-block 0:0.5 --foreign "$foreign" \
      --foreign-stride 2 --opencv-threads 1 --embed-threads 1 "${extra[@]}" --json "$f" > "$out/$name-$run.md" 2> "$out/$name-$run.log"
  done
done
echo "$out"
