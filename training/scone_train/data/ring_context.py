"""The ring context: a keypoint described with the image around it at fixed places in its own frame.

Reference implementation in numpy of what `src/describe/ring_context.rs` computes (the service's and the export's
one path; `tests/` check the two agree). For a keypoint at (x, y) with size s (pixels) and FREAK orientation theta:

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
GRADIENTS = 2 * SAMPLES


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
# The angle bins' cosines and sines, from the same libm calls as the offsets (numpy's own cos may differ in the
# last bit).
_COS = np.array([math.cos(2.0 * math.pi * a / ANGLE_BINS) for a in range(ANGLE_BINS)])
_SIN = np.array([math.sin(2.0 * math.pi * a / ANGLE_BINS) for a in range(ANGLE_BINS)])


def angle_bin(angle_deg: np.ndarray) -> np.ndarray:
    """The angle bin of orientations in degrees (any range): round(angle / 360 * ANGLE_BINS) mod ANGLE_BINS."""
    a = np.floor(np.asarray(angle_deg, dtype=np.float64) * (ANGLE_BINS / 360.0) + 0.5).astype(np.int64)
    return np.mod(a, ANGLE_BINS)


def _placed(grey: np.ndarray, keypoints: np.ndarray) -> tuple:
    """What `sample` and `gradients` share: the image's integral (int64 [H+1, W+1]), each sample's pixel cx, cy
    (int64 [N, SAMPLES]), its box half-width before the floor at 0 or 1 (`floor(half * s + 0.5)`), each
    keypoint's angle bin, and the image's size."""
    grey = np.asarray(grey)
    if grey.ndim != 2 or grey.dtype != np.uint8:
        raise ValueError("a grey uint8 image is required")
    h, w = grey.shape
    integral = np.zeros((h + 1, w + 1), dtype=np.int64)
    integral[1:, 1:] = grey.astype(np.int64).cumsum(0).cumsum(1)
    kp = np.asarray(keypoints, dtype=np.float64) if len(keypoints) else np.zeros((0, 4))
    x, y, s = kp[:, 0:1], kp[:, 1:2], kp[:, 2:3]
    dx, dy, half = _TABLE
    a = angle_bin(kp[:, 3])
    cx = np.clip(np.floor(x + s * dx[a] + 0.5), 0, w - 1).astype(np.int64)
    cy = np.clip(np.floor(y + s * dy[a] + 0.5), 0, h - 1).astype(np.int64)
    return integral, cx, cy, np.floor(half[None, :] * s + 0.5).astype(np.int64), a, w, h


def sample(grey: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """uint8 [N, SAMPLES]: the ring context of `keypoints` ([N, >=4]: x, y, size, angle in degrees) on the
    grey image `grey` (uint8 [H, W])."""
    integral, cx, cy, hw, _, w, h = _placed(grey, keypoints)
    hw = np.maximum(hw, 0)
    total, area = _box_sums(integral, np.maximum(cx - hw, 0), np.minimum(cx + hw + 1, w), np.maximum(cy - hw, 0),
                            np.minimum(cy + hw + 1, h))
    return ((total + area // 2) // area).astype(np.uint8).reshape(len(keypoints), SAMPLES)


def _box_sums(integral: np.ndarray, x0, x1, y0, y1) -> tuple[np.ndarray, np.ndarray]:
    """Sums and areas of the boxes [x0, x1) x [y0, y1), each bound already cut to the image (an empty box has
    area 0)."""
    x1, y1 = np.maximum(x1, x0), np.maximum(y1, y0)
    total = integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]
    return total, (x1 - x0) * (y1 - y0)


def _difference(a: tuple, b: tuple) -> np.ndarray:
    """mean(a) - mean(b) as f64, 0 where either box is empty (at the image's border)."""
    (sa, na), (sb, nb) = a, b
    ok = (na > 0) & (nb > 0)
    return np.where(ok, sa / np.maximum(na, 1) - sb / np.maximum(nb, 1), 0.0)


def gradients(grey: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """int8 [N, GRADIENTS]: the grey-level gradient at every ring sample, in the keypoint's own frame.

    At a sample's pixel (cx, cy) (as `sample` places it) with half-width g = max(its box half-width, 1): the
    image-axis differences gx = mean(right box) - mean(left box) and gy = mean(lower box) - mean(upper box),
    the boxes [cx+1, cx+g] x [cy-g, cy+g], [cx-g, cx-1] x [cy-g, cy+g] and their transposes, each cut to the
    image (a difference with an empty box is 0). Turned into the frame of the keypoint's quantised angle t:
    u = gx cos t + gy sin t (along the keypoint's direction), v = gy cos t - gx sin t; each halved (so that a
    full black-to-white step fits), rounded half up and clamped to -127..127. Columns: u of every sample (in
    `sample`'s order), then v of every sample."""
    integral, cx, cy, g, a, w, h = _placed(grey, keypoints)
    g = np.maximum(g, 1)
    lo_x, hi_x = np.maximum(cx - g, 0), np.minimum(cx + g + 1, w)
    lo_y, hi_y = np.maximum(cy - g, 0), np.minimum(cy + g + 1, h)
    gx = _difference(_box_sums(integral, np.minimum(cx + 1, w), hi_x, lo_y, hi_y), _box_sums(integral, lo_x, cx, lo_y, hi_y))
    gy = _difference(_box_sums(integral, lo_x, hi_x, np.minimum(cy + 1, h), hi_y), _box_sums(integral, lo_x, hi_x, lo_y, cy))
    cos, sin = _COS[a][:, None], _SIN[a][:, None]
    u = gx * cos + gy * sin
    v = gy * cos - gx * sin
    out = np.concatenate([u, v], axis=1) * 0.5
    return np.clip(np.floor(out + 0.5), -127, 127).astype(np.int8)
