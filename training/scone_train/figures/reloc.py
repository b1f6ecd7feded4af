"""Relocalisation success against distance to the map, from `scone eval reloc --map-block ... --json` reports.

One panel per scene: the share of queries localised within (0.25 m, 2 deg) (thresholds times the report's
unit scale) per bin of baseline to the nearest map camera (a share of the scene's camera path), one line per
method. Reports of one pipeline: solid without distractors and dashed with them. Reports of both pipelines
(issue 27: stage 1 alone, `--stages none`, against the staged defaults): solid for the staged pipeline and
dashed for stage 1 alone. Usage:

    python -m scone_train.figures.reloc --out ../docs/figures/reloc-far-map.png REPORT.json...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

COLOURS = {"SConE": "tab:blue", "FREAK": "tab:orange", "SIFT": "tab:green"}
NAMES = {"scone": "SConE", "freak": "FREAK", "sift": "SIFT"}
# Methods side by side on the categorical axis, so equal values stay visible.
SHIFT = {"SConE": -0.08, "FREAK": 0.0, "SIFT": 0.08}
# Baseline to the nearest map camera centre as a share of the scene's camera path extent.
BASELINE_BINS = [0.0, 0.05, 0.1, 0.25]
BIN_LABELS = ["<5%", "5-10%", "10-25%", ">25%"]


def pipeline(report: dict) -> str:
    """Which relocalisation pipeline a report ran: the staged one of issue 27, or stage 1 alone."""
    localize = report["config"].get("localize", {})
    stages = localize.get("candidate_matching") or localize.get("guided_search")
    return "staged" if stages else "stage 1 alone"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("reports", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    by_scene: dict[str, list[dict]] = {}
    for path in args.reports:
        report = json.loads(path.read_text())
        by_scene.setdefault(report["scene"], []).append(report)
    staged = {pipeline(r) for rs in by_scene.values() for r in rs}
    scenes = sorted(by_scene)
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for report in sorted(by_scene[scene], key=lambda r: (r["config"]["distractor_observations"], pipeline(r))):
            scale = report["config"].get("unit_scale", 1.0)
            extent = report["path_extent"]
            for s in report["summaries"]:
                method = NAMES.get(s["method"], s["method"])
                # A report of `eval reloc --also-caps` holds each cap's queries beside the configuration's own.
                cap = s.get("stage1_cap")
                records = [q for m, q in report["queries"] if m == s["method"] and q.get("stage1_cap") == cap]
                xs, ys = [], []
                for i, (lo, hi) in enumerate(zip(BASELINE_BINS, BASELINE_BINS[1:] + [float("inf")])):
                    inside = [q for q in records if lo <= q["baseline_to_map"] / extent < hi]
                    if inside:
                        ok = [q["translation_error"] is not None and q["translation_error"] <= 0.25 * scale
                              and q["rotation_error_deg"] <= 2.0 for q in inside]
                        xs.append(i + SHIFT.get(method, 0.0))
                        ys.append(sum(ok) / len(ok))
                distractors = s["distractor_observations"]
                if len(staged) > 1:
                    dashed = pipeline(report) == "stage 1 alone"
                    label = f"{method}, {pipeline(report)}"
                else:
                    dashed = distractors > 0
                    label = method + ("" if distractors == 0 else f" + {distractors / 1000:.0f}k distractors")
                # Dashed lines a little to the right, so a line that equals the solid one stays visible.
                xs = [x + (0.03 if dashed else 0.0) for x in xs]
                ax.plot(xs, ys, marker="o" if not dashed else "s", color=COLOURS.get(method, "grey"),
                        linestyle="--" if dashed else "-", label=label, markersize=5)
        ax.set_xticks(range(len(BASELINE_BINS)), BIN_LABELS)
        queries = by_scene[scene][0]["summaries"][0]["queries"]
        ax.set_title(f"{scene} ({queries} queries, path {by_scene[scene][0]['path_extent']:.1f})", fontsize=10)
        ax.set_xlabel("baseline to the nearest map camera / path extent")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("localised within (0.25 m, 2 deg)")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    distractors = {r["config"]["distractor_observations"] for rs in by_scene.values() for r in rs}
    extra = f", {max(distractors) / 1000:.0f}k distractor observations" if len(staged) > 1 and max(distractors) else ""
    fig.suptitle(f"Map: the first half of each scene; queries: the rest{extra}", fontsize=11)
    fig.tight_layout(rect=(0, 0.12, 1, 0.95))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
