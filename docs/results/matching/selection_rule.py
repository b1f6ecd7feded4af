#!/usr/bin/env python3
"""Applies the rule that chose the shipped model (written in docs/model-experiments.md) to the reports of score.sh.

    python3 docs/results/matching/selection_rule.py [--work $SCONE_PREFIX/work/i39] ring-e1 ring-e1-real

A (model, matcher) pair passes when (1) its mean AUC@10 over the five real selection parts is at least FREAK's +
0.01 and at least the shipped model's (scale-aware) on the same keypoints; (2) its share of warp pairs within 5 px
is at least FREAK's over all pairs and not more than 0.05 below FREAK's over the zoom 1.6-2.5x pairs; (3) within
5 px it is at least FREAK's - 0.02 in every zoom bin up to 2.5x and every rotation bin of at least 10 pairs.
Among the pairs that pass the highest mean ships; within 0.005 of it, the simpler matcher. Standard library only.
"""

import argparse
import json
import os
from pathlib import Path

PARTS = [
    "strecha-castle-P30-sel",
    "7scenes-redkitchen-sel",
    "sun3d-studyroom-sel",
    "middlebury-templeRing-sel",
    "liberty-internet-sel",
]
MATCHERS = ["plain", "union", "rerank", "scale-aware"]  # simplest first: the rule's order for ties
ZOOM_BINS = ["1-1.25x", "1.25-1.6x", "1.6-2x", "2-2.5x"]
WITHIN_5PX = 1  # index of the 5 px threshold in a summary's "within"


def summary(entries, method):
    return next(s for s in entries if s["method"] == method)


def pair_means(directory, matcher):
    """Mean AUC@10 of SConE (with the matcher) and of FREAK over the five parts, and each part's."""
    scone, freak = [], []
    for part in PARTS:
        report = json.loads((directory / f"pairs-{matcher}-{part}.json").read_text())
        scone.append(summary(report["summaries"], "scone")["auc10"])
        freak.append(summary(report["summaries"], "freak")["auc10"])
    return sum(scone) / len(scone), sum(freak) / len(freak), scone, freak


def warp_figures(directory, matcher):
    """Within 5 px over all pairs, over zoom 1.6-2.5x, and per bin, for SConE and FREAK."""
    report = json.loads((directory / f"warps-{matcher}.json").read_text())
    overall = {m: summary(report["summaries"], m)["within"][WITHIN_5PX] for m in ("scone", "freak")}
    bins = []
    zoomed = {"scone": [0.0, 0], "freak": [0.0, 0]}
    for b in report["bins"]:
        if b["axis"] not in ("zoom", "rotation"):
            continue
        row = {"axis": b["axis"], "label": b["label"]}
        for m in ("scone", "freak"):
            s = summary(b["summaries"], m)
            row[m] = s["within"][WITHIN_5PX]
            row["pairs"] = s["pairs"]
            if b["axis"] == "zoom" and b["label"] in ("1.6-2x", "2-2.5x"):
                zoomed[m][0] += s["within"][WITHIN_5PX] * s["pairs"]
                zoomed[m][1] += s["pairs"]
        bins.append(row)
    zoom = {m: (v[0] / v[1] if v[1] else float("nan")) for m, v in zoomed.items()}
    return overall, zoom, bins


def warp_failures(overall, zoom, bins):
    """Criteria 2 and 3 (the warps) on `warp_figures`' output: what fails, as sentences."""
    failures = []
    if overall["scone"] < overall["freak"]:
        failures.append(f"warps {overall['scone']:.3f} < FREAK {overall['freak']:.3f}")
    if zoom["scone"] < zoom["freak"] - 0.05:
        failures.append(f"zoom 1.6-2.5x {zoom['scone']:.3f} < FREAK {zoom['freak']:.3f} - 0.05")
    for b in bins:
        checked = (b["axis"] == "zoom" and b["label"] in ZOOM_BINS) or (
            b["axis"] == "rotation" and b["pairs"] >= 10
        )
        if checked and b["scone"] < b["freak"] - 0.02 - 1e-9:
            failures.append(f"{b['axis']} {b['label']} {b['scone']:.2f} < FREAK {b['freak']:.2f} - 0.02")
    return failures


def judge(directory, matcher, shipped_mean):
    mean, freak_mean, parts, _ = pair_means(directory, matcher)
    overall, zoom, bins = warp_figures(directory, matcher)
    failures = []
    if mean < freak_mean + 0.01:
        failures.append(f"pairs {mean:.4f} < FREAK {freak_mean:.4f} + 0.01")
    if mean < shipped_mean:
        failures.append(f"pairs {mean:.4f} < shipped {shipped_mean:.4f}")
    failures += warp_failures(overall, zoom, bins)
    return {
        "matcher": matcher,
        "mean": mean,
        "freak_mean": freak_mean,
        "parts": parts,
        "warps": overall,
        "zoom": zoom,
        "failures": failures,
    }


def table_header():
    return ("| model | matcher | " + " | ".join(PARTS) + " | mean AUC@10 | FREAK | warps 5 px (FREAK) "
            "| zoom 1.6-2.5x (FREAK) | verdict |\n" + "|" + "---|" * (len(PARTS) + 7))


def table_row(model, r, verdict):
    return (f"| {model} | {r['matcher']} | " + " | ".join(f"{p:.3f}" for p in r["parts"])
            + f" | **{r['mean']:.4f}** | {r['freak_mean']:.4f}"
            + f" | {r['warps']['scone']:.3f} ({r['warps']['freak']:.3f})"
            + f" | {r['zoom']['scone']:.3f} ({r['zoom']['freak']:.3f}) | {verdict} |")


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/i39"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("models", nargs="+")
    args = parser.parse_args()
    shipped_mean, _, _, _ = pair_means(args.work / "shipped-e1", "scale-aware")
    print(f"shipped model (scale-aware) mean AUC@10 on the same keypoints: {shipped_mean:.4f}\n")
    print(table_header())
    passing = []
    for model in args.models:
        for matcher in MATCHERS:
            try:
                r = judge(args.work / model, matcher, shipped_mean)
            except FileNotFoundError as missing:
                print(f"| {model} | {matcher} | not scored ({Path(missing.filename).name}) |")
                continue
            verdict = "passes" if not r["failures"] else "fails: " + "; ".join(r["failures"])
            if not r["failures"]:
                passing.append((model, r))
            print(table_row(model, r, verdict))
    if not passing:
        print("\nNo pair passes: nothing ships.")
        return
    best = max(r["mean"] for _, r in passing)
    near = [(m, r) for m, r in passing if r["mean"] >= best - 0.005]
    model, r = min(near, key=lambda mr: MATCHERS.index(mr[1]["matcher"]))
    print(f"\nShips: {model} with {r['matcher']} (mean AUC@10 {r['mean']:.4f}; best passing {best:.4f}).")


if __name__ == "__main__":
    main()
