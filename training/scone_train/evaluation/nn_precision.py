"""Nearest-neighbour precision, the paper's descriptor metric, on geometry-only ground truth.

Queries are keypoints whose landmark is observed in at least one other frame (within `window` frames when
set). For each query the nearest descriptor among **all** keypoints of the other frames (within the window;
with or without a landmark) is found; the query is correct when that keypoint observes the same landmark.
A tie at the nearest distance counts against the method unless every tied keypoint is correct (FREAK's
integer Hamming distances tie often). A bootstrap over queries gives a 95 % interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..data.features import FrameFeatures
from ..model.network import SconeNet


def freak_pm1(desc: np.ndarray) -> np.ndarray:
    """FREAK bytes -> ±1 float vectors; Hamming = (512 - a·b) / 2."""
    return np.unpackbits(desc, axis=1, bitorder="little").astype(np.float32) * 2 - 1


@torch.no_grad()
def embed_frames(model: SconeNet, frames: list[FrameFeatures]) -> list[np.ndarray]:
    model.eval()
    out = []
    for f in frames:
        if len(f) == 0:
            out.append(np.zeros((0, model.head[-1].out_features), np.float32))
            continue
        e = model(*model.frame_inputs(f))
        out.append(e.numpy())
    return out


@dataclass
class Precision:
    precision: float
    low: float
    high: float
    queries: int

    def as_dict(self) -> dict:
        return {"precision": self.precision, "ci95": [self.low, self.high], "queries": self.queries}


def nn_correct(
    vectors: list[np.ndarray],
    ids: list[np.ndarray],
    kind: str,
    window: int = 0,
    max_queries_per_frame: int = 0,
    seed: int = 0,
) -> np.ndarray:
    """Per-query correctness (bool array). kind: 'l2' (embeddings) or 'hamming' (±1 FREAK vectors)."""
    rng = np.random.default_rng(seed)
    n = len(vectors)
    results = []
    for i in range(n):
        others = [j for j in range(n) if j != i and (not window or abs(j - i) <= window) and len(vectors[j])]
        if not others:
            continue
        pool_ids = np.concatenate([ids[j] for j in others])
        q_idx = np.nonzero(ids[i] >= 0)[0]
        q_idx = q_idx[np.isin(ids[i][q_idx], pool_ids[pool_ids >= 0])]
        if max_queries_per_frame and len(q_idx) > max_queries_per_frame:
            q_idx = rng.choice(q_idx, max_queries_per_frame, replace=False)
        if len(q_idx) == 0:
            continue
        pool = np.concatenate([vectors[j] for j in others])
        q = vectors[i][q_idx]
        if kind == "hamming":
            dist = (q.shape[1] - q @ pool.T) / 2.0  # exact integers in float32
        else:
            dist = (q * q).sum(1)[:, None] - 2 * q @ pool.T + (pool * pool).sum(1)[None, :]
        best = dist.min(axis=1, keepdims=True)
        tol = 0.5 if kind == "hamming" else 1e-6
        tied = dist <= best + tol
        same = pool_ids[None, :] == ids[i][q_idx][:, None]
        correct = (tied & same).sum(1) == tied.sum(1)
        results.append(correct)
    return np.concatenate(results) if results else np.zeros(0, bool)


def bootstrap(correct: np.ndarray, reps: int = 1000, seed: int = 0) -> Precision:
    if len(correct) == 0:
        return Precision(float("nan"), float("nan"), float("nan"), 0)
    rng = np.random.default_rng(seed)
    means = correct[rng.integers(0, len(correct), (reps, len(correct)))].mean(1)
    return Precision(float(correct.mean()), float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5)), len(correct))


def freak_precision(frames: list[FrameFeatures], ids, window: int = 0, max_q: int = 0) -> Precision:
    return bootstrap(nn_correct([freak_pm1(f.descriptors) for f in frames], ids, "hamming", window, max_q))


def scone_precision(model: SconeNet, frames: list[FrameFeatures], ids, window: int = 0, max_q: int = 0) -> Precision:
    return bootstrap(nn_correct(embed_frames(model, frames), ids, "l2", window, max_q))
