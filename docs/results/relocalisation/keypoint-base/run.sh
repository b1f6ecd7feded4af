#!/usr/bin/env bash
# The detector x descriptor decomposition (README.md beside this file): FREAK, SIFT, DoG+FREAK (SIFT's keypoints,
# FREAK's descriptor) and FAST+SIFT (FREAK's keypoints, SIFT's descriptor) under the far-map protocol, every query
# diagnosed, on the four selection arcs (docs/results/training/orbits/run.sh, with its flags) and on two whole
# training orbits (map: the first half of the posed frames, the same distractors and foreign frames). None of the
# four reads the model; it is given so that the extraction is the one it declares, as in the arcs' other runs.
# Reports to $OUT/arcs and $OUT/orbits-full (default $SCONE_PREFIX/work/i60-base), then the tables:
#   docs/results/relocalisation/keypoint-base/run.sh
#   python3 docs/results/relocalisation/keypoint-base/table.py $SCONE_PREFIX/work/i60-base/arcs/far--*.json
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
out="${OUT:-$SCONE_PREFIX/work/i60-base}"
methods=freak,sift,dog-freak,fast-sift
model="$here/models/scone-ring-e1-real.onnx"
METHODS=$methods OUT="$out/arcs" "$here/docs/results/training/orbits/run.sh" i60-base "$model"
D=${SCONE_DATA:-$here/../shared/data}/scenes
SCENES="$D/llff-ethiopianhead $D/llff-lemontea-office" METHODS=$methods OUT="$out/orbits-full" \
  "$here/docs/results/training/orbits/run.sh" i60-base "$model"
