"""Issue 39, round 14's exploration, on the TRAINING units only (never the selection split): `union` with the
embedding's ratio at 0.7-0.9 and FREAK's at 0.8, correct matches per pair and precision, for the shipped ring
model (the ratio test of scone_train.train, without the same-corner radius). Output: explore_training.txt.

    cd training && OMP_NUM_THREADS=1 PYTHONPATH=. python ../docs/results/issue39/round14/explore_training.py
"""

from pathlib import Path

import numpy as np
import yaml
from scone_train import evaluate as E
from scone_train import export as X
from scone_train import train as T

RATIOS = [0.7, 0.75, 0.8, 0.85, 0.9]


def pairs_of(unit, rng):
    """Frame pairs: 15 random pairs at gaps 3 and 10 for a real scene's part, image 1 with each warp for a warp
    sequence."""
    n = len(unit.frames)
    if getattr(unit, "scene", False):
        out = []
        for g in (3, 10):
            if n > g:
                out += [(int(i), int(i) + g) for i in rng.choice(n - g, size=min(15, n - g), replace=False)]
        return out
    return [(0, g) for g in range(1, min(n, 6))]


def main():
    cfg = yaml.safe_load(Path("configs/scone-ring-real.yaml").read_text())
    units, _ = T.load_units(cfg)
    sess = X.session(Path("../models/scone-ring-e1-real.onnx"), 1)
    rng = np.random.default_rng(0)
    rows = {}
    for u in units:
        kind = "real" if getattr(u, "scene", False) else "warp"
        for i, j in pairs_of(u, rng):
            fa, fb = u.frames[i], u.frames[j]
            if min(len(fa), len(fb)) < 2:
                continue
            ea, eb = X.run_onnx(sess, fa.descriptors, fa.context), X.run_onnx(sess, fb.descriptors, fb.context)
            ida, idb = u.ids[i], u.ids[j]
            labelled = (ida >= 0) & np.isin(ida, idb[idb >= 0])

            def score(q, t, key, ida=ida, idb=idb, labelled=labelled):
                v = labelled[q]
                rows.setdefault(key, []).append((int((idb[t[v]] == ida[q[v]]).sum()), int(v.sum())))

            fq, ft = T.ratio_matches(E.freak_pm1(fa.descriptors), E.freak_pm1(fb.descriptors), "hamming", 0.8)
            score(fq, ft, (kind, "freak"))
            for r in RATIOS:
                sq, st = T.ratio_matches(ea, eb, "l2", r)
                answered = np.zeros(len(ida), bool)
                answered[sq] = True
                keep = ~answered[fq]
                score(np.concatenate([sq, fq[keep]]), np.concatenate([st, ft[keep]]), (kind, f"union {r}"))
                score(sq, st, (kind, f"plain {r}"))
    for key in sorted(rows):
        a = np.array(rows[key])
        print(key, len(a), f"correct/pair {a[:, 0].mean():.1f}", f"precision {a[:, 0].sum() / max(a[:, 1].sum(), 1):.3f}")


if __name__ == "__main__":
    main()
