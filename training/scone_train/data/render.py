"""Synthetic multi-view sequences with exact depth and camera poses (TUM RGB-D layout).

Each sequence is a small "room" (back wall, floor, sometimes side walls) holding a few boxes and free-standing
panels, all of them planar rectangles covered with grey photographs that ship inside the scikit-image wheel.
A camera flies along a smooth random path that rolls strongly, changes its distance to the content (scale)
and orbits around it (viewpoint), so that a descriptor trained on the sequences has to cope with rotation,
scale, perspective, occlusion and lighting changes. Depth and poses are exact by construction.

Rendering is a vectorised ray cast in numpy: every rectangle is intersected with all pixel rays through the
plane-to-image homography, the nearest hit wins, and the texture is read from a mip pyramid with a level chosen
from the pixel footprint on the plane (two taps along the major axis of the footprint for oblique surfaces).
Pixels on silhouettes are re-rendered with four sub-samples so object edges are anti-aliased like a real lens.

Output of one sequence (see `render_sequence`)::

    rgb.txt, rgb/NNNNNN.png        8-bit grey images
    depth.txt, depth/NNNNNN.png    16-bit, metres x 5000, 0 = no surface
    groundtruth.txt                camera-to-world pose per frame: tx ty tz qx qy qz qw
    camera.txt                     fx fy cx cy width height
    SOURCE                         provenance and texture licences

Camera convention: pinhole, x right, y down, z forward; u = fx*x/z + cx, v = fy*y/z + cy, pixel centres at
integer coordinates; stored depth is z (not the ray length).

Command line (from training/)::

    python -m scone_train.data.render --out DIR --sequences 40 --frames 30 --seed 0 [--width 640 --height 480]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

DEPTH_SCALE = 5000.0  # depth PNG units per metre (TUM convention)
BASE_FOCAL = 500.0  # focal length in pixels for a 640-pixel-wide image; scaled with the width
NEAR = 0.05  # metres: hits closer than this are ignored
FAR = 60.0  # metres: hits further than this are ignored
MAX_ATLAS = 2048  # largest side of a surface's texture atlas (beyond it the atlas is mirror-tiled)
UP = np.array([0.0, 0.0, 1.0])  # world z is up; the floor is z = 0

# Textures: sample photographs bundled with scikit-image (files under skimage/data, loaded offline through
# skimage.data). Only images whose docstring states public domain or CC0 are used; "moon" and "page" are left
# out because their docstrings give no licence. The text is the licence as scikit-image's docstrings state it.
TEXTURE_LICENCES: dict[str, str] = {
    "astronaut": "photograph of Eileen Collins from the NASA Great Images database, no known copyright "
    "restrictions, released into the public domain",
    "camera": "no copyright restrictions, CC0 by the photographer (Lav Varshney)",
    "coffee": "courtesy of Pikolo Espresso Bar, no copyright restrictions, CC0 by the photographer (Rachel Michetti)",
    "chelsea": "no copyright restrictions, CC0 by the photographer (Stefan van der Walt)",
    "brick": "from CC0Textures (Bricks25), Creative Commons CC0 License",
    "grass": "from DeviantArt (linolafett, Grass-01), Creative Commons CC0 License",
    "gravel": "from CC0Textures (Gravel04), Creative Commons CC0 License",
    "text": "from Wikipedia (File:Corner.png), no known copyright restrictions, released into the public domain",
    "rocket": "SpaceX launch photo of DSCOVR on Falcon 9, released into the public domain by SpaceX",
}
# Relative frequency of each source when a texture tile is drawn (the small "text" image less often).
TEXTURE_WEIGHTS: dict[str, float] = {
    "astronaut": 1.0,
    "camera": 1.0,
    "coffee": 1.0,
    "chelsea": 1.0,
    "brick": 1.0,
    "grass": 1.0,
    "gravel": 1.0,
    "text": 0.5,
    "rocket": 1.0,
}

_SOURCES: dict[str, np.ndarray] | None = None


def _load_sources() -> dict[str, np.ndarray]:
    """The source photographs as grey float32 in [0, 255] (loaded once per process)."""
    global _SOURCES
    if _SOURCES is None:
        import skimage.data

        out = {}
        for name in TEXTURE_LICENCES:
            img = np.asarray(getattr(skimage.data, name)())
            if img.ndim == 3:
                img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
            out[name] = img.astype(np.float32)
        _SOURCES = out
    return _SOURCES


def _skimage_version() -> str:
    import skimage

    return skimage.__version__


# ----------------------------------------------------------------------------------------------------------
# Textures
# ----------------------------------------------------------------------------------------------------------


@dataclass
class Pyramid:
    """Mip levels of one texture atlas, stored in one flat buffer with a one-texel reflected border per level
    so that a bilinear read never needs bounds checks. Level L texel i is centred on level-0 coordinate
    (i + 0.5) * 2**L - 0.5."""

    buf: np.ndarray  # float32, all padded levels one after the other
    offsets: np.ndarray  # int64 start of each padded level in buf
    widths: np.ndarray  # int64 unpadded width of each level
    heights: np.ndarray  # int64 unpadded height of each level

    @property
    def max_level(self) -> int:
        return len(self.widths) - 1


def _build_pyramid(atlas: np.ndarray) -> Pyramid:
    levels = [atlas.astype(np.float32)]
    while True:
        h, w = levels[-1].shape
        if h % 2 or w % 2 or min(h, w) < 8:
            break
        # Light Gaussian then a 2x2 box: a reasonable low-pass whose output texel i sits at input 2i + 0.5.
        blurred = cv2.GaussianBlur(levels[-1], (0, 0), 0.6, borderType=cv2.BORDER_REFLECT)
        levels.append(cv2.resize(blurred, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    padded = [cv2.copyMakeBorder(lv, 1, 1, 1, 1, cv2.BORDER_REFLECT) for lv in levels]
    sizes = [p.size for p in padded]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    return Pyramid(
        buf=np.concatenate([p.ravel() for p in padded]),
        offsets=offsets,
        widths=np.array([lv.shape[1] for lv in levels], np.int64),
        heights=np.array([lv.shape[0] for lv in levels], np.int64),
    )


def _texture_tile(rng: np.random.Generator, h: int, w: int, used: set[str]) -> np.ndarray:
    """An h x w patch cut from a randomly rotated, flipped and rescaled source photograph."""
    sources = _load_sources()
    names = list(TEXTURE_WEIGHTS)
    p = np.array([TEXTURE_WEIGHTS[n] for n in names])
    name = names[int(rng.choice(len(names), p=p / p.sum()))]
    used.add(name)
    img = np.rot90(sources[name], int(rng.integers(4)))
    if rng.random() < 0.5:
        img = img[:, ::-1]
    img = np.ascontiguousarray(img)
    scale = float(np.exp(rng.uniform(math.log(0.55), math.log(1.5))))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=interp)
    ih, iw = img.shape
    if ih < h or iw < w:  # small sources are mirror-tiled up to the tile size
        img = np.pad(img, ((0, max(0, h - ih)), (0, max(0, w - iw))), mode="symmetric")
        ih, iw = img.shape
    y0 = int(rng.integers(ih - h + 1))
    x0 = int(rng.integers(iw - w + 1))
    tile = img[y0 : y0 + h, x0 : x0 + w]
    mean = float(tile.mean())
    contrast = rng.uniform(0.75, 1.3)
    offset = rng.uniform(-20, 20)
    return np.clip(mean + contrast * (tile - mean) + offset, 0, 255)


def _split(rng: np.random.Generator, x: int, y: int, w: int, h: int, max_side: int, out: list) -> None:
    """Guillotine split of an atlas into tiles no longer than max_side (cut positions on a 16-texel grid)."""
    if max(w, h) <= max_side:
        out.append((x, y, w, h))
        return
    if w >= h:
        cut = int(round(w * rng.uniform(0.3, 0.7) / 16)) * 16
        cut = min(max(cut, 16), w - 16)
        _split(rng, x, y, cut, h, max_side, out)
        _split(rng, x + cut, y, w - cut, h, max_side, out)
    else:
        cut = int(round(h * rng.uniform(0.3, 0.7) / 16)) * 16
        cut = min(max(cut, 16), h - 16)
        _split(rng, x, y, w, cut, max_side, out)
        _split(rng, x, y + cut, w, h - cut, max_side, out)


def _make_texture(rng: np.random.Generator, size_u: float, size_v: float, used: set[str]) -> tuple[Pyramid, float]:
    """Texture for a size_u x size_v metre surface: a mosaic of photo tiles ("posters", "tiles", "boards").
    Returns the pyramid and its density in texels per metre."""
    density = float(rng.uniform(200, 380))
    w = int(min(MAX_ATLAS, max(32, math.ceil(size_u * density / 32) * 32)))
    h = int(min(MAX_ATLAS, max(32, math.ceil(size_v * density / 32) * 32)))
    atlas = np.empty((h, w), np.float32)
    tiles: list = []
    _split(rng, 0, 0, w, h, int(rng.integers(260, 700)), tiles)
    for x, y, tw, th in tiles:
        atlas[y : y + th, x : x + tw] = _texture_tile(rng, th, tw, used)
    return _build_pyramid(atlas), density


# ----------------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------------


@dataclass
class Rect:
    """A textured rectangle: points origin + s*axis_u + t*axis_v for s in [0, size_u], t in [0, size_v]."""

    origin: np.ndarray
    axis_u: np.ndarray
    axis_v: np.ndarray
    size_u: float
    size_v: float
    pyramid: Pyramid | None = None
    density: float = 300.0

    def corners(self) -> np.ndarray:
        a = self.axis_u * self.size_u
        b = self.axis_v * self.size_v
        return np.stack([self.origin, self.origin + a, self.origin + a + b, self.origin + b])


@dataclass
class Scene:
    rects: list[Rect]
    boxes: list[tuple[np.ndarray, np.ndarray]]  # axis-aligned bounds (lo, hi) of each box, for camera placement
    room: tuple[float, float, float, bool, bool]  # width, depth, height, has left wall, has right wall
    background: np.ndarray  # coefficients of the smooth background as a function of the world ray direction
    used: set[str] = field(default_factory=set)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _make_scene(rng: np.random.Generator) -> Scene:
    """A room with the back wall in the plane y = 0, the floor at z = 0 and content in front of the wall (y < 0)."""
    width = rng.uniform(7.0, 10.0)
    depth = rng.uniform(7.0, 9.0)
    height = rng.uniform(3.2, 4.5)
    ex, ey, ez = np.eye(3)
    rects = [
        Rect(np.array([-width / 2, 0.0, height]), ex, -ez, width, height),  # back wall, texture rows go down
        Rect(np.array([-width / 2, -depth, 0.0]), ex, ey, width, depth),  # floor
    ]
    left, right = bool(rng.random() < 0.5), bool(rng.random() < 0.5)
    if left:
        rects.append(Rect(np.array([-width / 2, -depth, height]), ey, -ez, depth, height))
    if right:
        rects.append(Rect(np.array([width / 2, 0.0, height]), -ey, -ez, depth, height))

    # Boxes standing on the floor, not overlapping each other (bounding circles).
    boxes = []
    placed: list[tuple[float, float, float]] = []
    for _ in range(int(rng.integers(2, 5))):
        for _attempt in range(30):
            hx, hy = rng.uniform(0.15, 0.45, 2)
            hz = rng.uniform(0.3, 0.9)
            radius = math.hypot(hx, hy)
            cx = rng.uniform(-1.6, 1.6)
            cy = rng.uniform(-2.3, -0.1 - radius)
            if all(math.hypot(cx - px, cy - py) > radius + pr + 0.05 for px, py, pr in placed):
                break
        else:
            continue
        placed.append((cx, cy, radius))
        yaw = rng.uniform(0, math.pi)
        bx = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        by = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        base = np.array([cx, cy, 0.0])
        top = base + ez * hz
        rects.append(Rect(top - hx * bx - hy * by, bx, by, 2 * hx, 2 * hy))  # lid
        for axis, other, half, half_other in ((bx, by, hx, hy), (by, bx, hy, hx)):
            for sign in (1.0, -1.0):
                # side face whose outward normal is sign*other; its u axis runs along `axis`, v downwards
                origin = top + sign * half_other * other - sign * half * axis
                rects.append(Rect(origin, sign * axis, -ez, 2 * half, hz))
        corners = np.array([base + sx * hx * bx + sy * hy * by for sx in (-1, 1) for sy in (-1, 1)])
        boxes.append((np.append(corners.min(0)[:2], 0.0), np.append(corners.max(0)[:2], hz)))

    # Free-standing (or floating) panels, some of them tilted.
    for _ in range(int(rng.integers(1, 4))):
        pw = rng.uniform(0.5, 1.2)
        ph = rng.uniform(0.4, 1.0)
        yaw = rng.uniform(-1.2, 1.2)
        tilt = rng.uniform(-0.5, 0.5)
        axis_u = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        normal_h = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        axis_v = math.cos(tilt) * -ez + math.sin(tilt) * normal_h
        bottom = rng.uniform(0.0, 0.6)
        centre_top = np.array([rng.uniform(-1.8, 1.8), rng.uniform(-2.6, -0.4), bottom + ph * math.cos(tilt)])
        rects.append(Rect(centre_top - axis_u * pw / 2, axis_u, axis_v, pw, ph))

    used: set[str] = set()
    for r in rects:
        r.pyramid, r.density = _make_texture(rng, r.size_u, r.size_v, used)
    background = np.concatenate(
        [
            [rng.uniform(60, 190)],  # mean level
            rng.uniform(-50, 50, 3),  # linear in the ray direction
            _unit(rng.normal(size=3)) * rng.uniform(1.0, 3.0),  # a slow sinusoidal ripple
            [rng.uniform(0, 2 * math.pi), rng.uniform(0, 25)],  # its phase and amplitude
        ]
    )
    return Scene(rects, boxes, (width, depth, height, left, right), background, used)


# ----------------------------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------------------------


@dataclass
class Camera:
    K: np.ndarray  # 3x3 intrinsics
    R_wc: np.ndarray  # camera-to-world rotation
    t_wc: np.ndarray  # camera centre in the world
    width: int
    height: int


def _intrinsics(width: int, height: int) -> np.ndarray:
    f = BASE_FOCAL * width / 640.0
    return np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])


def _plane_homography(rect: Rect, cam: Camera) -> np.ndarray | None:
    """H such that (s, t, 1) = z * H @ (u, v, 1) for the pixel (u, v) whose ray meets the rectangle's plane at
    plane coordinates (s, t) and camera depth z; in particular H[2] @ (u, v, 1) = 1 / z."""
    R_cw = cam.R_wc.T
    G = cam.K @ np.column_stack([R_cw @ rect.axis_u, R_cw @ rect.axis_v, R_cw @ (rect.origin - cam.t_wc)])
    if abs(np.linalg.det(G)) < 1e-9 * np.abs(G).max() ** 3:
        return None  # plane through the camera centre: seen edge-on
    return np.linalg.inv(G)


def _projected_bounds(rect: Rect, cam: Camera) -> tuple[int, int, int, int] | None:
    """Pixel bounds (u0, u1, v0, v1), end exclusive, of the rectangle's image after clipping it to z >= NEAR."""
    pts = (cam.R_wc.T @ (rect.corners() - cam.t_wc).T).T
    clipped = []
    for i in range(4):
        p, q = pts[i], pts[(i + 1) % 4]
        if p[2] >= NEAR:
            clipped.append(p)
        if (p[2] >= NEAR) != (q[2] >= NEAR):
            a = (NEAR - p[2]) / (q[2] - p[2])
            clipped.append(p + a * (q - p))
    if not clipped:
        return None
    c = np.array(clipped)
    uv = (cam.K @ (c / c[:, 2:3]).T).T
    u0 = max(int(math.floor(uv[:, 0].min())) - 1, 0)
    u1 = min(int(math.ceil(uv[:, 0].max())) + 2, cam.width)
    v0 = max(int(math.floor(uv[:, 1].min())) - 1, 0)
    v1 = min(int(math.ceil(uv[:, 1].max())) + 2, cam.height)
    if u0 >= u1 or v0 >= v1:
        return None
    return u0, u1, v0, v1


