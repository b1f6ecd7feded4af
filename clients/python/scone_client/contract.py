"""The client contract of proto/scone/v1/scone.proto (comment above ``message KeypointSet``), step by step.

Each function below is one paragraph of the contract, written to be ported line by line (a phone app does the
same with OpenCV's C++, Java or Swift API). Every floating-point step is done in the precision the server
uses: ``numpy.float32`` where the server computes in f32, Python floats (IEEE double) where it uses f64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

#: Bytes per FREAK descriptor (512 bits).
DESCRIPTOR_BYTES = 64
#: FAST's circle diameter: the size of a keypoint found on level 0.
FAST_SIZE = np.float32(7.0)
#: FREAK's pattern scale and octave count (OpenCV's defaults).
FREAK_PATTERN_SCALE = np.float32(22.0)
FREAK_OCTAVES = 4

_F32_HALF = np.float32(0.5)
_F32_TWO = np.float32(2.0)


@dataclass(frozen=True)
class ExtractorConfig:
    """The server's ``[extractor]`` settings; the defaults are the contract's revision 3 (what the embedded model
    was trained on and declares). ``ExtractorConfig.revision_2()`` is the extraction of a server that runs a
    model made before models declared theirs (``scone-freak-k20``)."""

    fast_threshold: int = 20
    max_keypoints: int = 2000
    levels: int = 8
    scale_factor: float = 1.2
    grid_cell: int = 32

    @classmethod
    def revision_2(cls) -> ExtractorConfig:
        """6 levels and 1,500 keypoints: the contract's revision 2."""
        return cls(max_keypoints=1500, levels=6)


@dataclass
class Features:
    """Keypoints of one image in full-resolution pixels, with their FREAK descriptors (row i for keypoint i)."""

    width: int
    height: int
    #: float32 [N, 2]: x, y.
    xy: np.ndarray
    #: float32 [N]: diameter of the described region.
    size: np.ndarray
    #: float32 [N]: FREAK orientation in degrees, [0, 360].
    angle: np.ndarray
    #: float32 [N]: FAST score.
    response: np.ndarray
    #: int32 [N]: pyramid level.
    octave: np.ndarray
    #: uint8 [N, 64]: FREAK descriptors, bit i in byte i // 8 at bit i % 8 (least significant first).
    descriptors: np.ndarray
    #: uint8 [N, 113]: the ring context (step 9), for a server whose model reads it; None when not computed.
    context: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.xy.shape[0])


def configure_opencv() -> None:
    """Single-threaded OpenCV, without Intel IPP (the server's OpenCV is built without it; see the contract)."""
    cv2.setNumThreads(1)
    cv2.ipp.setUseIPP(False)


# -- Grey image -------------------------------------------------------------------------------------------


def decode_grey(data: bytes) -> np.ndarray:
    """Decodes a PNG or JPEG as the server does: decode as stored, then convert to 8-bit grey.

    The image is decoded with ``IMREAD_UNCHANGED`` (no EXIF rotation, colour kept), 16-bit samples become
    8-bit by ``convertTo(CV_8U, 1/257)`` and colour becomes grey by ``cvtColor(BGR2GRAY)`` (``BGRA2GRAY`` with
    alpha). Decoding straight to grey (``IMREAD_GRAYSCALE``) takes the JPEG's luma instead, which differs by a
    few levels and changes most descriptors by a few bits.
    """
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a PNG or JPEG image OpenCV can decode")
    return to_grey(img)


def to_grey(img: np.ndarray) -> np.ndarray:
    """An 8- or 16-bit image with 1, 3 (BGR) or 4 (BGRA) channels as 8-bit grey, the server's conversion."""
    if img.dtype == np.uint16:
        img = cv2.convertScaleAbs(img, alpha=1.0 / 257.0)  # saturate(round(v / 257)), as convertTo(CV_8U)
    elif img.dtype != np.uint8:
        raise ValueError(f"unsupported sample type {img.dtype}")
    if img.ndim == 2:
        return img
    channels = img.shape[2]
    if channels == 1:
        return img[:, :, 0]
    if channels == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if channels == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    raise ValueError(f"unsupported channel count {channels}")


