#!/bin/bash
# Issue 31, rule point 3: the far-map protocol (issue 27's command) for SConE with each index setting.
cd "${OUT:-.}"   # where the reports go
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
for scene in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
  for pts in observations landmarks; do
    f=far-$scene-$pts.json
    [ -s $f ] || $B eval reloc --scene $D/$scene --map-block 0:0.5 --methods scone \
      --distractors $D/7scenes-redkitchen,$D/sun3d-studyroom --distractor-observations 100000 --distractor-stride 5 \
      --foreign $D/strecha-castle-P30 --foreign-stride 3 --index-points $pts --json $f > far-$scene-$pts.md 2> far-$scene-$pts.log || echo "FAILED $scene $pts"
  done
done
echo val-done
