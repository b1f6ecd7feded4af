#!/usr/bin/env python3
"""Applies RULE.md to the selection reports of run.sh: per candidate estimator, queries within (0.25 scene
units, 2 deg) per scene and method, the sum S, SConE's sum, foreign frames localised and SConE's mean query
time against the default's; then the rule's verdict.

    python3 docs/results/relocalisation/estimator/score.py REPORT.json...
"""

import collections
import json
import sys

DEFAULT = "epnp:2000"


def tag(summary):
    p = summary.get("pnp")
    return DEFAULT if p is None else f"{p['method']}:{p['max_iters']}"


def main(paths):
    within = collections.defaultdict(int)  # (candidate, method) -> queries
    per_scene = collections.defaultdict(dict)  # candidate -> scene -> "s / f / sift"
    foreign = collections.defaultdict(int)
    ms = collections.defaultdict(list)
    methods = ["scone", "freak", "sift"]
    for path in paths:
        r = json.load(open(path))
        rows = collections.defaultdict(dict)
        for s in r["summaries"]:
            if s.get("stage1_cap") is not None:
                continue
            c, m = tag(s), s["method"]
            n = round(s["within_025m_2deg"] * s["queries"])
            within[c, m] += n
            rows[c][m] = n
            foreign[c] += s["foreign_localised"]
            if m == "scone":
                ms[c].append(s["mean_query_ms"])
        for c, by in rows.items():
            per_scene[c][r["scene"]] = " / ".join(str(by.get(m, "-")) for m in methods)
    cands = sorted(per_scene, key=lambda c: (c != DEFAULT, c))
    scenes = sorted({s for c in cands for s in per_scene[c]})
    print("| estimator | " + " | ".join(scenes) + " | S | SConE | foreign | SConE query ms |")
    print("|---" * (len(scenes) + 5) + "|")
    total = {c: sum(within[c, m] for m in methods) for c in cands}
    mean_ms = {c: sum(ms[c]) / max(len(ms[c]), 1) for c in cands}
    for c in cands:
        print(f"| {c} | " + " | ".join(per_scene[c].get(s, "-") for s in scenes)
              + f" | {total[c]} | {within[c, 'scone']} | {foreign[c]} | {mean_ms[c]:.0f} |")
    print("\n(per scene: SConE / FREAK / SIFT queries within (0.25, 2 deg))\n")
    passing = []
    for c in cands:
        if c == DEFAULT:
            continue
        why = []
        if total[c] < total[DEFAULT] + 5:
            why.append(f"S {total[c]} < {total[DEFAULT]} + 5")
        if within[c, "scone"] < within[DEFAULT, "scone"]:
            why.append("SConE's sum below the default's")
        if foreign[c] > 0:
            why.append(f"{foreign[c]} foreign frames localised")
        if mean_ms[c] > 1.2 * mean_ms[DEFAULT]:
            why.append(f"SConE query time {mean_ms[c] / mean_ms[DEFAULT]:.2f}x the default's")
        print(f"- {c}: " + ("passes" if not why else "fails: " + "; ".join(why)))
        if not why:
            passing.append(c)
    if passing:
        best = max(passing, key=lambda c: (total[c], -mean_ms[c]))
        print(f"\nThe rule chooses {best}.")
    else:
        print(f"\nNo candidate passes: {DEFAULT} stays.")


if __name__ == "__main__":
    main(sys.argv[1:])