def grey_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """The contract's grey formula on an 8-bit RGB array (for ports without cvtColor): equals BGR2GRAY.

    ``Y = (9798 R + 19235 G + 3735 B + 16384) >> 15``: OpenCV 4.12's fixed-point 0.299 R + 0.587 G + 0.114 B
    (checked equal to ``cvtColor`` on all 2^24 colours).
    """
    r, g, b = (rgb[..., i].astype(np.uint32) for i in range(3))
    return ((9798 * r + 19235 * g + 3735 * b + 16384) >> 15).astype(np.uint8)


# -- Pyramid geometry -------------------------------------------------------------------------------------


def powi(base: float, exponent: int) -> float:
    """``base ** exponent`` in double by binary powering, as the server computes it (Rust ``f64::powi``).

    This differs from ``pow`` in the last bit for some exponents: 1.2^3 is ``1.2 * (1.2 * 1.2)`` here.
    """
    n = abs(exponent)
    result, factor = 1.0, base
    while True:
        if n & 1:
            result *= factor
        n >>= 1
        if n == 0:
            break
        factor *= factor
    return 1.0 / result if exponent < 0 else result


def round_half_away(value: float) -> int:
    """Rounds to the nearest integer, halves away from zero (Rust ``f64::round``; Python's ``round`` is not it)."""
    floor = math.floor(abs(value))
    n = floor + (1 if abs(value) - floor >= 0.5 else 0)
    return int(math.copysign(n, value))


def level_size(width: int, height: int, level: int, scale_factor: float = 1.2) -> tuple[int, int]:
    """(W_l, H_l): the full size divided by s_l = powi(scale_factor, l), rounded half away from zero."""
    s = powi(scale_factor, level)
    return round_half_away(width / s), round_half_away(height / s)


def keypoint_size(level: int, scale_factor: float = 1.2) -> np.float32:
    """7 * s_l in float32 (s_l rounded to float32 first)."""
    return np.float32(FAST_SIZE * np.float32(powi(scale_factor, level)))


def freak_border(size: np.float32) -> np.float32:
    """Margin in pixels FREAK's pattern needs at this size: 22 * size / 7 + 2, in float32, in that order."""
    return np.float32(np.float32(FREAK_PATTERN_SCALE * size) / FAST_SIZE + _F32_TWO)


def level_quotas(config: ExtractorConfig = ExtractorConfig()) -> list[int]:
    """Nominal keypoints per level: max_keypoints * w_l / sum(w), w_l = powi(scale_factor, -2 l), rounded.

    The last entry is informative only: the last level takes whatever the earlier levels left.
    """
    weights = [powi(config.scale_factor, -2 * level) for level in range(config.levels)]
    total = 0.0
    for w in weights:
        total += w
    return [round_half_away(config.max_keypoints * w / total) for w in weights]


def to_full_resolution(
    level_xy: np.ndarray, width: int, height: int, level_width: int, level_height: int
) -> np.ndarray:
    """x = (x_l + 0.5) * (W / W_l) - 0.5 (likewise y), every operation in float32, the ratio computed first."""
    sx = np.float32(width) / np.float32(level_width)
    sy = np.float32(height) / np.float32(level_height)
    xy = level_xy.astype(np.float32)
    out = np.empty_like(xy)
    out[:, 0] = (xy[:, 0] + _F32_HALF) * sx - _F32_HALF
    out[:, 1] = (xy[:, 1] + _F32_HALF) * sy - _F32_HALF
    return out


# -- Selection --------------------------------------------------------------------------------------------


