"""Scores a candidate on the real selection split with the pair protocol (`scone eval pairs`).

`python -m scone_train.evaluation.selection_pairs --name NAME [--model M.onnx] [--scone-matcher plain|union|rerank] [--seeds 3] [--scenes five|nine]`

Writes the selection parts as scene directories (scone_train.data.splits), runs `scone eval pairs --methods
scone,freak` on each with its window, and prints one markdown row per part plus the mean; the reports go to
`$SCONE_PREFIX/runs/selection/NAME/`. The rule that judges the scores is in docs/model-experiments.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np

from ..data.splits import SCENE_SETS, write_selection_scenes
from ..paths import prefix_dir, scone_binary


def reports(out: Path, model: str | None, matcher: str, seeds: int, methods: str = "scone,freak",
            scene_set: str = "five") -> dict[str, dict]:
    """`scone eval pairs` on every selection part with its window: part -> report, cached as `out/<part>.json`."""
    out.mkdir(parents=True, exist_ok=True)
    scenes = write_selection_scenes(prefix_dir() / "data" / "selection", SCENE_SETS[scene_set])
    result = {}
    for part, (d, window) in scenes.items():
        report = out / f"{part}.json"
        if not report.exists():
            cmd = [str(scone_binary()), "eval", "pairs", "--scene", str(d), "--window", str(window), "--seeds", str(seeds),
                   "--methods", methods, "--scone-matcher", matcher, "--json", str(report),
                   "--opencv-threads", "1", "--embed-threads", "1"]
            if model:
                cmd += ["--model", model]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        result[part] = json.loads(report.read_text())
    return result


def score(name: str, model: str | None, matcher: str, seeds: int, methods: str = "scone,freak",
          scene_set: str = "five") -> dict:
    out = prefix_dir() / "runs" / "selection" / name
    rows = {}
    for part, r in reports(out, model, matcher, seeds, methods, scene_set).items():
        rows[part] = {s["method"]: {"auc10": s["auc10"], "precision": s["match_precision"], "matches": s["mean_matches"],
                                    "pairs": s["pairs"]} for s in r["summaries"]}
    methods_seen = list(next(iter(rows.values())).keys())
    mean = {m: {k: float(np.mean([rows[p][m][k] for p in rows])) for k in ("auc10", "precision", "matches")} for m in methods_seen}
    result = {"name": name, "model": model, "matcher": matcher, "seeds": seeds, "parts": rows, "mean": mean}
    (out / "summary.json").write_text(json.dumps(result, indent=1))
    return result


def markdown(result: dict) -> str:
    methods = list(result["mean"].keys())
    head = "| part | " + " | ".join(f"{m} AUC@10 | {m} precision" for m in methods) + " |"
    lines = [head, "|---|" + "---|---|" * len(methods)]
    for part, r in result["parts"].items():
        lines.append(f"| {part} | " + " | ".join(f"{r[m]['auc10']:.3f} | {r[m]['precision']:.3f}" for m in methods) + " |")
    lines.append("| **mean** | " + " | ".join(f"**{result['mean'][m]['auc10']:.3f}** | {result['mean'][m]['precision']:.3f}" for m in methods) + " |")
    return "\n".join(lines)


BINS = [(0, 10), (10, 20), (20, 40), (40, 60), (60, 180)]


def by_angle(names: list[str], root: Path | None = None) -> str:
    """Pairs of every selection part pooled and binned by their rotation angle: per bin and candidate, the
    number of pairs and the share of (pair, seed) runs within 10 degrees, SConE and FREAK."""
    root = root or prefix_dir() / "runs" / "selection"
    cols = []
    for name in names:
        recs = []
        for f in sorted((root / name).glob("*.json")):
            if f.name == "summary.json":
                continue
            recs += json.loads(f.read_text())["pairs"]
        cols.append((name, recs))
    head = "| angle | pairs | FREAK | " + " | ".join(f"SConE, {n}" for n, _ in cols) + " |"
    lines = [head, "|---|---|---|" + "---|" * len(cols)]
    for lo, hi in BINS:
        def share(recs, method):
            errs = [e for r in recs if r["method"] == method and lo <= r["angular_distance_deg"] < hi for e in r["errors_deg"]]
            return (f"{np.mean(np.array(errs) <= 10):.2f}" if errs else "-"), len(errs)
        freak, _ = share(cols[0][1], "freak")
        n = len([r for r in cols[0][1] if r["method"] == "freak" and lo <= r["angular_distance_deg"] < hi])
        lines.append(f"| {lo}-{hi} deg | {n} | {freak} | " + " | ".join(share(recs, "scone")[0] for _, recs in cols) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--name", required=True)
    ap.add_argument("--model", default=None)
    ap.add_argument("--scone-matcher", default="plain")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--methods", default="scone,freak")
    ap.add_argument("--scenes", default="five", choices=sorted(SCENE_SETS), help="which real training scenes' selection parts")
    ap.add_argument("--by-angle", nargs="+", default=None, help="only print the angle-bin table of these runs")
    args = ap.parse_args()
    if args.by_angle:
        print(by_angle(args.by_angle))
        return
    r = score(args.name, args.model, args.scone_matcher, args.seeds, args.methods, args.scenes)
    print(f"{args.name} (matcher {args.scone_matcher}, model {args.model or 'shipped'})")
    print(markdown(r))


if __name__ == "__main__":
    main()
