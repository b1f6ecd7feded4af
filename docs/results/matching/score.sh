#!/usr/bin/env bash
# Scores one model on the selection split (or, with SPLIT=validation, the validation scenes once):
# the pair protocol on each part (3 seeds) and the exact warps, for SConE with the given matchers and for FREAK
# on the same keypoints. Reports go to $OUT (default $SCONE_PREFIX/work/i39/<name>).
#   docs/results/matching/score.sh NAME MODEL.onnx "plain union" [extractor flags...]
# Selection parts: python -m scone_train.data.splits [--scenes nine] --out $SCONE_PREFIX/work/sel (written once).
# Warps: python -m scone_train.data.warps --role selection --per-scene 4 --out $SCONE_PREFIX/work/warps/selection-g2
#        (validation: --role validation --out .../validation-g2, generated once before any candidate was scored).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
name=$1; model=$2; matchers=$3; shift 3
B="$CARGO_TARGET_DIR/release/scone"
out="${OUT:-$SCONE_PREFIX/work/i39/$name}"
mkdir -p "$out"
threads=(--opencv-threads 1 --embed-threads 1)
if [ "${SPLIT:-selection}" = validation ]; then
  D=${SCONE_DATA:-$here/../shared/data}/scenes
  parts="$D/strecha-fountain-P11:10 $D/kitti-clip2:10 $D/rgbd-slambook-5:5 $D/tum-fr3-long-office:30 $D/middlebury-dino48:10"
  warps="$SCONE_PREFIX/work/warps/validation-g2"
else
  S=$SCONE_PREFIX/work/sel
  parts="$S/strecha-castle-P30-sel:10 $S/7scenes-redkitchen-sel:20 $S/sun3d-studyroom-sel:20 $S/middlebury-templeRing-sel:10 $S/liberty-internet-sel:27"
  # ORBITS=1: the four orbits' selection arcs too (python -m scone_train.data.splits --scenes nine --out $S).
  if [ "${ORBITS:-0}" = 1 ]; then
    parts="$parts $S/llff-ethiopianhead-sel:13 $S/llff-blowtorch-sel:16 $S/llff-lemontea-office-sel:13 $S/turntable-squirrel-sel:8"
  fi
  warps="$SCONE_PREFIX/work/warps/selection-g2"
fi
for m in $matchers; do
  for p in $parts; do
    dir=${p%:*}; w=${p##*:}; f="$out/pairs-$m-$(basename "$dir").json"
    [ -s "$f" ] && continue
    "$B" eval pairs --scene "$dir" --window "$w" --seeds 3 --methods scone,freak --scone-matcher "$m" \
      --model "$model" --json "$f" "${threads[@]}" "$@" > /dev/null
  done
  f="$out/warps-$m.json"
  [ -s "$f" ] || "$B" eval homography --data "$warps" --methods scone,freak --scone-matcher "$m" --model "$model" \
    --json "$f" "${threads[@]}" "$@" > "$out/warps-$m.md"
done
echo "$out"
