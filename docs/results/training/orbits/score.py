#!/usr/bin/env python3
"""Applies RULE.md beside this file to the reports of the candidate and of the shipped model.

    python3 docs/results/training/orbits/score.py [--work $SCONE_PREFIX/work/orbits] CANDIDATE

Reads `WORK/shipped` and `WORK/CANDIDATE` (pairs and warps, `docs/results/matching/score.sh` with `ORBITS=1`)
and `WORK/reloc-shipped` and `WORK/reloc-CANDIDATE` (`run.sh`), and prints each criterion with its figures and
the verdict of criteria 1-3. Standard library only.
"""

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "matching"))
from selection_rule import PARTS, summary, warp_failures, warp_figures  # noqa: E402

ORBITS = ["llff-ethiopianhead-sel", "llff-blowtorch-sel", "llff-lemontea-office-sel", "turntable-squirrel-sel"]


def aucs(directory):
    """SConE's (union) AUC@10 on each of the nine parts."""
    out = {}
    for part in PARTS + ORBITS:
        report = json.loads((directory / f"pairs-union-{part}.json").read_text())
        out[part] = summary(report["summaries"], "scone")["auc10"]
    return out


def reloc(directory):
    """Queries within (0.25, 2 degrees) and foreign frames localised, per arc, by method."""
    out = {}
    for arc in ORBITS:
        report = json.loads((directory / f"far--{arc}.json").read_text())
        for s in report["summaries"]:
            out.setdefault(s["method"], {})[arc] = s
    return out


def within(s):
    return round(s["within_025m_2deg"] * s["queries"])


def mean(values):
    return sum(values) / len(values)


def main():
    default = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone")) / "work/orbits"
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=default)
    parser.add_argument("candidate")
    args = parser.parse_args()
    shipped, cand = aucs(args.work / "shipped"), aucs(args.work / args.candidate)
    failures = []

    print("| part | shipped | candidate |\n|---|---|---|")
    for part in PARTS + ORBITS:
        print(f"| {part} | {shipped[part]:.3f} | {cand[part]:.3f} |")
    m9 = (mean(list(shipped.values())), mean(list(cand.values())))
    m5 = (mean([shipped[p] for p in PARTS]), mean([cand[p] for p in PARTS]))
    print(f"| **mean of nine** | {m9[0]:.4f} | {m9[1]:.4f} |\n| mean of the five | {m5[0]:.4f} | {m5[1]:.4f} |")
    if m9[1] < m9[0] + 0.010:
        failures.append(f"1: nine-part mean {m9[1]:.4f} < shipped {m9[0]:.4f} + 0.010")
    if m5[1] < m5[0] - 0.005:
        failures.append(f"1: five-part mean {m5[1]:.4f} < shipped {m5[0]:.4f} - 0.005")

    overall, zoom, bins = warp_figures(args.work / args.candidate, "union")
    print(f"\nwarps within 5 px: candidate {overall['scone']:.3f}, FREAK {overall['freak']:.3f}; "
          f"zoom 1.6-2.5x {zoom['scone']:.3f} (FREAK {zoom['freak']:.3f})")
    failures += ["2: " + f for f in warp_failures(overall, zoom, bins)]

    rs, rc = reloc(args.work / "reloc-shipped"), reloc(args.work / f"reloc-{args.candidate}")
    rows = {"SConE, shipped": rs["scone"], "SConE, candidate": rc["scone"], "FREAK": rs["freak"], "SIFT": rs["sift"]}
    print("\n| method | " + " | ".join(ORBITS) + " | sum | foreign localised |\n|---|" + "---|" * (len(ORBITS) + 2))
    sums = {}
    for name, per_arc in rows.items():
        counts = [within(per_arc[a]) for a in ORBITS]
        foreign = sum(per_arc[a]["foreign_localised"] for a in ORBITS)
        sums[name] = (sum(counts), foreign)
        print(f"| {name} | " + " | ".join(str(c) for c in counts) + f" | {sum(counts)} | {foreign} |")
    if sums["SConE, candidate"][0] < sums["SConE, shipped"][0]:
        failures.append(f"3: arcs {sums['SConE, candidate'][0]} < shipped {sums['SConE, shipped'][0]}")
    if sums["SConE, candidate"][1] or sums["SConE, shipped"][1]:
        failures.append("3: a foreign frame localised")

    print("\n" + ("passes criteria 1-3: run the validation scenes once (criterion 4)" if not failures
                  else "fails:\n- " + "\n- ".join(failures)))


if __name__ == "__main__":
    main()
