#!/usr/bin/env python3
"""Issue 39, round 10: applies the round-10 rule of docs/model-experiments.md (three seeds a side) to score.sh's reports.

    python3 docs/results/issue39/round10.py [--work $SCONE_PREFIX/work/i39] [--candidate ring-e1-real75-ema]

Round 12 judges its candidate configuration with the same criteria (`--candidate ring-e1-real-10k`).

Criterion 1: the candidate configuration's mean over its seeds of the mean AUC@10 (with `union`) at least the
reference configuration's + 0.010. Criterion 2: the mean over its seeds of the share within 5 px over the zoom
1.25-2.5x warp pairs at least the reference configuration's. Criterion 3: the candidate's best seed (highest
mean AUC@10) passes round 8's criteria 1-3 against the shipped model scored again. Standard library only.
"""

import argparse
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round2 import ZOOM_BINS, pair_means, table_header, table_row, warp_figures  # noqa: E402
from round4 import criteria  # noqa: E402

REFERENCE = ["ring-e1-ema", "ring-e1-ema-s1", "ring-e1-ema-s2"]
SHIPPED = "ring-e1-real-s50"
PAIRS_MARGIN = 0.010
ZOOMED = ("1.25-1.6x", "1.6-2x", "2-2.5x")


def zoomed_share(directory):
    """SConE's share within 5 px over the pairs of the zoom bins 1.25-2.5x, each pair counted once."""
    bins = [b for b in warp_figures(directory, "union")[2] if b["axis"] == "zoom" and b["label"] in ZOOMED]
    return sum(b["scone"] * b["pairs"] for b in bins) / sum(b["pairs"] for b in bins)


def configuration(work, names):
    """Per seed (mean AUC@10, zoom 1.25-2.5x share) and the configuration's means of both."""
    seeds = {n: (pair_means(work / n, "union")[0], zoomed_share(work / n)) for n in names}
    return seeds, statistics.mean(s[0] for s in seeds.values()), statistics.mean(s[1] for s in seeds.values())


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("--candidate", default="ring-e1-real75-ema", help="seed 0's name; seeds 1-2 add -s1, -s2")
    args = parser.parse_args()
    candidate = [args.candidate, args.candidate + "-s1", args.candidate + "-s2"]
    ref_seeds, ref_pairs, ref_zoom = configuration(args.work, REFERENCE)
    cand_seeds, cand_pairs, cand_zoom = configuration(args.work, candidate)
    print("| configuration | seed 0 | seed 1 | seed 2 | mean AUC@10 (sd) | zoom 1.25-2.5x within 5 px, by seed | mean |")
    print("|---|---|---|---|---|---|---|")
    for label, seeds, pairs, zoom in (("reference (round 9, averaged)", ref_seeds, ref_pairs, ref_zoom),
                                      (f"candidate ({args.candidate})", cand_seeds, cand_pairs, cand_zoom)):
        values = [s[0] for s in seeds.values()]
        print(f"| {label} | " + " | ".join(f"{v:.4f}" for v in values)
              + f" | **{pairs:.4f}** ({statistics.stdev(values):.4f}) | "
              + " / ".join(f"{s[1]:.3f}" for s in seeds.values()) + f" | **{zoom:.3f}** |")
    failures = []
    if cand_pairs < ref_pairs + PAIRS_MARGIN:
        failures.append(f"1: pairs {cand_pairs:.4f} < reference {ref_pairs:.4f} + {PAIRS_MARGIN}")
    if cand_zoom < ref_zoom:
        failures.append(f"2: zoom 1.25-2.5x {cand_zoom:.3f} < reference {ref_zoom:.3f}")
    best = max(cand_seeds, key=lambda n: cand_seeds[n][0])
    shipped = args.work / SHIPPED
    shipped_mean = pair_means(shipped, "union")[0]
    r, mine, _ = criteria(args.work / best, "union", shipped, "union", SHIPPED, shipped_mean)
    failures += [f"3 ({best}): {f}" for f in r["failures"]]
    print()
    print(table_header())
    print(table_row(best, r, "its best seed") + " zoom 1.25-1.6x / 1.6-2x / 2-2.5x: "
          + " / ".join(f"{mine[b]:.2f}" for b in ZOOM_BINS[1:]))
    print()
    print("verdict: " + ("passes; ships " + best if not failures else "fails: " + "; ".join(failures)))


if __name__ == "__main__":
    main()
