#!/bin/bash
# Pair protocol on the real selection scenes: MODEL (default shipped), MATCHER, OUT dir; 3 seeds, each part's window.
source /work/main/scripts/env.sh
B=$CARGO_TARGET_DIR/release/scone; S=~/.cache/scone/work/sel
MATCHER=${MATCHER:-rerank}; OUT=${OUT:-sel-pairs-$MATCHER}; mkdir -p $OUT
M=${MODEL:+--model $MODEL}
for pair in strecha-castle-P30-sel:10 7scenes-redkitchen-sel:20 sun3d-studyroom-sel:20 middlebury-templeRing-sel:10 liberty-internet-sel:27; do
  sc=${pair%%:*}; w=${pair##*:}
  f=$OUT/$sc.json; [ -s $f ] && continue
  $B eval pairs --scene $S/$sc --methods ${METHODS:-scone} --scone-matcher $MATCHER --window $w --seeds 3 $M --embed-threads 1 --opencv-threads 1 --json $f > $OUT/$sc.md 2>$OUT/$sc.log || echo "FAILED $sc"
done
python3 - "$OUT" <<'PY'
import json,sys,glob
v=[]
for f in sorted(glob.glob(sys.argv[1]+'/*.json')):
    r=json.load(open(f))
    for m in r['summaries']:
        print(r['scene'], m['method'], round(m['auc10'],4)); v.append(m['auc10'])
print('mean', round(sum(v)/len(v),4))
PY
