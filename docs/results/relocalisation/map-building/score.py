#!/usr/bin/env python3
"""Applies RULE.md: maps built with their known poses (this folder's run) against the estimator run's maps,
both at the estimator that rule chose.

    python3 docs/results/relocalisation/map-building/score.py --estimator usac-magsac:2000 \\
        --without EST_RUN/far--A.json ... --with BUILD_RUN/far--A.json ...
"""

import argparse
import collections
import json


def totals(paths, estimator):
    """(S, SConE's sum, foreign frames localised, SConE's mean query ms, per-scene rows) at `estimator`."""
    within, foreign, ms, rows = collections.Counter(), 0, [], {}
    for path in paths:
        r = json.load(open(path))
        by = {}
        for s in r["summaries"]:
            p = s.get("pnp")
            tag = "epnp:2000" if p is None else f"{p['method']}:{p['max_iters']}"
            if s.get("stage1_cap") is not None or tag != estimator:
                continue
            n = round(s["within_025m_2deg"] * s["queries"])
            within[s["method"]] += n
            by[s["method"]] = n
            foreign += s["foreign_localised"]
            if s["method"] == "scone":
                ms.append(s["mean_query_ms"])
        rows[r["scene"]] = " / ".join(str(by.get(m, "-")) for m in ("scone", "freak", "sift"))
    return sum(within.values()), within["scone"], foreign, sum(ms) / max(len(ms), 1), rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--estimator", default="epnp:2000")
    ap.add_argument("--without", nargs="+", required=True)
    ap.add_argument("--with", dest="with_", nargs="+", required=True)
    a = ap.parse_args()
    base, built = totals(a.without, a.estimator), totals(a.with_, a.estimator)
    scenes = sorted(base[4])
    print("| maps | " + " | ".join(scenes) + " | S | SConE | foreign | SConE query ms |")
    print("|---" * (len(scenes) + 5) + "|")
    for name, t in (("descriptors alone (today)", base), ("with the known poses", built)):
        print(f"| {name} | " + " | ".join(t[4].get(s, "-") for s in scenes) + f" | {t[0]} | {t[1]} | {t[2]} | {t[3]:.0f} |")
    why = []
    if built[0] < base[0] + 5:
        why.append(f"S {built[0]} < {base[0]} + 5")
    if built[1] < base[1]:
        why.append("SConE's sum falls")
    if built[2] > 0:
        why.append(f"{built[2]} foreign frames localised")
    if built[3] > 1.2 * base[3]:
        why.append(f"SConE query time {built[3] / base[3]:.2f}x")
    print("\n(per scene: SConE / FREAK / SIFT queries within (0.25, 2 deg))\n")
    print("Building with the known poses " + ("passes: it becomes the default." if not why else "fails: " + "; ".join(why)))


if __name__ == "__main__":
    main()
