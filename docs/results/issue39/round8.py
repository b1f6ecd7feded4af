#!/usr/bin/env python3
"""Issue 39, round 8: applies criteria 1-3 of the round-8 rule of docs/model-experiments.md to score.sh's reports.

    python3 docs/results/issue39/round8.py [--work $SCONE_PREFIX/work/i39] [--reference ring-e1-real-s50] ring-e1-inv [MORE...]

Round 4's criteria, with the reference's mean AUC@10 read from its own reports (the shipped model scored again
by the same score.sh this session) instead of round 2's 0.3110: the candidate with `union` must (1) pass round
2's rule, (2) reach the reference's mean + 0.005 and (3) be within 5 px in no zoom bin up to 2.5x below the
reference. Criterion 4 (the path's time) is a bench, run only for a candidate that passes these. Standard
library only.
"""

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round2 import ZOOM_BINS, judge, pair_means, table_header, table_row  # noqa: E402
from round4 import ROUND2_CONSTELLATION_MEAN, criteria, zoom_bins  # noqa: E402


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("models", nargs="+", help="candidates and readings, each a score.sh directory name")
    parser.add_argument("--reference", default="ring-e1-real-s50")
    args = parser.parse_args()
    reference = args.work / args.reference
    ref_mean = pair_means(reference, "union")[0]
    ref_zoom = zoom_bins(reference)
    print(f"reference {args.reference}: mean AUC@10 {ref_mean:.4f}; zoom bins within 5 px "
          + ", ".join(f"{b}: {ref_zoom[b]:.2f}" for b in ZOOM_BINS))
    print(table_header())
    for name in [args.reference, *args.models]:
        if name == args.reference:
            print(table_row(name, judge(reference, "union", ROUND2_CONSTELLATION_MEAN), "the reference"))
            continue
        r, mine, _ = criteria(args.work / name, "union", reference, "union", args.reference, ref_mean)
        zooms = " / ".join(f"{mine[b]:.2f}" for b in ZOOM_BINS[1:])
        verdict = "passes criteria 1-3" if not r["failures"] else "fails: " + "; ".join(r["failures"])
        print(table_row(name, r, verdict) + f" zoom 1.25-1.6x / 1.6-2x / 2-2.5x: {zooms}")


if __name__ == "__main__":
    main()
