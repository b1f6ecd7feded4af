#!/usr/bin/env python3
"""Why the ring model's candidates stop short of +0.03 over FREAK, as one picture (docs/figures/issue39-limits.png),
read from the reports kept in runs/ and frames/.

Left: runs of the shipped recipe, its rerun over the whole 10,000-step schedule (ring-e1-real-nnp) and three
seeds to step 3,000 (ring-e1-real-10k*). The training loss keeps falling while the selection F1 (the ratio test
on the held-out selection units and warps) stops rising by step 1,000-2,000 and then falls: more fitting of these
training data does not carry over. Right: on the selection warps, how many of a keypoint's context samples land within 3 px of its
correspondent's, above chance, by zoom: the detected neighbours (ring-e1-warps24's report) and the ring placed by
several keypoint frames (`frames/frames.py`, its variants A, B, G, S and E): the ring is only as shared as the
frame it is placed in.

    $SCONE_PREFIX/venv-train/bin/python docs/results/training/limits_figure.py
"""

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HERE = Path(__file__).resolve().parent
# (report directory, drawn as): the shipped recipe's runs whose logs are kept here
RUNS = [
    ("runs/ring-e1-real-nnp", "-"),
    ("runs/ring-e1-real-10k", ":"),
    ("runs/ring-e1-real-10k-s1", ":"),
    ("runs/ring-e1-real-10k-s2", ":"),
]


def curves(run: str) -> tuple[list, list, list, float]:
    rows = [json.loads(line) for line in (HERE / run / "train-log.jsonl").read_text().splitlines() if line]
    return ([r["step"] for r in rows], [r["loss"] for r in rows], [r["selection_ratio"]["f1"] for r in rows],
            rows[0]["freak_selection_ratio"]["f1"])


def shares_by_zoom(report: Path) -> tuple[list, list, list, list]:
    r = json.loads(report.read_text())
    labels, nbr, ring, pairs = [], [], [], []
    for b in r["bins"]:
        if b["axis"] != "zoom":
            continue
        s = next(x for x in b["summaries"] if x["method"] == "scone")
        labels.append(b["label"])
        nbr.append(s["mean_neighbour_above_chance"])
        ring.append(s["mean_ring_above_chance"])
        pairs.append(s["pairs"])
    return labels, nbr, ring, pairs


def main():
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.8))
    f1_axis = left.twinx()
    for k, (run, style) in enumerate(RUNS):
        steps, loss, f1, freak = curves(run)
        left.plot(steps, loss, color="tab:gray", marker="o", ls=style, label="training loss" if k == 0 else None)
        f1_axis.plot(steps, f1, color="tab:blue", marker="s", ls=style, label="selection F1, SConE" if k == 0 else None)
    f1_axis.axhline(freak, color="tab:red", ls="--", label=f"selection F1, FREAK ({freak:.3f})")
    left.set_xlabel("training step (the shipped recipe: round 5's rerun, solid; round 12's seeds 0-2, dotted)")
    left.set_ylabel("training loss (interval mean)")
    f1_axis.set_ylabel("ratio-test F1 on the selection units")
    f1_axis.set_ylim(0.33, 0.42)
    handles = left.get_legend_handles_labels()[0] + f1_axis.get_legend_handles_labels()[0]
    left.legend(handles, [h.get_label() for h in handles], fontsize=8, loc="center right")
    left.set_title("The loss keeps falling; the held-out F1 stops by step 1,000-2,000, then falls", fontsize=10)

    labels, nbr, _, pairs = shares_by_zoom(HERE / "runs" / "ring-e1-warps24" / "warps-union.json")
    frames = json.loads((HERE / "frames" / "frames.json").read_text())
    x = range(len(labels))
    right.plot(x, nbr, marker="o", color="tab:gray", ls="--", label="detected neighbours (20 nearest; shipped before)")
    for variant, colour, text in (
        ("A", "tab:blue", "ring, FAST's level and FREAK's angle (shipped)"),
        ("B", "tab:cyan", "ring, the best level of the same corner"),
        ("G", "tab:purple", "ring, a Laplacian scale between levels"),
        ("S", "tab:orange", "ring, SIFT's scale and angle (SIFT: 6.25x FREAK's time a pair)"),
        ("E", "tab:green", "ring, the exact scale and angle (no detector)"),
    ):
        right.plot(x, [frames[lab][variant][0] for lab in labels], marker="s", color=colour, label=text)
    right.set_xticks(list(x), [f"{lab}\n({n} pairs)" for lab, n in zip(labels, pairs)], fontsize=8)
    right.set_xlabel("zoom of the true homography (selection warps)")
    right.set_ylabel("context samples within 3 px, above chance")
    right.set_ylim(0, 1.0)
    right.legend(fontsize=7, loc="center right", bbox_to_anchor=(1.0, 0.71))
    right.set_title("The ring is as shared as the frame it is placed in", fontsize=10)
    fig.tight_layout()
    out = HERE.parents[1] / "figures" / "issue39-limits.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
