"""Scenes in the TUM RGB-D layout: images, camera-to-world poses, intrinsics and depth (`rgb.txt`,
`groundtruth.txt`, `camera.txt`, `depth.txt`), the layout every scene of the data sets, the renderer and the
selection parts is written in."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

MAX_GAP = 0.02  # seconds, as TUM's associate.py


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
