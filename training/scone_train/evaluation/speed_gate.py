"""Issue 29's accuracy gate: may a faster model (a distilled student, a quantised graph) replace the shipped one?

`python -m scone_train.evaluation.speed_gate --candidate RUN/best.pt --out DIR [--stage selection|validation]` (from
`training/`; `scripts/speed` runs it after `scone_train.model.distill`):

- `selection` (the choice, training scenes only): AUC@10 of `scone eval pairs` (shipped matcher, each part's
  window, 3 seeds) on every selection part of `splits.SPLIT`; the candidate passes when no part is lower than
  the shipped model's by more than `--auc-tolerance` (0.005).
- `validation` (run once per candidate that passed selection): AUC@10 of `scone_train.evaluation.validation_pairs` on every
  validation scene, within the same tolerance, and the NN precision of `scone_train.evaluation.validate` on every
  validation scene at least the lower end of the shipped model's 95 % bootstrap interval.

A candidate given as a checkpoint (`.pt`) is exported to ONNX beside its reports; a `.onnx` candidate (a
quantised graph) is scored as it is, and its NN precision is then read through onnxruntime. Reports are cached
under `--out/<key>`, the key naming the content of the candidate and of the `scone` binary (the shipped model's
likewise, under `<prefix>/work/speed-gate/shipped-<key>`), so a rerun scores only what is missing and never
reuses a report of another network or binary. The verdict, naming the candidate, its sha256 and the graph that
was scored, is printed and written to `DIR/<stage>.json`; the exit status is 0 when the candidate passes.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from ..model.export import check_parity, export_onnx, run_onnx, session
from ..model.network import load_checkpoint
from ..paths import REPO, prefix_dir

SHIPPED = REPO / "models" / "scone-freak-k20"


def selection_auc(model: Path, out: Path, seeds: int) -> dict[str, dict]:
    """`scone eval pairs` reports of the shipped matcher on every selection part, with `model`."""
    from .selection_pairs import reports

    return reports(out, str(model), "scale-aware", seeds, "scone")


def validation_auc(model: Path, out: Path, seeds: int) -> dict[str, dict]:
    from .validation_pairs import run

    return run(out, seeds, str(model), "scone")


def pair_scores(report: dict) -> dict[tuple[str, str], float]:
    """Each pair's share of AUC@10 (the mean over seeds of max(0, 1 - error / 10 deg), as `stats::auc`)."""
    return {(p["reference"], p["frame"]): float(np.mean([max(0.0, 1.0 - e / 10.0) for e in p["errors_deg"]]))
            for p in report["pairs"] if p["method"] == "scone"}


def paired_interval(a: dict, b: dict, reps: int = 2000, seed: int = 0) -> list[float]:
    """95 % bootstrap interval of AUC@10(b) - AUC@10(a) over the pairs both reports scored (for reading the
    tolerance against the protocol's own noise; the verdict does not use it)."""
    keys = sorted(set(a) & set(b))
    d = np.array([b[k] - a[k] for k in keys])
    if len(d) == 0:
        return [float("nan"), float("nan")]
    means = d[np.random.default_rng(seed).integers(0, len(d), (reps, len(d)))].mean(1)
    return [float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))]


class OnnxNet:
    """An exported graph behind the PyTorch model's call signature, for `validate` (NN precision)."""

    def __init__(self, path: Path, k: int = 20, embed_dim: int = 48):
        self.sess = session(path, threads=1)
        self.k = k
        self.head = [SimpleNamespace(out_features=embed_dim)]  # what evaluate.embed_frames reads of a model

    def eval(self):
        return self

    def __call__(self, *inputs):
        return torch.from_numpy(run_onnx(self.sess, *[t.numpy() for t in inputs]))


def nn_precision(model, out: Path) -> dict:
    from .validate import validate

    report = out / "nn-precision.json"
    if not report.exists():
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text(json.dumps(validate(model), indent=1))
    return json.loads(report.read_text())


