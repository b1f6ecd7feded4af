#!/bin/bash
# Selection runs of issue 27: every configuration, SConE, far-map protocol, the five selection scenes.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes; S=~/.cache/scone/work/sel
OUT=${OUT:-sel}; METHODS=${METHODS:-scone}
mkdir -p $OUT
scenes="$D/strecha-castle-P30 $HOME/.cache/scone/work/cal/templeRing-1-31 $S/7scenes-redkitchen-sel $S/sun3d-studyroom-sel $S/liberty-internet-sel"
for cfg in ${CONFIGS:-none candidates freak guided build candidates,guided candidates,build guided,build candidates,guided,build freak,guided freak,build freak,guided,build}; do
  for sc in $scenes; do
    name=$(basename $sc)
    foreign=$S/7scenes-redkitchen-sel; [ "$name" = 7scenes-redkitchen-sel ] && foreign=$S/strecha-castle-P30-sel
    f=$OUT/$cfg--$name.json
    [ -s $f ] && continue
    $B eval reloc --scene $sc --methods $METHODS --map-block 0:0.5 --stages $cfg --foreign $foreign --foreign-stride 2 --json $f > $OUT/$cfg--$name.md 2> $OUT/$cfg--$name.log || echo "FAILED $cfg $name"
  done
done
echo done
