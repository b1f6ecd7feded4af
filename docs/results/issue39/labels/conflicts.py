"""Issue 39 (session 52): where the real training parts' labels go. For each real training part (as
`scone_train.dataset.build_unit` builds it, with its own geometry), the keypoints per frame that some link joins
to another frame's, and how many of those are dropped because their track holds two keypoints of one frame.
Output: conflicts.txt.

    cd training && OMP_NUM_THREADS=1 PYTHONPATH=. python ../docs/results/issue39/labels/conflicts.py
"""

from pathlib import Path

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
        stats = {}
        C.landmarks(scene, frames, C.GeometryParams(**spec.get("geometry", {})), stats)
        n = len(frames)
        print(f"{name}: {n} frames, per frame: keypoints {sum(len(f) for f in frames) / n:.0f}, linked "
              f"{stats['linked'] / n:.0f}, dropped for two keypoints of one frame {stats['conflicted'] / n:.0f}, "
              f"kept {stats['kept'] / n:.0f}")


if __name__ == "__main__":
    main()
