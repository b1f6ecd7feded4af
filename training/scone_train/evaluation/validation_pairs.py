"""The pair protocol on every validation scene, once per shipped model: `scone eval pairs` with each scene's
window and checks, every method, and one table of AUC@10 / precision / time per pair.

`python -m scone_train.evaluation.validation_pairs --out DIR [--seeds 3] [--model M.onnx]` (from `training/`)

Writes DIR/<scene>.json and .md (the eval's own report), DIR/summary.md and the figures of each report
(scone_train.figures.pairs). The validation scenes are never used for a choice: this is what a shipped model scores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np

from ..paths import scone_binary, shared_data

# scene, eval flags (window, ground-truth checks, short-baseline split)
SCENES = [
    ("strecha-fountain-P11", ["--window", "100"]),
    ("kitti-clip2", ["--window", "10"]),
    ("rgbd-slambook-5", ["--window", "100", "--depth-px", "12", "--epipolar-px", "6"]),
    # TUM: the first frame against every later one, as the paper; pairs within 5 cm are its 30 Hz burst
    # (1-19 mm), the others 9 cm to 4 m.
    ("tum-fr3-long-office", ["--window", "100", "--short-baseline", "0.05"]),
    ("middlebury-dino48", ["--window", "10"]),
]
METHODS = "scone,scone-plain,freak,freak-gms,orb,sift"


def run(out: Path, seeds: int, model: str | None, methods: str = METHODS) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, flags in SCENES:
        report = out / f"{name}.json"
        if not report.exists():
            cmd = [str(scone_binary()), "eval", "pairs", "--scene", str(shared_data() / "scenes" / name), "--seeds",
                   str(seeds), "--methods", methods, "--json", str(report), *flags]
            if model:
                cmd += ["--model", model]
            md = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
            (out / f"{name}.md").write_text(md)
        results[name] = json.loads(report.read_text())
    return results


def summary(results: dict) -> str:
    methods = [s["method"] for s in next(iter(results.values()))["summaries"]]
    lines = ["| method | " + " | ".join(results) + " | mean AUC@10 | ms per pair (describe 2 + match) |",
             "|---|" + "---|" * (len(results) + 2)]
    for m in methods:
        cells, aucs, times = [], [], []
        for r in results.values():
            s = next(x for x in r["summaries"] if x["method"] == m)
            cells.append(f"{s['auc10']:.3f} ({s['match_precision']:.3f})")
            aucs.append(s["auc10"])
            times.append(2 * s["describe_ms"] + s["match_ms"])
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {np.mean(aucs):.3f} | {np.mean(times):.1f} |")
    return "\n".join(lines)


NAMES = {"scone": "SConE (shipped matcher)", "scone-plain": "SConE (plain)", "freak": "FREAK", "freak-gms": "FREAK+GMS",
         "orb": "ORB", "sift": "SIFT"}


def scene_tables(results: dict) -> str:
    """One compact table per scene (the figures BENCHMARKS.md keeps)."""
    out = []
    for name, r in results.items():
        c = r["config"]
        pairs = r["summaries"][0]["pairs"]
        out.append(f"{name} ({pairs} pairs, window {c['window']}, {c['seeds']} seeds):\n")
        out.append("| method | AUC@5 | AUC@10 | AUC@20 | fail | matches | match precision | RANSAC iters needed (median) |")
        out.append("|---|---|---|---|---|---|---|---|")
        for m in r["summaries"]:
            name = f"SConE ({c.get('scone_matcher', 'rerank')}, shipped)" if m["method"] == "scone" else NAMES[m["method"]]
            out.append(f"| {name} | {m['auc5']:.3f} | {m['auc10']:.3f} | {m['auc20']:.3f} | {100 * m['failures']:.0f} % | "
                       f"{m['mean_matches']:.0f} | {m['match_precision']:.3f} | {m['median_iterations_needed']:.0f} |")
        out.append("")
    return "\n".join(out)


BINS = [(0, 10), (10, 20), (20, 40), (40, 60), (60, 180)]


def by_angle(results: dict) -> str:
    """Every scene's pairs pooled and binned by their rotation angle: pairs per bin and, per method, the share of
    (pair, seed) runs within 10 degrees and the mean correct matches per pair."""
    methods = [s["method"] for s in next(iter(results.values()))["summaries"]]
    recs = [r for rep in results.values() for r in rep["pairs"]]
    lines = ["| angle | pairs | " + " | ".join(NAMES[m] for m in methods) + " |", "|---|---|" + "---|" * len(methods)]
    for lo, hi in BINS:
        cells, n = [], 0
        for m in methods:
            sel = [r for r in recs if r["method"] == m and lo <= r["angular_distance_deg"] < hi]
            n = len(sel)
            errs = np.array([e for r in sel for e in r["errors_deg"]])
            cells.append(f"{(errs <= 10).mean():.2f} / {np.mean([r['correct'] for r in sel]):.0f}" if n else "-")
        lines.append(f"| {lo}-{hi}° | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def time_auc(results: dict, timing: Path, figure: Path | None = None) -> str:
    """(time per pair, mean AUC@10) per method: the time from quiet single-core runs in `timing` (reports of
    `scone eval pairs --seeds 1` on one or more scenes, averaged), the accuracy from the validation results."""
    reports = [json.loads(f.read_text()) for f in sorted(timing.glob("*.json"))]
    methods = [s["method"] for s in next(iter(results.values()))["summaries"]]
    rows = []
    for m in methods:
        ms = np.mean([2 * s["describe_ms"] + s["match_ms"] for r in reports for s in r["summaries"] if s["method"] == m])
        auc = np.mean([next(s["auc10"] for s in r["summaries"] if s["method"] == m) for r in results.values()])
        rows.append((m, float(ms), float(auc)))
    lines = ["| method | ms per pair (2 x describe + match) | mean AUC@10, validation | faster and more accurate than SConE? |",
             "|---|---|---|---|"]
    ref = next(r for r in rows if r[0] == "scone")
    for m, ms, auc in rows:
        dom = "-" if m == "scone" else ("yes" if ms < ref[1] and auc > ref[2] else "no")
        lines.append(f"| {NAMES[m]} | {ms:.1f} | {auc:.3f} | {dom} |")
    if figure is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for m, ms, auc in rows:
            ax.scatter(ms, auc, s=60)
            ax.annotate(NAMES[m], (ms, auc), textcoords="offset points", xytext=(5, 5))
        ax.set_xscale("log")
        ax.set_xlabel("time per pair, one core: 2 x (extract + describe) + match (ms, log)")
        ax.set_ylabel("mean AUC@10, five validation scenes")
        ax.set_title("accuracy against cost (Fig. 7)")
        fig.tight_layout()
        fig.savefig(figure, dpi=100)
        plt.close(fig)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--model", default=None)
    ap.add_argument("--methods", default=METHODS)
    ap.add_argument("--timing", default=None, help="directory of quiet single-core timing reports")
    ap.add_argument("--figure", default=None, help="with --timing: write the time/accuracy plot here")
    args = ap.parse_args()
    out = Path(args.out)
    results = run(out, args.seeds, args.model, args.methods)
    if args.timing:
        print(time_auc(results, Path(args.timing), Path(args.figure) if args.figure else None))
        return
    text = "AUC@10 (match precision) per validation scene\n\n" + summary(results) + "\n\n" + scene_tables(results) + "\n\nBy angle (share within 10 deg / correct matches per pair):\n\n" + by_angle(results) + "\n"
    (out / "summary.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
