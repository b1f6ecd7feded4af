#!/usr/bin/env python3
"""Issue 39, round 14: applies the round-14 rule of docs/model-experiments.md (`union` with the embedding's own
ratio at 0.85 and 0.9, against `union` at 0.8, on six runs of the shipped recipe) to score.sh's reports.

    python3 docs/results/issue39/round14.py [--work $SCONE_PREFIX/work/i39]

Each candidate is round 11's two criteria, its reports in `<model>-r85` / `<model>-r90` beside each model's
`union` reports. If both pass, the one with the higher mean difference ships. Standard library only.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round11 import six_models, work_dir  # noqa: E402

RATIOS = ["85", "90"]


def main():
    work = work_dir()
    passing = {}
    for r in RATIOS:
        print(f"## union, the embedding's ratio at 0.{r}")
        print()
        failures, mean_diff = six_models(work, lambda w, name, r=r: w / f"{name}-r{r}", "union", f"0.{r}")
        print()
        print(f"0.{r}: " + ("passes" if not failures else "fails: " + "; ".join(failures)))
        print()
        if not failures:
            passing[r] = mean_diff
    best = max(passing, key=passing.get) if passing else None
    print("verdict: " + (f"0.{best} ships as the embedded model's embedding ratio" if best else "neither ships"))


if __name__ == "__main__":
    main()
