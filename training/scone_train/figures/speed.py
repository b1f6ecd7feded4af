"""Issue 29's candidates on one picture: inference time against the accuracy gate on the selection split.

`python -m scone_train.figures.speed --candidate LABEL=GATE_DIR [...] --out ../docs/figures/speed-gate.png`
(from `training/`): each GATE_DIR is a `scone_train.evaluation.speed_gate --out` directory (its `selection.json`, which
names the graph that was scored). Inference time is measured here, in one process: the shipped graph and every candidate run
in turn, `--reps` rounds over the same real training frames (`--frames` per training scene, onnxruntime on
`--threads` intra-op threads, spinning off); each time is the median round, given as a ratio to the shipped
graph's. Prints the table and draws, per candidate, its AUC@10 difference to the shipped model on every
selection part, against that ratio, with the gate's tolerance.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..evaluation.ort_bench import inference_ratios
from ..evaluation.speed_gate import SHIPPED


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--candidate", action="append", required=True, help="LABEL=GATE_DIR")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--frames", type=int, default=2, help="per training scene")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--tolerance", type=float, default=0.005)
    a = ap.parse_args()
    labels, dirs = zip(*(c.split("=", 1) for c in a.candidate))
    dirs = [Path(d) for d in dirs]
    verdicts = [json.loads((d / "selection.json").read_text()) for d in dirs]
    ratios = inference_ratios([SHIPPED.with_suffix(".onnx"), *(Path(v["onnx"]) for v in verdicts)], a.frames,
                              a.threads, a.reps)[1:]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    print("| candidate | inference, ratio to shipped | AUC@10 difference per selection part | worst | passes |")
    print("|---|---|---|---|---|")
    fig, ax = plt.subplots(figsize=(10, 4.8))
    ax.axhspan(-a.tolerance, 0.2, color="tab:green", alpha=0.08, label=f"gate: no part below -{a.tolerance}")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.axvline(1.0, color="grey", lw=0.8, ls=":")
    lows = []
    for i, (label, ratio, v) in enumerate(zip(labels, ratios, verdicts)):
        deltas = [r["delta"] for r in v["auc10"]]
        color = f"C{i}"
        ax.scatter([ratio] * len(deltas), deltas, s=14, color=color, alpha=0.6)
        ax.scatter([ratio], [min(deltas)], s=70, color=color, marker="v", label=f"{label} (worst part)")
        lows.append(min(deltas))
        cells = ", ".join(f"{r['scene'].split('-')[0]} {r['delta']:+.3f}" for r in v["auc10"])
        print(f"| {label} | {ratio:.2f}x | {cells} | {min(deltas):+.3f} | {'yes' if v['passes'] else 'no'} |")
    ax.scatter([1.0], [0.0], s=90, color="black", marker="*", label="shipped model")
    highs = [r["delta"] for v in verdicts for r in v["auc10"]]
    ax.set_ylim(min(lows + [-a.tolerance]) - 0.01, max(highs + [0.02]) + 0.01)
    ax.set_xlabel(f"SConE inference time, ratio to the shipped graph (onnxruntime, {a.threads} thread)")
    ax.set_ylabel("AUC@10 minus the shipped model's, per selection part")
    ax.set_title("Cheaper networks against the accuracy gate (issue 29, selection split)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=110)
    plt.close(fig)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
