"""Tests of the correct-match layout diagnostic (scone_train.evaluation.planarity) on synthetic geometry."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_train.evaluation import planarity as P  # noqa: E402


def test_same_corner_copy_does_not_compete_but_a_distinct_corner_does():
    # One query; train rows: the true match, its copy 1 px away (nearly as close), a distinct corner 50 px away.
    pts = np.array([[10.0, 10.0], [11.0, 10.0], [60.0, 10.0]])
    d = np.array([[1.0, 1.1, 3.0]])
    assert P.ratio_matches(d, pts).tolist() == [[0, 0]]
    d = np.array([[1.0, 1.1, 1.2]])  # the distinct corner is nearly as close: ambiguous
    assert P.ratio_matches(d, pts).shape == (0, 2)


def _two_views(points: np.ndarray):
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    yaw = np.radians(10)
    R = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    t = np.array([-0.5, 0.0, 0.1])
    xa = (K @ points.T).T
    xb = (K @ (R @ points.T + t[:, None])).T
    F = np.linalg.inv(K).T @ P.skew(t) @ R @ np.linalg.inv(K)
    return xa[:, :2] / xa[:, 2:], xb[:, :2] / xb[:, 2:], F


def test_layout_counts_correct_matches_and_sees_a_plane():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, 60), rng.uniform(-1, 1, 60), np.full(60, 5.0)]
    xa, xb, F = _two_views(plane)
    wrong = xb.copy()
    wrong[:10] += 40.0  # ten matches off their epipolar lines
    r = P.layout(xa, wrong, F, 2.0, 640 * 480)
    assert r["matches"] == 60 and r["correct"] == 50
    assert r["one_plane"] > 0.99
    # Points spread in depth are not explained by one homography.
    spread = np.c_[rng.uniform(-1, 1, 60), rng.uniform(-1, 1, 60), rng.uniform(3, 9, 60)]
    xa, xb, F = _two_views(spread)
    r = P.layout(xa, xb, F, 2.0, 640 * 480)
    assert r["correct"] == 60 and r["one_plane"] < 0.8
    assert 0 < r["hull"] < 1
