"""Localize p50 against the map's size, the service's default beside every query keypoint searched, from one run
of `SCONE_BENCH_1M=1 cargo bench --bench reloc` (its first table: one row per level and configuration).
Usage:

    python -m scone_train.figures.reloc_latency --out ../docs/figures/reloc-latency-per-map-size.png BENCH_OUTPUT.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROWS = {
    "HNSW, one point per landmark": "default: stage 1 capped at 100, fallback below 100 inliers",
    "HNSW, one point per landmark, every query keypoint searched": "every query keypoint searched (before)",
}


def table(text: str) -> dict[str, list[tuple[int, float, float]]]:
    """Per configuration of `ROWS`: (observations, search ms, total p50 ms) per level."""
    out: dict[str, list[tuple[int, float, float]]] = {label: [] for label in ROWS}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) > 8 and cells[1] in ROWS and cells[0].isdigit():
            out[cells[1]].append((int(cells[0]), float(cells[5]), float(cells[8])))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("bench", type=Path)
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args()
    rows = table(a.bench.read_text())
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for (label, name), colour in zip(ROWS.items(), ["tab:blue", "tab:grey"]):
        obs = [r[0] for r in rows[label]]
        ax.plot(obs, [r[2] for r in rows[label]], "o-", color=colour, label=f"{name}: total p50")
        ax.plot(obs, [r[1] for r in rows[label]], "s--", color=colour, alpha=0.7, label=f"{name}: index search")
    ax.set_xscale("log")
    ax.set_xlabel("map observations (real frames, no repeats)")
    ax.set_ylabel("ms (median over 20 queries)")
    ax.set_ylim(bottom=0)
    ax.set_title("Localize of a 640x480 JPEG, decode to pose, 2 cores")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper left")
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=120)
    print(a.out)


if __name__ == "__main__":
    main()
