#!/usr/bin/env bash
# Issue 41: time to ready of one map in a fresh server, two binaries alternately (BENCHMARKS.md, "The largest
# map, with the ring model"). Each run starts `scone serve` on DATA_DIR (a local data directory whose maps load
# at start), waits for the "map loaded" line, prints the wall time and the "map opened" line's data_s / index_s,
# with open_s (the map data alone) and graph_s (the graph read beside it, alone) where the binary logs them, and
# the process's RSS, then kills the server (kill -9: nothing is written on the way out).
#   docs/results/issue41/ready.sh OLD_BINARY NEW_BINARY DATA_DIR [ROUNDS]
# The bench's largest map with its per-landmark dump: $SCONE_PREFIX/bench/reloc/<model>-1000000-<list>/per-landmark
set -euo pipefail
old=$1; new=$2; dir=$3; rounds=${4:-3}
log=$(mktemp)
trap 'rm -f "$log"' EXIT
one() {
  local start end pid
  start=$(date +%s.%N)
  RUST_LOG=info "$1" serve --data-dir "$dir" --grpc-addr 127.0.0.1:50091 --http-addr 127.0.0.1:8091 > "$log" 2>&1 &
  pid=$!
  for _ in $(seq 1 1200); do
    grep -q "map loaded" "$log" && break
    sleep 0.05
  done
  end=$(date +%s.%N)
  rss=$(awk '/VmRSS/ {print $2}' "/proc/$pid/status")
  kill -9 "$pid"; wait "$pid" 2>/dev/null || true
  echo "$1: loaded after $(echo "$end - $start" | bc) s, RSS $((rss / 1024)) MiB; $(grep -o 'data_s=[0-9.]*.*from_dump=[a-z]*' "$log")"
}
for _ in $(seq 1 "$rounds"); do
  one "$old"
  one "$new"
done
