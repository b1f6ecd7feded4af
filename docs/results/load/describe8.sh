#!/usr/bin/env bash
# Describe throughput at 8 clients: two scone binaries, each with its own embedded default, in the same run.
#   docs/results/load/describe8.sh OLD_BINARY NEW_BINARY [ROUNDS]
# Each round starts OLD then NEW on a fresh data directory, pinned to core 0 (taskset -c 0: one core, as
# load-tests/run pins its servers), and drives it with wrk on core 1: 8 connections, closed loop, 30 s,
# POST /v1/describe with the 640x480 JPEGs of rgbd-slambook-5 (quality 90) in turn, after a 5 s warm-up.
# Prints one line per server and round (req/s, latency p50/p99 from wrk's HdrHistogram) and the ratio of the
# rounds' means. SCONE_DESCRIBE_CLIENTS=N sets the connections (default 8), SCONE_DESCRIBE_UNPINNED=1 leaves
# the server and wrk free to use both cores (a lone client's latency). Needs wrk (apt-get install wrk) and python3 with OpenCV (the client venv) for the JPEGs.
set -euo pipefail
old="$1" new="$2" rounds="${3:-2}"
clients="${SCONE_DESCRIBE_CLIENTS:-8}"
pin_server=(taskset -c 0) pin_wrk=(taskset -c 1)
if [ "${SCONE_DESCRIBE_UNPINNED:-0}" = 1 ]; then pin_server=() pin_wrk=(); fi
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)"
scene="${SCONE_LOAD_SCENE:-$root/../shared/data/scenes/rgbd-slambook-5}"
py="${SCONE_PY:-${SCONE_PREFIX:-$HOME/.cache/scone}/venv-client/bin/python}"
work="$(mktemp -d)"
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
"$py" - "$scene" "$work" <<'PY'
import sys, pathlib, cv2
scene, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
for p in sorted((scene / "rgb").glob("*.png")):
    cv2.imwrite(str(out / (p.stem + ".jpg")), cv2.imread(str(p), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_JPEG_QUALITY, 90])
PY
files="$(printf '%s:' "$work"/*.jpg)"
files="${files%:}"
lua="$root/load-tests/wrk/post-jpeg.lua"
run() {  # binary label -> prints "label req/s p50 p99"
  local data="$work/data-$RANDOM" port=$((20000 + RANDOM % 20000))
  "${pin_server[@]}" "$1" serve --grpc-addr 127.0.0.1:$((port + 1)) --http-addr 127.0.0.1:$port --data-dir "$data" \
    > "$work/server.log" 2>&1 &
  local pid=$!
  for _ in $(seq 100); do curl -sf "http://127.0.0.1:$port/healthz" >/dev/null && break; sleep 0.2; done
  SCONE_WRK_FILES="$files" "${pin_wrk[@]}" wrk -t1 -c"$clients" -d5s --timeout 60s -s "$lua" "http://127.0.0.1:$port/v1/describe" >/dev/null
  local out
  out="$(SCONE_WRK_FILES="$files" "${pin_wrk[@]}" wrk -t1 -c"$clients" -d30s --timeout 60s -s "$lua" "http://127.0.0.1:$port/v1/describe" | sed -n 's/^SCONE-WRK-JSON //p')"
  kill "$pid"; wait "$pid" 2>/dev/null || true
  python3 -c 'import json,sys; d=json.loads(sys.argv[2]); print(sys.argv[1], round(d["rps"], 2), d["p50_ms"], d["p99_ms"], "non2xx", d["non2xx"], "socket_errors", d["socket_errors"])' "$2" "$out"
}
for r in $(seq "$rounds"); do
  run "$old" "old-round$r"
  run "$new" "new-round$r"
done | tee "$work/results.txt"
python3 - "$work/results.txt" <<'PY'
import sys, statistics
rows = [l.split() for l in open(sys.argv[1])]
mean = lambda tag: statistics.mean(float(r[1]) for r in rows if r[0].startswith(tag))
print(f"mean req/s: old {mean('old'):.2f}, new {mean('new'):.2f}, new/old {mean('new') / mean('old'):.2f}x")
PY
