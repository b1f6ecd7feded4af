#!/usr/bin/env bash
# Issue 41 (session 49): the reloc bench at 1M from copies of bench binaries, run in the order given, each run's
# whole output under a "### NAME time" line. Build each variant's bench binary and copy it to
# $SCONE_PREFIX/reloc-NAME first (`cargo build --release --bench reloc --message-format=json` names the file).
#   docs/results/issue41/reloc-ab.sh base mi mi base > log
set -euo pipefail
prefix=${SCONE_PREFIX:-$HOME/.cache/scone}
SCONE_DATA=${SCONE_DATA:-$(realpath "$(dirname "$0")/../../../../shared/data")}
export SCONE_DATA SCONE_BENCH_1M=1
for b in "$@"; do
  echo "### $b $(date +%T)"
  "$prefix/reloc-$b" --bench 2>&1 | grep -v '^\s*$'
done
echo "### done $(date +%T)"