def _hit(Hm: np.ndarray, rect: Rect, u: np.ndarray, v: np.ndarray, zbest: np.ndarray):
    """Intersection of the rays through pixels (u, v) (broadcastable) with one rectangle: returns z, s, t and
    the mask of rays that hit it in front of the camera and nearer than zbest."""
    inv_z = Hm[2, 0] * u + (Hm[2, 1] * v + Hm[2, 2])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        z = 1.0 / inv_z
        s = (Hm[0, 0] * u + (Hm[0, 1] * v + Hm[0, 2])) * z
        t = (Hm[1, 0] * u + (Hm[1, 1] * v + Hm[1, 2])) * z
    m = (inv_z > 1.0 / FAR) & (inv_z < 1.0 / NEAR) & (z < zbest)
    m &= (s >= 0) & (s <= rect.size_u) & (t >= 0) & (t <= rect.size_v)
    return z, s, t, m


@dataclass
class Trace:
    ids: np.ndarray  # int16 rectangle index per ray, -1 = background
    z: np.ndarray  # camera depth (inf for background)
    s: np.ndarray  # plane coordinates of the hit (metres)
    t: np.ndarray
    homographies: list  # per rectangle, None when not visible


def _trace_grid(scene: Scene, cam: Camera) -> Trace:
    """Nearest hit for the ray through every pixel centre of the image."""
    h, w = cam.height, cam.width
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    zbest = np.full((h, w), np.inf)
    ids = np.full((h, w), -1, np.int16)
    S = np.zeros((h, w))
    T = np.zeros((h, w))
    homs: list = []
    for k, rect in enumerate(scene.rects):
        Hm = _plane_homography(rect, cam)
        bounds = None if Hm is None else _projected_bounds(rect, cam)
        if bounds is None:
            homs.append(None)
            continue
        homs.append(Hm)
        u0, u1, v0, v1 = bounds
        zb = zbest[v0:v1, u0:u1]
        z, s, t, m = _hit(Hm, rect, u[:, u0:u1], v[v0:v1], zb)
        np.copyto(zb, z, where=m)
        np.copyto(ids[v0:v1, u0:u1], np.int16(k), where=m)
        np.copyto(S[v0:v1, u0:u1], s, where=m)
        np.copyto(T[v0:v1, u0:u1], t, where=m)
    return Trace(ids, zbest, S, T, homs)


