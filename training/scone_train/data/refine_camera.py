"""Refine a scene's shared camera model against the images, for scenes whose poses belong to another camera.

`python -m scone_train.data.refine_camera --scene 7scenes-redkitchen --out $SCONE_PREFIX/data/refined`

7-Scenes gives the poses of the depth camera and no calibration of the colour camera (its `camera.txt` is the
usual f = 525 guess). Both errors are shared by every frame, so they are fitted as one rigid offset between the
two cameras (rotation and translation, 6 values) and one pinhole model (f, cx, cy): 9 values for the whole
scene, against the symmetric epipolar error of SIFT correspondences (not a descriptor under test) that are
consistent with the images alone (RANSAC fundamental matrix, 1 px). Half of the sampled pairs fit, the other half
measure. The refined scene (colour-camera poses T_wd * T_dc, the fitted intrinsics, the same images) is
written in the scene layout, so the labelling and the evaluation read it like any other scene.

Per-frame pose errors (tracking drift) are not fitted: that would be a bundle adjustment, and what remains is
reported as the scene's residual.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from ..paths import shared_data
from . import residuals as R
from .correspondences import _fundamental
from .scenes import load_scene


def _offset(p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(p[3:6]).as_matrix()
    T[:3, 3] = p[6:9]
    return T


def _K(p: np.ndarray) -> np.ndarray:
    return np.array([[p[0], 0, p[1]], [0, p[0], p[2]], [0, 0, 1.0]])


def correspondences(scene, pairs, sift) -> list:
    out = []
    cache = {}
    for i, j in pairs:
        for k in (i, j):
            if k not in cache:
                cache[k] = R._sift(cv2.imread(str(scene.rgb[k]), cv2.IMREAD_GRAYSCALE), sift)
        (xa, da), (xb, db) = cache[i], cache[j]
        if da is None or db is None:
            continue
        m = R._mutual_ratio(da, db)
        if len(m) < 15:
            continue
        pa, pb = xa[m[:, 0]], xb[m[:, 1]]
        _, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999, 10000)
        if inl is None or inl.sum() < 15:
            continue
        keep = inl.ravel() > 0
        out.append((i, j, pa[keep], pb[keep]))
    return out


def residual_vector(p, scene, corr):
    K = _K(p)
    Tdc = _offset(p)
    res = []
    for i, j, pa, pb in corr:
        F = _fundamental(K, scene.T_wc[i] @ Tdc, scene.T_wc[j] @ Tdc)
        res.append(R.epipolar_distance(F, pa, pb))
    return np.concatenate(res)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", required=True)
    ap.add_argument("--out", required=True, help="root of refined scenes")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    src = shared_data() / "scenes" / args.scene
    scene = load_scene(src)
    rng = np.random.default_rng(args.seed)
    pairs = R.sample_pairs(scene, args.pairs, rng, lo=5.0, hi=60.0)
    corr = correspondences(scene, pairs, cv2.SIFT_create(2000))
    fit, held = corr[0::2], corr[1::2]
    p0 = np.array([scene.K[0, 0], scene.K[0, 2], scene.K[1, 2], 0, 0, 0, 0, 0, 0], float)
    before = {"fit": float(np.median(residual_vector(p0, scene, fit))), "held_out": float(np.median(residual_vector(p0, scene, held)))}
    sol = least_squares(residual_vector, p0, args=(scene, fit), loss="soft_l1", f_scale=1.0, x_scale=[50, 10, 10, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    p = sol.x
    after_res = residual_vector(p, scene, held)
    report = {
        "scene": args.scene,
        "pairs_fit": len(fit),
        "pairs_held_out": len(held),
        "matches_held_out": int(len(after_res)),
        "median_epipolar_px_before": before,
        "median_epipolar_px_after_held_out": float(np.median(after_res)),
        "p80_epipolar_px_after_held_out": float(np.percentile(after_res, 80)),
        "f": float(p[0]),
        "cx": float(p[1]),
        "cy": float(p[2]),
        "offset_rotation_deg": float(np.degrees(np.linalg.norm(p[3:6]))),
        "offset_translation_m": [float(v) for v in p[6:9]],
    }
    print(json.dumps(report, indent=1))
    out = Path(args.out) / args.scene
    out.mkdir(parents=True, exist_ok=True)
    Tdc = _offset(p)
    lines = ["# colour-camera poses: the source's depth-camera poses times the fitted offset (scone_train.data.refine_camera)"]
    for stamp, T in zip(scene.stamps, scene.T_wc):
        if T is None:
            continue
        Tc = T @ Tdc
        q = Rotation.from_matrix(Tc[:3, :3]).as_quat()  # x y z w
        lines.append(f"{stamp} " + " ".join(f"{v:.9f}" for v in [*Tc[:3, 3], *q]))
    (out / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    (out / "camera.txt").write_text(f"{p[0]:.4f} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f} {scene.width} {scene.height}\n")
    (out / "rgb.txt").write_text((src / "rgb.txt").read_text())
    if not (out / "rgb").exists():
        os.symlink(src / "rgb", out / "rgb")
    (out / "SOURCE").write_text(
        f"Derived from {src} by scone_train.data.refine_camera (camera model and depth-to-colour offset fitted to SIFT "
        f"correspondences); images are the source's (symlink). Licence: as the source.\n"
    )
    (out / "refine.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
