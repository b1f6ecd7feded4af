#!/usr/bin/env python3
"""Issue 39, round 11: applies the round-11 rule of docs/model-experiments.md (the matcher `both` against `union`
on six runs of the shipped recipe) to score.sh's reports.

    python3 docs/results/issue39/round11.py [--work $SCONE_PREFIX/work/i39]

Criterion 1: with the shipped model, round 6's criteria 1-3 (round 2's rule, `union`'s mean + 0.005, no zoom bin
up to 2.5x below `union`'s). Criterion 2: over the six models, `both` above `union` in mean AUC@10 on at least
five, and by at least 0.005 on average. Standard library only.
"""

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from round2 import PARTS, ZOOM_BINS, pair_means, summary, table_header, table_row, warp_figures  # noqa: E402
from round4 import criteria  # noqa: E402

SHIPPED = "ring-e1-real-s50"
MODELS = [SHIPPED, "ring-e1-real-4k", "ring-e1-real-4k-s1", "ring-e1-ema", "ring-e1-ema-s1", "ring-e1-ema-s2"]
MEAN_MARGIN = 0.005


def matches_and_precision(directory, matcher):
    """SConE's matches per pair and match precision, averaged over the five parts."""
    rows = [summary(json.loads((directory / f"pairs-{matcher}-{part}.json").read_text())["summaries"], "scone")
            for part in PARTS]
    return statistics.mean(r["mean_matches"] for r in rows), statistics.mean(r["match_precision"] for r in rows)


def six_models(work, candidate_dir, matcher, label):
    """Round 11's two criteria for a candidate scored into `candidate_dir(work, model)` with `matcher`, against
    `union` in each model's own directory; prints the table and the shipped model's row, and returns the
    failures and the mean difference. `label` names the candidate in the printed lines."""
    print(f"| model | union | {label} | difference | parts ({label} - union) | warps 5 px union / {label} | matches per pair union / {label} |")
    print("|---|---|---|---|---|---|---|")
    diffs = []
    for name in MODELS:
        d, c = work / name, candidate_dir(work, name)
        u, _, u_parts, _ = pair_means(d, "union")
        b, _, b_parts, _ = pair_means(c, matcher)
        wu, wb = warp_figures(d, "union")[0]["scone"], warp_figures(c, matcher)[0]["scone"]
        diffs.append(b - u)
        (mu, pu), (mb, pb) = matches_and_precision(d, "union"), matches_and_precision(c, matcher)
        print(f"| {name} | {u:.4f} | {b:.4f} | {b - u:+.4f} | "
              + " / ".join(f"{y - x:+.3f}" for x, y in zip(u_parts, b_parts)) + f" | {wu:.3f} / {wb:.3f} | {mu:.0f}, {pu:.3f} / {mb:.0f}, {pb:.3f} |")
    failures = []
    shipped = work / SHIPPED
    union_mean = pair_means(shipped, "union")[0]
    r, mine, ref = criteria(candidate_dir(work, SHIPPED), matcher, shipped, "union", "union", union_mean)
    failures += [f"1: {f}" for f in r["failures"]]
    above, mean_diff = sum(x > 0 for x in diffs), statistics.mean(diffs)
    if above < 5:
        failures.append(f"2: {label} above union on {above} of {len(diffs)} models, 5 needed")
    if mean_diff < MEAN_MARGIN:
        failures.append(f"2: mean difference {mean_diff:+.4f} < +{MEAN_MARGIN}")
    print()
    print(f"mean difference {mean_diff:+.4f}, {label} above union on {above} of {len(diffs)}")
    print(table_header())
    print(table_row(SHIPPED, r, f"the shipped model with {label}") + " zoom 1.25-1.6x / 1.6-2x / 2-2.5x: "
          + " / ".join(f"{mine[b]:.2f}" for b in ZOOM_BINS[1:]) + " (union "
          + " / ".join(f"{ref[b]:.2f}" for b in ZOOM_BINS[1:]) + ")")
    return failures, mean_diff


def work_dir():
    """The directory score.sh writes its reports under, or --work."""
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=sys.modules["__main__"].__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    return parser.parse_args().work


def main():
    failures, _ = six_models(work_dir(), lambda work, name: work / name, "both", "both")
    print()
    print("verdict: " + ("passes; both becomes the declared matcher" if not failures else "fails: " + "; ".join(failures)))


if __name__ == "__main__":
    main()