def _trace_points(scene: Scene, cam: Camera, u: np.ndarray, v: np.ndarray, homs: list) -> Trace:
    """Nearest hit for rays through arbitrary (sub-)pixel positions u, v (1-D arrays)."""
    n = len(u)
    zbest = np.full(n, np.inf)
    ids = np.full(n, -1, np.int16)
    S = np.zeros(n)
    T = np.zeros(n)
    for k, rect in enumerate(scene.rects):
        Hm = homs[k]
        if Hm is None:
            continue
        z, s, t, m = _hit(Hm, rect, u, v, zbest)
        np.copyto(zbest, z, where=m)
        np.copyto(ids, np.int16(k), where=m)
        np.copyto(S, s, where=m)
        np.copyto(T, t, where=m)
    return Trace(ids, zbest, S, T, homs)


def _sample(pyr: Pyramid, x: np.ndarray, y: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Bilinear read of pyramid level `level` (per point) at level-0 texel coordinates (x, y), with the atlas
    repeated by mirroring beyond its edges."""
    w = pyr.widths[level]
    h = pyr.heights[level]
    stride = w + 2  # padded rows; the border makes x0 = -1 and x0 + 1 = w valid
    scale = np.ldexp(np.float32(1.0), -level.astype(np.int32)).astype(np.float32)
    # Coordinates in level units, measured from the texel edge, folded into one mirror period [0, 2n).
    w = w.astype(np.float32)
    h = h.astype(np.float32)
    ex = np.mod((x + 0.5) * scale, 2 * w)
    ey = np.mod((y + 0.5) * scale, 2 * h)
    ex = np.where(ex > w, 2 * w - ex, ex) - 0.5  # now in [-0.5, w - 0.5], texel centres at integers
    ey = np.where(ey > h, 2 * h - ey, ey) - 0.5
    x0 = np.floor(ex)
    y0 = np.floor(ey)
    fx = (ex - x0).astype(np.float32)
    fy = (ey - y0).astype(np.float32)
    i00 = pyr.offsets[level] + (y0.astype(np.int64) + 1) * stride + (x0.astype(np.int64) + 1)
    buf = pyr.buf
    a = buf[i00]
    b = buf[i00 + 1]
    c = buf[i00 + stride]
    d = buf[i00 + stride + 1]
    top = a + fx * (b - a)
    bottom = c + fx * (d - c)
    return top + fy * (bottom - top)


def _shade(scene: Scene, cam: Camera, tr: Trace, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Intensity of every traced ray (flat arrays): texture with footprint-aware filtering, or background."""
    ids = tr.ids.ravel()
    out = np.empty(ids.shape, np.float32)
    present = np.flatnonzero(np.bincount(ids.astype(np.int64) + 1, minlength=len(scene.rects) + 1)[1:])
    for k in present:
        rect = scene.rects[k]
        pyr = rect.pyramid
        Hm = tr.homographies[k]
        idx = np.flatnonzero(ids == k)
        z = tr.z.ravel()[idx]
        s = tr.s.ravel()[idx]
        t = tr.t.ravel()[idx]
        # Jacobian of the texel coordinates with respect to the pixel coordinates (texels per pixel).
        kd = rect.density * z
        dsdu = kd * (Hm[0, 0] - s * Hm[2, 0])
        dsdv = kd * (Hm[0, 1] - s * Hm[2, 1])
        dtdu = kd * (Hm[1, 0] - t * Hm[2, 0])
        dtdv = kd * (Hm[1, 1] - t * Hm[2, 1])
        len_u = np.hypot(dsdu, dtdu)
        len_v = np.hypot(dsdv, dtdv)
        major_is_u = len_u >= len_v
        major = np.where(major_is_u, len_u, len_v)
        minor = np.abs(dsdu * dtdv - dsdv * dtdu) / np.maximum(major, 1e-12)
        jx = np.where(major_is_u, dsdu, dsdv).astype(np.float32)
        jy = np.where(major_is_u, dtdu, dtdv).astype(np.float32)
        # Two taps a quarter footprint either side of the centre along the major axis, each read at the level
        # matching max(major / 2, minor): a 2x anisotropic filter, trilinear between levels.
        lod = np.log2(np.maximum(np.maximum(major * 0.5, minor), 1e-6))
        lod = np.clip(lod, 0, pyr.max_level).astype(np.float32)
        l0 = np.floor(lod).astype(np.int64)
        l1 = np.minimum(l0 + 1, pyr.max_level)
        frac = lod - l0
        x = (s * rect.density - 0.5).astype(np.float32)
        y = (t * rect.density - 0.5).astype(np.float32)
        acc = np.zeros(len(idx), np.float32)
        for side in (-0.25, 0.25):
            xs = x + side * jx
            ys = y + side * jy
            a = _sample(pyr, xs, ys, l0)
            b = _sample(pyr, xs, ys, l1)
            acc += a + frac * (b - a)
        out[idx] = 0.5 * acc
    bg = np.flatnonzero(ids < 0)
    if len(bg):
        out[bg] = _background(scene, cam, u[bg], v[bg])
    return out


def _background(scene: Scene, cam: Camera, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth random shading as a function of the world ray direction (the same "sky" from every view)."""
    Kinv = np.linalg.inv(cam.K)
    rays = Kinv @ np.stack([u, v, np.ones_like(u)])
    d = cam.R_wc @ (rays / np.linalg.norm(rays, axis=0))
    c = scene.background
    val = c[0] + c[1:4] @ d + c[8] * np.sin(c[4:7] @ d + c[7])
    return np.clip(val, 0, 255).astype(np.float32)


# Rotated-grid sub-sample offsets used on silhouettes.
_SUBSAMPLES = np.array([[-0.125, -0.375], [0.375, -0.125], [0.125, 0.375], [-0.375, 0.125]])


def render_view(scene: Scene, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free grey image (float32, 0..255) and depth (float64 metres, 0 = no surface) of one view."""
    h, w = cam.height, cam.width
    tr = _trace_grid(scene, cam)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    img = _shade(scene, cam, tr, uu.ravel(), vv.ravel()).reshape(h, w)
    # Anti-aliasing: pixels whose neighbour sees another surface are re-rendered from four sub-samples.
    ids = tr.ids
    edge = np.zeros((h, w), bool)
    dx = ids[:, 1:] != ids[:, :-1]
    dy = ids[1:, :] != ids[:-1, :]
    edge[:, 1:] |= dx
    edge[:, :-1] |= dx
    edge[1:, :] |= dy
    edge[:-1, :] |= dy
    ey, ex = np.nonzero(edge)
    if len(ex):
        su = (ex[:, None] + _SUBSAMPLES[None, :, 0]).ravel()
        sv = (ey[:, None] + _SUBSAMPLES[None, :, 1]).ravel()
        sub = _trace_points(scene, cam, su, sv, tr.homographies)
        vals = _shade(scene, cam, sub, su, sv).reshape(-1, len(_SUBSAMPLES))
        img[ey, ex] = vals.mean(axis=1)
    depth = np.where(tr.ids >= 0, tr.z, 0.0)
    return img, depth


# ----------------------------------------------------------------------------------------------------------
# Camera path
# ----------------------------------------------------------------------------------------------------------


def _look_at(centre: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Camera-to-world rotation looking from centre at target (z forward, y down), rolled about the axis."""
    f = _unit(target - centre)
    r = _unit(np.cross(f, UP))
    d = np.cross(f, r)
    c, s = math.cos(roll), math.sin(roll)
    return np.column_stack([c * r + s * d, -s * r + c * d, f])


def _catmull_rom(keys: np.ndarray, n: int) -> np.ndarray:
    """n samples of the uniform Catmull-Rom curve through the rows of keys (end tangents by reflection)."""
    keys = np.asarray(keys, np.float64)
    if keys.ndim == 1:
        keys = keys[:, None]
    k = len(keys)
    ext = np.concatenate([2 * keys[:1] - keys[1:2], keys, 2 * keys[-1:] - keys[-2:-1]])
    pos = np.linspace(0.0, k - 1, n) if n > 1 else np.zeros(1)
    seg = np.minimum(np.floor(pos).astype(int), k - 2)
    x = (pos - seg)[:, None]
    p0, p1, p2, p3 = ext[seg], ext[seg + 1], ext[seg + 2], ext[seg + 3]
    return 0.5 * (
        2 * p1 + (p2 - p0) * x + (2 * p0 - 5 * p1 + 4 * p2 - p3) * x**2 + (3 * p1 - p0 - 3 * p2 + p3) * x**3
    )


def _spread_keys(rng: np.random.Generator, k: int) -> np.ndarray:
    """k values in [0, 1] in random order that include both 0 and 1 (so a key range is fully used)."""
    vals = rng.uniform(0, 1, k)
    i, j = rng.choice(k, 2, replace=False)
    vals[i], vals[j] = 0.0, 1.0
    return vals


# Range of the orbit's azimuth span over one sequence, degrees.
ORBIT_DEG = (20.0, 60.0)


def _random_path(
    rng: np.random.Generator, frames: int, orbit_deg: tuple[float, float] = ORBIT_DEG
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Smooth camera path through 3-5 random key poses: (R_wc, centre) per frame. The azimuth sweeps a span drawn
    from `orbit_deg` (degrees) over the sequence."""
    k = int(rng.integers(3, 6))
    # Roll: monotonic sweep, nearly a full turn in some sequences, a smaller range in others.
    sweep = rng.uniform(4.7, 6.1) if rng.random() < 0.4 else rng.uniform(1.0, 4.7)
    sweep *= 1 if rng.random() < 0.5 else -1
    inner = np.sort(rng.uniform(0.1, 0.9, k - 2))
    roll_keys = rng.uniform(0, 2 * math.pi) + sweep * np.concatenate([[0.0], inner, [1.0]])
    # Distance to the target: ratio far/near up to 2.5.
    near = rng.uniform(1.3, 1.9)
    ratio = rng.uniform(1.2, 2.5)
    dist_keys = near * ratio ** _spread_keys(rng, k)
    # Orbit (azimuth about the vertical) and elevation.
    span = math.radians(rng.uniform(*orbit_deg))
    azim_keys = math.radians(rng.uniform(-35, 35)) + span * (_spread_keys(rng, k) - 0.5)
    elev_keys = np.clip(math.radians(rng.uniform(20, 45)) + np.radians(rng.uniform(-12, 12, k)), 0.17, 1.05)
    target_c = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-1.6, -0.7), rng.uniform(0.3, 0.8)])
    target_keys = target_c + rng.uniform(-1, 1, (k, 3)) * np.array([0.3, 0.3, 0.15])

    params = _catmull_rom(np.column_stack([roll_keys, dist_keys, azim_keys, elev_keys, target_keys]), frames)
    path = []
    for roll, dist, azim, elev, tx, ty, tz in params:
        target = np.array([tx, ty, tz])
        offset = dist * np.array(
            [math.sin(azim) * math.cos(elev), -math.cos(azim) * math.cos(elev), math.sin(elev)]
        )
        centre = target + offset
        path.append((_look_at(centre, target, roll), centre))
    return path


