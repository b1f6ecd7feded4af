"""Figure of `scone eval homography` reports: share of pairs within 5 px and correct matches per zoom bin, one
line per method, and the constellations' neighbour share on a second axis.

`python -m scone_train.figures.homography --out ../docs/figures/homography-zoom.png REPORT.json [LABEL=REPORT.json ...]`
(from `training/`). A report given as LABEL=PATH adds its SConE row (method `scone`) under that label (another model or matcher).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

NAMES = {"scone": "SConE", "scone-plain": "SConE (plain)", "freak": "FREAK", "orb": "ORB", "sift": "SIFT",
         "freak-gms": "FREAK+GMS"}


def bins(report: dict, axis: str) -> list[dict]:
    return [b for b in report["bins"] if b["axis"] == axis]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--title", default="Exact warps: matching by zoom")
    ap.add_argument("reports", nargs="+")
    args = ap.parse_args()
    base = json.loads(Path(args.reports[0]).read_text())
    extra = []
    for r in args.reports[1:]:
        label, path = r.split("=", 1)
        extra.append((label, json.loads(Path(path).read_text())))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.6))
    zb = bins(base, "zoom")
    labels = [b["label"] for b in zb]
    x = range(len(labels))
    matcher = base["config"]["scone_matcher"]
    for m_idx, m in enumerate(base["config"]["methods"]):
        name = NAMES.get(m, m) + (f" ({matcher})" if m == "scone" else "")
        within = [b["summaries"][m_idx]["within"][1] for b in zb]
        correct = [b["summaries"][m_idx]["mean_correct"] for b in zb]
        style = "-o" if m.startswith("scone") else "--s"
        ax1.plot(x, within, style, label=name)
        ax2.plot(x, correct, style, label=name)
    for label, rep in extra:
        eb = {b["label"]: b for b in bins(rep, "zoom")}
        for m_idx, m in enumerate(rep["config"]["methods"]):
            if m != "scone":
                continue
            within = [eb[lab]["summaries"][m_idx]["within"][1] if lab in eb else float("nan") for lab in labels]
            correct = [eb[lab]["summaries"][m_idx]["mean_correct"] if lab in eb else float("nan") for lab in labels]
            ax1.plot(x, within, ":^", label=f"SConE ({label})")
            ax2.plot(x, correct, ":^", label=f"SConE ({label})")
    share = [next((s["mean_neighbour_share"] for s in b["summaries"] if s.get("mean_neighbour_share") is not None), None)
             for b in zb]
    if any(s is not None for s in share):
        tw = ax1.twinx()
        tw.bar(list(x), [s or 0 for s in share], alpha=0.12, color="grey", label="neighbour share")
        tw.set_ylim(0, 1)
        tw.set_ylabel("neighbour share (bars)")
        ax1.set_zorder(tw.get_zorder() + 1)  # the lines over the bars
        ax1.patch.set_visible(False)
    pairs = [b["summaries"][0]["pairs"] for b in zb]
    ticks = [f"{lab}\n({n} pairs)" for lab, n in zip(labels, pairs)]
    for ax, ylabel in ((ax1, "share of pairs within 5 px (corner error)"), (ax2, "correct matches per pair (3 px)")):
        ax.set_xticks(list(x), ticks, fontsize=8)
        ax.set_xlabel("zoom between the two images")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    ax1.set_ylim(0, 1.02)
    ax2.legend(fontsize=7)
    fig.suptitle(args.title)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
