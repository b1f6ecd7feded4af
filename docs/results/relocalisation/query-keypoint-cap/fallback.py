#!/usr/bin/env python3
"""Applies the rule for a capped stage 1 that falls back to every keypoint (docs/history/benchmarks-log.md, "A
capped search that falls back to every keypoint") to the selection scenes' reports; same_graph.py reads its
`summary_figures`.

    python3 docs/results/relocalisation/query-keypoint-cap/fallback.py REFERENCE_DIR RUN_DIR [K ...]

REFERENCE_DIR holds the every-keypoint reports the rule compares with (an earlier run); RUN_DIR holds this
run's, `all--SCENE.json` and `K-fallback100--SCENE.json`. Prints one table row per configuration and the
verdict per K. Standard library only.
"""

import json
import sys
from pathlib import Path

SCENES = ["strecha-castle-P30", "templeRing-1-31", "7scenes-redkitchen-sel", "sun3d-studyroom-sel", "liberty-internet-sel"]


def figures(path):
    return summary_figures(json.loads(path.read_text())["summaries"][0])


def summary_figures(s):
    """Queries within (0.25 m, 2°) and (0.5 m, 5°), mean query time and foreign frames of one summary."""
    n = s["queries"]
    return {
        "near": round(s["within_025m_2deg"] * n),
        "wide": round(s["within_05m_5deg"] * n),
        "ms": s["mean_query_ms"],
        "foreign": s["foreign_localised"],
        "foreign_queries": s["foreign_queries"],
        "queries": n,
    }


def row(label, figs):
    cells = [f"{f['near']} / {f['wide']}, {f['ms']:.0f} ms" for f in figs]
    score = sum(f["near"] + f["wide"] for f in figs)
    foreign = sum(f["foreign"] for f in figs)
    return f"| {label} | " + " | ".join(cells) + f" | {score} | {foreign} of {sum(f['foreign_queries'] for f in figs)} |"


def main():
    reference, run = Path(sys.argv[1]), Path(sys.argv[2])
    caps = sys.argv[3:] or ["400", "200", "100"]
    ref = [figures(reference / f"all--{s}.json") for s in SCENES]
    print("| stage 1 searches | " + " | ".join(SCENES) + " | score | foreign localised |")
    print("|---" * (len(SCENES) + 3) + "|")
    print(row("every keypoint (the reference run)", ref))
    print(row("every keypoint (this run)", [figures(run / f"all--{s}.json") for s in SCENES]))
    verdicts = []
    for k in caps:
        figs = [figures(run / f"{k}-fallback100--{s}.json") for s in SCENES]
        print(row(f"{k}, full search below 100 inliers", figs))
        fails = [
            f"{s} {f['near']}/{f['wide']} < {r['near']}/{r['wide']}"
            for s, f, r in zip(SCENES, figs, ref)
            if f["near"] < r["near"] or f["wide"] < r["wide"]
        ]
        fails += [f"{s}: {f['foreign']} foreign localised" for s, f in zip(SCENES, figs) if f["foreign"]]
        verdicts.append((int(k), fails))
        print(f"<!-- K = {k}: {'passes' if not fails else 'fails: ' + '; '.join(fails)} -->")
    passing = sorted(k for k, fails in verdicts if not fails)
    print(f"\nK chosen by the rule: {passing[0] if passing else 'none (the default stays every keypoint)'}")


if __name__ == "__main__":
    main()
