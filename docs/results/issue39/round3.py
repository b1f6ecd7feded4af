#!/usr/bin/env python3
"""Issue 39, round 3: applies the round-3 rule of docs/model-experiments.md to score.sh's reports.

    python3 docs/results/issue39/round3.py [--work $SCONE_PREFIX/work/i39] ring-e1-narrow

The candidate with `union` must (1) pass round 2's rule (round2.judge; the constellation model's scale-aware
mean on the same keypoints, 0.2806 in round 2's run, is the "shipped" figure that rule compares with) and (2)
reach a mean AUC@10 of at least ring-e1-real + union's 0.3110 - 0.005. Criterion 3 (the path's time) is read
from `cargo bench --bench embedding`. Standard library only.
"""

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round2 import judge, table_header, table_row  # noqa: E402

ROUND2_CONSTELLATION_MEAN = 0.2806
RING_E1_REAL_UNION_MEAN = 0.3110


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("model")
    args = parser.parse_args()
    r = judge(args.work / args.model, "union", ROUND2_CONSTELLATION_MEAN)
    if r["mean"] < RING_E1_REAL_UNION_MEAN - 0.005:
        r["failures"].append(f"pairs {r['mean']:.4f} < ring-e1-real {RING_E1_REAL_UNION_MEAN:.4f} - 0.005")
    verdict = "passes criteria 1 and 2" if not r["failures"] else "fails: " + "; ".join(r["failures"])
    print(table_header())
    print(table_row(args.model, r, verdict))

if __name__ == "__main__":
    main()
