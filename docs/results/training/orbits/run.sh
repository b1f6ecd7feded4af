#!/usr/bin/env bash
# Relocalisation on the four orbits' selection arcs (RULE.md beside this file): far-map protocol inside each arc,
# 100k distractor observations, castle's every 3rd frame as foreign frames, the service's estimator; SConE with
# the model given beside FREAK and SIFT. Reports to $OUT (default $SCONE_PREFIX/work/orbits/reloc-NAME, where
# score.py reads them; METHODS=scone leaves out FREAK and SIFT, which do not depend on the model).
#   docs/results/training/orbits/run.sh NAME MODEL.onnx
# The arcs: python -m scone_train.data.splits --scenes nine --out $SCONE_PREFIX/work/sel (from training/).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
name=$1; model=$2
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
S=$SCONE_PREFIX/work/sel
out="${OUT:-$SCONE_PREFIX/work/orbits/reloc-$name}"
mkdir -p "$out"
# SCENES: other scene directories under the same protocol (default: the four arcs).
for dir in ${SCENES:-$S/llff-ethiopianhead-sel $S/llff-blowtorch-sel $S/llff-lemontea-office-sel $S/turntable-squirrel-sel}; do
  arc=$(basename "$dir")
  f="$out/far--$arc.json"
  [ -s "$f" ] || "$B" eval reloc --scene "$dir" --map-block 0:0.5 --methods "${METHODS:-scone,freak,sift}" \
    --model "$model" --distractors "$D/7scenes-redkitchen,$D/sun3d-studyroom" --distractor-observations 100000 \
    --distractor-stride 5 --foreign "$D/strecha-castle-P30" --foreign-stride 3 --opencv-threads 1 --embed-threads 1 \
    --json "$f" > "$out/far--$arc.md" 2> "$out/far--$arc.log" || echo "FAILED $arc"
done
echo "$out"
