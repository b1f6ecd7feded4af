"""Issue 39 (session 52): where the real training parts' labels go. For each real training part (as
`scone_train.dataset.build_unit` builds it, with its own geometry), the keypoints per frame that some link joins
to another frame's, and how many of those are dropped because their track holds two keypoints of one frame; then
the same with `tracks: refuse` (conflicting links refused instead of tracks dropped). For both, how well the kept
tracks agree with the ground truth: the distance in pixels of each member to the epipolar line of another member
of its track (up to 20,000 random member pairs in different frames). Output: conflicts.txt.

    cd training && OMP_NUM_THREADS=1 PYTHONPATH=. python ../docs/results/issue39/labels/conflicts.py
"""

from pathlib import Path

import numpy as np
import yaml
from scone_train import correspondences as C
from scone_train.data import export_features, load_features, load_scene
from scone_train.dataset import subset
from scone_train.splits import SPLIT, part, scene_dir
from scone_train.train import extractor_args, prefix


def main():
    cfg = yaml.safe_load(Path("configs/scone-ring-real.yaml").read_text())
    args = extractor_args(cfg["data"]["extractor"])
    cache = prefix() / "data" / ("cache-" + "".join(a.strip("-") for a in args)) / "real"
    for name, spec in SPLIT.items():
        if not scene_dir(name).is_dir():
            continue
        src, keep = part(name, "train")
        npz = export_features(src, cache / f"{src.name}.features.npz", args)
        scene, frames = subset(load_scene(src), load_features(npz)[1], keep)
        for rule in ("drop", "refuse"):
            stats = {}
            ids = C.landmarks(scene, frames, C.GeometryParams(**spec.get("geometry", {}), tracks=rule), stats)
            n = len(frames)
            d = epipolar_errors(scene, frames, ids)
            print(f"{name} ({rule}): {n} frames, per frame: keypoints {sum(len(f) for f in frames) / n:.0f}, linked "
                  f"{stats['linked'] / n:.0f}, dropped for two keypoints of one frame {stats['conflicted'] / n:.0f}, "
                  f"kept {stats['kept'] / n:.0f}; links refused {stats['refused']}; epipolar distance of member pairs "
                  f"median {np.median(d):.2f} px, 90 % {np.quantile(d, 0.9):.2f} px")


def epipolar_errors(scene, frames, ids, pairs: int = 20_000, seed: int = 0) -> np.ndarray:
    """Distances (px) of track members to the epipolar line of another member, for random member pairs."""
    rng = np.random.default_rng(seed)
    members: dict[int, list] = {}
    for f, frame_ids in enumerate(ids):
        for k in np.nonzero(frame_ids >= 0)[0]:
            members.setdefault(int(frame_ids[k]), []).append((f, int(k)))
    tracks = [m for m in members.values() if len(m) >= 2]
    out = []
    for t in rng.choice(len(tracks), size=min(pairs, len(tracks)), replace=False):
        (fa, a), (fb, b) = (tracks[t][i] for i in rng.choice(len(tracks[t]), 2, replace=False))
        F = C._fundamental(scene.K, scene.T_wc[fa], scene.T_wc[fb])
        line = F @ np.r_[frames[fa].keypoints[a, :2], 1.0]
        out.append(abs(line @ np.r_[frames[fb].keypoints[b, :2], 1.0]) / max(np.hypot(line[0], line[1]), 1e-12))
    return np.array(out)

if __name__ == "__main__":
    main()
