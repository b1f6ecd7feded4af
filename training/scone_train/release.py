"""Train (resumable), export the selected checkpoint to ONNX, check it, validate once on the real validation
scenes, and write the model card and the golden fixture. The command behind `scripts/train`.

Steps, each skipped when its output exists (delete the file to redo it):
1. train `configs/scone-set.yaml` into `$SCONE_PREFIX/runs/<name>` (best checkpoint by selection-split precision);
2. k ablation (k = 0, 5, 10, 20 with equal, shorter schedules) for the precision-vs-k figure;
3. export `models/scone-freak-k20.onnx` (+ onnx.checker, onnxruntime parity on random and real inputs);
4. validation on fountain-P11, kitti-clip2, rgbd-slambook-5: NN precision, SConE vs FREAK, bootstrap CI;
5. `models/scone-freak-k20.json` + `.md` model card, `tests/fixtures/golden/`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
from pathlib import Path

import numpy as np
import onnxruntime
import torch
import yaml

from .evaluation import nn_precision as E
from .evaluation.validate import validate, validation_units
from .model import export as X
from .model.golden import make_golden
from .model.network import load_checkpoint
from .paths import REPO, prefix_dir
from .train import load_units, plot_log, train

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "scone-set.yaml"
MODEL = REPO / "models" / "scone-freak-k20.onnx"


def k_ablation(cfg: dict, units, steps: int, scene: str) -> dict:
    """Precision against k on one validation scene, each k trained with the same shorter schedule."""
    out = {}
    vunits = {u.name: (u, w) for u, w in validation_units()}
    unit, window = vunits[scene]
    for k in (0, 5, 10, 20):
        c = json.loads(json.dumps(cfg))
        c["name"] = f"ablation-k{k}"
        c["model"]["k"] = k
        c["train"]["steps"] = steps
        c["train"]["eval_every"] = max(steps // 4, 1)
        best = train(c, prefix_dir() / "runs" / c["name"], steps, units=units)
        model = load_checkpoint(best)
        out[str(k)] = E.scone_precision(model, unit.frames, unit.ids, window).as_dict()
    out["freak"] = E.freak_precision(unit.frames, unit.ids, window).as_dict()
    out["scene"] = scene
    out["steps"] = steps
    return out


def plot_ablation(ab: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ks = [0, 5, 10, 20]
    p = [ab[str(k)]["precision"] for k in ks]
    lo = [ab[str(k)]["precision"] - ab[str(k)]["ci95"][0] for k in ks]
    hi = [ab[str(k)]["ci95"][1] - ab[str(k)]["precision"] for k in ks]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.errorbar(ks, p, yerr=[lo, hi], marker="o", capsize=3, label="SConE")
    ax.axhline(ab["freak"]["precision"], color="gray", ls="--", label="FREAK")
    ax.set_xlabel("constellation size k (0 = central descriptor only)")
    ax.set_ylabel("NN precision")
    ax.set_title(f"{ab['scene']}: precision vs k ({ab['steps']} steps each)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def describe_architecture(m: dict) -> str:
    """One paragraph naming the layers the config builds (the card must say what the file is)."""
    hidden = "-".join(str(v) for v in m.get("desc_hidden", [512, 256]))
    desc = f"every keypoint's FREAK descriptor is embedded once (MLP 512-{hidden}-{m['desc_dim']}, SELU)"
    if m.get("bits_skip"):
        desc += f", beside a linear projection of its bits to {m['bits_skip']} dimensions that goes to the head"
    k = m["k"]
    if k == 0:
        neigh = "no constellation (ablation: the central descriptor only)"
    elif m.get("encoder", "lstm") == "set":
        neigh = (
            f"its {k} nearest neighbours' descriptor embeddings are gathered by index with their relative position, "
            f"orientation and scale and read by a permutation-invariant set encoder (per member two layers of "
            f"{m.get('set_hidden', 64)}, the first split so its descriptor part runs once per keypoint; masked max "
            f"and mean pooling; FC 64-32) instead of the paper's bidirectional LSTM"
        )
    else:
        neigh = (
            f"its {k} nearest neighbours, gathered by index with their relative position, orientation and scale, are "
            f"read by a 2-layer bidirectional LSTM ({m['lstm_hidden']} units) and FC 64-64-32 (the paper's Table 1)"
        )
    hh = m.get("head_hidden", 64)
    return (
        f"The SConE network of Trzcinski et al.: {desc}; {neigh}; the result is joined with the central descriptor "
        f"embedding, orientation and scale in a head {hh}-{hh}-{m['embed_dim']}. Output: {m['embed_dim']}-d, unit "
        f"length; match with L2."
    )


def describe_loss(t: dict) -> str:
    if t.get("loss", "contrastive") == "triplet_frames":
        kind = t.get("frame_loss", "softmax")
        parts = {
            "softmax": f"cross-entropy of picking the positive among every keypoint of the other frame (cosine / {t.get('tau', 0.05)})",
            "triplet": f"triplet margin {t['margin']} with the hardest negative among every keypoint of both frames",
            "softmax+triplet": (
                f"cross-entropy of picking the positive among every keypoint of the other frame (cosine / "
                f"{t.get('tau', 0.05)}) plus a triplet margin {t['margin']} on the hardest negative of both frames"
            ),
        }[kind]
        return (
            f"Loss: {parts}, both directions, over groups of {t.get('group_frames', 4)} frames of one sequence "
            f"(every pair of the group with shared landmarks; up to {t['anchors']} anchors per pair); keypoints "
            f"within {t.get('exclude_px', 2.0)} px of the positive are not negatives."
        )
    return (
        f"Loss: contrastive with margin {t['margin']}, hardest negative among the other anchors' positives and "
        f"{t['pool']} random keypoints of the second frame."
    )


def model_card(cfg: dict, run: Path, ckpt: dict, val: dict, ab: dict | None, parity: dict, units) -> tuple[dict, str]:
    train_units, sel_units = units
    card = {
        "name": "scone-freak-k20",
        "file": MODEL.name,
        "sha256": X.sha256(MODEL),
        "date": datetime.date.today().isoformat(),
        "architecture": describe_architecture(cfg["model"]),
        "loss": describe_loss(cfg["train"]),
        "inputs": {
            "descriptors": "uint8 [N, 64] FREAK bytes, bit i in byte i//8 at i%8 (LSB first)",
            "keypoints": "float32 [N, 2] angle (degrees), size (pixels)",
            "neighbours": f"int64 [N, {cfg['model']['k']}] nearest first; padding = own index",
            "mask": f"float32 [N, {cfg['model']['k']}] 1 real, 0 padding",
            "relative": f"float32 [N, {cfg['model']['k']}, 4] u, v (central sizes), dtheta (rad), ln size ratio",
        },
        "output": "embeddings float32 [N, 48], unit L2 norm",
        "normalisation_inside_graph": "bits -> ±1; angles -> sin, cos; u, v / 8; sizes -> pyramid levels log_1.2(size/7) / 5",
        "extractor": "scone FAST pyramid (6 levels x 1.2, threshold 20, 1,500 keypoints, 32 px grid) + FREAK (OpenCV 4.12 xfeatures2d), k = 20",
        "training": {
            "config": cfg,
            "train_units": [u.name for u in train_units],
            "selection_units": [u.name for u in sel_units],
            "train_observations": int(sum(u.observations() for u in train_units)),
            "selected_step": ckpt["step"],
            "selection_precision": ckpt["selection_precision"],
            "log": str(run / "log.jsonl"),
        },
        "validation_nn_precision": val,
        "k_ablation": ab,
        "parity": parity,
        "versions": {
            "torch": torch.__version__,
            "onnxruntime": onnxruntime.__version__,
            "python": platform.python_version(),
        },
    }
    rows = "\n".join(
        f"| {n} | {v['freak']['precision']:.3f} [{v['freak']['ci95'][0]:.3f}, {v['freak']['ci95'][1]:.3f}] | "
        f"{v['scone']['precision']:.3f} [{v['scone']['ci95'][0]:.3f}, {v['scone']['ci95'][1]:.3f}] | {v['gain_points']:+.1f} | {v['freak']['queries']} |"
        for n, v in val.items()
        if n != "mean"
    )
    md = f"""# Model card: scone-freak-k20

