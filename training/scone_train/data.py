"""Scenes (TUM RGB-D layout) and the feature exports written by `scone features`.

The features always come from the Rust extraction (`scone features --scene DIR --out FILE`), so the network
is trained on exactly what the service computes. This module reads them and the scene's poses, intrinsics and
depth; it never detects or describes anything itself.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
MAX_GAP = 0.02  # seconds, as TUM's associate.py


def scone_binary() -> Path:
    """Path of the release binary built by scripts/setup."""
    if "SCONE_BIN" in os.environ:
        return Path(os.environ["SCONE_BIN"])
    prefix = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))
    target = Path(os.environ.get("CARGO_TARGET_DIR", prefix / "target"))
    return target / "release" / "scone"


def prefix_dir() -> Path:
    """The prefix outside the clone where data, caches and runs live ($SCONE_PREFIX)."""
    return Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))


def shared_data() -> Path:
    return Path(os.environ.get("SCONE_DATA", REPO.parent / "shared" / "data"))


def _read_list(path: Path) -> list[list[str]]:
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append(line.split())
    return rows


def quat_to_rot(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _nearest(times: np.ndarray, t: float) -> int | None:
    if len(times) == 0:
        return None
    i = int(np.argmin(np.abs(times - t)))
    return i if abs(times[i] - t) <= MAX_GAP else None


@dataclass
class Scene:
    root: Path
    name: str
    K: np.ndarray  # 3x3
    width: int
    height: int
    stamps: list[str]
    rgb: list[Path]
    T_wc: list[np.ndarray | None]  # 4x4 camera-to-world per frame
    depth: list[Path | None] = field(default_factory=list)

    @property
    def has_depth(self) -> bool:
        return any(d is not None for d in self.depth)

    def load_depth(self, i: int) -> np.ndarray | None:
        """Depth of frame i in metres (0 = no reading)."""
        if self.depth[i] is None:
            return None
        d = cv2.imread(str(self.depth[i]), cv2.IMREAD_ANYDEPTH)
        return d.astype(np.float32) / 5000.0


def load_scene(root: Path) -> Scene:
    root = Path(root)
    cam = [float(v) for v in _read_list(root / "camera.txt")[0][:6]]
    K = np.array([[cam[0], 0, cam[2]], [0, cam[1], cam[3]], [0, 0, 1]], dtype=np.float64)
    rgb_rows = _read_list(root / "rgb.txt")
    gt_rows = _read_list(root / "groundtruth.txt") if (root / "groundtruth.txt").exists() else []
    gt_t = np.array([float(r[0]) for r in gt_rows])
    depth_rows = _read_list(root / "depth.txt") if (root / "depth.txt").exists() else []
    depth_t = np.array([float(r[0]) for r in depth_rows])
    stamps, rgb, poses, depth = [], [], [], []
    for row in rgb_rows:
        t = float(row[0])
        stamps.append(row[0])
        rgb.append(root / row[1])
        g = _nearest(gt_t, t)
        if g is None:
            poses.append(None)
        else:
            v = [float(x) for x in gt_rows[g][1:8]]
            T = np.eye(4)
            T[:3, :3] = quat_to_rot(*v[3:7])
            T[:3, 3] = v[:3]
            poses.append(T)
        d = _nearest(depth_t, t)
        depth.append(None if d is None else root / depth_rows[d][1])
    return Scene(root, root.name, K, int(cam[4]), int(cam[5]), stamps, rgb, poses, depth)


@dataclass
class FrameFeatures:
    keypoints: np.ndarray  # [N, 6] float32: x, y, size, angle (deg), response, octave
    descriptors: np.ndarray  # [N, 64] uint8, FREAK bits LSB first
    neighbours: np.ndarray  # [N, k] int32
    mask: np.ndarray  # [N, k] uint8
    relative: np.ndarray  # [N, k, 4] float32
    context: np.ndarray | None = None  # [N, 113] uint8, the ring context (export format 2)
    gradients: np.ndarray | None = None  # [N, 226] int8, the ring's gradients (`context.gradients`), when asked for

    def __len__(self) -> int:
        return len(self.keypoints)

    def model_inputs(self, k: int) -> tuple:
        """The network's five inputs as torch tensors, constellations cut to the first k (nearest) members."""
        import torch

        return (
            torch.from_numpy(self.descriptors),
            torch.from_numpy(np.ascontiguousarray(self.keypoints[:, [3, 2]])),
            torch.from_numpy(self.neighbours[:, :k].astype(np.int64)),
            torch.from_numpy(self.mask[:, :k].astype(np.float32)),
            torch.from_numpy(np.ascontiguousarray(self.relative[:, :k])),
        )


