"""The feature exports written by `scone features`, and the extraction settings they are made at.

The features always come from the Rust extraction (`scone features --scene DIR --out FILE`), so the network
is trained on exactly what the service computes. This module runs it and reads its exports; it never detects or
describes anything itself.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..paths import REPO, scone_binary


@dataclass
class FrameFeatures:
    keypoints: np.ndarray  # [N, 6] float32: x, y, size, angle (deg), response, octave
    descriptors: np.ndarray  # [N, 64] uint8, FREAK bits LSB first
    neighbours: np.ndarray  # [N, k] int32
    mask: np.ndarray  # [N, k] uint8
    relative: np.ndarray  # [N, k, 4] float32
    context: np.ndarray | None = None  # [N, 113] uint8, the ring context (export format 2)
    gradients: np.ndarray | None = None  # [N, 226] int8, the ring's gradients (`ring_context.gradients`), when asked for

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
    """An image file as the service's decoder makes it grey (`src/describe/decode.rs`: decoded unchanged, 16-bit
    scaled by 1/257, BGR(A) to grey with OpenCV's weights)."""
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
    from . import ring_context

    key = hashlib.sha256(Path(ring_context.__file__).read_bytes() + Path(npz_path).with_suffix(".key").read_bytes()).hexdigest()[:16]
    cache = Path(npz_path).with_name(Path(npz_path).name.replace(".features.npz", f".{key}.gradients.npz"))
    if cache.exists():
        z = np.load(cache)
        for f, frame in zip(meta["frames"], frames):
            frame.gradients = z[f"f{f['index']:04d}"]
        return
    out = {}
    for f, frame in zip(meta["frames"], frames):
        frame.gradients = ring_context.gradients(grey_image(scene_dir / f["file"]), frame.keypoints)
        out[f"f{f['index']:04d}"] = frame.gradients
    np.savez(cache, **out)


def load_features(npz_path: Path, scene_dir: Path | None = None, gradients: bool = False) -> tuple[dict, list[FrameFeatures]]:
    """The frames of an export; with `scene_dir` and `gradients`, their ring gradients too (`ring_context.gradients`,
    for a model that reads them: the Rust export does not write them, so they are computed here from the frames'
    images as `src/describe/decode.rs` decodes them, and cached beside the features)."""
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
EXTRACTION_SOURCES = [
    "src/describe/decode.rs",
    "src/describe/features.rs",
    "src/describe/constellation.rs",
    "src/describe/ring_context.rs",
    "src/offline/training_features.rs",
    "Cargo.lock",
]


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


# The extraction every model was trained at unless its config's `data.extractor` says otherwise: the client
# contract's revision 2 (the Rust extractor's defaults until issue 39). A model that declares nothing is served
# at it.
REVISION_2_EXTRACTION = {"fast_threshold": 20, "max_keypoints": 1500, "levels": 6, "scale_factor": 1.2, "grid_cell": 32}
# The Rust extractor's defaults: the client contract's revision 3 (E1 of issue 39, src/describe/features.rs).
REVISION_3_EXTRACTION = {**REVISION_2_EXTRACTION, "levels": 8, "max_keypoints": 2000}


def extractor_args(settings: dict | None) -> list[str]:
    """`scone features` flags for the config's `data.extractor` settings, which are relative to revision 2 (the
    extractor's defaults when every config before issue 39 was written): a flag for each setting given and each
    where revision 2 differs from the extractor's defaults (revision 3), so a config means what it meant."""
    settings = settings or {}
    full = {**REVISION_2_EXTRACTION, **settings}
    out: list[str] = []
    for key, value in sorted(full.items()):
        if key in settings or value != REVISION_3_EXTRACTION[key]:
            out += [f"--{key.replace('_', '-')}", str(value)]
    return out
