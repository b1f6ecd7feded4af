#!/bin/bash
# FREAK through the staged pipeline again, after the fix that gives its stage-2 ratio the square root like its
# stage-1 ratio (a ratio on Hamming distances); the first new-pipeline FREAK rows used 0.9 on L2 of ±1 vectors.
cd ~/.cache/scone/work/i27
sleep 60
while pgrep -f "chain.sh" > /dev/null && ! grep -q "relocalisation\|observations" bench.md 2>/dev/null; do sleep 20; done
while pgrep -f "cargo bench" > /dev/null || pgrep -f "deps/reloc-" > /dev/null; do sleep 20; done
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
for sc in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
  foreign=$D/strecha-castle-P30; [ $sc = strecha-fountain-P11 ] && foreign=$D/7scenes-redkitchen
  [ $sc = strecha-fountain-P11 ] && foreign=$D/strecha-castle-P30
  f=val/far-$sc-new-freak.json
  [ -s $f ] || $B eval reloc --scene $D/$sc --map-block 0:0.5 --methods freak \
    --distractors $D/7scenes-redkitchen,$D/sun3d-studyroom --distractor-observations 100000 --distractor-stride 5 \
    --foreign $foreign --foreign-stride 3 --json $f > val/far-$sc-new-freak.md 2> val/far-$sc-new-freak.log || echo "FAILED $sc"
done
for sc in kitti-clip2 middlebury-dino48 tum-fr3-long-office; do
  f=val/sparse-$sc-new-freak.json
  [ -s $f ] || $B eval reloc --scene $D/$sc --map-stride 10 --methods freak --json $f > val/sparse-$sc-new-freak.md 2> val/sparse-$sc-new-freak.log
done
echo freak-done
