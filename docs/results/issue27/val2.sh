#!/bin/bash
# Sparse-map protocol (map from every 10th frame), validation scenes with at least 30 frames, old and new.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
cd ~/.cache/scone/work/i27
while pgrep -f val.sh > /dev/null; do sleep 20; done
for sc in kitti-clip2 middlebury-dino48 tum-fr3-long-office; do
  for cfg in new old; do
    st=""; [ $cfg = old ] && st="--stages none"
    f=val/sparse-$sc-$cfg.json
    [ -s $f ] || $B eval reloc --scene $D/$sc --map-stride 10 --methods scone,freak,sift $st \
      --json $f > val/sparse-$sc-$cfg.md 2> val/sparse-$sc-$cfg.log || echo "FAILED sparse $sc $cfg"
  done
done
echo sparse-done
