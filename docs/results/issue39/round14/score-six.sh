#!/usr/bin/env bash
# Round 14: union with the embedding's own ratio, on six runs of the shipped recipe; two scorings at a time.
# Reports: $SCONE_PREFIX/work/i39/<model>-r85 and -r90; then python3 docs/results/issue39/round14.py.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../../../.."
P=${SCONE_PREFIX:-$HOME/.cache/scone}
jobs=()
for r in 85 90; do
  for name in ring-e1-real-s50 ring-e1-real-4k ring-e1-real-4k-s1 ring-e1-ema ring-e1-ema-s1 ring-e1-ema-s2; do
    model=$P/work/i39/models/scone-$name.onnx
    [ "$name" = ring-e1-real-s50 ] && model=models/scone-ring-e1-real.onnx
    jobs+=("$name $r $model")
  done
done
# The single quotes are meant: the inner shell expands $0-$3 (the prefix, then a job's three words).
# shellcheck disable=SC2016
printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c 'OUT=$0/work/i39/$1-r$2 SCONE_PREFIX=$0 docs/results/issue39/score.sh $1 $3 union --levels 8 --max-keypoints 2000 --scone-ratio 0.$2 > /dev/null && echo "$1 r$2 done $(date +%T)"' "$P"
