"""One drawn pair of ground-truth correspondences per real training scene, to look at the labels.

`python -m scone_train.label_figures --out ../docs/figures` (from `training/`); the pair is the training part's
pair of frames `--gap` apart (in the part's own order) from its first frame.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from . import correspondences as C
from .data import prefix_dir
from .dataset import build_unit
from .splits import SPLIT, frames, scene_dir
from .validate import draw_landmark_matches


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", required=True)
    ap.add_argument("--gap", type=int, default=3)
    args = ap.parse_args()
    cache = prefix_dir() / "data" / "cache" / "real"
    for name, spec in SPLIT.items():
        src = scene_dir(name)
        stamps = [r.split()[0] for r in (src / "rgb.txt").read_text().splitlines() if r.strip() and r[0] != "#"]
        keep = frames(spec["train"], stamps)
        unit = build_unit(src, cache, keep, C.GeometryParams(**spec.get("geometry", {})), f"{name}-train")
        print(draw_landmark_matches(unit, src, Path(args.out), 0, args.gap, keep))


if __name__ == "__main__":
    main()
