#!/usr/bin/env bash
# The validation scenes once with stage 1's cap on query keypoints (BENCHMARKS.md, "Relocalisation on the
# validation scenes"): the far-map protocol (SConE, 100k distractor observations, a foreign scene), every query
# keypoint searched against stage 1 capped (CAPS, default 800; ALSO_CAPS compares caps on one graph).
#   docs/results/relocalisation/query-keypoint-cap/run.sh          (reports to $OUT, default $SCONE_PREFIX/work/i41/val)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="${OUT:-$SCONE_PREFIX/work/i41/val}"
mkdir -p "$out"
for scene in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
  # ALSO_CAPS=K1,K2,...: every keypoint and each cap on the same map, one report per scene (the rule same_graph.py applies).
  caps=${CAPS:-all 800}; [ -n "${ALSO_CAPS:-}" ] && caps=all
  for cap in $caps; do
    k=$cap; [ "$cap" = all ] && k=1000000000
    extra=(); tag=$cap
    # FALLBACK=T: a capped query short of T inliers is searched with every keypoint (the default's fallback).
    if [ -n "${FALLBACK:-}" ] && [ "$cap" != all ]; then extra=(--full-search-below-inliers "$FALLBACK"); tag=$cap-fallback$FALLBACK; fi
    if [ -n "${ALSO_CAPS:-}" ]; then
      extra=(--also-caps "$ALSO_CAPS"); tag=same-graph
      [ -n "${FALLBACK:-}" ] && { extra+=(--full-search-below-inliers "$FALLBACK"); tag=same-graph-fallback$FALLBACK; }
    fi
    f="$out/$tag--$scene.json"
    [ -s "$f" ] || "$B" eval reloc --scene "$D/$scene" --map-block 0:0.5 --methods scone \
      --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000 --distractor-stride 5 \
      --foreign "$D/strecha-castle-P30" --foreign-stride 3 --max-query-keypoints "$k" "${extra[@]}" \
      --opencv-threads 1 --embed-threads 1 --json "$f" > "$out/$tag--$scene.md" 2> "$out/$tag--$scene.log" \
      || echo "FAILED $tag $scene"
  done
done
echo "$out"
