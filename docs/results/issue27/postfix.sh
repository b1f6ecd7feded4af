#!/bin/bash
# After the review fixes (ranking of unambiguous matches, prior in stages 2-3): the selection scenes again for
# the chosen configuration and the baseline, then the far-map validation runs of the new pipeline.
cd ~/.cache/scone/work/i27
OUT=sel-postfix CONFIGS="none candidates" ./sel.sh
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
mkdir -p val-postfix
for sc in strecha-fountain-P11 tum-fr3-long-office middlebury-dino48 kitti-clip2; do
  f=val-postfix/far-$sc-new.json
  [ -s $f ] || $B eval reloc --scene $D/$sc --map-block 0:0.5 --methods scone,sift,freak \
    --distractors $D/7scenes-redkitchen,$D/sun3d-studyroom --distractor-observations 100000 --distractor-stride 5 \
    --foreign $D/strecha-castle-P30 --foreign-stride 3 --json $f > val-postfix/far-$sc-new.md 2> val-postfix/far-$sc-new.log || echo "FAILED $sc"
done
echo postfix-done