`{MODEL.name}` (sha256 `{card['sha256']}`), exported {card['date']} by `scripts/train`.

**What it is.** {card['architecture']}

**Input contract** (one call per image, dynamic N; all normalisation is inside the graph):

| input | contract |
|---|---|
""" + "\n".join(f"| `{k}` | {v} |" for k, v in card["inputs"].items()) + f"""

Features must come from scone's extractor ({card['extractor']}).

**Training data.** {len(train_units)} training units ({', '.join(u.name for u in train_units[:3])}, ...): rendered
multi-view sequences with exact depth and poses (textured planes and boxes with CC0 / public-domain photographs
from scikit-image, strong in-plane rotation, scale and viewpoint change, lighting, noise, blur) and frames 0-19 of
strecha-castle-P30 (geometry-only landmarks). {card['training']['train_observations']} landmark observations.
Similar pairs: two keypoints observing the same landmark (depth reprojection, or epipolar + triangulation +
third-view check; no descriptor is consulted). {card['loss']}
Checkpoint selected on the selection split ({', '.join(u.name for u in sel_units)}): step {ckpt['step']}
(selected on {ckpt.get('selected_on', 'nn_precision')}), nearest-neighbour precision {ckpt['selection_precision']:.3f}.

**Validation** (never used for a choice), nearest-neighbour precision on geometry-only ground truth, SConE (L2)
vs FREAK (Hamming) on the same keypoints, bootstrap 95 % intervals:

