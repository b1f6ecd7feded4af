"""Validation of a frozen model on the real validation scenes (never used for any choice): nearest-neighbour
precision of SConE against FREAK on the same keypoints with geometry-only ground truth, and drawings of the
ground-truth landmark matches of one pair per scene.

`python -m scone_train.evaluation.validate --checkpoint CHECKPOINT [--out DIR]`: the features come from the extraction the
checkpoint was trained at (its config's `data.extractor`, a feature cache of its own per setting, with the ring
context for a ring-context model), FREAK on the same keypoints.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from ..data import correspondences as C
from ..data.features import extractor_args
from ..data.training_units import Unit, build_unit
from ..model.network import SconeNet, load_checkpoint
from ..paths import prefix_dir, shared_data
from . import nn_precision as E

# Scene, link window (0 = all pairs). KITTI: links within 3 frames, as the FREAK reference figures.
# TUM: depth links in its 30 Hz burst, epipolar links (mocap poses) elsewhere; dino48: calibrated, all pairs.
VALIDATION = [("strecha-fountain-P11", 0), ("kitti-clip2", 3), ("rgbd-slambook-5", 0), ("tum-fr3-long-office", 0),
              ("middlebury-dino48", 0)]


def validation_units(extractor: dict | None = None) -> list[tuple[Unit, int]]:
    """The validation scenes' units, features at `extractor` (a config's `data.extractor`; None: the defaults)."""
    args = extractor_args(extractor)
    cache = prefix_dir() / "data" / ("cache" if not args else "cache-" + "".join(a.strip("-") for a in args)) / "real"
    out = []
    for name, window in VALIDATION:
        scene = shared_data() / "scenes" / name
        unit = build_unit(scene, cache, None, C.GeometryParams(window=window), name, extractor_args=args)
        out.append((unit, window))
    return out


def draw_landmark_matches(unit: Unit, scene_dir: Path, out: Path, a: int = 0, b: int = 1,
                          keep: list[int] | None = None) -> Path:
    """Side-by-side frames a and b of the unit with a line per ground-truth landmark seen in both. `keep`: the
    unit's frames as indices into the scene's `rgb.txt`, for a unit made of part of a scene."""
    from ..data.scenes import load_scene

    scene = load_scene(scene_dir)
    ra, rb = (keep[a], keep[b]) if keep is not None else (a, b)
    ia, ib = cv2.imread(str(scene.rgb[ra])), cv2.imread(str(scene.rgb[rb]))
    h = max(ia.shape[0], ib.shape[0])
    canvas = np.zeros((h, ia.shape[1] + ib.shape[1], 3), np.uint8)
    canvas[: ia.shape[0], : ia.shape[1]] = ia
    canvas[: ib.shape[0], ia.shape[1] :] = ib
    ida, idb = unit.ids[a], unit.ids[b]
    shared, pa, pb = np.intersect1d(ida, idb, return_indices=True)
    rng = np.random.default_rng(0)
    for lm, i, j in zip(shared, pa, pb):
        if lm < 0:
            continue
        p = tuple(int(v) for v in unit.frames[a].keypoints[i, :2])
        q = unit.frames[b].keypoints[j, :2]
        q = (int(q[0]) + ia.shape[1], int(q[1]))
        color = tuple(int(c) for c in rng.integers(64, 256, 3))
        cv2.line(canvas, p, q, color, 1, cv2.LINE_AA)
        cv2.circle(canvas, p, 3, color, 1)
        cv2.circle(canvas, q, 3, color, 1)
    path = out / f"{unit.name}-landmarks-{a}-{b}.png"
    out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)
    return path


def validate(model: SconeNet, out: Path | None = None, extractor: dict | None = None) -> dict:
    results = {}
    for unit, window in validation_units(extractor):
        f = E.freak_precision(unit.frames, unit.ids, window)
        s = E.scone_precision(model, unit.frames, unit.ids, window)
        results[unit.name] = {
            "window": window,
            "landmarks": C.summary(unit.ids),
            "freak": f.as_dict(),
            "scone": s.as_dict(),
            "gain_points": 100 * (s.precision - f.precision),
        }
        if out is not None:
            draw_landmark_matches(unit, shared_data() / "scenes" / unit.name, out)
    results["mean"] = {
        "freak": float(np.mean([results[n]["freak"]["precision"] for n, _ in VALIDATION])),
        "scone": float(np.mean([results[n]["scone"]["precision"] for n, _ in VALIDATION])),
    }
    results["mean"]["gain_points"] = 100 * (results["mean"]["scone"] - results["mean"]["freak"])
    return results


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--out", default=None)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    extractor = torch.load(Path(a.checkpoint), weights_only=False)["config"]["data"].get("extractor")
    res = validate(load_checkpoint(Path(a.checkpoint)), Path(a.out) if a.out else None, extractor)
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
