"""One drawn pair of ground-truth correspondences per real training scene, to look at the labels.

`python -m scone_train.figures.labels --out ../docs/figures` (from `training/`); the pair is the training part's
pair sharing the most ground-truth landmarks among its first 20 frames, each with its next `--within`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..data import correspondences as C
from ..data.splits import SPLIT, part
from ..data.training_units import build_unit
from ..evaluation.validate import draw_landmark_matches
from ..paths import prefix_dir


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--within", type=int, default=12)
    args = ap.parse_args()
    cache = prefix_dir() / "data" / "cache" / "real"
    for name, spec in SPLIT.items():
        src, keep = part(name, "train")
        unit = build_unit(src, cache, keep, C.GeometryParams(**spec.get("geometry", {})), f"{name}-train")
        n = len(unit.ids)
        best = max(
            ((len(np.intersect1d(unit.ids[a][unit.ids[a] >= 0], unit.ids[b])), a, b)
             for a in range(min(20, n)) for b in range(a + 1, min(a + 1 + args.within, n))),
        )
        print(draw_landmark_matches(unit, src, Path(args.out), best[1], best[2], keep), best[0], "landmarks")


if __name__ == "__main__":
    main()
