"""How good is each scene's ground truth, in pixels? `python -m scone_train.data.residuals [--scenes A,B] [--out F.json]`

Measured with a descriptor that is not under test (OpenCV SIFT, ratio 0.8, mutual), on frame pairs drawn
across the scene's range of viewpoints. The matches are first made consistent with the images alone (a
fundamental matrix by RANSAC at 1 px, no ground truth involved), so what remains are true correspondences up to
about a pixel; their distance to the ground-truth epipolar lines is then the ground truth's own error. Where the
scene has depth, the reference keypoint is also back-projected with its depth and projected with the poses.

The per-scene tolerances of the training labels (`tolerances`) are derived from these figures by a rule
fixed before training (see `docs/model-experiments.md`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from ..paths import shared_data
from .correspondences import _fundamental
from .scenes import Scene, load_scene


def _sift(img: np.ndarray, sift) -> tuple[np.ndarray, np.ndarray]:
    kps, desc = sift.detectAndCompute(img, None)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    return xy, desc


def _mutual_ratio(da: np.ndarray, db: np.ndarray) -> np.ndarray:
    bf = cv2.BFMatcher(cv2.NORM_L2)
    fwd = bf.knnMatch(da, db, k=2)
    back = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(db, da, k=1) if m}
    out = [(m[0].queryIdx, m[0].trainIdx) for m in fwd if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    return np.array([(a, b) for a, b in out if back.get(b) == a], int).reshape(-1, 2)


def epipolar_distance(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distance (the larger of the two), pixels."""
    pa = np.c_[xa, np.ones(len(xa))]
    pb = np.c_[xb, np.ones(len(xb))]
    lb = pa @ F.T
    la = pb @ F
    db = np.abs((lb * pb).sum(1)) / np.hypot(lb[:, 0], lb[:, 1])
    da = np.abs((la * pa).sum(1)) / np.hypot(la[:, 0], la[:, 1])
    return np.maximum(da, db)


def optical_angle(Ta: np.ndarray, Tb: np.ndarray) -> float:
    c = float(np.clip(Ta[:3, 2] @ Tb[:3, 2], -1, 1))
    return float(np.degrees(np.arccos(c)))


def sample_pairs(scene: Scene, n: int, rng: np.random.Generator, lo: float = 3.0, hi: float = 45.0) -> list:
    """Up to n frame pairs whose optical axes are lo..hi degrees apart and whose centres differ."""
    posed = [k for k in range(len(scene.rgb)) if scene.T_wc[k] is not None]
    cand = []
    for _ in range(n * 200):
        i, j = rng.choice(posed, 2, replace=False)
        a = optical_angle(scene.T_wc[i], scene.T_wc[j])
        base = np.linalg.norm(scene.T_wc[i][:3, 3] - scene.T_wc[j][:3, 3])
        if lo <= a <= hi and base > 1e-6:
            cand.append((int(min(i, j)), int(max(i, j))))
        if len(set(cand)) >= n:
            break
    return sorted(set(cand))[:n]


