#!/usr/bin/env python3
"""Every ring model scored with `union` on the selection pairs whose reports are kept in runs/, as one picture
(docs/figures/issue39-ring-runs.png). Runs of the shipped model's network, loss and data mix (its own config, or
the same with another schedule, seed, checkpoint rule or averaged weights; the rerun ring-e1-real-nnp read a
rebuild of the data) are drawn apart from other recipes, so their spread can be read beside the
differences between recipes.

    $SCONE_PREFIX/venv-train/bin/python docs/results/training/ring_runs_figure.py
"""

import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "matching"))
from selection_rule import PARTS, pair_means  # noqa: E402

# (report directory, label, a run of the shipped recipe?)
RUNS = [
    ("runs/ring-e1-real", "ring-e1-real\n(shipped)", True),
    ("runs/ring-e1-real-nnp", "rerun, NN-prec.\ncheckpoint (r5)", True),
    ("runs/ring-e1-real-4k", "4k steps (r8)", True),
    ("runs/ring-e1-real-4k-s1", "4k steps,\nseed 1 (r9)", True),
    ("runs/ring-e1-ema", "4k, averaged (r9)", True),
    ("runs/ring-e1-ema-s1", "4k, averaged,\nseed 1 (r9)", True),
    ("runs/ring-e1-ema-s2", "4k, averaged,\nseed 2 (r9)", True),
    ("runs/ring-e1-real-10k", "own schedule,\nseed 0 again (r12)", True),
    ("runs/ring-e1-real-10k-s1", "own schedule,\nseed 1 (r12)", True),
    ("runs/ring-e1-real-10k-s2", "own schedule,\nseed 2 (r12)", True),
    ("runs/ring-e1-narrow", "narrow (r3)", False),
    ("runs/ring-e1-warps24", "warps24 (r4)", False),
    ("runs/ring-e1-warps24-s4000", "warps24 at\n4,000 (r5)", False),
    ("runs/ring-e1-inv", "ring invariants\n(r8)", False),
    ("runs/ring-e1-real75-ema", "3/4 real views,\naveraged (r10)", False),
    ("runs/ring-e1-real75-ema-s1", "3/4 real, avg.,\nseed 1 (r10)", False),
    ("runs/ring-e1-real75-ema-s2", "3/4 real, avg.,\nseed 2 (r10)", False),
    ("runs/ring-e1-tracks3", "tracks kept (r16)", False),
    ("runs/ring-e1-tracks3-s1", "tracks kept,\nseed 1 (r16)", False),
    ("runs/ring-e1-tracks3-s2", "tracks kept,\nseed 2 (r16)", False),
]
SHOWN = {"strecha-castle-P30-sel": "castle", "7scenes-redkitchen-sel": "redkitchen", "middlebury-templeRing-sel": "templeRing"}


def main():
    rows = [(label, same, *pair_means(HERE / d, "union")) for d, label, same in RUNS]
    freak = rows[0][3]
    fig, axes = plt.subplots(1, 2, figsize=(15, 5.2), gridspec_kw={"width_ratios": [1.1, 1]})
    ax = axes[0]
    for i, (label, same, mean, _, _, _) in enumerate(rows):
        ax.bar(i, mean, color="tab:blue" if same else "tab:gray")
        ax.text(i, mean + 0.002, f"{mean:.3f}", ha="center", fontsize=8)
    ax.axhline(freak, color="tab:red", ls="--", label=f"FREAK {freak:.4f}")
    ax.axhline(rows[0][2] + 0.005, color="k", ls=":", label="the shipped model + 0.005 (one run's bar since round 4)")
    ax.set_xticks(range(len(rows)), [r[0] for r in rows], rotation=60, ha="right", fontsize=8)
    ax.set_ylim(0.26, 0.345)
    ax.set_ylabel("mean AUC@10, five selection parts (union)")
    ax.set_title("Ring models on the selection pairs, rounds 3-16 (13 and 14 scored none)\n(blue: runs of the shipped recipe; grey: other recipes)", fontsize=10)
    ax.legend(fontsize=8, loc="upper left", ncol=2)
    ax = axes[1]
    for j, (part, name) in enumerate(SHOWN.items()):
        k = PARTS.index(part)
        for label, same, _, _, parts, fparts in rows:
            ax.scatter(j + (-0.12 if same else 0.12), parts[k], color="tab:blue" if same else "tab:gray", s=28)
        ax.hlines(rows[0][5][k], j - 0.3, j + 0.3, color="tab:red", ls="--")
    ax.set_xticks(range(len(SHOWN)), list(SHOWN.values()))
    ax.set_ylabel("AUC@10 of the part (3 seeds)")
    ax.set_title("The three parts that decide the mean\n(red: FREAK; SUN3D and liberty are near 0 for every method)", fontsize=10)
    fig.tight_layout()
    out = HERE.parents[1] / "figures" / "issue39-ring-runs.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
