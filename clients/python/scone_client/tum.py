"""A scene in the TUM RGB-D layout as the repository's fixtures have it (rgb.txt, depth.txt, groundtruth.txt,
camera.txt), with colour, depth and pose associated by equal timestamps (the fixtures' convention; the server's
own loader also associates nearest stamps within 20 ms, which real TUM sequences need)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from scone_client.client import Camera


@dataclass(frozen=True)
class Frame:
    stamp: str
    rgb: Path
    depth: Path | None
    #: Camera-to-world (tx, ty, tz, qx, qy, qz, qw), or None.
    pose: tuple[float, ...] | None


@dataclass(frozen=True)
class Scene:
    camera: Camera
    frames: list[Frame]


def _rows(path: Path) -> list[list[str]]:
    if not path.exists():
        return []
    lines = (line.split() for line in path.read_text().splitlines())
    return [parts for parts in lines if parts and not parts[0].startswith("#")]


def load(directory: str | Path) -> Scene:
    d = Path(directory)
    fx, fy, cx, cy, w, h = _rows(d / "camera.txt")[0][:6]
    camera = Camera(float(fx), float(fy), float(cx), float(cy), int(float(w)), int(float(h)))
    depth = {r[0]: d / r[1] for r in _rows(d / "depth.txt")}
    poses = {r[0]: tuple(float(v) for v in r[1:8]) for r in _rows(d / "groundtruth.txt")}
    frames = [Frame(r[0], d / r[1], depth.get(r[0]), poses.get(r[0])) for r in _rows(d / "rgb.txt")]
    return Scene(camera, frames)