def grey_image(path: Path) -> np.ndarray:
    """An image file as the service's decoder makes it grey (`src/decode.rs`: decoded unchanged, 16-bit scaled
    by 1/257, BGR(A) to grey with OpenCV's weights)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: the decoder could not read the image")
    if img.dtype == np.uint16:
        img = cv2.convertScaleAbs(img, alpha=1.0 / 257.0)  # convertTo(CV_8U, 1/257): the same saturating round
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    return img


def _attach_gradients(npz_path: Path, scene_dir: Path, meta: dict, frames: list[FrameFeatures]) -> None:
    from . import context

    key = hashlib.sha256(Path(context.__file__).read_bytes() + Path(npz_path).with_suffix(".key").read_bytes()).hexdigest()[:16]
    cache = Path(npz_path).with_name(Path(npz_path).name.replace(".features.npz", f".{key}.gradients.npz"))
    if cache.exists():
        z = np.load(cache)
        for f, frame in zip(meta["frames"], frames):
            frame.gradients = z[f"f{f['index']:04d}"]
        return
    out = {}
    for f, frame in zip(meta["frames"], frames):
        frame.gradients = context.gradients(grey_image(scene_dir / f["file"]), frame.keypoints)
        out[f"f{f['index']:04d}"] = frame.gradients
    np.savez(cache, **out)


def load_features(npz_path: Path, scene_dir: Path | None = None, gradients: bool = False) -> tuple[dict, list[FrameFeatures]]:
    """The frames of an export; with `scene_dir` and `gradients`, their ring gradients too (`context.gradients`,
    for a model that reads them: the Rust export does not write them, so they are computed here from the frames'
    images as `src/decode.rs` decodes them, and cached beside the features)."""
    z = np.load(npz_path)
    meta = json.loads(bytes(z["meta_json"]))
    frames = []
    for f in meta["frames"]:
        p = f"f{f['index']:04d}_"
        frames.append(
            FrameFeatures(
                z[p + "keypoints"], z[p + "descriptors"], z[p + "neighbours"], z[p + "mask"], z[p + "relative"],
                z[p + "context"] if p + "context" in z.files else None,
            )
        )
    if gradients and scene_dir is not None:
        _attach_gradients(npz_path, Path(scene_dir), meta, frames)
    return meta, frames


# The Rust sources whose behaviour decides the exported features: a change to any of them re-exports.
EXTRACTION_SOURCES = ["src/decode.rs", "src/features.rs", "src/constellation.rs", "src/context.rs", "src/offline/training_features.rs", "Cargo.lock"]


def extraction_key(extra_args: list[str] | None = None) -> str:
    h = hashlib.sha256()
    for rel in EXTRACTION_SOURCES:
        h.update(rel.encode())
        h.update((REPO / rel).read_bytes())
    h.update(json.dumps(extra_args or []).encode())
    return h.hexdigest()[:16]


def export_features(scene_dir: Path, out: Path, extra_args: list[str] | None = None, force: bool = False) -> Path:
    """Runs the Rust extraction on a scene; skipped when `out` was made by the same extraction code (a key of
    the extraction sources is kept beside it)."""
    out = Path(out)
    binary = scone_binary()
    if not binary.exists():
        raise FileNotFoundError(f"{binary} not found: run scripts/setup first")
    key_path = out.with_suffix(".key")
    key = extraction_key(extra_args)
    if out.exists() and not force and key_path.exists() and key_path.read_text() == key:
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [str(binary), "features", "--scene", str(scene_dir), "--out", str(out), "--opencv-threads", "1"]
    cmd += extra_args or []
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    key_path.write_text(key)
    return out
