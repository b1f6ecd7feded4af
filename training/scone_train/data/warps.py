"""Exact-homography sequences from real photographs, in the HPatches layout (`1.png .. 6.png`, `H_1_k`).

Each source photograph gives one sequence of each kind:

- `zoom`: zooms of about 1.2, 1.5, 1.9, 2.3 and 2.8 (each jittered by up to 5 %), with at most 5 degrees of
  in-plane rotation and of tilt (generator 1 drew the rotation from -180..180 here: generator 2 separates the
  effects, so each bin of `scone eval homography` holds one);
- `rotation`: in-plane rotations of about 30, 60, 90, 135 and 180 degrees (either sense, jittered by up to 5),
  with a zoom of 1-1.1 and at most 5 degrees of tilt;
- `viewpoint`: the photograph seen as a plane tilted by about 15, 25, 35, 45 and 55 degrees about a random
  in-plane axis (up to about 60), with a zoom of 1-1.1 and up to 5 degrees of rotation;
- `photometric`: small geometric changes (zoom up to 1.1, 10 degrees, 8 degrees of tilt) under changes of
  light (gamma and gain), Gaussian blur and JPEG quality, one after the other and stronger with k.

Image 1 is the centre 75 % of the photograph; image k renders the whole photograph through
`H_1_k @ T(-offset)`, so image k holds no interpolation of image 1 and the labels are exact to the pixel grid.
Pixels that come from outside the photograph are black. Every warped image also gets a gain of 0.85-1.15 and
sensor noise (sigma 2 grey levels) unless it is a `photometric` step of light.

Roles (`--role`), which frames they read:
- `validation`: the validation scenes' frames (`VALIDATION_SCENES`, evenly spaced); generated once, before
  training, with `VALIDATION_SEED`; never used for a choice;
- `selection`: the selection frames of the training scenes (`splits.SPLIT`);
- `training`: the training frames of the training scenes plus scikit-image's CC0 / public-domain photographs.

`python -m scone_train.data.warps --role validation --out DIR` writes `DIR/<scene>-<frame>-<kind>/` and a
`manifest.json` with every pair's parameters (zoom, rotation, tilt, photometric change). The warps are research
data derived from the scenes (see each scene's `SOURCE`): they live under the prefix, never in the product.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np

from ..paths import prefix_dir, shared_data
from .scenes import load_scene

VALIDATION_SEED = 20261203
VALIDATION_SCENES = {
    "strecha-fountain-P11": 4,
    "kitti-clip2": 4,
    "rgbd-slambook-5": 4,
    "tum-fr3-long-office": 4,
    "middlebury-dino48": 4,
}
KINDS = ("zoom", "rotation", "viewpoint", "photometric")
#: The generator's version: part of the directories the training and the rules read, so that warps made by
#: another generator are never taken for these.
GENERATOR = 2
CROP = 0.75
STEPS = 5


def similarity_about(centre: tuple[float, float], zoom: float, rotation_deg: float, shift: tuple[float, float]) -> np.ndarray:
    cx, cy = centre
    a = math.radians(rotation_deg)
    c, s = math.cos(a) * zoom, math.sin(a) * zoom
    t = np.array([[1, 0, cx + shift[0]], [0, 1, cy + shift[1]], [0, 0, 1]], dtype=np.float64)
    r = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    back = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], dtype=np.float64)
    return t @ r @ back


def tilt_homography(centre: tuple[float, float], focal: float, tilt_deg: float, axis_deg: float) -> np.ndarray:
    """The image as a plane at distance `focal` (pixels), turned by `tilt_deg` about an in-plane axis through
    its centre at `axis_deg`, seen by the same pinhole camera; centred so the centre stays put."""
    cx, cy = centre
    axis = np.array([math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg)), 0.0])
    rot, _ = cv2.Rodrigues(axis * math.radians(tilt_deg))
    f = focal
    h = np.array(
        [[f * rot[0, 0], f * rot[0, 1], 0.0], [f * rot[1, 0], f * rot[1, 1], 0.0], [rot[2, 0], rot[2, 1], f]],
        dtype=np.float64,
    )
    to = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1]], dtype=np.float64)
    back = np.array([[1, 0, -cx], [0, 1, -cy], [0, 0, 1]], dtype=np.float64)
    return to @ h @ back


def pair_parameters(kind: str, step: int, rng: np.random.Generator) -> dict:
    """Parameters of pair (1, step + 2) of a sequence of `kind`."""
    if kind == "zoom":
        zoom = (1.2, 1.5, 1.9, 2.3, 2.8)[step] * rng.uniform(0.95, 1.05)
        return {"zoom": zoom, "rotation": rng.uniform(-5, 5), "tilt": rng.uniform(0, 5),
                "axis": rng.uniform(0, 180), "photometric": None}
    if kind == "rotation":
        turn = (30, 60, 90, 135, 180)[step] + rng.uniform(-5, 5)
        return {"zoom": rng.uniform(1.0, 1.1), "rotation": float(rng.choice([-1, 1])) * turn,
                "tilt": rng.uniform(0, 5), "axis": rng.uniform(0, 180), "photometric": None}
    if kind == "viewpoint":
        return {"zoom": rng.uniform(1.0, 1.1), "rotation": rng.uniform(-5, 5),
                "tilt": (15, 25, 35, 45, 55)[step] + rng.uniform(-5, 5), "axis": rng.uniform(0, 180),
                "photometric": None}
    if kind == "photometric":
        change = ("light", "blur", "jpeg")[step % 3]
        strength = (step + 1) / STEPS
        if change == "light":
            gamma = math.exp(rng.choice([-1, 1]) * strength * math.log(2.5))
            p = {"change": "light", "gamma": gamma, "gain": rng.uniform(0.6, 1.4)}
        elif change == "blur":
            p = {"change": "blur", "sigma": 0.5 + 3.0 * strength}
        else:
            p = {"change": "jpeg", "quality": int(round(60 - 50 * strength))}
        return {"zoom": rng.uniform(1.0, 1.1), "rotation": rng.uniform(-10, 10), "tilt": rng.uniform(0, 8),
                "axis": rng.uniform(0, 180), "photometric": p}
    raise ValueError(f"unknown kind {kind!r}")


def homography(size: tuple[int, int], p: dict, rng: np.random.Generator) -> np.ndarray:
    """H_1_k of image 1 (width, height) for parameters `p`: tilt, then rotation and zoom about the centre,
    plus a shift of up to 5 % of the size."""
    w, h = size
    centre = (w / 2.0, h / 2.0)
    shift = (rng.uniform(-0.05, 0.05) * w, rng.uniform(-0.05, 0.05) * h)
    tilt = tilt_homography(centre, float(max(w, h)), p["tilt"], p["axis"])
    m = similarity_about(centre, p["zoom"], p["rotation"], shift) @ tilt
    return m / m[2, 2]


def photometric(img: np.ndarray, p: dict | None, rng: np.random.Generator) -> np.ndarray:
    out = img.astype(np.float32)
    if p is not None and p["change"] == "light":
        out = 255.0 * np.power(out / 255.0, p["gamma"]) * p["gain"]
    else:
        out = out * rng.uniform(0.85, 1.15)
    out = out + rng.normal(0.0, 2.0, size=out.shape)
    out = np.clip(out, 0, 255).astype(np.uint8)
    if p is not None and p["change"] == "blur":
        out = cv2.GaussianBlur(out, (0, 0), p["sigma"])
    if p is not None and p["change"] == "jpeg":
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, p["quality"]])
        assert ok
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return out


def write_sequence(photo: np.ndarray, kind: str, out: Path, rng: np.random.Generator, source: str) -> list[dict]:
    """One sequence of `kind` from `photo` into `out`; returns each pair's parameters."""
    hs, ws = photo.shape[:2]
    w, h = int(round(ws * CROP)), int(round(hs * CROP))
    ox, oy = (ws - w) / 2.0, (hs - h) / 2.0
    to_image1 = np.array([[1, 0, -ox], [0, 1, -oy], [0, 0, 1]], dtype=np.float64)
    out.mkdir(parents=True, exist_ok=True)
    image1 = cv2.warpPerspective(photo, to_image1, (w, h), flags=cv2.INTER_AREA)
    cv2.imwrite(str(out / "1.png"), image1)
    pairs = []
    for step in range(STEPS):
        p = pair_parameters(kind, step, rng)
        hk = homography((w, h), p, rng)
        # INTER_AREA is not defined for perspective maps; linear is what a camera's resampling is closest to.
        warped = cv2.warpPerspective(photo, hk @ to_image1, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        cv2.imwrite(str(out / f"{step + 2}.png"), photometric(warped, p["photometric"], rng))
        np.savetxt(out / f"H_1_{step + 2}", hk, fmt="%.10g")
        pairs.append({"image": step + 2, **{k: v for k, v in p.items()}})
    # The scene layout too (rgb.txt, camera.txt), so `scone features --scene` exports the sequence for training.
    (out / "rgb.txt").write_text("".join(f"{i} {i}.png\n" for i in range(1, STEPS + 2)))
    (out / "camera.txt").write_text(f"{max(w, h)} {max(w, h)} {w / 2} {h / 2} {w} {h}\n")
    (out / "SOURCE").write_text(
        f"Exact warps of {source}, written by scone_train.data.warps (kind {kind}). Same licence as the source scene "
        "(see its SOURCE): research data, not part of the product.\n"
    )
    return pairs


def evenly(n_frames: int, count: int) -> list[int]:
    if count >= n_frames:
        return list(range(n_frames))
    return [int(round(i * (n_frames - 1) / max(count - 1, 1))) for i in range(count)]


def sources(role: str, per_scene: int | None) -> list[tuple[str, Path]]:
    """(name, image path) of the photographs a role reads."""
    out: list[tuple[str, Path]] = []
    if role == "validation":
        for scene, count in VALIDATION_SCENES.items():
            s = load_scene(shared_data() / "scenes" / scene)
            for i in evenly(len(s.rgb), per_scene or count):
                out.append((f"{scene}-{s.stamps[i]}", s.rgb[i]))
        return out
    from .splits import SPLIT, frames

    part = "select" if role == "selection" else "train"
    for scene, spec in SPLIT.items():
        s = load_scene(shared_data() / "scenes" / scene)
        chosen = frames(spec[part], s.stamps)
        if per_scene:
            chosen = [chosen[i] for i in evenly(len(chosen), per_scene)]
        out.extend((f"{scene}-{s.stamps[i]}", s.rgb[i]) for i in chosen)
    if role == "training":
        out.extend(skimage_photographs())
    return out


def skimage_photographs() -> list[tuple[str, Path]]:
    """scikit-image's bundled photographs whose docstrings state CC0 or public domain (the rendered
    sequences' textures, `render.TEXTURE_LICENCES`), written once under the prefix."""
    import skimage.data

    from .render import TEXTURE_LICENCES

    cache = prefix_dir() / "data" / "skimage-photos"
    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for name in TEXTURE_LICENCES:
        path = cache / f"{name}.png"
        if not path.exists():
            img = np.asarray(getattr(skimage.data, name)())
            if img.ndim == 3:
                img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2BGR)
            cv2.imwrite(str(path), img)
        out.append((f"skimage-{name}", path))
    return out


