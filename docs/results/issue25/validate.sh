#!/bin/bash
# Validation of the shipped method, once: pairs on the five scenes, the validation warps, graffiti and the EF sequences.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
OUT=$(realpath -m ${OUT:-val}); mkdir -p $OUT
M=${MODEL:+--model $MODEL}
cd /work/main/training
[ -s $OUT/pairs/summary.md ] || SCONE_BIN=$B OMP_NUM_THREADS=1 ~/.cache/scone/venv-train/bin/python -m scone_train.validation_pairs --out $OUT/pairs ${MODEL:+--model $MODEL} --methods scone,scone-plain,freak,sift > $OUT/pairs.out 2>&1
[ -s $OUT/warps.json ] || $B eval homography --data ~/.cache/scone/work/warps/validation --methods scone,scone-plain,freak,orb,sift $M --embed-threads 1 --opencv-threads 1 --json $OUT/warps.json > $OUT/warps.md 2>/dev/null
[ -s $OUT/real-h.json ] || $B eval homography --data $D/hpatches-v_graffiti,$D/ef-notredame,$D/ef-obama,$D/ef-paintedladies,$D/ef-rushmore,$D/ef-yosemite --methods scone,scone-plain,freak,orb,sift $M --embed-threads 1 --opencv-threads 1 --json $OUT/real-h.json > $OUT/real-h.md 2>/dev/null
[ -s $OUT/graffiti.json ] || $B eval homography --data $D/hpatches-v_graffiti --methods scone,scone-plain,freak,orb,sift $M --embed-threads 1 --opencv-threads 1 --json $OUT/graffiti.json > $OUT/graffiti.md 2>/dev/null
echo done
