#!/usr/bin/env bash
# Issue 41: Localize latency of two binaries on the same map, interleaved request by request (the host's speed
# drifts within minutes, so runs one after the other do not compare). Starts `scone serve` of each binary on its
# own copy of DATA_DIR, waits until both have loaded the map, then sends every 25th frame of
# 7scenes-redkitchen (by frame number; most of them are frames of the bench's map, since this measures the
# time a request takes, not whether it is right) as a Localize request to one and then the other (the order
# swapped each round), one request in flight at a time, and prints each binary's p50 and the median of the
# per-request ratio B/A. Both load the map at once, so their "map opened" lines do not compare.
#   docs/results/issue41/localize-ab.sh A_BINARY B_BINARY DATA_DIR [ROUNDS]
# The bench's largest map: $SCONE_PREFIX/bench/reloc/<model>-1000000-<list>/per-landmark (a map `m`).
set -euo pipefail
a=$1; b=$2; dir=$3; rounds=${4:-5}
data=${SCONE_DATA:-$(dirname "$0")/../../../../shared/data}
work=$(mktemp -d)
trap 'kill -9 $(jobs -p) 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$work"' EXIT
cp -r "$dir" "$work/a"; cp -r "$dir" "$work/b"
RUST_LOG=info "$a" serve --data-dir "$work/a" --grpc-addr 127.0.0.1:50093 --http-addr 127.0.0.1:8093 > "$work/a.log" 2>&1 &
RUST_LOG=info "$b" serve --data-dir "$work/b" --grpc-addr 127.0.0.1:50094 --http-addr 127.0.0.1:8094 > "$work/b.log" 2>&1 &
for x in a b; do
  for _ in $(seq 1 1200); do
    grep -q "map loaded" "$work/$x.log" && break
    # A server that exited (a port taken, a bad binary) fails the run at once.
    pgrep -f -- "--data-dir $work/$x " > /dev/null || break
    sleep 0.1
  done
  grep -q "map loaded" "$work/$x.log" || { echo "no map loaded by $x:"; cat "$work/$x.log"; exit 1; }
done
for x in a b; do
  echo "$x: $(grep -o 'data_s=[0-9.]*.*from_dump=[a-z]*' "$work/$x.log" | sed 's/\x1b\[[0-9;]*m//g')"
done
python3 - "$data/scenes/7scenes-redkitchen" "$rounds" <<'PY'
import statistics, sys, time, urllib.error, urllib.request
from pathlib import Path
scene, rounds = Path(sys.argv[1]), int(sys.argv[2])
fx, fy, cx, cy, w, h = open(scene / "camera.txt").read().split()
frames = sorted((scene / "rgb").glob("*.jpg"), key=lambda f: int(f.stem))[::25]
images = [f.read_bytes() for f in frames]
def localize(port, image):
    url = f"http://127.0.0.1:{port}/v1/maps/m/localize?fx={fx}&fy={fy}&cx={cx}&cy={cy}"
    req = urllib.request.Request(url, data=image, headers={"content-type": "image/jpeg"})
    t = time.perf_counter()
    with urllib.request.urlopen(req) as r:
        r.read()
    return (time.perf_counter() - t) * 1e3
def ready(port):
    # The "map loaded" line comes just before the map is in the server's cache: wait for a first answer.
    for _ in range(100):
        try:
            return localize(port, images[0])
        except urllib.error.HTTPError as e:
            if e.code != 503:
                raise
            time.sleep(0.1)
    raise SystemExit(f"port {port} never answered")
ready(8093); ready(8094)
for image in images[:3]:  # warm-up, not counted
    localize(8093, image); localize(8094, image)
ta, tb, ratios = [], [], []
for r in range(rounds):
    for image in images:
        if r % 2 == 0:
            x = localize(8093, image); y = localize(8094, image)
        else:
            y = localize(8094, image); x = localize(8093, image)
        ta.append(x); tb.append(y); ratios.append(y / x)
print(f"{len(ta)} requests each ({len(images)} frames x {rounds} rounds)")
print(f"A p50 {statistics.median(ta):.1f} ms, B p50 {statistics.median(tb):.1f} ms, B/A per request (median) {statistics.median(ratios):.3f}x")
PY
