"""Plots of a `scone eval pairs --json` report, like the paper's figures:

* `<scene>-tp-vs-angle.png` (Fig. 3): correct putative matches per pair against the angle between the frames;
* `<scene>-accuracy.png` (Fig. 4): share of pairs with pose error below a threshold, per method;
* `<scene>-speed.png` (Fig. 7-like): AUC@10 against the time per pair (two extractions + descriptions and the
  matching; pose estimation excluded, it is the same estimator for every method).

`python -m scone_train.figures.pairs --report REPORT.json --out DIR`
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

NAMES = {"scone": "SConE", "scone-plain": "SConE (plain)", "freak": "FREAK", "freak-gms": "FREAK+GMS", "orb": "ORB",
         "sift": "SIFT"}


def pair_ms(s: dict) -> float:
    """Time per pair of a method summary: two descriptions and one matching, milliseconds."""
    return 2 * s["describe_ms"] + s["match_ms"]


def plot_report(report: dict, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    scene = report["scene"]
    methods = [s["method"] for s in report["summaries"]]
    paths = []

    fig, ax = plt.subplots(figsize=(6, 4))
    for m in methods:
        recs = sorted((r for r in report["pairs"] if r["method"] == m), key=lambda r: r["angular_distance_deg"])
        ax.plot([r["angular_distance_deg"] for r in recs], [r["correct"] for r in recs], marker="o", ls="none", alpha=0.7, label=NAMES[m])
    ax.set_xlabel("angle between the frames (deg)")
    ax.set_ylabel("correct putative matches")
    ax.set_title(f"{scene}: true positives vs viewpoint change")
    ax.legend()
    fig.tight_layout()
    paths.append(out / f"{scene}-tp-vs-angle.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    thresholds = np.linspace(0, 20, 81)
    for m in methods:
        errs = np.array([e for r in report["pairs"] if r["method"] == m for e in r["errors_deg"]])
        ax.plot(thresholds, [(errs <= t).mean() for t in thresholds], label=NAMES[m])
    ax.set_xlabel("pose error threshold (deg), max(rotation, translation)")
    ax.set_ylabel("share of pairs (all seeds)")
    ax.set_title(f"{scene}: relative pose accuracy")
    ax.legend()
    fig.tight_layout()
    paths.append(out / f"{scene}-accuracy.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    for s in report["summaries"]:
        ax.scatter(pair_ms(s), s["auc10"], s=60)
        ax.annotate(NAMES[s["method"]], (pair_ms(s), s["auc10"]), textcoords="offset points", xytext=(5, 5))
    ax.set_xscale("log")
    ax.set_xlabel("time per pair: 2 x (extract + describe) + match (ms, log)")
    ax.set_ylabel("AUC@10")
    ax.set_title(f"{scene}: accuracy against cost")
    fig.tight_layout()
    paths.append(out / f"{scene}-speed.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return paths


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--report", required=True, nargs="+")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    for r in a.report:
        for p in plot_report(json.loads(Path(r).read_text()), Path(a.out)):
            print(p)


if __name__ == "__main__":
    main()
