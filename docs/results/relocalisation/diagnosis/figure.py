#!/usr/bin/env python3
"""One far query as each method matched it: the query image with every 2D-3D match drawn at its keypoint,
green when the landmark projects within the precision radius under the true pose, red otherwise; the
estimator's inliers ringed. From the match dumps of ../validation/run.sh (`eval reloc --dump-matches`).

    python figure.py --dumps OUT/matches/llff-goldcape --frame 040 --methods SConE,FREAK,SIFT --out fig.jpg
(run with the training environment's Python, which has matplotlib.)
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dumps", required=True, type=Path)
    ap.add_argument("--frame", required=True)
    ap.add_argument("--methods", default="SConE,FREAK,SIFT", help="as the reports name them")
    ap.add_argument("--out", required=True, type=Path)
    args = ap.parse_args()
    methods = args.methods.split(",")
    fig, axes = plt.subplots(1, len(methods), figsize=(6.5 * len(methods), 7))
    for ax, method in zip(axes if len(methods) > 1 else [axes], methods):
        d = json.load(open(args.dumps / f"{method}--{args.frame}.json"))
        image = plt.imread(d["image"])
        ax.imshow(image, cmap="gray" if image.ndim == 2 else None)
        matches = d["matches"]
        inliers = set(d["inliers"])
        for ok, colour in ((False, "#e0301e"), (True, "#21c24a")):
            pts = [m for m in matches if m["correct"] == ok]
            ax.scatter([m["x"] for m in pts], [m["y"] for m in pts], s=9, c=colour, linewidths=0,
                       label=f"{'correct' if ok else 'wrong'}: {len(pts)}")
        ring = [matches[i] for i in inliers if i < len(matches)]
        if ring:
            ax.scatter([m["x"] for m in ring], [m["y"] for m in ring], s=40, facecolors="none",
                       edgecolors="#ffd400", linewidths=0.8, label=f"estimator's inliers: {len(ring)}")
        g = d["diagnosis"]
        ax.set_title(
            f"{method}: {len(matches)} matches, "
            f"{sum(m['correct'] for m in matches)} correct; lost at: {g['lost_at']}\n"
            f"reachable in map {g['reachable_map']}, among candidates {g['reachable_candidates']}, "
            f"true inliers {g['true_inliers']}",
            fontsize=10,
        )
        ax.legend(loc="lower right", fontsize=8, framealpha=0.8)
        ax.set_axis_off()
    fig.suptitle(f"{d['scene']}, query {d['frame']}: 2D-3D matches against the far map", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80, **({"pil_kwargs": {"quality": 85}} if args.out.suffix == ".jpg" else {}))


if __name__ == "__main__":
    main()
