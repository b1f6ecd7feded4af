#!/usr/bin/env bash
# Map building with the known poses (RULE.md beside this file): the estimator selection's runs
# (../estimator/run.sh) with the maps built from the keyframes' poses. Then score.py beside this file.
#   docs/results/relocalisation/map-building/run.sh  (reports to $OUT, default $SCONE_PREFIX/work/reloc-map-building)
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/../../../.." && pwd)"
# shellcheck source=scripts/env.sh
. "$here/scripts/env.sh"
OUT="${OUT:-$SCONE_PREFIX/work/reloc-map-building}" STAGES="candidates,build" \
  exec bash "$here/docs/results/relocalisation/estimator/run.sh"