def _camera_inside(scene: Scene, centre: np.ndarray, margin: float = 0.25) -> bool:
    width, depth, _height, left, right = scene.room
    x, y, z = centre
    if z < margin or y > -margin or y < -depth + margin:
        return True
    if (left and x < -width / 2 + margin) or (right and x > width / 2 - margin):
        return True
    return any(np.all(centre > lo - margin) and np.all(centre < hi + margin) for lo, hi in scene.boxes)


def _overlap(d0: np.ndarray, cam0: Camera, d1: np.ndarray, cam1: Camera) -> float:
    """Fraction of the surface pixels of view 0 that are visible (not occluded, inside) in view 1."""
    v, u = np.nonzero(d0 > 0)
    if len(u) == 0:
        return 0.0
    z = d0[v, u]
    Xc = np.linalg.inv(cam0.K) @ np.stack([u * z, v * z, z])
    Xw = cam0.R_wc @ Xc + cam0.t_wc[:, None]
    X1 = cam1.R_wc.T @ (Xw - cam1.t_wc[:, None])
    p = cam1.K @ X1
    with np.errstate(divide="ignore", invalid="ignore"):
        pu = np.rint(p[0] / p[2])
        pv = np.rint(p[1] / p[2])
    ok = (X1[2] > NEAR) & (pu >= 0) & (pu < cam1.width) & (pv >= 0) & (pv < cam1.height)
    z1 = d1[pv[ok].astype(int), pu[ok].astype(int)]
    visible = np.abs(z1 - X1[2, ok]) < 0.03 * X1[2, ok]
    return float(visible.sum()) / len(u)


