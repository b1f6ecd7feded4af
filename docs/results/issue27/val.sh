#!/bin/bash
# Validation runs of issue 27 (once): far-map protocol with 100k distractors and the sparse-map protocol,
# old pipeline (--stages none) and the shipped defaults (no --stages), every method.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
mkdir -p val
for sc in kitti-clip2 middlebury-dino48 strecha-fountain-P11 tum-fr3-long-office; do
  foreign=$D/strecha-castle-P30; [ $sc = strecha-fountain-P11 ] && foreign=$D/7scenes-redkitchen
  for cfg in new old; do
    st=""; [ $cfg = old ] && st="--stages none"
    f=val/far-$sc-$cfg.json
    [ -s $f ] || $B eval reloc --scene $D/$sc --map-block 0:0.5 --methods scone,freak,sift $st \
      --distractors $D/7scenes-redkitchen,$D/sun3d-studyroom --distractor-observations 100000 --distractor-stride 5 \
      --foreign $foreign --foreign-stride 3 --json $f > val/far-$sc-$cfg.md 2> val/far-$sc-$cfg.log || echo "FAILED far $sc $cfg"
  done
done
for sc in kitti-clip2 middlebury-dino48 tum-fr3-long-office strecha-castle-P30; do :; done
echo far-done
