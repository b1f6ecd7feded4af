"""Search time and success against the number of query keypoints searched, from `cargo bench --bench reloc`.

Reads the bench's printed output (its last table: one row per map size and cap of
`store.localize.max_query_keypoints`). Left: median search time against the map's observations, one line per
cap. Right: on the largest map, the share of queries within (0.25 m, 2 deg) and (0.5 m, 5 deg) per cap.
Usage:

    python -m scone_train.figures.reloc_sweep --out ../docs/figures/reloc-query-keypoints.png --default all BENCH_OUTPUT.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HEADER = "| observations | query keypoints |"


def sweep_rows(text: str) -> list[dict]:
    """The rows of the sweep table: observations, cap, queries, within counts, search ms."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(HEADER))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        c = [x.strip() for x in line.strip("|").split("|")]
        rows.append(
            {
                "observations": int(c[0]),
                "cap": c[1],
                "queries": int(c[2]),
                "within_025_2": int(c[4]),
                "within_05_5": int(c[5]),
                "search_ms": float(c[7]),
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("output", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--default", help="the cap the service ships, marked on the axis")
    args = ap.parse_args()
    rows = sweep_rows(args.output.read_text())
    caps = list(dict.fromkeys(r["cap"] for r in rows))
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    for cap in caps:
        mine = sorted((r for r in rows if r["cap"] == cap), key=lambda r: r["observations"])
        label = "all keypoints" if cap == "all" else f"strongest {cap}"
        left.plot([r["observations"] for r in mine], [r["search_ms"] for r in mine], marker="o", label=label)
    left.set_xscale("log")
    left.set_xlabel("observations in the map (real frames)")
    left.set_ylabel("search ms per query image (median)")
    left.set_title("Index search (HNSW, 2 threads)")
    left.legend(fontsize=8)
    left.grid(alpha=0.3)
    largest = max(r["observations"] for r in rows)
    big = [r for r in rows if r["observations"] == largest]
    xs = range(len(big))
    right.bar([x - 0.2 for x in xs], [r["within_025_2"] / r["queries"] for r in big], 0.4, label="(0.25 m, 2°)")
    right.bar([x + 0.2 for x in xs], [r["within_05_5"] / r["queries"] for r in big], 0.4, label="(0.5 m, 5°)")
    ticks = [r["cap"] + ("\n(default)" if r["cap"] == args.default else "") for r in big]
    right.set_xticks(list(xs), ticks)
    right.set_ylim(0.8, 1.01)
    right.set_xlabel("query keypoints searched")
    right.set_ylabel("share of queries localised within")
    right.set_title(f"{big[0]['queries']} held-out kitchen frames, {largest:,} observations")
    right.legend(fontsize=8, loc="lower left")
    right.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)


if __name__ == "__main__":
    main()