| scene | FREAK | SConE | gain (points) | queries |
|---|---|---|---|---|
{rows}
| **mean** | {val['mean']['freak']:.3f} | {val['mean']['scone']:.3f} | {val['mean']['gain_points']:+.1f} | |

**How the configuration was chosen.** On the selection split only, with the pair protocol (`scone eval pairs
--window 10` on each held-out sequence and on castle frames 20-29): whole-frame loss against the previous
contrastive loss, set encoder against the BiLSTM, the linear bits path, k = 0 against k = 20, margins and a
ratio hinge. The table and what it shows are in BENCHMARKS.md ("What the current model is, and the experiments
behind it"). Pair-matching and relocalisation results on the validation scenes are there too.

**Parity.** PyTorch vs onnxruntime max |diff| {parity['random']:.2e} (random inputs), {parity['real']:.2e} (real features).

**Versions.** torch {torch.__version__}, onnxruntime {onnxruntime.__version__}, Python {platform.python_version()}.
"""
    return card, md


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--ablation-steps", type=int, default=1000)
    ap.add_argument("--skip-ablation", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(2)
    cfg = yaml.safe_load(Path(a.config).read_text())
    run = prefix_dir() / "runs" / cfg["name"]
    units = load_units(cfg)
    best = train(cfg, run, a.steps, units=units)
    ckpt = torch.load(best, weights_only=False)
    model = load_checkpoint(best)
    X.export_onnx(model, MODEL)
    torch.save({"model": ckpt["model"], "config": cfg, "step": ckpt["step"]}, MODEL.with_suffix(".pt"))
    f = units[1][0].frames[0]
    real = X.run_onnx(X.session(MODEL), f.descriptors, f.keypoints[:, [3, 2]], f.neighbours, f.mask, f.relative)
    parity = {"random": X.check_parity(model, MODEL), "real": float(np.abs(real - E.embed_frames(model, [f])[0]).max())}
    val_path = run / "validation.json"
    if not val_path.exists():
        val_path.write_text(json.dumps(validate(model, REPO / "models" / "figures"), indent=2))
    val = json.loads(val_path.read_text())
    plot_log([json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()], REPO / "models" / "scone-training-curves.png")
    print(json.dumps(make_golden(MODEL, REPO / "tests" / "fixtures" / "astronaut.jpg", REPO / "tests" / "fixtures" / "golden"), indent=2))
    ab = None
    ab_path = run / "k_ablation.json"
    if not a.skip_ablation:
        if not ab_path.exists():
            ab_path.write_text(json.dumps(k_ablation(cfg, units, a.ablation_steps, "kitti-clip2"), indent=2))
    if ab_path.exists():
        ab = json.loads(ab_path.read_text())
        plot_ablation(ab, REPO / "models" / "scone-k-ablation.png")
    card, md = model_card(cfg, run, ckpt, val, ab, parity, units)
    MODEL.with_suffix(".json").write_text(json.dumps(card, indent=2) + "\n")
    MODEL.with_suffix(".md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
