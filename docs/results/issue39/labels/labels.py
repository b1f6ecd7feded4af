"""Issue 39 (session 52): label density of the training units, real views against warps. Labelled keypoints per
frame, and for the frame pairs the group sampler draws from (at least 8 shared landmarks), how many landmarks they
share, plain and weighted as the sampler weights them. Output: labels.txt.

    cd training && OMP_NUM_THREADS=1 PYTHONPATH=. python ../docs/results/issue39/labels/labels.py
"""

from pathlib import Path

import numpy as np
import yaml
from scone_train import train as T
from scone_train.dataset import PairSampler

cfg = yaml.safe_load(Path("configs/scone-ring-real.yaml").read_text())
units, _ = T.load_units(cfg)
kinds = {"real": [u for u in units if getattr(u, "scene", False)], "warp": [u for u in units if not getattr(u, "scene", False)]}
for kind, us in kinds.items():
    kps = np.array([len(f) for u in us for f in u.frames])
    lab = np.array([(ids >= 0).sum() for u in us for ids in u.ids])
    ps = PairSampler(us, anchors=128, pool=0, seed=0, min_shared=8, weight="shared")
    shared = np.array([len(np.intersect1d(u.ids[a][u.ids[a] >= 0], u.ids[b])) for u, a, b in ps.pairs])
    w = ps.weights
    print(kind, "units", len(us), "frames", len(kps), "keypoints/frame %.0f" % kps.mean(), "labelled/frame %.0f" % lab.mean(),
          "pairs", len(shared), "shared/pair median %.0f mean %.0f" % (np.median(shared), shared.mean()),
          "shared/pair weighted by the sampler %.0f" % (shared * w / w.sum()).sum())
    for u in us if kind == "real" else []:
        lab_u = np.array([(ids >= 0).sum() for ids in u.ids])
        print("  ", u.name, "frames", len(u.frames), "labelled/frame median %.0f" % np.median(lab_u))
