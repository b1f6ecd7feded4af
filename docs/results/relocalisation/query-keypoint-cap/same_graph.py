#!/usr/bin/env python3
"""Applies the rule for stage 1's caps compared on one graph (docs/history/benchmarks-log.md, "Caps compared on
one graph") to the reports of `run.sh` (or of the selection scenes' run) with `ALSO_CAPS` (one report per scene,
every keypoint and each cap on the same map).

    python3 docs/results/relocalisation/query-keypoint-cap/same_graph.py RUN_DIR [SCENE ...]

Prints one table row per configuration (queries within (0.25 m, 2°) / within (0.5 m, 5°), mean query time),
the verdict per cap under the selection rule (each count at least every keypoint's on every scene, no foreign
frame), and the validation bar (each count within one query of every keypoint's). Standard library only.
"""

import json
import sys
from pathlib import Path

from fallback import summary_figures  # the figures the fallback's rule read

SELECTION = ["strecha-castle-P30", "templeRing-1-31", "7scenes-redkitchen-sel", "sun3d-studyroom-sel", "liberty-internet-sel"]


def main():
    run = Path(sys.argv[1])
    scenes = sys.argv[2:] or SELECTION
    rows = {}
    for scene in scenes:
        (path,) = run.glob(f"same-graph*--{scene}.json")
        for s in json.loads(path.read_text())["summaries"]:
            rows.setdefault(s.get("stage1_cap"), []).append(summary_figures(s))
    ref = rows.pop(None)
    print("| stage 1 searches | " + " | ".join(f"{s} ({f['queries']})" for s, f in zip(scenes, ref)) + " | score | foreign localised |")
    print("|---" * (len(scenes) + 3) + "|")

    def row(label, figs):
        cells = [f"{f['near']} / {f['wide']}, {f['ms']:.0f} ms" for f in figs]
        score = sum(f["near"] + f["wide"] for f in figs)
        foreign = f"{sum(f['foreign'] for f in figs)} of {sum(f['foreign_queries'] for f in figs)}"
        print(f"| {label} | " + " | ".join(cells) + f" | {score} | {foreign} |")

    row("every keypoint", ref)
    verdicts = []
    for cap in sorted(rows, reverse=True):
        figs = rows[cap]
        row(f"{cap}, on the same map", figs)
        below = [f"{s} {f['near']}/{f['wide']} < {r['near']}/{r['wide']}" for s, f, r in zip(scenes, figs, ref)
                 if f["near"] < r["near"] or f["wide"] < r["wide"]]
        foreign = [f"{s}: {f['foreign']} foreign localised" for s, f in zip(scenes, figs) if f["foreign"]]
        beyond_one = [s for s, f, r in zip(scenes, figs, ref) if f["near"] < r["near"] - 1 or f["wide"] < r["wide"] - 1]
        verdicts.append((cap, below + foreign))
        print(f"<!-- K = {cap}: selection rule {'passes' if not below + foreign else 'fails: ' + '; '.join(below + foreign)};"
              f" validation bar (within one query, no foreign) {'met' if not beyond_one + foreign else 'missed: ' + ', '.join(beyond_one + foreign)} -->")
    passing = sorted(k for k, fails in verdicts if not fails)
    print(f"\nK chosen by the selection rule: {passing[0] if passing else 'none (the default stays every keypoint)'}")


if __name__ == "__main__":
    main()