def generate(role: str, out: Path, seed: int, per_scene: int | None = None, kinds: tuple[str, ...] = KINDS) -> dict:
    rng = np.random.default_rng(seed)
    manifest = {"role": role, "seed": seed, "crop": CROP, "generator": GENERATOR, "sequences": []}
    for name, path in sources(role, per_scene):
        photo = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if photo is None:
            raise FileNotFoundError(path)
        for kind in kinds:
            seq = f"{name}-{kind}"
            pairs = write_sequence(photo, kind, out / seq, rng, f"{path}")
            manifest["sequences"].append({"name": seq, "source": str(path), "kind": kind, "pairs": pairs})
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--role", choices=("validation", "selection", "training"), required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=None, help=f"default: {VALIDATION_SEED} for validation, 1 otherwise")
    ap.add_argument("--per-scene", type=int, default=None, help="photographs per scene (default: the role's)")
    ap.add_argument("--kinds", default=",".join(KINDS))
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else (VALIDATION_SEED if args.role == "validation" else 1)
    if args.role == "validation" and seed != VALIDATION_SEED:
        raise SystemExit(f"the validation warps are fixed: seed {VALIDATION_SEED}")
    m = generate(args.role, args.out, seed, args.per_scene, tuple(args.kinds.split(",")))
    print(f"{len(m['sequences'])} sequences, {sum(len(s['pairs']) for s in m['sequences'])} pairs in {args.out}")


if __name__ == "__main__":
    main()
