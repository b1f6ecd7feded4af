#!/usr/bin/env bash
# The validation scenes, once, for the pair that the selection rule ships (ring-e1-real with `union`), at
# its extraction (E1: 8 levels, 2,000 keypoints), FREAK on the same keypoints:
#   1. the pair protocol on the five validation scenes and the validation warps (score.sh, SPLIT=validation);
#   2. real homographies: graffiti and the five EF sequences (SIFT beside);
#   3. relocalisation, far-map protocol with 100k distractors (SConE and FREAK; BENCHMARKS.md's relocalisation
#      figures, SIFT's included, are docs/results/relocalisation/validation/run.sh's).
#   docs/results/matching/validate.sh MODEL.onnx      (reports to $SCONE_PREFIX/work/i39/val-ring-e1-real)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
model=$1
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
out="$SCONE_PREFIX/work/i39/val-ring-e1-real"
mkdir -p "$out"
e1=(--levels 8 --max-keypoints 2000 --opencv-threads 1 --embed-threads 1)
part=${2:-all}
if [ "$part" = all ] || [ "$part" = pairs ]; then
  SPLIT=validation OUT="$out" "$here/docs/results/matching/score.sh" ring-e1-real "$model" union --levels 8 --max-keypoints 2000
  f="$out/real-h.json"
  [ -s "$f" ] || "$B" eval homography --data "$D/hpatches-v_graffiti,$D/ef-notredame,$D/ef-obama,$D/ef-paintedladies,$D/ef-rushmore,$D/ef-yosemite" \
    --methods scone,freak,sift --scone-matcher union --model "$model" "${e1[@]}" --json "$f" > "$out/real-h.md"
fi
if [ "$part" = all ] || [ "$part" = reloc ]; then
  for sc in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
    f="$out/far-$sc.json"
    [ -s "$f" ] || "$B" eval reloc --scene "$D/$sc" --methods scone,freak --map-block 0:0.5 --model "$model" \
      --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000 --distractor-stride 5 \
      --foreign "$D/strecha-castle-P30" --foreign-stride 3 "${e1[@]}" --json "$f" > "$out/far-$sc.md" 2> "$out/far-$sc.log"
  done
fi
echo "$out"
