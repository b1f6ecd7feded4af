"""The ring context: a keypoint described with the image around it at fixed places in its own frame.

Reference implementation in numpy of what `src/context.rs` computes (the service's and the export's one path;
`tests/` check the two agree). For a keypoint at (x, y) with size s (pixels) and FREAK orientation theta:

- the sample positions are the centre and `RINGS` rings of `ANGLES` points, ring i at radius `RADII[i] * s`,
  point j at angle theta + 2 pi j / ANGLES (image axes, y down, as OpenCV's keypoint angle);
- theta is quantised to one of `ANGLE_BINS` bins, so the positions come from a fixed table of offsets (in
  units of s) and every sample is integer arithmetic on the image from there on;
- each sample is the mean of a square box of the grey image (its integral image), centred on the sample's
  pixel (x + s * dx rounded half up, clamped into the image) with half-width round(BOX * r * s) (at least 0,
  a single pixel) and cut to the image; the mean is rounded half up to an integer 0..255.

So the context of a keypoint is `SAMPLES` bytes. Under a change of view it moves with the keypoint's position,
scale and orientation only: unlike detected neighbours, every sample exists in both views by construction.
"""

from __future__ import annotations

import math

import numpy as np

RADII = (0.5, 1.0, 1.5, 2.25, 3.25, 4.5, 6.0)
RINGS = len(RADII)
ANGLES = 16
ANGLE_BINS = 256
BOX = 0.2
SAMPLES = 1 + RINGS * ANGLES


def offsets() -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) [ANGLE_BINS, SAMPLES] in units of the keypoint size, and the box half-width factor
    [SAMPLES] (times the size, before rounding)."""
    dx = np.zeros((ANGLE_BINS, SAMPLES), dtype=np.float64)
    dy = np.zeros((ANGLE_BINS, SAMPLES), dtype=np.float64)
    half = np.zeros(SAMPLES, dtype=np.float64)
    step = ANGLE_BINS // ANGLES
    for a in range(ANGLE_BINS):
        for i, r in enumerate(RADII):
            for j in range(ANGLES):
                m = (a + j * step) % ANGLE_BINS
                t = 2.0 * math.pi * m / ANGLE_BINS
                dx[a, 1 + i * ANGLES + j] = r * math.cos(t)
                dy[a, 1 + i * ANGLES + j] = r * math.sin(t)
    for i, r in enumerate(RADII):
        half[1 + i * ANGLES : 1 + (i + 1) * ANGLES] = BOX * r
    return dx, dy, half


_TABLE = offsets()


def angle_bin(angle_deg: np.ndarray) -> np.ndarray:
    """The angle bin of orientations in degrees (any range): round(angle / 360 * ANGLE_BINS) mod ANGLE_BINS."""
    a = np.floor(np.asarray(angle_deg, dtype=np.float64) * (ANGLE_BINS / 360.0) + 0.5).astype(np.int64)
    return np.mod(a, ANGLE_BINS)


def sample(grey: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """uint8 [N, SAMPLES]: the ring context of `keypoints` ([N, >=4]: x, y, size, angle in degrees) on the
    grey image `grey` (uint8 [H, W])."""
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise ValueError("a grey uint8 image is required")
    h, w = grey.shape
    n = len(keypoints)
    if n == 0:
        return np.zeros((0, SAMPLES), dtype=np.uint8)
    integral = np.zeros((h + 1, w + 1), dtype=np.int64)
    integral[1:, 1:] = grey.astype(np.int64).cumsum(0).cumsum(1)
    kp = np.asarray(keypoints, dtype=np.float64)
    x, y, s = kp[:, 0:1], kp[:, 1:2], kp[:, 2:3]
    dx, dy, half = _TABLE
    a = angle_bin(kp[:, 3])
    cx = np.clip(np.floor(x + s * dx[a] + 0.5), 0, w - 1).astype(np.int64)
    cy = np.clip(np.floor(y + s * dy[a] + 0.5), 0, h - 1).astype(np.int64)
    hw = np.maximum(np.floor(half[None, :] * s + 0.5), 0).astype(np.int64)
    x0, x1 = np.maximum(cx - hw, 0), np.minimum(cx + hw + 1, w)
    y0, y1 = np.maximum(cy - hw, 0), np.minimum(cy + hw + 1, h)
    total = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
    area = (x1 - x0) * (y1 - y0)
    return ((total + area // 2) // area).astype(np.uint8).reshape(n, SAMPLES)
