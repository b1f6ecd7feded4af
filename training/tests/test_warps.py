"""Tests of the exact-warp generator (scone_train.data.warps): the written H_1_k carries image 1 onto image k, the
pair parameters are what the file says, and a seed gives the same sequences."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from scone_train.data import warps  # noqa: E402


def _photo() -> np.ndarray:
    """A textured 320 x 240 test photograph (smoothed noise: corners everywhere, no repeats)."""
    rng = np.random.default_rng(3)
    img = cv2.resize(rng.uniform(0, 255, (60, 80, 3)).astype(np.uint8), (320, 240), interpolation=cv2.INTER_CUBIC)
    return cv2.GaussianBlur(img, (0, 0), 1.0)


def _zoom_rotation(h: np.ndarray, x: float, y: float) -> tuple[float, float]:
    def apply(px, py):
        p = h @ np.array([px, py, 1.0])
        return p[:2] / p[2]

    c, dx, dy = apply(x, y), apply(x + 0.5, y), apply(x, y + 0.5)
    a, cc = (dx - c) / 0.5
    b, dd = (dy - c) / 0.5
    return float(np.sqrt(abs(a * dd - b * cc))), float(np.degrees(np.arctan2(cc - b, a + dd)))


def test_homography_carries_image_1_onto_image_k(tmp_path):
    photo = _photo()
    rng = np.random.default_rng(0)
    for kind in ("zoom", "viewpoint"):
        out = tmp_path / kind
        pairs = warps.write_sequence(photo, kind, out, rng, "test")
        assert len(pairs) == warps.STEPS
        one = cv2.imread(str(out / "1.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        hgt, wid = one.shape
        assert (wid, hgt) == (240, 180)
        for p in pairs:
            k = p["image"]
            h = np.loadtxt(out / f"H_1_{k}")
            img_k = cv2.imread(str(out / f"{k}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
            # Image 1 pushed through H against image k, where both are defined and away from the borders.
            pushed = cv2.warpPerspective(one, h, (wid, hgt), flags=cv2.INTER_LINEAR, borderValue=-1)
            valid = cv2.erode((pushed >= 0).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
            valid &= img_k > 0
            assert valid.sum() > 0.05 * wid * hgt, (kind, k)
            a, b = pushed[valid], img_k[valid]
            # Gain and noise are applied to image k: compare after matching the means and spreads.
            a = (a - a.mean()) / a.std()
            b = (b - b.mean()) / b.std()
            corr = float((a * b).mean())
            assert corr > 0.9, (kind, k, corr)
            # A wrong H decorrelates: shift it by 4 px.
            off = np.array([[1, 0, 4.0], [0, 1, 0], [0, 0, 1]]) @ h
            shifted = cv2.warpPerspective(one, off, (wid, hgt), flags=cv2.INTER_LINEAR, borderValue=-1)
            s = shifted[valid]
            assert float(((s - s.mean()) / s.std() * b).mean()) < corr - 0.1
            zoom, rot = _zoom_rotation(h, wid / 2, hgt / 2)
            if kind == "zoom":
                assert abs(zoom - p["zoom"]) / p["zoom"] < 0.03, (zoom, p)
                assert abs((rot - p["rotation"] + 180) % 360 - 180) < 3.0, (rot, p)


def test_a_seed_gives_the_same_sequences(tmp_path):
    photo = _photo()
    for run in ("a", "b"):
        warps.write_sequence(photo, "photometric", tmp_path / run, np.random.default_rng(7), "test")
    for k in range(2, warps.STEPS + 2):
        assert (tmp_path / "a" / f"H_1_{k}").read_text() == (tmp_path / "b" / f"H_1_{k}").read_text()
        assert np.array_equal(cv2.imread(str(tmp_path / "a" / f"{k}.png")), cv2.imread(str(tmp_path / "b" / f"{k}.png")))
    rows = (tmp_path / "a" / "rgb.txt").read_text().split()
    assert rows[:2] == ["1", "1.png"]


def test_warp_ids_label_the_keypoints_a_homography_carries():
    from scone_train.data.training_units import warp_ids

    rng = np.random.default_rng(5)
    n = 200
    kp1 = np.c_[rng.uniform(0, 300, (n, 2)), 7.0 * 1.2 ** rng.integers(0, 3, n), rng.uniform(0, 360, n)].astype(np.float32)
    h = np.array([[1.5 * np.cos(0.3), -1.5 * np.sin(0.3), 20.0], [1.5 * np.sin(0.3), 1.5 * np.cos(0.3), -5.0], [0, 0, 1]])
    p = np.c_[kp1[:, :2], np.ones(n)] @ h.T
    kpk = kp1.copy()
    kpk[:, :2] = p[:, :2] / p[:, 2:3] + rng.normal(0, 0.3, (n, 2))
    kpk[:, 2] = kp1[:, 2] * 1.5
    order = rng.permutation(n)
    ids = warp_ids(kp1, kpk[order], h)
    assert (ids == order).mean() > 0.97
    # A size that disagrees with the zoom by more than 1.5 levels, or a position 5 px off, gets no id.
    wrong = kpk[order].copy()
    wrong[:10, 2] = kp1[order[:10], 2] * 1.5 * 1.2**2
    wrong[10:20, 0] += 5.0
    ids = warp_ids(kp1, wrong, h)
    assert (ids[:20] == -1).all() and (ids[20:] == order[20:]).mean() > 0.97