def _path_is_good(scene: Scene, path: list, width: int, height: int) -> bool:
    """Checks a path on a coarse render: every frame mostly textured, nothing too close, overlap kept."""
    if any(_camera_inside(scene, c) for _R, c in path):
        return False
    lw, lh = max(16, width // 8), max(12, height // 8)
    K = _intrinsics(lw, lh)  # about the same field of view as the full image
    depths, cams = [], []
    for R, c in path:
        cam = Camera(K, R, c, lw, lh)
        tr = _trace_grid(scene, cam)
        hit = tr.ids >= 0
        if hit.mean() < 0.75 or tr.z[hit].min() < 0.35:
            return False
        depths.append(np.where(hit, tr.z, 0.0))
        cams.append(cam)
    for i in range(len(path) - 1):
        if _overlap(depths[i], cams[i], depths[i + 1], cams[i + 1]) < 0.5:
            return False
    return len(path) < 2 or _overlap(depths[0], cams[0], depths[-1], cams[-1]) >= 0.25


# ----------------------------------------------------------------------------------------------------------
# Photometric variation
# ----------------------------------------------------------------------------------------------------------


def _motion_kernel(length: float, angle: float) -> np.ndarray:
    """Normalised kernel of a straight motion streak `length` pixels long."""
    size = int(math.ceil(length)) | 1
    size += 2
    kernel = np.zeros((size, size), np.float64)
    c = (size - 1) / 2
    for s in np.linspace(-length / 2, length / 2, 64):
        x, y = c + s * math.cos(angle), c + s * math.sin(angle)
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return (kernel / kernel.sum()).astype(np.float32)


def _photometric(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random per-frame lighting, blur and sensor noise applied to a float image in [0, 255]."""
    h, w = img.shape
    out = img.astype(np.float32)
    if rng.random() < 0.2:  # occasional defocus or motion blur
        if rng.random() < 0.5:
            out = cv2.GaussianBlur(out, (0, 0), rng.uniform(0.5, 1.5), borderType=cv2.BORDER_REFLECT)
        else:
            kernel = _motion_kernel(rng.uniform(2.0, 7.0), rng.uniform(0, math.pi))
            out = cv2.filter2D(out, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if rng.random() < 0.5:  # smooth illumination change across the image
        x = np.linspace(-1, 1, w, dtype=np.float32)[None, :]
        y = np.linspace(-1, 1, h, dtype=np.float32)[:, None] * (h / w)
        angle = rng.uniform(0, 2 * math.pi)
        field = 1 + rng.uniform(0.05, 0.35) * (math.cos(angle) * x + math.sin(angle) * y)
        if rng.random() < 0.5:  # plus a spot of light or shadow
            cx, cy = rng.uniform(-1, 1), rng.uniform(-0.7, 0.7)
            radius = rng.uniform(0.4, 1.2)
            field = field + rng.uniform(-0.3, 0.3) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / radius**2)
        out *= np.maximum(field, 0.1)
    out = out * rng.uniform(0.6, 1.4) + rng.uniform(-25, 25)
    sigma = rng.uniform(0, 4)
    out += sigma * rng.standard_normal((h, w), dtype=np.float32)
    return out


# ----------------------------------------------------------------------------------------------------------
# Output
# ----------------------------------------------------------------------------------------------------------


def _rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, with w >= 0."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2 * math.sqrt(1 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2 * math.sqrt(1 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2 * math.sqrt(1 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _source_text(seed: int, frames: int, width: int, height: int, used: set[str]) -> str:
    textures = "; ".join(f"{name} ({TEXTURE_LICENCES[name]})" for name in sorted(used))
    return (
        f"Synthetic sequence generated by scone's renderer (training/scone_train/data/render.py) with seed {seed}: "
        f"{frames} frames of {width}x{height} pixels ray-cast from textured planar rectangles (a room with a back "
        "wall and floor, boxes and free-standing panels) along a smooth random camera path, with exact depth and "
        "camera poses; no real scene was photographed. The surface textures are crops of sample images bundled "
        f"with scikit-image {_skimage_version()} (skimage.data), used under the licences stated in scikit-image's "
        f"documentation: {textures}.\n"
    )


def _write_list(path: Path, folder: str, frames: int) -> None:
    lines = ["# stamp filename"] + [f"{i:06d} {folder}/{i:06d}.png" for i in range(frames)]
    path.write_text("\n".join(lines) + "\n")


def _imwrite(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise OSError(f"could not write {path}")


def render_sequence(
    out_dir: Path,
    seed: int,
    frames: int = 30,
    width: int = 640,
    height: int = 480,
    *,
    photometric: bool = True,
    orbit_deg: tuple[float, float] = ORBIT_DEG,
) -> None:
    """Renders one sequence into out_dir (created if needed). The same arguments give byte-identical files.
    With photometric=False the images are the clean renderings (no lighting change, blur or noise); the
    geometry, depth and poses do not depend on that switch. `orbit_deg` bounds the azimuth span of the path
    (a wider span gives wider baselines between the sequence's frames)."""
    if frames < 1:
        raise ValueError("frames must be >= 1")
    out_dir = Path(out_dir)
    seq = np.random.SeedSequence(int(seed))
    scene_ss, path_ss, photo_ss = seq.spawn(3)
    scene_rng = np.random.default_rng(scene_ss)
    path_rng = np.random.default_rng(path_ss)
    photo_rng = np.random.default_rng(photo_ss)

    path = None
    for _scene_try in range(20):
        scene = _make_scene(scene_rng)
        for _path_try in range(40):
            candidate = _random_path(path_rng, frames, orbit_deg)
            if _path_is_good(scene, candidate, width, height):
                path = candidate
                break
        if path is not None:
            break
    if path is None:
        raise RuntimeError(f"no usable camera path found for seed {seed}")

    (out_dir / "rgb").mkdir(parents=True, exist_ok=True)
    (out_dir / "depth").mkdir(parents=True, exist_ok=True)
    K = _intrinsics(width, height)
    poses = []
    for i, (R, c) in enumerate(path):
        img, depth = render_view(scene, Camera(K, R, c, width, height))
        if photometric:
            img = _photometric(img, photo_rng)
        _imwrite(out_dir / "rgb" / f"{i:06d}.png", np.rint(np.clip(img, 0, 255)).astype(np.uint8))
        d = np.rint(depth * DEPTH_SCALE)
        d[(d > 65535) | (depth <= 0)] = 0
        _imwrite(out_dir / "depth" / f"{i:06d}.png", d.astype(np.uint16))
        q = _rotation_to_quaternion(R)
        poses.append(f"{i:06d} " + " ".join(f"{x:.9f}" for x in (*c, *q)))

    _write_list(out_dir / "rgb.txt", "rgb", frames)
    _write_list(out_dir / "depth.txt", "depth", frames)
    f = K[0, 0]
    (out_dir / "camera.txt").write_text(
        f"# fx fy cx cy width height\n{f:g} {f:g} {K[0, 2]:g} {K[1, 2]:g} {width} {height}\n"
    )
    (out_dir / "SOURCE").write_text(_source_text(seed, frames, width, height, scene.used))
    # groundtruth.txt last: its presence with every pose marks a complete sequence.
    tmp = out_dir / "groundtruth.txt.tmp"
    tmp.write_text("# stamp tx ty tz qx qy qz qw (camera-to-world)\n" + "\n".join(poses) + "\n")
    os.replace(tmp, out_dir / "groundtruth.txt")


def sequence_seed(seed: int, index: int) -> int:
    """Seed of sequence `index` of a dataset rendered with `seed` (stable across versions of numpy's PCG64)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, np.uint64)[0] >> 1)


def _is_complete(seq_dir: Path, frames: int) -> bool:
    gt = seq_dir / "groundtruth.txt"
    if not gt.is_file():
        return False
    rows = [ln for ln in gt.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return len(rows) == frames and all(len(r.split()) == 8 for r in rows)


def render_dataset(
    out_root: Path,
    sequences: int,
    frames: int,
    seed: int,
    width: int = 640,
    height: int = 480,
    skip_existing: bool = True,
    orbit_deg: tuple[float, float] = ORBIT_DEG,
) -> list[Path]:
    """Renders seq000 ... into out_root; sequences already complete are skipped (resumable). Each sequence is
    rendered into a temporary directory and moved into place when finished. Returns the sequence paths."""
    from tqdm import tqdm

    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in tqdm(range(sequences), desc="render", unit="seq"):
        final = out_root / f"seq{i:03d}"
        paths.append(final)
        if skip_existing and _is_complete(final, frames):
            continue
        partial = out_root / f".seq{i:03d}.partial"
        if partial.exists():
            shutil.rmtree(partial)
        render_sequence(partial, sequence_seed(seed, i), frames, width, height, orbit_deg=orbit_deg)
        if final.exists():
            shutil.rmtree(final)
        os.replace(partial, final)
    return paths


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description="Render synthetic training sequences (TUM RGB-D layout).")
    ap.add_argument("--out", type=Path, required=True, help="output directory (seqNNN folders are created in it)")
    ap.add_argument("--sequences", type=int, default=40)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument(
        "--orbit-deg", type=float, nargs=2, default=ORBIT_DEG, metavar=("LO", "HI"), help="azimuth span range"
    )
    ap.add_argument("--overwrite", action="store_true", help="re-render sequences that are already complete")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    render_dataset(
        args.out, args.sequences, args.frames, args.seed, args.width, args.height, skip_existing=not args.overwrite,
        orbit_deg=tuple(args.orbit_deg),
    )


if __name__ == "__main__":
    main()
