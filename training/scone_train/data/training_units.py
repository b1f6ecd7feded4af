"""Training units (a sequence or a part of a scene): features from the Rust export with geometry-only landmarks;
and the samplers of frame pairs and groups of frames that the training draws from them."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import correspondences as C
from .features import FrameFeatures, export_features, load_features
from .scenes import Scene, load_scene


@dataclass
class Unit:
    name: str
    frames: list[FrameFeatures]
    ids: list[np.ndarray]  # landmark id per keypoint, -1 none
    real: bool = False  # photographs (castle-P30) rather than rendered frames
    scene: bool = False  # views of a real 3D scene (multi-view labels), not warps of one photograph

    def observations(self) -> int:
        return int(sum((i >= 0).sum() for i in self.ids))


def subset(scene: Scene, frames: list[FrameFeatures], keep: list[int]) -> tuple[Scene, list[FrameFeatures]]:
    s = Scene(
        scene.root,
        scene.name,
        scene.K,
        scene.width,
        scene.height,
        [scene.stamps[k] for k in keep],
        [scene.rgb[k] for k in keep],
        [scene.T_wc[k] for k in keep],
        [scene.depth[k] for k in keep],
    )
    return s, [frames[k] for k in keep]


def build_unit(
    scene_dir: Path,
    cache: Path,
    keep: list[int] | None = None,
    params: C.GeometryParams | None = None,
    name: str | None = None,
    extractor_args: list[str] | None = None,
    gradients: bool = False,
) -> Unit:
    """Features (Rust export with `extractor_args`, cached; with `gradients`, the ring's gradients too) +
    landmarks (cached by a key of the inputs) for one scene or a part."""
    scene_dir = Path(scene_dir)
    cache.mkdir(parents=True, exist_ok=True)
    npz = export_features(scene_dir, cache / f"{scene_dir.name}.features.npz", extractor_args)
    scene = load_scene(scene_dir)
    _, frames = load_features(npz, scene_dir, gradients)
    if keep is not None:
        scene, frames = subset(scene, frames, keep)
    p = params or C.GeometryParams()
    # The default track rule ("drop") is left out of the key: it is how every cache before the option was made.
    geometry = {k: v for k, v in p.__dict__.items() if not (k == "tracks" and v == "drop")}
    key = hashlib.sha256(
        json.dumps([str(npz), npz.with_suffix(".key").read_text(), keep, geometry], sort_keys=True).encode()
    ).hexdigest()[:16]
    lm_path = cache / f"{scene_dir.name}.{key}.landmarks.npz"
    if lm_path.exists():
        z = np.load(lm_path)
        ids = [z[f"f{k}"] for k in range(len(frames))]
    else:
        ids = C.landmarks(scene, frames, p)
        np.savez(lm_path, **{f"f{k}": v for k, v in enumerate(ids)})
    return Unit(name or scene_dir.name, frames, ids)


def warp_ids(kp1: np.ndarray, kpk: np.ndarray, h: np.ndarray, tol_px: float = 2.0, levels: float = 1.5) -> np.ndarray:
    """Landmark ids of image k's keypoints under the exact homography `h` (image 1 -> k): the index of the
    image-1 keypoint whose image lies within `tol_px` of it, mutual nearest, and whose size times the local zoom
    of `h` agrees with its size within `levels` pyramid levels (a factor 1.2 each); -1 otherwise.
    Keypoint rows are x, y, size, angle, ... as in `FrameFeatures`."""
    ids = np.full(len(kpk), -1, dtype=np.int64)
    if len(kp1) == 0 or len(kpk) == 0:
        return ids
    p = np.c_[kp1[:, :2].astype(np.float64), np.ones(len(kp1))] @ h.T
    ok = p[:, 2] > 1e-9
    proj = np.where(ok[:, None], p[:, :2] / np.where(ok, p[:, 2], 1.0)[:, None], np.inf)
    # Local zoom of h at each image-1 keypoint (square root of the Jacobian's determinant).
    d = 0.5
    px = np.c_[kp1[:, 0] + d, kp1[:, 1], np.ones(len(kp1))] @ h.T
    py = np.c_[kp1[:, 0], kp1[:, 1] + d, np.ones(len(kp1))] @ h.T
    with np.errstate(divide="ignore", invalid="ignore"):
        jx = (px[:, :2] / px[:, 2:3] - proj) / d
        jy = (py[:, :2] / py[:, 2:3] - proj) / d
        zoom = np.sqrt(np.abs(jx[:, 0] * jy[:, 1] - jx[:, 1] * jy[:, 0]))
    from scipy.spatial import cKDTree

    finite = np.isfinite(proj).all(1)
    idx1 = np.nonzero(finite)[0]
    if len(idx1) == 0:
        return ids
    tree1 = cKDTree(proj[idx1])
    dk, nk = tree1.query(kpk[:, :2].astype(np.float64), distance_upper_bound=tol_px)
    treek = cKDTree(kpk[:, :2].astype(np.float64))
    _, back = treek.query(proj[idx1], distance_upper_bound=tol_px)
    limit = levels * np.log(1.2)
    for j in range(len(kpk)):
        if not np.isfinite(dk[j]):
            continue
        i = idx1[nk[j]]
        if back[nk[j]] != j:
            continue
        if abs(np.log(kpk[j, 2] / (kp1[i, 2] * zoom[i]))) > limit:
            continue
        ids[j] = i
    return ids


def build_warp_unit(seq_dir: Path, cache: Path, tol_px: float = 2.0, extractor_args: list[str] | None = None,
                    gradients: bool = False) -> Unit:
    """A sequence of `scone_train.data.warps` (HPatches layout plus rgb.txt) as a training unit: features from the
    Rust export, landmarks from the exact homographies (`warp_ids`; image 1's keypoint i is landmark i)."""
    seq_dir = Path(seq_dir)
    cache.mkdir(parents=True, exist_ok=True)
    npz = export_features(seq_dir, cache / f"{seq_dir.name}.features.npz", extractor_args)
    _, frames = load_features(npz, seq_dir, gradients)
    ids = [np.arange(len(frames[0]), dtype=np.int64)]
    for k in range(1, len(frames)):
        h = np.loadtxt(seq_dir / f"H_1_{k + 1}")
        ids.append(warp_ids(frames[0].keypoints, frames[k].keypoints, h, tol_px))
    return Unit(f"warp-{seq_dir.name}", frames, ids, real=True)


def shared_anchors(ida: np.ndarray, idb: np.ndarray, cap: int, rng: np.random.Generator):
    """Landmarks seen in both frames with the keypoint that observes each in a and in b: (ids, ia, ib),
    at most `cap` of them, drawn with `rng` when there are more."""
    shared, ia, ib = np.intersect1d(ida, idb, return_indices=True)
    keep = shared >= 0
    shared, ia, ib = shared[keep], ia[keep], ib[keep]
    if len(shared) > cap:
        pick = rng.choice(len(shared), cap, replace=False)
        shared, ia, ib = shared[pick], ia[pick], ib[pick]
    return shared, ia, ib


@dataclass
class PairBatch:
    """One frame pair: anchors in frame a, their positives in frame b, and a pool of other keypoints of b."""

    fa: FrameFeatures
    fb: FrameFeatures
    anchors: np.ndarray
    positives: np.ndarray
    pool: np.ndarray
    anchor_ids: np.ndarray
    pool_ids: np.ndarray


class PairSampler:
    """Draws frame pairs (weighted by their shared landmarks) and, per pair, anchors with their positives."""

    def __init__(self, units: list[Unit], anchors: int, pool: int, seed: int, min_shared: int = 8, near: int = 0,
                 weight: str = "shared"):
        """`weight`: "shared" draws a pair in proportion to its shared landmarks (capped at `anchors`);
        "uniform" draws every pair with at least `min_shared` alike, which gives wide baselines more weight."""
        if weight not in ("shared", "uniform"):
            raise ValueError(f"unknown pair weight {weight!r}")
        self.anchors = anchors
        self.pool = pool
        self.near = near
        self.rng = np.random.default_rng(seed)
        self.pairs: list[tuple[Unit, int, int]] = []
        weights = []
        for u in units:
            for a in range(len(u.frames)):
                ids_a = np.unique(u.ids[a][u.ids[a] >= 0])
                for b in range(len(u.frames)):
                    if a == b:
                        continue
                    shared = len(np.intersect1d(ids_a, u.ids[b], assume_unique=False))
                    if shared >= min_shared:
                        self.pairs.append((u, a, b))
                        weights.append(min(shared, anchors) if weight == "shared" else 1)
        if not self.pairs:
            raise RuntimeError("no frame pair with enough shared landmarks")
        w = np.asarray(weights, dtype=np.float64)
        self.weights = w / w.sum()

    def sample(self) -> PairBatch:
        u, a, b = self.pairs[self.rng.choice(len(self.pairs), p=self.weights)]
        idb = u.ids[b]
        shared, ia, ib = shared_anchors(u.ids[a], idb, self.anchors, self.rng)
        nb = len(u.frames[b])
        pool = self.rng.choice(nb, min(self.pool, nb), replace=False)
        if self.near:
            # Spatial hard negatives: the keypoints nearest to each positive in the second frame. Their
            # constellations overlap the positive's, so they are what an embedding confuses first.
            fb = u.frames[b]
            near = fb.neighbours[ib, : self.near][fb.mask[ib, : self.near] > 0]
            pool = np.unique(np.concatenate([pool, near]))
        return PairBatch(u.frames[a], u.frames[b], ia, ib, pool, shared, idb[pool])


@dataclass
class FrameGroup:
    """A few frames of one unit that see common landmarks; every ordered pair with shared landmarks is used."""

    unit: Unit
    frames: list[int]
    pairs: list[tuple[int, int]]  # positions in `frames`


class GroupSampler:
    """Draws a frame pair as `PairSampler` does, then adds up to `size - 2` more frames that share landmarks
    with the first. Each frame is embedded once per step and every pair of the group contributes, so the
    whole-frame negatives cost one embedding per frame rather than one per pair."""

    def __init__(self, units: list[Unit], size: int, seed: int, min_shared: int = 8, weight: str = "shared",
                 real_share: float = 0.0, scene_share: float = 0.0):
        """`real_share` > 0: that share of the groups comes from real units (`Unit.real`), the rest from
        rendered ones; within each part pairs are drawn by `weight`. 0 draws from all pairs by `weight`; with the
        default castle labels the real scene then gets about 0.02 % of the groups (12 of 23,358 pairs).
        `scene_share` > 0 does the same between the views of real 3D scenes (`Unit.scene`) and the rest (warps
        of photographs, rendered sequences)."""
        self.pairs = PairSampler(units, anchors=128, pool=0, seed=seed, min_shared=min_shared, weight=weight)
        if real_share > 0 and scene_share > 0:
            raise ValueError("give real_share or scene_share, not both")
        self.real_share = real_share or scene_share
        if self.real_share > 0:
            attr = "real" if real_share > 0 else "scene"
            real = np.array([getattr(u, attr) for u, _, _ in self.pairs.pairs])
            if real.all() or not real.any():
                raise ValueError(f"{attr}_share needs frame pairs of both kinds")
            w = self.pairs.weights
            self.parts = [(np.nonzero(sel)[0], w[sel] / w[sel].sum()) for sel in (~real, real)]
        self.rng = self.pairs.rng
        self.size = size
        self.partners: dict[tuple[int, int], list[int]] = {}
        for u, a, b in self.pairs.pairs:
            self.partners.setdefault((id(u), a), []).append(b)
        self.min_shared = min_shared

    def sample(self) -> FrameGroup:
        if self.real_share > 0:
            idx, p = self.parts[int(self.rng.random() < self.real_share)]
            u, a, b = self.pairs.pairs[idx[self.rng.choice(len(idx), p=p)]]
        else:
            u, a, b = self.pairs.pairs[self.rng.choice(len(self.pairs.pairs), p=self.pairs.weights)]
        others = [f for f in self.partners[(id(u), a)] if f != b]
        extra = list(self.rng.choice(others, min(self.size - 2, len(others)), replace=False)) if others else []
        frames = [a, b, *[int(f) for f in extra]]
        pairs = []
        for i in range(len(frames)):
            ids_i = u.ids[frames[i]]
            for j in range(len(frames)):
                if i == j:
                    continue
                shared = np.intersect1d(ids_i[ids_i >= 0], u.ids[frames[j]])
                if len(shared) >= self.min_shared:
                    pairs.append((i, j))
        return FrameGroup(u, frames, pairs)