def measure(scene: Scene, pairs: list, sift=None) -> dict:
    sift = sift or cv2.SIFT_create(2000)
    cache: dict[int, tuple] = {}

    def feats(k: int):
        if k not in cache:
            cache[k] = _sift(cv2.imread(str(scene.rgb[k]), cv2.IMREAD_GRAYSCALE), sift)
        return cache[k]

    epi, dep, per_pair = [], [], []
    for i, j in pairs:
        (xa, da), (xb, db) = feats(i), feats(j)
        if da is None or db is None or len(xa) < 8 or len(xb) < 8:
            continue
        m = _mutual_ratio(da, db)
        if len(m) < 15:
            continue
        pa, pb = xa[m[:, 0]], xb[m[:, 1]]
        _, inl = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, 1.0, 0.999, 10000)
        if inl is None:
            continue
        keep = inl.ravel() > 0
        if keep.sum() < 15:
            continue
        pa, pb = pa[keep], pb[keep]
        F = _fundamental(scene.K, scene.T_wc[i], scene.T_wc[j])
        e = epipolar_distance(F, pa, pb)
        epi.append(e)
        per_pair.append({"pair": [scene.stamps[i], scene.stamps[j]], "matches": int(len(pa)), "median_px": float(np.median(e))})
        if scene.depth and scene.depth[i] is not None:
            d = scene.load_depth(i)
            z = d[np.clip(np.round(pa[:, 1]).astype(int), 0, d.shape[0] - 1), np.clip(np.round(pa[:, 0]).astype(int), 0, d.shape[1] - 1)]
            ok = z > 0
            if ok.any():
                Kinv = np.linalg.inv(scene.K)
                Xc = (np.c_[pa[ok], np.ones(ok.sum())] @ Kinv.T) * z[ok, None]
                Tab = np.linalg.inv(scene.T_wc[j]) @ scene.T_wc[i]
                Xb = Xc @ Tab[:3, :3].T + Tab[:3, 3]
                front = Xb[:, 2] > 1e-6
                uv = Xb[front] @ scene.K.T
                uv = uv[:, :2] / uv[:, 2:3]
                dep.append(np.hypot(*(uv - pb[ok][front]).T))
    out = {"pairs": len(per_pair), "per_pair": per_pair}
    if epi:
        e = np.concatenate(epi)
        out["epipolar_px"] = {q: float(np.percentile(e, p)) for q, p in (("p50", 50), ("p75", 75), ("p80", 80), ("p90", 90))}
        out["matches"] = int(len(e))
    if dep:
        d = np.concatenate(dep)
        out["depth_reprojection_px"] = {q: float(np.percentile(d, p)) for q, p in (("p50", 50), ("p75", 75), ("p80", 80), ("p90", 90))}
    return out


def tolerances(r: dict) -> dict:
    """The labelling tolerances a residual report implies (the rule in docs/model-experiments.md): the epipolar
    band is the 75th percentile of the ground truth's own epipolar error at the frame gaps the labels link, at
    least 1 px; the third-view radius 1.5 times that; the depth radius the 75th percentile of the depth
    reprojection error, at least 2 px."""
    epi = max(1.0, r["epipolar_px"]["p75"]) if "epipolar_px" in r else 1.0
    out = {"epi_px": round(epi, 2), "third_px": round(1.5 * epi, 2)}
    if "depth_reprojection_px" in r:
        out["radius"] = round(max(2.0, r["depth_reprojection_px"]["p75"]), 2)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="strecha-castle-P30,7scenes-redkitchen,sun3d-studyroom,middlebury-templeRing,liberty-internet")
    ap.add_argument("--root", default=None, help="scene directory root (default: ../shared/data/scenes)")
    ap.add_argument("--pairs", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    ap.add_argument("--gaps", default=None, help="instead: pairs this many frames apart, e.g. 3,10,30,60 (12 each)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    root = Path(args.root) if args.root else shared_data() / "scenes"
    report = {}
    for name in args.scenes.split(","):
        scene = load_scene(root / name)
        rng = np.random.default_rng(args.seed)
        if args.gaps:
            for g in (int(v) for v in args.gaps.split(",")):
                starts = rng.choice(len(scene.rgb) - g, 12, replace=False)
                r = measure(scene, [(int(i), int(i) + g) for i in starts])
                angle = float(np.median([optical_angle(scene.T_wc[i], scene.T_wc[i + g]) for i in starts]))
                report[f"{name}@{g}"] = {**r, "median_axis_angle_deg": angle}
                print(name, g, json.dumps({k: v for k, v in r.items() if k != "per_pair"}), f"angle {angle:.1f}", flush=True)
            continue
        r = measure(scene, sample_pairs(scene, args.pairs, rng))
        r["tolerances"] = tolerances(r)
        report[name] = r
        print(name, json.dumps({k: v for k, v in r.items() if k != "per_pair"}), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
