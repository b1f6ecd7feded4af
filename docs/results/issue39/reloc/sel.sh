#!/usr/bin/env bash
# Issue 39, step 4: issue 27's selection rule for the staged pipeline run again with the shipped model
# (BENCHMARKS.md, "Issue 39, step 4: relocalisation chosen again"). SConE, far-map protocol (map = first half of
# the posed frames), the map alone, one foreign scene, on issue 27's five selection scenes; one report per
# configuration and scene.
#   docs/results/issue39/reloc/sel.sh          (reports to $OUT, default $SCONE_PREFIX/work/i39/reloc-sel)
# Needs the selection parts (python -m scone_train.splits --out $SCONE_PREFIX/work/sel) and templeRing stamps
# 1-31 as a scene directory ($SCONE_PREFIX/work/cal/templeRing-1-31). JOBS=2 runs two at a time.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
B="$CARGO_TARGET_DIR/release/scone"
D=${SCONE_DATA:-$here/../shared/data}/scenes
S=$SCONE_PREFIX/work/sel
out="${OUT:-$SCONE_PREFIX/work/i39/reloc-sel}"
mkdir -p "$out"
one() {
  local cfg=$1 sc=$2 name foreign f
  name=$(basename "$sc")
  foreign=$S/7scenes-redkitchen-sel; [ "$name" = 7scenes-redkitchen-sel ] && foreign=$S/strecha-castle-P30-sel
  f="$out/$cfg--$name.json"
  [ -s "$f" ] && return 0
  "$B" eval reloc --scene "$sc" --methods scone --map-block 0:0.5 --stages "$cfg" --foreign "$foreign" \
    --foreign-stride 2 --opencv-threads 1 --embed-threads 1 --json "$f" > "$out/$cfg--$name.md" \
    2> "$out/$cfg--$name.log" || echo "FAILED $cfg $name"
}
configs=${CONFIGS:-none candidates freak candidates,guided freak,guided candidates,build candidates,guided,build freak,build freak,guided,build}
jobs=()
for cfg in $configs; do
  for sc in "$D/strecha-castle-P30" "$SCONE_PREFIX/work/cal/templeRing-1-31" "$S/7scenes-redkitchen-sel" \
    "$S/sun3d-studyroom-sel" "$S/liberty-internet-sel"; do
    jobs+=("$cfg $sc")
  done
done
n=${JOBS:-1}
for ((i = 0; i < ${#jobs[@]}; i += n)); do
  for ((j = i; j < i + n && j < ${#jobs[@]}; j++)); do
    # shellcheck disable=SC2086
    one ${jobs[j]} &
  done
  wait
done
echo "$out"
