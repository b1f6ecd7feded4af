#!/bin/bash
# After the far-map runs: fountain again with a foreign scene that is not among the distractors (the first run
# used 7scenes-redkitchen, which is in the map as a distractor), the sparse-map runs, the bench, then the
# selection scenes' map-building variants for FREAK and SIFT.
cd ~/.cache/scone/work/i27
while pgrep -f "val.sh" > /dev/null; do sleep 15; done
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; D=/work/shared/data/scenes
for cfg in new old; do
  st=""; [ $cfg = old ] && st="--stages none"
  f=val/far-strecha-fountain-P11-$cfg.json
  [ -s $f ] || $B eval reloc --scene $D/strecha-fountain-P11 --map-block 0:0.5 --methods scone,freak,sift $st \
    --distractors $D/7scenes-redkitchen,$D/sun3d-studyroom --distractor-observations 100000 --distractor-stride 5 \
    --foreign $D/strecha-castle-P30 --foreign-stride 3 --json $f > val/far-strecha-fountain-P11-$cfg.md 2> val/far-strecha-fountain-P11-$cfg.log || echo "FAILED fountain $cfg"
done
./val2.sh
cd /work/main && cargo bench --bench reloc --locked > ~/.cache/scone/work/i27/bench.md 2> ~/.cache/scone/work/i27/bench.log
cd ~/.cache/scone/work/i27 && OUT=sel-all METHODS=scone,freak,sift CONFIGS="none build candidates" ./sel.sh
echo chain-done
