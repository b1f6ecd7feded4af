"""Ground-truth correspondences from geometry alone ("similar" = the same 3D landmark).

No descriptor is consulted here: a landmark found by matching FREAK (or SConE) and then checked geometrically
would favour that descriptor, because its nearest neighbours would be correct by construction.

* With depth: a keypoint with a depth reading is back-projected with the frame's pose and projected into the
  other frame. It is linked to the nearest keypoint there when that keypoint lies within `radius` pixels,
  the projected depth agrees with the other frame's depth reading (relative `depth_tol`, which rejects
  occluded points), the keypoint sizes agree with the depth ratio within `scale_tol` (one pyramid level is
  1.2), and the link is mutual (the same test from the other side picks the first keypoint).
* Without depth (Strecha, KITTI; and the pairs of a partly depth-covered scene where a frame lacks it): for keypoint a of frame i, the keypoints of frame j within `epi_px` of its
  epipolar line are candidates. Each candidate is triangulated with the known poses; it survives when the
  point lies in front of both cameras, the sizes agree with the depth ratio, and the point lands within
  `third_px` of a keypoint of at least one third frame. a is linked to b only when exactly one candidate
  survives; the third-frame keypoint is linked too.

Links are chained into tracks (union-find); a track holding two keypoints of one frame is dropped. The result
is a landmark id per keypoint per frame (-1 = none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .features import FrameFeatures
from .scenes import Scene


@dataclass
class GeometryParams:
    radius: float = 2.0  # px, depth case
    depth_tol: float = 0.05
    scale_tol: float = 1.3
    epi_px: float = 1.0
    third_px: float = 1.5
    window: int = 0  # link frames at most this far apart in index (0 = all pairs)
    neighbours: int = 0  # >0: link each frame only to this many others with the nearest optical axes
    # "drop": join every link, then drop each track that holds two keypoints of one frame; "refuse": refuse a
    # link that would join two tracks seen in a common frame (first come, first kept), so no track is dropped
    tracks: str = "drop"


class UnionFind:
    def __init__(self, n: int):
        self.parent = np.arange(n)

    def find(self, a: int) -> int:
        root = a
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[a] != root:
            self.parent[a], a = root, self.parent[a]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


class Tracks:
    """Keypoints (numbered across frames, `frame_of` giving each one's frame) joined into tracks link by link.
    With `refuse`, a link that would join two tracks seen in a common frame is refused and counted (`refused`),
    so no track ever holds two keypoints of one frame; without, every link is joined."""

    def __init__(self, frame_of: np.ndarray, refuse: bool):
        self.uf = UnionFind(len(frame_of))
        self.frame_of = frame_of
        self.refuse = refuse
        self.frames: dict[int, set] = {}  # the frames of each track of two or more keypoints, by its root
        self.refused = 0

    def join(self, a: int, b: int) -> None:
        if not self.refuse:
            self.uf.union(a, b)
            return
        ra, rb = self.uf.find(a), self.uf.find(b)
        if ra == rb:
            return
        fa = self.frames.get(ra) or {int(self.frame_of[ra])}
        fb = self.frames.get(rb) or {int(self.frame_of[rb])}
        if fa & fb:
            self.refused += 1
            return
        self.frames.pop(ra, None)
        self.frames.pop(rb, None)
        self.uf.union(ra, rb)
        big, small = (fa, fb) if len(fa) >= len(fb) else (fb, fa)
        big |= small
        self.frames[self.uf.find(ra)] = big


def _world_to_cam(T_wc: np.ndarray, X: np.ndarray) -> np.ndarray:
    R, t = T_wc[:3, :3], T_wc[:3, 3]
    return (X - t) @ R  # R^T (X - t)


def _backproject(K: np.ndarray, T_wc: np.ndarray, xy: np.ndarray, z: np.ndarray) -> np.ndarray:
    Kinv = np.linalg.inv(K)
    rays = np.c_[xy, np.ones(len(xy))] @ Kinv.T
    Xc = rays * z[:, None]
    return Xc @ T_wc[:3, :3].T + T_wc[:3, 3]


def _project(K: np.ndarray, Xc: np.ndarray) -> np.ndarray:
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3]


def _depth_at(depth: np.ndarray, xy: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    xi = np.clip(np.round(xy[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.round(xy[:, 1]).astype(int), 0, h - 1)
    return depth[yi, xi]


def _depth_links(scene: Scene, feats: list[FrameFeatures], depths, i: int, j: int, p: GeometryParams):
    """Mutual depth-consistent links between frames i and j: list of (a, b)."""

    def one_way(s: int, t: int):
        ks, kt = feats[s].keypoints, feats[t].keypoints
        zs = _depth_at(depths[s], ks[:, :2])
        ok = zs > 0
        idx = np.nonzero(ok)[0]
        if len(idx) == 0 or len(kt) == 0:
            return {}
        Xw = _backproject(scene.K, scene.T_wc[s], ks[idx, :2].astype(np.float64), zs[idx].astype(np.float64))
        Xc = _world_to_cam(scene.T_wc[t], Xw)
        front = Xc[:, 2] > 1e-6
        idx, Xc = idx[front], Xc[front]
        uv = _project(scene.K, Xc)
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= scene.width - 1) & (uv[:, 1] <= scene.height - 1)
        idx, Xc, uv = idx[inside], Xc[inside], uv[inside]
        zt = _depth_at(depths[t], uv)
        visible = (zt > 0) & (np.abs(zt - Xc[:, 2]) <= p.depth_tol * Xc[:, 2])
        idx, Xc, uv = idx[visible], Xc[visible], uv[visible]
        tree = cKDTree(kt[:, :2])
        out = {}
        # Several keypoints (pyramid levels) can sit at one spot: among those within the radius take the one
        # whose size best fits the depth ratio, then the nearest.
        for a, z_t, cand in zip(idx, Xc[:, 2], tree.query_ball_point(uv, p.radius)):
            if not cand:
                continue
            expected = ks[a, 2] * zs[a] / z_t
            ratios = np.abs(np.log(kt[cand, 2] / expected))
            best = int(np.argmin(ratios))
            if ratios[best] <= np.log(p.scale_tol):
                out[a] = cand[best]
        return out

    fwd, bwd = one_way(i, j), one_way(j, i)
    return [(a, b) for a, b in fwd.items() if bwd.get(b) == a]


def _fundamental(K: np.ndarray, T_i: np.ndarray, T_j: np.ndarray) -> np.ndarray:
    T_ji = np.linalg.inv(T_j) @ T_i  # frame i -> frame j
    R, t = T_ji[:3, :3], T_ji[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Kinv = np.linalg.inv(K)
    return Kinv.T @ tx @ R @ Kinv


def _triangulate(K, T_i, T_j, xi: np.ndarray, xj: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of many point pairs; world coordinates."""
    P_i = K @ np.linalg.inv(T_i)[:3]
    P_j = K @ np.linalg.inv(T_j)[:3]
    A = np.stack(
        [
            xi[:, 0:1] * P_i[2] - P_i[0],
            xi[:, 1:2] * P_i[2] - P_i[1],
            xj[:, 0:1] * P_j[2] - P_j[0],
            xj[:, 1:2] * P_j[2] - P_j[1],
        ],
        axis=1,
    )
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    return X[:, :3] / X[:, 3:4]


def _epipolar_links(scene: Scene, feats, trees, i: int, j: int, p: GeometryParams):
    """Links (frame, keypoint) pairs between i, j and third frames from epipolar geometry + a third view."""
    K = scene.K
    ki, kj = feats[i].keypoints, feats[j].keypoints
    if len(ki) == 0 or len(kj) == 0:
        return []
    F = _fundamental(K, scene.T_wc[i], scene.T_wc[j])
    xi = np.c_[ki[:, :2], np.ones(len(ki))]
    xj = np.c_[kj[:, :2], np.ones(len(kj))]
    lines = xi @ F.T  # epipolar lines in j, one per keypoint of i
    norm = np.hypot(lines[:, 0], lines[:, 1])[:, None]
    dist = np.abs(lines @ xj.T) / np.maximum(norm, 1e-12)  # [Ni, Nj]
    ai, bj = np.nonzero(dist <= p.epi_px)
    if len(ai) == 0:
        return []
    X = _triangulate(K, scene.T_wc[i], scene.T_wc[j], ki[ai, :2].astype(np.float64), kj[bj, :2].astype(np.float64))
    zi = _world_to_cam(scene.T_wc[i], X)[:, 2]
    zj = _world_to_cam(scene.T_wc[j], X)[:, 2]
    ok = (zi > 0) & (zj > 0) & np.isfinite(X).all(axis=1)
    expected = ki[ai, 2] * zi / np.where(zj > 0, zj, 1)
    ok &= np.abs(np.log(np.maximum(kj[bj, 2], 1e-6) / np.maximum(expected, 1e-6))) <= np.log(p.scale_tol)
    third_hit = np.full(len(ai), -1)
    third_frame = np.full(len(ai), -1)
    others = [f for f in range(len(feats)) if f not in (i, j) and scene.T_wc[f] is not None and len(feats[f])]
    if p.window:
        others = [f for f in others if abs(f - i) <= p.window and abs(f - j) <= p.window]
    if p.neighbours:
        near_i = set(_axis_neighbours(scene, p.neighbours)[i])
        others = [f for f in others if f in near_i]
    for f in others:
        todo = np.nonzero(ok & (third_hit < 0))[0]
        if len(todo) == 0:
            break
        Xc = _world_to_cam(scene.T_wc[f], X[todo])
        front = Xc[:, 2] > 0
        todo, Xc = todo[front], Xc[front]
        uv = _project(K, Xc)
        d, nn = trees[f].query(uv, distance_upper_bound=p.third_px)
        hit = np.isfinite(d)
        third_hit[todo[hit]] = nn[hit]
        third_frame[todo[hit]] = f
    ok &= third_hit >= 0
    links = []
    counts = np.bincount(ai[ok], minlength=len(ki))
    # Also require b to be unambiguous from j's side (only one a of i on its line survives).
    counts_b = np.bincount(bj[ok], minlength=len(kj))
    for n in np.nonzero(ok)[0]:
        a, b = ai[n], bj[n]
        if counts[a] == 1 and counts_b[b] == 1:
            links.append(((i, a), (j, b)))
            links.append(((i, a), (third_frame[n], third_hit[n])))
    return links


def _axis_neighbours(scene: Scene, n: int) -> dict[int, list[int]]:
    """For each posed frame, the n other posed frames whose optical axes are nearest in angle (cached)."""
    key = (id(scene), n)
    if key not in _AXIS_CACHE:
        posed = [k for k in range(len(scene.T_wc)) if scene.T_wc[k] is not None]
        axes = np.array([scene.T_wc[k][:3, 2] for k in posed])
        cos = axes @ axes.T
        out = {}
        for r, k in enumerate(posed):
            order = [posed[c] for c in np.argsort(-cos[r]) if posed[c] != k]
            out[k] = order[:n]
        _AXIS_CACHE[key] = out
    return _AXIS_CACHE[key]


_AXIS_CACHE: dict = {}


def landmarks(scene: Scene, feats: list[FrameFeatures], params: GeometryParams | None = None,
              stats: dict | None = None) -> list[np.ndarray]:
    """Landmark id per keypoint of every frame (-1 = not part of a consistent track of >= 2 frames). `stats`, when
    given, receives the keypoints that some link joined to another frame's (`linked`), those of them dropped
    because their track holds two keypoints of one frame (`conflicted`), those kept (`kept`), and the links
    refused (`refused`, with `params.tracks` "refuse")."""
    p = params or GeometryParams()
    if p.tracks not in ("drop", "refuse"):
        raise ValueError(f"tracks must be 'drop' or 'refuse', not {p.tracks!r}")
    offsets = np.cumsum([0] + [len(f) for f in feats])
    n = len(feats)
    frame_of = np.repeat(np.arange(n), [len(f) for f in feats])
    tracks = Tracks(frame_of, refuse=p.tracks == "refuse")
    join = tracks.join
    posed = [k for k in range(n) if scene.T_wc[k] is not None]
    pairs = [(i, j) for i in posed for j in posed if i < j and (not p.window or j - i <= p.window)]
    if p.neighbours:
        near = _axis_neighbours(scene, p.neighbours)
        pairs = [(i, j) for i, j in pairs if j in near[i] or i in near[j]]
    # Depth where both frames have it; the epipolar rule for the other pairs of a scene whose depth covers only
    # some frames (TUM's 30 Hz burst has depth, its 1 Hz frames do not). A scene with depth on every frame
    # is labelled by depth alone, as before.
    depths = [scene.load_depth(k) for k in range(n)] if scene.has_depth else [None] * n
    all_depth = all(depths[k] is not None for k in posed)
    trees = None
    for i, j in pairs:
        if depths[i] is not None and depths[j] is not None:
            for a, b in _depth_links(scene, feats, depths, i, j, p):
                join(offsets[i] + a, offsets[j] + b)
        elif not all_depth:
            if trees is None:
                trees = [cKDTree(f.keypoints[:, :2]) if len(f) else None for f in feats]
            for (fa, a), (fb, b) in _epipolar_links(scene, feats, trees, i, j, p):
                join(offsets[fa] + a, offsets[fb] + b)
    roots = np.array([tracks.uf.find(x) for x in range(offsets[-1])])
    # Drop tracks with two keypoints in one frame, and singletons.
    order = np.lexsort((frame_of, roots))
    r_sorted, f_sorted = roots[order], frame_of[order]
    dup = np.zeros(len(roots), bool)
    same = (r_sorted[1:] == r_sorted[:-1]) & (f_sorted[1:] == f_sorted[:-1])
    bad_roots = set(r_sorted[1:][same].tolist())
    size = np.bincount(roots, minlength=len(roots))
    for k in range(len(roots)):
        dup[k] = roots[k] in bad_roots or size[roots[k]] < 2
    ids = np.where(dup, -1, roots)
    if stats is not None:
        linked = size[roots] >= 2
        stats.update(linked=int(linked.sum()), conflicted=int((linked & dup).sum()), kept=int((~dup).sum()),
                     refused=tracks.refused)
    # Renumber to 0..L-1.
    uniq, inv = np.unique(ids[ids >= 0], return_inverse=True)
    out_ids = np.full(len(ids), -1)
    out_ids[ids >= 0] = inv
    return [out_ids[offsets[k] : offsets[k + 1]] for k in range(n)]


def summary(ids: list[np.ndarray]) -> dict:
    allids = np.concatenate(ids) if ids else np.zeros(0, int)
    valid = allids[allids >= 0]
    track_len = np.bincount(valid) if len(valid) else np.zeros(0, int)
    return {
        "frames": len(ids),
        "keypoints": int(len(allids)),
        "observations": int(len(valid)),
        "landmarks": int(len(track_len)),
        "mean_track_length": float(track_len.mean()) if len(track_len) else 0.0,
    }
