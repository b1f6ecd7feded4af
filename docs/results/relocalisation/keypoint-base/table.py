#!/usr/bin/env python3
"""The detector x descriptor table (README.md beside this file) from `scone eval reloc` reports with diagnoses.

Per method over all the reports given: queries placed within (0.25 scene units, 2 deg), the stage every other
query was lost at (`src/offline/eval/reloc/diagnose.rs`), the scenes' own landmarks in the maps, and for the far
queries (20-40 deg from the most similarly oriented map keyframe, the report's bin): how many, how many placed,
the median of the query keypoints some map landmark projects to under the true pose, correct / all 2D-3D
matches given to PnP, and their precision.

    python3 docs/results/relocalisation/keypoint-base/table.py REPORT.json...
"""

import collections
import json
import statistics
import sys

ORDER = ["freak", "dog-freak", "fast-sift", "sift"]
STAGES = ["map", "candidates", "matching", "estimator", "floor", "wrong-pose"]
FAR = (20.0, 40.0)


def main():
    rows = collections.defaultdict(lambda: collections.defaultdict(list))
    for path in sys.argv[1:]:
        report = json.load(open(path))
        scale = report["config"].get("unit_scale", 1.0)
        for s in report["summaries"]:
            if s.get("stage1_cap") is None and s.get("pnp") is None:
                rows[s["method"]]["landmarks"].append(s["scene_landmarks"])
        for method, rec in report["queries"]:
            if rec.get("stage1_cap") is not None or rec.get("pnp") is not None:
                continue
            rec["placed"] = rec["translation_error"] is not None and (
                rec["translation_error"] <= 0.25 * scale and rec["rotation_error_deg"] <= 2.0)
            rows[method]["queries"].append(rec)
    print("| method | placed / queries | " + " | ".join(f"lost at {s}" for s in STAGES)
          + " | scene landmarks | far queries: placed / all | far: median reachable in map | far: correct / all "
          "matches | far: precision |")
    print("|---" * (len(STAGES) + 7) + "|")
    for method in [m for m in ORDER if m in rows] + sorted(set(rows) - set(ORDER)):
        recs = rows[method]["queries"]
        lost = collections.Counter((r.get("diagnosis") or {}).get("lost_at") for r in recs)
        far = [r for r in recs if FAR[0] <= r["angle_to_map_deg"] < FAR[1]]
        reach = [r["diagnosis"]["reachable_map"] for r in far if r.get("diagnosis")]
        correct, matches = sum(r["correct_matches"] for r in far), sum(r["matches"] for r in far)
        cells = [
            f"{sum(r['placed'] for r in recs)} / {len(recs)}",
            *(str(lost[s]) for s in STAGES),
            f"{sum(rows[method]['landmarks']):,}",
            f"{sum(r['placed'] for r in far)} / {len(far)}",
            f"{statistics.median(reach):.0f}" if reach else "-",
            f"{correct:,} / {matches:,}",
            f"{correct / max(matches, 1):.3f}",
        ]
        print(f"| {method} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
