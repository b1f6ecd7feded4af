#!/usr/bin/env python3
"""Where each far query is lost, from `scone eval reloc` reports with diagnoses (../validation/run.sh).

Prints, per scene, every query that SIFT places within (0.25, 2 deg) and SConE does not, with the counts down
the pipeline for both (reachable in the map / among the candidates, stage 1's correct matches, correct / all
matches, true inliers, the estimator's inliers without the floor) and the stage SConE lost it at; then, for every
method, how many queries each stage lost over all scenes.

    python3 docs/results/relocalisation/diagnosis/table.py REPORT.json...   [--variant none|METHOD:ITERS]
"""

import argparse
import collections
import json


def records(report, variant):
    """method -> frame -> record, for the rows of the configuration's own estimator (or one of also_pnp)."""
    out = collections.defaultdict(dict)
    for method, rec in report["queries"]:
        pnp = rec.get("pnp")
        tag = "none" if pnp is None else f"{pnp['method']}:{pnp['max_iters']}"
        if rec.get("stage1_cap") is None and tag == variant:
            out[method][rec["frame"]] = rec
    return out


def placed(rec, scale):
    t = rec["translation_error"]
    return t is not None and t <= 0.25 * scale and rec["rotation_error_deg"] <= 2.0


def counts(rec):
    d = rec.get("diagnosis") or {}
    return (
        f"{d.get('reachable_map', '-')} / {d.get('reachable_candidates', '-')} | {d.get('stage1_correct', '-')} | "
        f"{rec['correct_matches']} / {rec['matches']} | {d.get('true_inliers', '-')} | {d.get('unfloored_inliers', '-')}"
    )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--variant", default="none")
    args = ap.parse_args()
    lost = collections.defaultdict(collections.Counter)
    print("| scene | query | angle to map (deg) | SConE: reachable map / candidates \\| stage-1 correct \\| correct / all "
          "matches \\| true inliers \\| estimator's inliers without the floor | SConE lost at | SIFT: same counts |")
    print("|---|---|---|---|---|---|")
    for path in args.reports:
        report = json.load(open(path))
        scale = report["config"].get("unit_scale", 1.0)
        by = records(report, args.variant)
        for method, recs in by.items():
            for rec in recs.values():
                d = rec.get("diagnosis")
                if d:
                    lost[method][d["lost_at"]] += 1
        for frame, s in sorted(by.get("sift", {}).items(), key=lambda kv: kv[1]["angle_to_map_deg"]):
            c = by.get("scone", {}).get(frame)
            if c is None or not placed(s, scale) or placed(c, scale):
                continue
            where = (c.get("diagnosis") or {}).get("lost_at", "-")
            print(f"| {report['scene']} | {frame} | {s['angle_to_map_deg']:.1f} | {counts(c)} | **{where}** | {counts(s)} |")
    stages = ["localised", "map", "candidates", "matching", "estimator", "floor", "wrong-pose"]
    print()
    print("| method | " + " | ".join(stages) + " |")
    print("|---" * (len(stages) + 1) + "|")
    for method in sorted(lost):
        print(f"| {method} | " + " | ".join(str(lost[method][s]) for s in stages) + " |")


if __name__ == "__main__":
    main()
