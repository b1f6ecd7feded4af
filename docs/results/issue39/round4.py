#!/usr/bin/env python3
"""Issue 39, round 4: applies the round-4 rule of docs/model-experiments.md to score.sh's reports.

    python3 docs/results/issue39/round4.py [--work $SCONE_PREFIX/work/i39] ring-e1-warps24 [ring-e1-real]

The candidate with `union` must (1) pass round 2's rule (round2.judge, with the constellation model's
scale-aware mean of round 2's run as the "shipped" figure), (2) reach a mean AUC@10 of at least ring-e1-real +
union's 0.3110 + 0.005, and (3) be within 5 px in no zoom bin up to 2.5x below the reference (ring-e1-real +
union, scored on the same warps by the same score.sh). Standard library only.
"""

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round2 import ZOOM_BINS, judge, table_header, table_row, warp_figures  # noqa: E402

ROUND2_CONSTELLATION_MEAN = 0.2806
RING_E1_REAL_UNION_MEAN = 0.3110


def zoom_bins(directory, matcher="union"):
    return {b["label"]: b["scone"] for b in warp_figures(directory, matcher)[2] if b["axis"] == "zoom"}


def criteria(candidate, matcher, reference, reference_matcher, reference_name, reference_mean=RING_E1_REAL_UNION_MEAN):
    """Criteria 1-3 for `candidate` (a score.sh directory) with `matcher`, against `reference` with
    `reference_matcher` and its mean AUC@10: round2.judge's result with the failures of criteria 2-3 added, and
    the zoom bins within 5 px of both."""
    r = judge(candidate, matcher, ROUND2_CONSTELLATION_MEAN)
    if r["mean"] < reference_mean + 0.005:
        r["failures"].append(f"pairs {r['mean']:.4f} < {reference_name} {reference_mean:.4f} + 0.005")
    mine, ref = zoom_bins(candidate, matcher), zoom_bins(reference, reference_matcher)
    for label in ZOOM_BINS[1:]:
        if mine[label] < ref[label]:
            r["failures"].append(f"zoom {label} {mine[label]:.2f} < {reference_name} {ref[label]:.2f}")
    return r, mine, ref


def report(candidate, matcher, reference, reference_matcher, reference_name):
    """Criteria 1-3 against `reference` (mean AUC@10 0.3110); prints the zoom bins and the table row."""
    r, mine, ref = criteria(candidate, matcher, reference, reference_matcher, reference_name)
    print("zoom bins within 5 px, " + ", ".join(f"{b}: {mine[b]:.2f} ({reference_name} {ref[b]:.2f})" for b in ZOOM_BINS))
    verdict = "passes criteria 1-3" if not r["failures"] else "fails: " + "; ".join(r["failures"])
    print(table_header())
    print(table_row(candidate.name, r, verdict))


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("model")
    parser.add_argument("reference", nargs="?", default="ring-e1-real")
    args = parser.parse_args()
    report(args.work / args.model, "union", args.work / args.reference, "union", args.reference)


if __name__ == "__main__":
    main()
