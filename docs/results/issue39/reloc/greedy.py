#!/usr/bin/env python3
"""Issue 39, step 4: applies issue 27's greedy rule for the staged pipeline to `sel.sh`'s reports (BENCHMARKS.md,
"Issue 39, step 4: relocalisation chosen again").

    python3 docs/results/issue39/reloc/greedy.py RUN_DIR

Score of a configuration: over the five selection scenes, SConE's queries within (0.25 m, 2°) plus those within
(0.5 m, 5°). From stage 1 alone, the parts are added in the order stage 2 (`candidates`), FREAK's join
(`freak`, which implies stage 2), stage 3 (`guided`), map building with the known poses (`build`); a part is
kept when it raises the score of the configuration so far by at least one and no foreign frame is localised
(a tie keeps the configuration without it). Prints every configuration's row and the path. Standard library only.
"""

import json
import sys
from pathlib import Path

SCENES = ["strecha-castle-P30", "templeRing-1-31", "7scenes-redkitchen-sel", "sun3d-studyroom-sel", "liberty-internet-sel"]
ORDER = ["candidates", "freak", "guided", "build"]


def name(parts):
    """The `--stages` value of a set of parts (`freak` stands for stage 2 with FREAK's join)."""
    parts = set(parts)
    if "freak" in parts:
        parts.discard("candidates")
    return ",".join(p for p in ORDER if p in parts) or "none"


def row(run, cfg):
    cells = []
    for scene in SCENES:
        s = json.loads((run / f"{cfg}--{scene}.json").read_text())["summaries"][0]
        n = s["queries"]
        cells.append((round(s["within_025m_2deg"] * n), round(s["within_05m_5deg"] * n), n, s["foreign_localised"],
                      s["landmarks"], s["match_precision"], s["mean_query_ms"]))
    return cells


def main():
    run = Path(sys.argv[1])
    rows = {}
    for path in sorted(run.glob("*--strecha-castle-P30.json")):
        cfg = path.name.split("--")[0]
        rows[cfg] = row(run, cfg)
    print("| configuration | " + " | ".join(f"{s} ({c[2]})" for s, c in zip(SCENES, rows["none"])) + " | score | foreign localised |")
    print("|---" * (len(SCENES) + 3) + "|")
    score = {cfg: sum(c[0] + c[1] for c in cells) for cfg, cells in rows.items()}
    foreign = {cfg: sum(c[3] for c in cells) for cfg, cells in rows.items()}
    for cfg, cells in rows.items():
        text = " | ".join(f"{c[0]}/{c[1]} ({c[4]:,} lm, {c[5]:.2f}, {c[6]:.0f} ms)" for c in cells)
        print(f"| {cfg} | {text} | {score[cfg]} | {foreign[cfg]} |")
    kept = []
    path = [f"none {score['none']}"]
    for part in ORDER:
        cfg = name(kept + [part])
        if cfg not in rows:
            print(f"\nmissing configuration {cfg}: run sel.sh with it")
            return
        now = name(kept)
        verdict = score[cfg] >= score[now] + 1 and foreign[cfg] == 0
        path.append(f"+{part} -> {cfg} {score[cfg]} ({'kept' if verdict else 'dropped'})")
        if verdict:
            kept.append(part)
    print("\n" + "; ".join(path))
    print(f"\nchosen: {name(kept)}")


if __name__ == "__main__":
    main()