def select_spread(level_xy: np.ndarray, response: np.ndarray, budget: int, cell: int) -> np.ndarray:
    """Indices of at most ``budget`` keypoints of one level, in the order the server keeps them.

    "Stronger" is: higher response, then smaller y_l, then smaller x_l (level coordinates). Without a grid,
    or when every keypoint fits, the strongest ``budget`` in that order. Otherwise each keypoint gets the cell
    (floor(y_l / cell), floor(x_l / cell)) and its rank r among its cell's keypoints by strength (0 = strongest);
    keypoints are taken by (r, strength): every cell's strongest, strongest of those first, then every cell's
    second, and so on, the last partial round cut in strength order.
    """
    n = len(response)
    order = sorted(range(n), key=lambda i: (-float(response[i]), float(level_xy[i, 1]), float(level_xy[i, 0])))
    if cell == 0 or n <= budget:
        return np.asarray(order[:budget], dtype=np.int64)
    rank = np.empty(n, np.int64)
    seen: dict[tuple[int, int], int] = {}
    for i in order:  # strongest first, so a keypoint's rank is the count of stronger ones in its cell
        key = (int(level_xy[i, 1]) // cell, int(level_xy[i, 0]) // cell)
        rank[i] = seen.get(key, 0)
        seen[key] = rank[i] + 1
    position = np.empty(n, np.int64)
    position[order] = np.arange(n)
    by_round = sorted(range(n), key=lambda i: (int(rank[i]), int(position[i])))
    return np.asarray(by_round[:budget], dtype=np.int64)


# -- Detection and description ----------------------------------------------------------------------------


def detect(grey: np.ndarray, config: ExtractorConfig = ExtractorConfig()) -> list[cv2.KeyPoint]:
    """FAST on every pyramid level, border-filtered and budgeted, in full-resolution coordinates (angle -1)."""
    if grey.dtype != np.uint8 or grey.ndim != 2:
        raise ValueError("expected an 8-bit single-channel image")
    h, w = grey.shape
    fast = cv2.FastFeatureDetector_create(
        threshold=config.fast_threshold, nonmaxSuppression=True, type=cv2.FAST_FEATURE_DETECTOR_TYPE_9_16
    )
    quotas = level_quotas(config)
    remaining = config.max_keypoints
    selected: list[cv2.KeyPoint] = []
    for level in range(config.levels):
        lw, lh = level_size(w, h, level, config.scale_factor)
        size = keypoint_size(level, config.scale_factor)
        border = freak_border(size)
        if lw < 16 or lh < 16 or _F32_TWO * border >= np.float32(min(w, h)):
            break  # this level and all coarser ones are skipped; their quota is not used
        img = grey if level == 0 else cv2.resize(grey, (lw, lh), interpolation=cv2.INTER_LINEAR)
        raw = fast.detect(img, None)
        if not raw:
            level_xy = np.zeros((0, 2), np.float32)
            response = np.zeros(0, np.float32)
        else:
            level_xy = np.array([k.pt for k in raw], np.float32)
            response = np.array([k.response for k in raw], np.float32)
        xy = to_full_resolution(level_xy, w, h, lw, lh)
        inside = (
            (xy[:, 0] >= border)
            & (xy[:, 1] >= border)
            & (xy[:, 0] < np.float32(w) - border)
            & (xy[:, 1] < np.float32(h) - border)
        )
        level_xy, response, xy = level_xy[inside], response[inside], xy[inside]
        budget = remaining if level == config.levels - 1 else min(quotas[level], remaining)
        kept = select_spread(level_xy, response, budget, config.grid_cell)
        remaining -= len(kept)
        for i in kept:
            selected.append(
                cv2.KeyPoint(float(xy[i, 0]), float(xy[i, 1]), float(size), -1.0, float(response[i]), level, -1)
            )
    return selected


_FREAK = None


def describe(grey: np.ndarray, keypoints: list[cv2.KeyPoint]) -> Features:
    """FREAK on the full-resolution image: assigns orientation, drops keypoints its pattern would leave."""
    global _FREAK
    if _FREAK is None:  # building FREAK's lookup table costs more than describing one image
        _FREAK = cv2.xfeatures2d.FREAK_create(True, True, float(FREAK_PATTERN_SCALE), FREAK_OCTAVES)
    h, w = grey.shape
    kept, desc = _FREAK.compute(grey, keypoints) if keypoints else ((), None)
    n = len(kept)
    if desc is None:
        desc = np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
    if desc.shape != (n, DESCRIPTOR_BYTES):
        raise RuntimeError(f"FREAK returned {desc.shape} descriptors for {n} keypoints")
    angle = np.array([k.angle for k in kept], np.float32)
    angle = np.fmod(angle, np.float32(360.0))
    angle = np.where(angle < 0, angle + np.float32(360.0), angle).astype(np.float32)
    return Features(
        width=w,
        height=h,
        xy=np.array([k.pt for k in kept], np.float32).reshape(n, 2),
        size=np.array([k.size for k in kept], np.float32),
        angle=angle,
        response=np.array([k.response for k in kept], np.float32),
        octave=np.array([k.octave for k in kept], np.int32),
        descriptors=np.ascontiguousarray(desc, np.uint8),
    )


# -- Ring context (step 9) ----------------------------------------------------------------------------------

#: Ring radii in units of the keypoint size, points per ring, orientation bins and box half-width factor.
RING_RADII = (0.5, 1.0, 1.5, 2.25, 3.25, 4.5, 6.0)
RING_ANGLES = 16
RING_ANGLE_BINS = 256
RING_BOX = 0.2
#: Bytes of one keypoint's ring context: the centre, then ring 0's points, ring 1's, ...
RING_SAMPLES = 1 + len(RING_RADII) * RING_ANGLES


def ring_offsets() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dx, dy) [RING_ANGLE_BINS, RING_SAMPLES] in units of the keypoint size, in double, and each sample's box
    half-width factor [RING_SAMPLES]: bin a, ring i, point j is at angle 2 pi ((a + 16 j) mod 256) / 256 (the
    expression evaluated as ``2.0 * pi * m / 256``) and radius RING_RADII[i]; the centre is (0, 0), factor 0."""
    dx = np.zeros((RING_ANGLE_BINS, RING_SAMPLES), np.float64)
    dy = np.zeros((RING_ANGLE_BINS, RING_SAMPLES), np.float64)
    half = np.zeros(RING_SAMPLES, np.float64)
    step = RING_ANGLE_BINS // RING_ANGLES
    for a in range(RING_ANGLE_BINS):
        for i, r in enumerate(RING_RADII):
            for j in range(RING_ANGLES):
                t = 2.0 * math.pi * ((a + j * step) % RING_ANGLE_BINS) / RING_ANGLE_BINS
                dx[a, 1 + i * RING_ANGLES + j] = r * math.cos(t)
                dy[a, 1 + i * RING_ANGLES + j] = r * math.sin(t)
    for i, r in enumerate(RING_RADII):
        half[1 + i * RING_ANGLES : 1 + (i + 1) * RING_ANGLES] = RING_BOX * r
    return dx, dy, half


def ring_context(grey: np.ndarray, features: Features) -> np.ndarray:
    """uint8 [N, RING_SAMPLES]: each keypoint's ring context on the full-resolution grey image.

    The keypoint's angle picks bin a = floor(angle * 256 / 360 + 0.5) mod 256 (double); sample n is centred
    on the pixel (cx, cy) = (floor(x + size * dx[a, n] + 0.5), floor(y + size * dy[a, n] + 0.5)) in double,
    each clamped into the image, and is the mean of the box of half-width hw = floor(half[n] * size + 0.5)
    around it, cut to the image: floor((sum + area // 2) / area) over the integer sums of the grey levels.
    """
    h, w = grey.shape
    n = len(features)
    if n == 0:
        return np.zeros((0, RING_SAMPLES), np.uint8)
    integral = cv2.integral(grey, sdepth=cv2.CV_64F)
    dx, dy, half = ring_offsets()
    x = features.xy[:, 0:1].astype(np.float64)
    y = features.xy[:, 1:2].astype(np.float64)
    s = features.size[:, None].astype(np.float64)
    a = np.mod(np.floor(features.angle.astype(np.float64) * (RING_ANGLE_BINS / 360.0) + 0.5), RING_ANGLE_BINS)
    a = a.astype(np.int64)
    cx = np.clip(np.floor(x + s * dx[a] + 0.5), 0, w - 1).astype(np.int64)
    cy = np.clip(np.floor(y + s * dy[a] + 0.5), 0, h - 1).astype(np.int64)
    hw = np.maximum(np.floor(half[None, :] * s + 0.5), 0).astype(np.int64)
    x0, x1 = np.maximum(cx - hw, 0), np.minimum(cx + hw + 1, w)
    y0, y1 = np.maximum(cy - hw, 0), np.minimum(cy + hw + 1, h)
    total = (integral[y1, x1] - integral[y0, x1] - integral[y1, x0] + integral[y0, x0]).astype(np.int64)
    area = (x1 - x0) * (y1 - y0)
    return ((total + area // 2) // area).astype(np.uint8)


def extract(grey: np.ndarray, config: ExtractorConfig = ExtractorConfig(), context: bool = True) -> Features:
    """The whole contract on an 8-bit grey image: what the server does with an image it receives, with the
    ring context (step 9) unless ``context`` is false: the embedded model reads it, a server that runs the
    constellation model ignores it."""
    features = describe(grey, detect(grey, config))
    if context:
        features.context = ring_context(grey, features)
    return features


def extract_encoded(data: bytes, config: ExtractorConfig = ExtractorConfig(), context: bool = True) -> Features:
    """``extract(decode_grey(data))``: the server's result for an encoded PNG or JPEG."""
    return extract(decode_grey(data), config, context)
