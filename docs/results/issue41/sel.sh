#!/usr/bin/env bash
# Issue 41, section 3: the rule for stage 1's searches (BENCHMARKS.md, "A query whose cost does not grow with
# the map"). SConE, far-map protocol (map = first half of the posed frames), 100k distractor observations from
# two other training scenes, a foreign scene; every query keypoint searched against a cap K on stage 1.
#   docs/results/issue41/sel.sh          (reports to $OUT, default $SCONE_PREFIX/work/i41/sel)
# Needs the selection parts (python -m scone_train.splits --out $SCONE_PREFIX/work/sel) and templeRing
# stamps 1-31 as a scene directory ($SCONE_PREFIX/work/cal/templeRing-1-31: rgb.txt listing those stamps,
# camera.txt and groundtruth.txt copied).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
S=$SCONE_PREFIX/work/sel
out="${OUT:-$SCONE_PREFIX/work/i41/sel}"
mkdir -p "$out"
# ALSO_CAPS=K1,K2,...: every keypoint and each cap on the same map, one report per scene (session 45's rule).
caps=${CAPS:-all 800 400}; [ -n "${ALSO_CAPS:-}" ] && caps=all
for cap in $caps; do
  for sc in "$D/strecha-castle-P30" "$SCONE_PREFIX/work/cal/templeRing-1-31" "$S/7scenes-redkitchen-sel" \
    "$S/sun3d-studyroom-sel" "$S/liberty-internet-sel"; do
    name=$(basename "$sc")
    # The foreign scene is never one of the distractor scenes (its frames would localise against them).
    foreign=$S/strecha-castle-P30-sel; distractors=$D/7scenes-redkitchen,$D/sun3d-studyroom
    case $name in
      strecha-castle-P30) foreign=$S/liberty-internet-sel ;;
      7scenes-redkitchen-sel) distractors=$D/liberty-internet,$D/sun3d-studyroom ;;
      sun3d-studyroom-sel) distractors=$D/liberty-internet,$D/7scenes-redkitchen ;;
    esac
    extra=(); tag=$cap
    [ "$cap" = all ] || extra=(--max-query-keypoints "$cap")
    # FALLBACK=T: a capped query short of T inliers is searched with every keypoint (session 43's rule).
    if [ -n "${FALLBACK:-}" ] && [ "$cap" != all ]; then extra+=(--full-search-below-inliers "$FALLBACK"); tag=$cap-fallback$FALLBACK; fi
    if [ -n "${ALSO_CAPS:-}" ]; then
      extra=(--also-caps "$ALSO_CAPS"); tag=same-graph
      [ -n "${FALLBACK:-}" ] && { extra+=(--full-search-below-inliers "$FALLBACK"); tag=same-graph-fallback$FALLBACK; }
    fi
    f="$out/$tag--$name.json"
    [ -s "$f" ] || "$B" eval reloc --scene "$sc" --methods scone --map-block 0:0.5 --distractors "$distractors" \
      --distractor-observations 100000 --distractor-stride 5 --foreign "$foreign" --foreign-stride 2 \
      --opencv-threads 1 --embed-threads 1 "${extra[@]}" --json "$f" > "$out/$tag--$name.md" 2> "$out/$tag--$name.log" \
      || echo "FAILED $tag $name"
  done
done
echo "$out"
