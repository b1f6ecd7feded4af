#!/usr/bin/env python3
"""The picture of README.md beside this file: 2D-3D match precision against the query's angle to the nearest
map view, per method (detector x descriptor), pooled over the reports given.

    python3 docs/results/relocalisation/keypoint-base/figure.py OUT.png REPORT.json...

(needs matplotlib: `$SCONE_PREFIX/venv-train/bin/python`).
"""

import collections
import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

BINS = [(0, 10), (10, 20), (20, 40), (40, 180)]
STYLE = {  # detector by colour, descriptor by line
    "freak": ("FAST + FREAK", "tab:blue", "-"),
    "fast-sift": ("FAST + SIFT descriptor", "tab:blue", "--"),
    "dog-freak": ("DoG + FREAK", "tab:orange", "-"),
    "sift": ("DoG + SIFT descriptor (SIFT)", "tab:orange", "--"),
}


def main():
    out, paths = sys.argv[1], sys.argv[2:]
    sums = collections.defaultdict(lambda: [[0, 0, 0] for _ in BINS])
    for path in paths:
        for method, rec in json.load(open(path))["queries"]:
            if rec.get("stage1_cap") is not None or rec.get("pnp") is not None:
                continue
            for i, (lo, hi) in enumerate(BINS):
                if lo <= rec["angle_to_map_deg"] < hi:
                    sums[method][i][0] += rec["correct_matches"]
                    sums[method][i][1] += rec["matches"]
                    sums[method][i][2] += 1
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    xs = range(len(BINS))
    for method, (label, colour, line) in STYLE.items():
        if method not in sums:
            continue
        ys = [c / m if m else float("nan") for c, m, _ in sums[method]]
        ax.plot(xs, ys, line, color=colour, marker="o", label=label)
    counts = [sums["freak"][i][2] for i in xs] if "freak" in sums else [0] * len(BINS)
    ax.set_xticks(list(xs), [(f"{lo}-{hi}°" if hi < 180 else f"{lo}°+") + f"\n({n} queries)" for (lo, hi), n in zip(BINS, counts)])
    ax.set_xlabel("query's angle to the most similarly oriented map view")
    ax.set_ylabel("correct / all 2D-3D matches")
    ax.set_ylim(0, None)
    ax.grid(alpha=0.3)
    ax.legend(frameon=False)
    ax.set_title("Far-map protocol, 100k distractors, training scenes: match precision", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=120)


if __name__ == "__main__":
    main()
