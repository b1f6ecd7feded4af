#!/usr/bin/env python3
"""Issue 39, round 6: applies the round-6 rule of docs/model-experiments.md to score.sh's reports.

    python3 docs/results/issue39/round6.py [--work $SCONE_PREFIX/work/i39] [ring-e1-real-joint [ring-e1-real]]

The shipped model with the matcher `joint` must (1) pass round 2's rule (round2.judge, with the constellation
model's scale-aware mean of round 2's run as the "shipped" figure), (2) reach a mean AUC@10 of at least `union`'s
0.3110 + 0.005, and (3) be within 5 px in no zoom bin up to 2.5x below `union`'s (the reference directory,
scored on the same warps by the same score.sh). Standard library only.
"""

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round4 import report  # noqa: E402


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("candidate", nargs="?", default="ring-e1-real-joint")
    parser.add_argument("reference", nargs="?", default="ring-e1-real")
    args = parser.parse_args()
    report(args.work / args.candidate, "joint", args.work / args.reference, "union", "union")


if __name__ == "__main__":
    main()
