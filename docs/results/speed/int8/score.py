#!/usr/bin/env python3
"""Applies RULE.md beside this file to the reports of the shipped model and of the int8 candidates.

    python3 docs/results/speed/int8/score.py [--validation] SHIPPED_DIR CANDIDATE_DIR [CANDIDATE_DIR ...]

Each directory holds `docs/results/matching/score.sh`'s reports of one model (matcher `union`): the selection
(`$SCONE_PREFIX/work/orbits/shipped` against `$SCONE_PREFIX/work/i61/NAME`) or the validation scenes
(`SPLIT=validation`, with `--validation`: every scene and the warps, no mean criterion, as RULE.md's validation
stage says). Every part the shipped directory holds is compared; the warps' criteria hold over all pairs and in
each zoom bin up to 2.5x and rotation bin of at least 10 pairs. Prints the figures of each criterion
and the candidates' verdicts; exits 0. Standard library only.
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "matching"))
from selection_rule import WITHIN_5PX, ZOOM_BINS, summary  # noqa: E402


def seed_spread(directory):
    """Per part: the standard deviation over RANSAC seeds of SConE's AUC@10 (the binary's definition: the mean
    of max(0, 1 - error / 10 degrees), failures 180), and the standard error of the seeds' mean."""
    out = {}
    for f in sorted(directory.glob("pairs-union-*.json")):
        pairs = [p for p in json.loads(f.read_text())["pairs"] if p["method"] == "scone"]
        seeds = len(pairs[0]["errors_deg"])
        per = [sum(max(0.0, 1 - (p["errors_deg"][s] if p["errors_deg"][s] is not None else 180.0) / 10) for p in pairs)
               / len(pairs) for s in range(seeds)]
        m = sum(per) / seeds
        sd = (sum((x - m) ** 2 for x in per) / (seeds - 1)) ** 0.5
        out[f.name[len("pairs-union-"):-len(".json")]] = (sd, sd / seeds ** 0.5)
    return out


def aucs(directory):
    """SConE's AUC@10 on each part whose report is in `directory`."""
    return {
        f.name[len("pairs-union-"):-len(".json")]: summary(json.loads(f.read_text())["summaries"], "scone")["auc10"]
        for f in sorted(directory.glob("pairs-union-*.json"))
    }


def warp_bins(directory):
    """Within 5 px and mean correct matches of SConE: over all warp pairs, and per checked bin."""
    report = json.loads((directory / "warps-union.json").read_text())
    s = summary(report["summaries"], "scone")
    out = {"all": (s["within"][WITHIN_5PX], s["mean_correct"], s["pairs"])}
    for b in report["bins"]:
        s = summary(b["summaries"], "scone")
        if (b["axis"] == "zoom" and b["label"] in ZOOM_BINS) or (b["axis"] == "rotation" and s["pairs"] >= 10):
            out[f"{b['axis']} {b['label']}"] = (s["within"][WITHIN_5PX], s["mean_correct"], s["pairs"])
    return out


def part_failures(sa, ca, allowed, column, note):
    """Prints a row per part of the shipped model's AUC@10 `sa` against the candidate's `ca`, with the column
    `column` holding `note(part)`; returns the parts where the candidate is below the shipped model by more than
    `allowed(part)`, or not scored, as failures. (`allowed` returns the shortfall's text too, as the verdict names it.)"""
    failures = []
    print(f"| part | shipped AUC@10 | candidate | difference | {column} |\n|---|---|---|---|---|")
    for part, a in sa.items():
        c = ca.get(part)
        if c is None:
            failures.append(f"{part} not scored")
            continue
        print(f"| {part} | {a:.4f} | {c:.4f} | {c - a:+.4f} | {note(part)} |")
        tolerance, text = allowed(part)
        if c < a - tolerance - 1e-9:
            failures.append(f"{part} AUC@10 {c:.4f} < shipped {a:.4f} - {text}")
    return failures


def judge(shipped, cand, validation):
    sa, ca, spread = aucs(shipped), aucs(cand), seed_spread(shipped)
    failures = part_failures(sa, ca, lambda part: (0.005, "0.005"), "shipped's seed-to-seed SD (SE of 3)",
                             lambda part: f"{spread[part][0]:.4f} ({spread[part][1]:.4f})")
    ms, mc = sum(sa.values()) / len(sa), sum(ca.get(p, 0.0) for p in sa) / len(sa)
    print(f"| **mean** | {ms:.4f} | {mc:.4f} | {mc - ms:+.4f} | |\n")
    if not validation and mc < ms - 0.002:
        failures.append(f"mean AUC@10 {mc:.4f} < shipped {ms:.4f} - 0.002")
    sw, cw = warp_bins(shipped), warp_bins(cand)
    print("| warps | pairs | within 5 px shipped | candidate | correct matches shipped | candidate |\n|---|---|---|---|---|---|")
    for k, (w, n, pairs) in sw.items():
        cwk, cnk, _ = cw[k]
        print(f"| {k} | {pairs} | {w:.3f} | {cwk:.3f} | {n:.1f} | {cnk:.1f} |")
        if cwk < w - 0.01 - 1e-9:
            failures.append(f"warps {k} within 5 px {cwk:.3f} < shipped {w:.3f} - 0.01")
        if cnk < 0.98 * n:
            failures.append(f"warps {k} correct matches {cnk:.1f} < 0.98 x shipped {n:.1f}")
    return failures


def run(judge_fn):
    """The command line: `judge_fn(shipped, candidate, validation)` on each candidate directory, with its verdict."""
    args = sys.argv[1:]
    validation = "--validation" in args
    shipped, *candidates = (Path(a) for a in args if a != "--validation")
    for cand in candidates:
        print(f"## {cand.name} against {shipped}\n")
        failures = judge_fn(shipped, cand, validation)
        print("\n**passes**\n" if not failures else "\n**fails**: " + "; ".join(failures) + "\n")


if __name__ == "__main__":
    run(judge)
