#!/bin/bash
# Issue 39 step 1: FREAK at E0 (6 levels, 1,500 keypoints) and E1 (8 levels, 2,000): selection pairs and far-map relocalisation.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes; S=~/.cache/scone/work/sel; OUT=~/.cache/scone/work/i39/step1
cd $OUT
for e in E0 E1; do
  flags=""; [ $e = E1 ] && flags="--levels 8 --max-keypoints 2000"
  for part in strecha-castle-P30:10 7scenes-redkitchen:20 sun3d-studyroom:20 middlebury-templeRing:10 liberty-internet:27; do
    name=${part%%:*}; w=${part##*:}
    f=pairs-$e-$name.json; [ -s $f ] && continue
    $B eval pairs --scene $S/$name-sel --window $w --seeds 3 --methods freak --json $f --opencv-threads 1 $flags > /dev/null 2>pairs-$e-$name.log || echo FAILED pairs $e $name
  done
  for sc in $D/strecha-castle-P30 $HOME/.cache/scone/work/cal/templeRing-1-31 $S/7scenes-redkitchen-sel $S/sun3d-studyroom-sel $S/liberty-internet-sel; do
    name=$(basename $sc); foreign=$S/7scenes-redkitchen-sel; [ "$name" = 7scenes-redkitchen-sel ] && foreign=$S/strecha-castle-P30-sel
    f=reloc-$e-$name.json; [ -s $f ] && continue
    $B eval reloc --scene $sc --methods freak --map-block 0:0.5 --foreign $foreign --foreign-stride 2 --json $f --opencv-threads 1 $flags > reloc-$e-$name.md 2> reloc-$e-$name.log || echo FAILED reloc $e $name
  done
done
echo done