def compare(shipped: dict[str, dict], candidate: dict[str, dict], tolerance: float) -> tuple[list[dict], bool]:
    rows = []
    for s in shipped:
        a, b = shipped[s]["summaries"][0]["auc10"], candidate[s]["summaries"][0]["auc10"]
        rows.append({"scene": s, "shipped": a, "candidate": b, "delta": b - a, "passes": b >= a - tolerance,
                     "delta_ci95": paired_interval(pair_scores(shipped[s]), pair_scores(candidate[s]))})
    return rows, all(r["passes"] for r in rows)


def content_key(*paths: Path) -> str:
    """12 hex digits naming the content of these files together (a model and the `scone` binary that scores it)."""
    import hashlib

    from ..model.export import sha256

    return hashlib.sha256("".join(sha256(p) for p in paths).encode()).hexdigest()[:12]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--candidate", required=True, type=Path, help="a checkpoint (.pt) or an exported graph (.onnx)")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--stage", choices=["selection", "validation"], default="selection")
    ap.add_argument("--auc-tolerance", type=float, default=0.005)
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from ..model.export import sha256
    from ..paths import scone_binary

    candidate = a.candidate.resolve()
    # Reports are kept per content of the candidate and of the binary that scores it, so a retrained candidate or
    # a rebuilt `scone` is scored anew, and a verdict can only ever name the graph it judged.
    work = a.out / content_key(candidate, scone_binary())
    work.mkdir(parents=True, exist_ok=True)
    onnx = work / "candidate.onnx"
    if candidate.suffix == ".pt":
        net = load_checkpoint(candidate)
        if not onnx.exists():
            export_onnx(net, onnx)
            check_parity(net, onnx)
    else:
        if not onnx.exists():
            shutil.copyfile(candidate, onnx)
        net = OnnxNet(onnx)
    shipped_onnx = SHIPPED.with_suffix(".onnx")
    base = prefix_dir() / "work" / "speed-gate" / f"shipped-{content_key(shipped_onnx, scone_binary())}"
    verdict: dict = {"candidate": str(candidate), "candidate_sha256": sha256(candidate), "onnx": str(onnx),
                     "stage": a.stage, "auc_tolerance": a.auc_tolerance}
    if a.stage == "selection":
        rows, ok = compare(selection_auc(shipped_onnx, base / "selection", a.seeds),
                           selection_auc(onnx, work / "selection", a.seeds), a.auc_tolerance)
        verdict.update(auc10=rows, passes=ok)
    else:
        rows, auc_ok = compare(validation_auc(shipped_onnx, base / "validation", a.seeds),
                               validation_auc(onnx, work / "validation", a.seeds), a.auc_tolerance)
        ref = nn_precision(load_checkpoint(SHIPPED.with_suffix(".pt")), base)
        got = nn_precision(net, work)
        nn_rows = [{"scene": s, "shipped": ref[s]["scone"]["precision"], "shipped_ci": ref[s]["scone"]["ci95"],
                    "candidate": got[s]["scone"]["precision"],
                    "passes": got[s]["scone"]["precision"] >= ref[s]["scone"]["ci95"][0]} for s in ref if s != "mean"]
        verdict.update(auc10=rows, nn_precision=nn_rows, passes=auc_ok and all(r["passes"] for r in nn_rows))
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / f"{a.stage}.json").write_text(json.dumps(verdict, indent=1))
    for r in verdict["auc10"]:
        print(f"AUC@10 {r['scene']:28s} shipped {r['shipped']:.4f} candidate {r['candidate']:.4f} "
              f"({r['delta']:+.4f}, paired bootstrap {np.round(r['delta_ci95'], 3).tolist()}) "
              f"{'ok' if r['passes'] else 'FAILS'}")
    for r in verdict.get("nn_precision", []):
        print(f"NN precision {r['scene']:22s} shipped {r['shipped']:.4f} {np.round(r['shipped_ci'], 4).tolist()} "
              f"candidate {r['candidate']:.4f} {'ok' if r['passes'] else 'FAILS'}")
    print("PASSES" if verdict["passes"] else "DOES NOT PASS")
    sys.exit(0 if verdict["passes"] else 1)


if __name__ == "__main__":
    main()
