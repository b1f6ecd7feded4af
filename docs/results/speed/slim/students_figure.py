#!/usr/bin/env python3
"""The runs of `slim64-kd200` (seeds 0-2) and the averaged-weight readings of seeds 0 and 1 against the shipped
model: each selection part's AUC@10 difference with the shortfall the rule allows, and the
arcs' far-map queries. Reads the reports under `$SCONE_PREFIX/work/slim` (RESULT.md's commands made them) and
writes `docs/figures/slim-students.png`.

    $SCONE_PREFIX/venv-train/bin/python docs/results/speed/slim/students_figure.py
"""

import importlib.util
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("slim_score", HERE / "score.py")
_score = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_score)

WORK = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone")) / "work" / "slim"
STUDENTS = {
    "slim64-kd200": "seed 0",
    "slim64-kd200-s1": "seed 1",
    "slim64-kd200-s2": "seed 2",
    "slim64-kd200-ema-s0": "seed 0, averaged weights",
    "slim64-kd200-ema-s1": "seed 1, averaged weights",
}


def main() -> None:
    shipped = WORK / "shipped"
    sa, spread = _score.aucs(shipped), _score.seed_spread(shipped)
    parts = sorted(sa)
    allowed = [_score.selection_tolerance(spread, p) for p in parts]
    arcs_shipped = sum(c for c, _ in _score.reloc(WORK / "reloc-shipped").values())

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 4.8), gridspec_kw={"width_ratios": [4, 1]})
    ys = range(len(parts))
    ax.barh(ys, [-a for a in allowed], color="#e8e8e8", label="shortfall the rule allows")
    ax.axvline(0, color="black", lw=0.8)
    arcs = []
    for k, (name, label) in enumerate(STUDENTS.items()):
        ca = _score.aucs(WORK / name)
        ax.scatter([ca[p] - sa[p] for p in parts], [y + (k - 2) * 0.12 for y in ys], s=22, label=label, zorder=3)
        arcs.append(sum(c for c, _ in _score.reloc(WORK / f"reloc-{name}").values()))
    ax.set_yticks(list(ys), [p.removesuffix("-sel") for p in parts])
    ax.invert_yaxis()
    lo = -0.13
    ax.set_xlim(lo, 0.13)
    for y, a in zip(ys, allowed):
        if -a < lo:
            ax.annotate(f"allowed {a:.2f}", (lo, y), xytext=(3, -3), textcoords="offset points", fontsize=7, va="top")
    ax.set_xlabel("AUC@10, student minus the shipped model (selection parts, 3 evaluation seeds)")
    ax.set_title("slim64-kd200 against the shipped model, per selection part")
    ax.legend(fontsize=8, loc="upper right")

    bx.bar(range(len(arcs)), arcs, color=[f"C{k}" for k in range(len(arcs))])
    bx.axhline(arcs_shipped, color="black", lw=1, label=f"shipped ({arcs_shipped})")
    bx.axhline(arcs_shipped - 1, color="grey", lw=1, ls="--", label="the rule's least")
    bx.set_xticks(range(len(arcs)), ["s0", "s1", "s2", "s0\navg", "s1\navg"], fontsize=8)
    bx.set_ylim(0, arcs_shipped + 4)
    bx.set_ylabel("far-map queries localised, four arcs")
    bx.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    out = HERE.parents[2] / "figures" / "slim-students.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
