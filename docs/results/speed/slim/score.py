#!/usr/bin/env python3
"""Applies RULE.md beside this file to the reports of the shipped model and of the slim candidates.

    python3 docs/results/speed/slim/score.py [--validation] SHIPPED_DIR CANDIDATE_DIR [CANDIDATE_DIR ...]

Each directory holds `docs/results/matching/score.sh`'s reports of one model (matcher `union`) and, beside it,
`reloc-<name>` with the arcs' relocalisation (`docs/results/training/orbits/run.sh`; with `--validation`, the
validation scenes' far-map reports of `docs/results/relocalisation/validation/run.sh`). Prints each criterion's
figures and the verdicts; exits 0. Standard library only.
"""

import importlib.util
import json
from pathlib import Path

# The int8 rule's readers of the pair and warp reports (a file of the same name, so loaded by its path).
_spec = importlib.util.spec_from_file_location("int8_score", Path(__file__).resolve().parent.parent / "int8" / "score.py")
_int8 = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_int8)
aucs, seed_spread, warp_bins = _int8.aucs, _int8.seed_spread, _int8.warp_bins


def reloc(directory):
    """Far-map queries within (0.25 units, 2 degrees) and foreign frames localised by SConE, per scene."""
    out = {}
    for f in sorted(directory.glob("far--*.json")):
        for s in json.loads(f.read_text())["summaries"]:
            if s["method"] == "scone":
                out[f.name[len("far--"):-len(".json")]] = (round(s["within_025m_2deg"] * s["queries"]), s["foreign_localised"])
    return out


def selection_tolerance(spread, part):
    """RULE.md's allowed shortfall of a selection part: max(0.005, 2 sqrt(2) se), `spread` from `seed_spread`."""
    return max(0.005, 2 * 2 ** 0.5 * spread[part][1])


def judge(shipped, cand, validation):
    sa, ca, spread = aucs(shipped), aucs(cand), seed_spread(shipped)

    def allowed(part):
        tolerance = 0.005 if validation else selection_tolerance(spread, part)
        return tolerance, f"{tolerance:.4f}"

    failures = _int8.part_failures(sa, ca, allowed, "allowed shortfall", lambda part: f"{allowed(part)[0]:.4f}")
    ms, mc = sum(sa.values()) / len(sa), sum(ca.get(p, 0.0) for p in sa) / len(sa)
    print(f"| **mean** | {ms:.4f} | {mc:.4f} | {mc - ms:+.4f} | {'' if validation else '0.0050'} |\n")
    if not validation and mc < ms - 0.005 - 1e-9:
        failures.append(f"mean AUC@10 {mc:.4f} < shipped {ms:.4f} - 0.005")

    sw, cw = warp_bins(shipped), warp_bins(cand)
    least = 1.0 if validation else 0.95
    print("| warps | pairs | within 5 px shipped | candidate | correct matches shipped | candidate |\n|---|---|---|---|---|---|")
    for k, (w, n, pairs) in sw.items():
        if k not in cw:
            failures.append(f"warps {k} not scored")
            continue
        cwk, cnk, _ = cw[k]
        print(f"| {k} | {pairs} | {w:.3f} | {cwk:.3f} | {n:.1f} | {cnk:.1f} |")
        if k == "all" and not validation and cwk < w - 0.01 - 1e-9:
            failures.append(f"warps within 5 px {cwk:.3f} < shipped {w:.3f} - 0.01")
        if cnk < least * n - 1e-9:
            failures.append(f"warps {k} correct matches {cnk:.1f} < {least:.2f} x shipped {n:.1f}")

    rs, rc = reloc(shipped.parent / f"reloc-{shipped.name}"), reloc(cand.parent / f"reloc-{cand.name}")
    print("\n| far-map queries localised | " + " | ".join(rs) + " | sum | foreign |\n|---|" + "---|" * (len(rs) + 2))
    for label, r in (("shipped", rs), ("candidate", rc)):
        counts = [r.get(s, (0, 0))[0] for s in rs]
        print(f"| {label} | " + " | ".join(map(str, counts)) + f" | {sum(counts)} | {sum(f for _, f in r.values())} |")
    missing = [s for s in rs if s not in rc]
    if missing:
        failures.append("relocalisation not run on " + ", ".join(missing))
    total_s, total_c = sum(c for c, _ in rs.values()), sum(c for c, _ in rc.values())
    slack = 0 if validation else 1
    if total_c < total_s - slack:
        failures.append(f"far-map queries localised {total_c} < shipped {total_s}" + (" - 1" if slack else ""))
    if any(f for _, f in rc.values()):
        failures.append("a foreign frame localised")
    return failures


if __name__ == "__main__":
    _int8.run(judge)
