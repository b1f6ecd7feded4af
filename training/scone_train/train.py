"""Train SConE: `python -m scone_train.train --config configs/scone-ring-real.yaml [--steps N] [--run-dir DIR]`.

Seeded, resumable (a checkpoint every `checkpoint_every` steps; rerunning the same command continues), with a
per-interval log of loss and selection-split precision (`log.jsonl`, `curves.png`). The best checkpoint on
the selection split is kept as `best.pt`; validation scenes are never read here.

The configs of the shipped models are `configs/scone-ring-real.yaml` (the embedded ring-context model, the default
here) and `configs/scone-set.yaml` (the constellation model, which `scone_train.release` trains); every other
config, a candidate or a reading of the lab notebook (docs/model-experiments.md), is in `configs/experiments/`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml
from tqdm import tqdm

from .data import correspondences as C
from .data.features import FrameFeatures, extractor_args
from .data.training_units import GroupSampler, PairSampler, Unit, build_unit, shared_anchors
from .evaluation import nn_precision as E
from .model.distill import relational_loss
from .model.network import SconeNet, build_model, ring_from_onnx
from .paths import REPO, prefix_dir, shared_data


def load_units(cfg: dict, rendered_root: Path | None = None) -> tuple[list[Unit], list[Unit]]:
    """(train units, selection units) as the config says; renders what is missing. Features come from the
    extraction `data.extractor` sets (a cache of its own per setting), with the ring's gradients on every frame
    when the model reads them (`model.ring_gradients`)."""
    d = cfg["data"]
    args = extractor_args(d.get("extractor"))
    grads = bool(cfg["model"].get("ring_gradients", False))
    cache = prefix_dir() / "data" / ("cache" if not args else "cache-" + "".join(a.strip("-") for a in args))
    rendered_root = rendered_root or prefix_dir() / "data" / f"rendered-{d['rendered_seed']}"
    seqs = []
    if d["rendered_sequences"] > 0:
        from .data.render import render_dataset

        seqs = render_dataset(rendered_root, d["rendered_sequences"], d["rendered_frames"], d["rendered_seed"])
    n_sel = d["selection_sequences"]
    train, select = [], []
    for k, s in enumerate(tqdm(seqs, desc="features + landmarks", leave=False)):
        unit = build_unit(s, cache / rendered_root.name, extractor_args=args, gradients=grads)
        (select if k >= len(seqs) - n_sel else train).append(unit)
    # Wide-orbit sequences (training only, so the selection split stays as it was): the default paths sweep
    # 20-60 degrees of azimuth, and 99 % of their frame pairs are within 43 degrees of each other.
    if d.get("wide_sequences", 0) > 0:
        from .data.render import render_dataset

        lo, hi = (float(x) for x in d.get("wide_orbit_deg", [70, 120]))
        seed = d.get("wide_seed", 1)
        wide_root = prefix_dir() / "data" / f"rendered-orbit{lo:g}-{hi:g}-{seed}"
        wide = render_dataset(wide_root, d["wide_sequences"], d["rendered_frames"], seed, orbit_deg=(lo, hi))
        for s in tqdm(wide, desc="wide features + landmarks", leave=False):
            train.append(build_unit(s, cache / wide_root.name, name=f"wide-{s.name}", extractor_args=args, gradients=grads))
    if d.get("real_split"):
        # The real training scenes, split by scone_train.data.splits (written down before training on them):
        # `real_split: true` the five of the shipped recipe, `real_split: nine` those and the four orbits.
        from .data.splits import part, scene_dir, scene_set

        for name, spec in scene_set(d["real_split"]).items():
            if not scene_dir(name).is_dir():
                continue
            geo = C.GeometryParams(**spec.get("geometry", {}))
            src, keep = part(name, "train")
            # `train_tracks` changes how the training parts' links become tracks (C.GeometryParams.tracks): one
            # rule for every part, or a rule per scene name (the rest "drop"). The selection parts keep the
            # labels every earlier run was selected on.
            rule = d.get("train_tracks", "drop")
            train_geo = dataclasses.replace(geo, tracks=rule.get(name, "drop") if isinstance(rule, dict) else rule)
            u = build_unit(src, cache / "real", keep, train_geo, f"{name}-train", args, grads)
            u.real = True
            u.scene = True
            train.append(u)
            select.append(build_unit(src, cache / "real", part(name, "select")[1], geo, f"{name}-sel", args, grads))
    if d.get("warps"):
        # Exact-warp sequences (scone_train.data.warps): training from the training frames and scikit-image's
        # photographs, and a few selection sequences beside the real selection units.
        from .data.training_units import build_warp_unit
        from .data.warps import GENERATOR, generate

        w = d["warps"]
        for role, seed, per_scene, kinds, into in (
            ("training", w.get("seed", 1), w.get("per_scene", 12), w.get("kinds", ["zoom", "viewpoint", "photometric"]), train),
            ("selection", 1, w.get("selection_per_scene", 1), w.get("selection_kinds", ["zoom", "viewpoint"]), select),
        ):
            root = prefix_dir() / "data" / f"warps-g{GENERATOR}-{role}-{seed}-{per_scene}-{'+'.join(kinds)}"
            if not (root / "manifest.json").exists():
                generate(role, root, seed, per_scene, tuple(kinds))
            seqs = sorted(p.parent for p in root.glob("*/H_1_2"))
            for s in tqdm(seqs, desc=f"{role} warps", leave=False):
                into.append(build_warp_unit(s, cache / root.name, extractor_args=args, gradients=grads))
    if d.get("castle") and not d.get("real_split"):
        castle = shared_data() / "scenes" / d["castle"]
        if castle.is_dir():
            cut = d["castle_train_frames"]
            total = len([line for line in (castle / "rgb.txt").read_text().splitlines() if line and line[0] != "#"])
            # castle_window: link frames (and look for third views) at most this many frames apart. With all 20
            # training frames (0), chance third-view hits make nearly every link ambiguous: 23 observations
            # per frame and 12 usable pairs, against 188 and 166 with a window of 3.
            geo = C.GeometryParams(window=d.get("castle_window", 0))
            train.append(build_unit(castle, cache / "real", list(range(cut)), geo, "castle-train", args, grads))
            train[-1].real = True
            train[-1].scene = True
            select.append(build_unit(castle, cache / "real", list(range(cut, total)), C.GeometryParams(), "castle-sel", args, grads))
    return train, select


class TensorCache:
    """Torch views of a frame's arrays as the model reads them (`frame_inputs`), made once."""

    def __init__(self, model):
        self.model = model
        self.cache: dict[int, tuple] = {}

    def get(self, f: FrameFeatures):
        key = id(f)
        if key not in self.cache:
            self.cache[key] = self.model.frame_inputs(f)
        return self.cache[key]


class Teacher:
    """`train.teacher`: a frozen ring network (an exported graph, `model.network.ring_from_onnx`) whose similarities
    between the keypoints of two frames the student is pulled towards, beside the labelled loss. Each frame's
    teacher embeddings are computed once."""

    def __init__(self, spec: dict, tensors: TensorCache):
        path = Path(os.path.expandvars(str(spec["model"])))
        if not path.is_absolute():
            path = REPO / path

        self.model, self.weight, self.tensors = ring_from_onnx(path), float(spec["weight"]), tensors
        self.cache: dict[int, torch.Tensor] = {}

    def embed(self, f: FrameFeatures) -> torch.Tensor:
        key = id(f)
        if key not in self.cache:
            with torch.no_grad():
                self.cache[key] = self.model(*self.tensors.get(f))
        return self.cache[key]



def pair_distances(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    sq = (x * x).sum(1, keepdim=True) - 2 * x @ y.T + (y * y).sum(1)[None, :]
    return torch.sqrt(sq.clamp_min(1e-12))


def contrastive_loss(ea, ep, epool, aid, pid, margin: float, hard: bool, gen: torch.Generator):
    """Contrastive loss (Hadsell et al.): 1/2 D^2 for similar pairs, 1/2 max(0, m - D)^2 for dissimilar.

    Dissimilar partners of each anchor: the other anchors' positives and a pool of other keypoints of the
    second frame (anything not observing the anchor's landmark). With `hard`, the nearest of them (and,
    symmetrically, each positive's nearest other anchor); otherwise one drawn at random.
    """
    d_pos = (ea - ep).norm(dim=1)
    cand = torch.cat([ep, epool])
    cid = torch.cat([aid, pid])
    same = aid[:, None] == cid[None, :]
    d_ab = pair_distances(ea, cand).masked_fill(same, float("inf"))
    d_ba = pair_distances(ep, ea).masked_fill(aid[:, None] == aid[None, :], float("inf"))
    if hard:
        neg = torch.cat([d_ab.min(1).values, d_ba.min(1).values])
    else:
        valid = torch.isfinite(d_ab)
        scores = torch.rand(d_ab.shape, generator=gen).masked_fill(~valid, -1.0)
        neg = d_ab.gather(1, scores.argmax(1, keepdim=True)).squeeze(1)
    neg = neg[torch.isfinite(neg)]
    pos_term = 0.5 * (d_pos**2).mean()
    neg_term = 0.5 * (torch.relu(margin - neg) ** 2).mean()
    return pos_term + neg_term, d_pos.detach().mean().item(), neg.detach().mean().item()


def near(xy: np.ndarray, centres: np.ndarray, radius: float) -> torch.Tensor:
    """[len(centres), len(xy)] bool: keypoint within `radius` pixels of each centre."""
    d2 = ((centres[:, None, :] - xy[None, :, :]) ** 2).sum(-1)
    return torch.from_numpy(d2 <= radius * radius)


def frame_triplet_loss(ea_all, eb_all, fa, fb, ia, ib, lid, ida, idb, margin: float, exclude_px: float, kind: str = "triplet", tau: float = 0.05):
    """Losses over whole frames, which is what nearest-neighbour matching with a ratio test searches.

    For anchor a_i in frame a with positive b_i in frame b, the hardest negative is the nearest keypoint of b
    that does not observe the landmark, or the nearest keypoint of a that does not (seen from b_i), whichever
    is nearer. `kind`:

    * "triplet": relu(margin + D(a_i, b_i) - D-) (HardNet's loss, over every keypoint of both images);
    * "softmax": cross-entropy of picking the positive among every keypoint of the other frame (cosine / tau),
      both directions. Unlike the triplet it does not collapse from a random start, and it still weights the
      hardest negatives most;
    * "softmax+triplet": both; the ratio test needs D- well above D+, not only ranked above;
    * "softmax+ratio": softmax plus relu(D+ / D- - margin), a hinge on Lowe's ratio itself.

    Keypoints within `exclude_px` of the positive (or anchor) are not negatives: they are the same corner found
    again (another pyramid level, an unlabelled duplicate), which the geometric ground truth cannot tell from
    the labelled one, and a match to them is correct. Returns (loss, mean D+, mean D-).
    """
    a, p = ea_all[ia], eb_all[ib]
    d_pos = (a - p).norm(dim=1)
    lid_t = torch.from_numpy(lid)
    bad_b = (torch.from_numpy(idb)[None, :] == lid_t[:, None]) | near(fb.keypoints[:, :2], fb.keypoints[ib, :2], exclude_px)
    bad_a = (torch.from_numpy(ida)[None, :] == lid_t[:, None]) | near(fa.keypoints[:, :2], fa.keypoints[ia, :2], exclude_px)
    neg = torch.minimum(
        pair_distances(a, eb_all).masked_fill(bad_b, float("inf")).min(1).values,
        pair_distances(p, ea_all).masked_fill(bad_a, float("inf")).min(1).values,
    )
    ok = torch.isfinite(neg)
    terms = []
    if kind.startswith("softmax"):
        rows = torch.arange(len(ia))
        la = (a @ eb_all.T / tau).masked_fill(bad_b, float("-inf"))
        la[rows, torch.from_numpy(ib)] = (a * p).sum(1) / tau
        lb = (p @ ea_all.T / tau).masked_fill(bad_a, float("-inf"))
        lb[rows, torch.from_numpy(ia)] = (a * p).sum(1) / tau
        terms.append(0.5 * (F.cross_entropy(la, torch.from_numpy(ib)) + F.cross_entropy(lb, torch.from_numpy(ia))))
    if kind in ("triplet", "softmax+triplet"):
        terms.append(torch.relu(margin + d_pos[ok] - neg[ok]).mean())
    if kind == "softmax+ratio":
        terms.append(torch.relu(d_pos[ok] / neg[ok].clamp_min(1e-3) - margin).mean())
    if not terms:
        raise ValueError(f"unknown frame loss {kind!r}")
    return sum(terms), d_pos.detach().mean().item(), neg[ok].detach().mean().item()


def augment_constellations(inputs: tuple, affine: float, drop: float, rng: np.random.Generator) -> tuple:
    """A copy of one frame's model inputs with each constellation distorted as a change of viewpoint distorts
    it: the members' offsets (u, v) go through a random affine map R(phi) diag(s1, s2) R(-phi) per keypoint,
    ln s uniform in [-affine, affine] (foreshortening and scale), and each real member is dropped with
    probability `drop` (a neighbour the detector misses in the other view)."""
    desc, kps, nbr, mask, rel = inputs
    n, k = mask.shape
    rel, mask = rel.clone(), mask.clone()
    if affine > 0:
        phi = rng.uniform(0, math.pi, n)
        s = np.exp(rng.uniform(-affine, affine, (n, 2)))
        c, si = np.cos(phi), np.sin(phi)
        R = np.stack([np.stack([c, -si], -1), np.stack([si, c], -1)], -2)  # [n, 2, 2]
        A = R @ (s[:, :, None] * np.transpose(R, (0, 2, 1)))
        rel[:, :, :2] = torch.einsum("nij,nkj->nki", torch.from_numpy(A).float(), rel[:, :, :2])
    if drop > 0:
        mask = mask * torch.from_numpy((rng.random((n, k)) >= drop).astype(np.float32))
    return desc, kps, nbr, mask, rel


def group_step(model: SconeNet, g, tensors: "TensorCache", t: dict, teacher: Teacher | None = None) -> tuple[float, float, float]:
    """Embeds every frame of the group once and backpropagates the whole-frame triplet loss of all its pairs,
    each pair's anchors capped at `anchors` (drawn at random), plus, with a `teacher`, its weight times the
    relational loss on the same anchors. Returns (loss, mean D+, mean D-)."""
    u = g.unit
    rng = np.random.default_rng(int(torch.randint(0, 2**31 - 1, (1,)).item()))
    aff, drop = t.get("augment_affine", 0.0), t.get("augment_drop", 0.0)
    inputs = [tensors.get(u.frames[f]) for f in g.frames]
    if aff > 0 or drop > 0:
        inputs = [augment_constellations(x, aff, drop, rng) for x in inputs]
    emb = [model(*x) for x in inputs]
    losses, dps, dns = [], [], []
    for i, j in g.pairs:
        fa, fb = g.frames[i], g.frames[j]
        ida, idb = u.ids[fa], u.ids[fb]
        shared, ia, ib = shared_anchors(ida, idb, t["anchors"], rng)
        loss, dp, dn = frame_triplet_loss(
            emb[i], emb[j], u.frames[fa], u.frames[fb], ia, ib, shared, ida, idb, t["margin"], t.get("exclude_px", 2.0),
            t.get("frame_loss", "softmax"), t.get("tau", 0.05),
        )
        if teacher is not None:
            ta, tb = teacher.embed(u.frames[fa]), teacher.embed(u.frames[fb])
            loss = loss + teacher.weight * relational_loss(emb[i], emb[j], ta, tb, torch.from_numpy(ia))
        losses.append(loss)
        dps.append(dp)
        dns.append(dn)
    if not losses:
        return 0.0, 0.0, 0.0
    total = torch.stack(losses).mean()
    total.backward()
    return total.item(), float(np.mean(dps)), float(np.mean(dns))


def ratio_matches(qa: np.ndarray, qb: np.ndarray, kind: str, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Nearest neighbour of every row of qa among qb with the ratio test: (query indices, target indices)."""
    if kind == "hamming":
        d = (qa.shape[1] - qa @ qb.T) / 2.0
    else:
        d = np.sqrt(np.maximum((qa * qa).sum(1)[:, None] - 2 * qa @ qb.T + (qb * qb).sum(1)[None, :], 0))
    two = np.partition(d, 1, axis=1)[:, :2]
    nn = d.argmin(1)
    keep = two[:, 0] < ratio * two[:, 1]
    return np.nonzero(keep)[0], nn[keep]


def ratio_test_score(vectors: list[np.ndarray], unit: Unit, kind: str, gap: int = 3) -> dict:
    """Ratio-test (0.8) matching between frames `gap` apart, as pair matching does: precision of the matches
    whose query observes a landmark seen in the other frame, recall = correct matches / such queries."""
    correct = verifiable = queries = 0
    for i in range(len(vectors) - gap):
        j = i + gap
        ida, idb = unit.ids[i], unit.ids[j]
        q, t = ratio_matches(vectors[i], vectors[j], kind)
        labelled = (ida >= 0) & np.isin(ida, idb[idb >= 0])
        queries += int(labelled.sum())
        v = labelled[q]
        verifiable += int(v.sum())
        correct += int((idb[t[v]] == ida[q[v]]).sum())
    p = correct / max(verifiable, 1)
    r = correct / max(queries, 1)
    return {"precision": p, "recall": r, "f1": 2 * p * r / max(p + r, 1e-12)}


def selection_ratio_score(model, units: list[Unit]) -> dict:
    rows = [ratio_test_score(E.embed_frames(model, u.frames) if model is not None else [E.freak_pm1(f.descriptors) for f in u.frames],
                             u, "l2" if model is not None else "hamming") for u in units]
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


def selection_precision(model: SconeNet, units: list[Unit], max_q: int) -> float:
    correct = np.concatenate(
        [E.nn_correct(E.embed_frames(model, u.frames), u.ids, "l2", 0, max_q, seed=k) for k, u in enumerate(units)]
    )
    return float(correct.mean())


def plot_log(log: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evals = [r for r in log if "selection_precision" in r]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot([r["step"] for r in evals], [r["loss"] for r in evals], marker="o")
    ax[0].set_xlabel("step")
    ax[0].set_ylabel("training loss (interval mean)")
    ax[1].plot([r["step"] for r in evals], [r["selection_precision"] for r in evals], marker="o", label="SConE")
    if evals and "freak_selection_precision" in evals[0]:
        ax[1].axhline(evals[0]["freak_selection_precision"], color="gray", ls="--", label="FREAK")
    ax[1].set_xlabel("step")
    ax[1].set_ylabel("NN precision, selection split")
    ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def train(cfg: dict, run_dir: Path, steps: int | None = None, units=None) -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(yaml.safe_dump(cfg))
    t = cfg["train"]
    steps = steps or t["steps"]
    # `stop_after` ends a run early on its schedule: the learning rate still decays over `steps`
    stop = steps if t.get("stop_after") is None else t["stop_after"]
    if not 0 < stop <= steps:
        raise ValueError(f"train.stop_after {stop} is outside 1..steps ({steps})")
    torch.set_num_threads(t["threads"])
    torch.manual_seed(cfg["seed"])
    train_units, sel_units = units or load_units(cfg)
    freak_sel = float(
        np.concatenate(
            [
                E.nn_correct([E.freak_pm1(f.descriptors) for f in u.frames], u.ids, "hamming", 0,
                             cfg["data"]["selection_max_queries"], seed=k)
                for k, u in enumerate(sel_units)
            ]
        ).mean()
    )
    freak_ratio = selection_ratio_score(None, sel_units)
    select_on = t.get("select_on", "nn_precision")
    m = cfg["model"]
    model = build_model(m)
    opt = torch.optim.Adam(model.parameters(), lr=t["lr"], weight_decay=t["weight_decay"])
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: (t["lr_final"] + 0.5 * (t["lr"] - t["lr_final"]) * (1 + math.cos(math.pi * min(s, steps) / steps))) / t["lr"]
    )
    grouped = t.get("loss", "contrastive") == "triplet_frames"
    if not grouped and not isinstance(model, SconeNet):
        raise ValueError("the ring network trains with the whole-frame loss (train.loss: triplet_frames)")
    if grouped:
        sampler = GroupSampler(train_units, t.get("group_frames", 4), seed=cfg["seed"], weight=t.get("pair_weight", "shared"),
                               real_share=t.get("real_share", 0.0), scene_share=t.get("scene_share", 0.0))
    else:
        sampler = PairSampler(train_units, t["anchors"], t["pool"], seed=cfg["seed"], near=t.get("near_negatives", 0))
    gen = torch.Generator().manual_seed(cfg["seed"])
    # `train.ema`: evaluate, pick and save an exponential moving average of the weights (Polyak averaging), which
    # the export then ships; the optimiser still steps the raw weights
    ema = None
    if t.get("ema"):
        ema = torch.optim.swa_utils.AveragedModel(model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(t["ema"]))
    start, best, log = 0, -1.0, []
    last = run_dir / "last.pt"
    if t.get("init") and not last.exists():
        init = Path(os.path.expandvars(t["init"]))
        model.load_state_dict(torch.load(init, weights_only=False)["model"])
        print(f"initialised from {init}")
    if last.exists():
        ck = torch.load(last, weights_only=False)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        sched.load_state_dict(ck["sched"])
        sampler.rng.bit_generator.state = ck["sampler_rng"]
        gen.set_state(ck["gen"])
        start, best, log = ck["step"], ck["best"], ck["log"]
        if ema is not None and "ema" in ck:
            ema.load_state_dict(ck["ema"])  # (a run begun without averaging starts its average here)
        print(f"resuming {run_dir} at step {start}")
        if start >= stop:
            print(f"{run_dir} already holds step {start}, at or past its stop at {stop}: nothing to train")
    tensors = TensorCache(model)
    teacher = Teacher(t["teacher"], tensors) if t.get("teacher") else None
    if teacher is not None and not grouped:
        raise ValueError("train.teacher needs the whole-frame loss (train.loss: triplet_frames)")
    acc = {"loss": 0.0, "pos": 0.0, "neg": 0.0, "n": 0}
    t0 = time.time()
    bar = tqdm(range(start, stop), initial=start, total=stop, desc=cfg["name"], mininterval=1 if sys.stderr.isatty() else 60)
    for step in bar:
        model.train()
        opt.zero_grad()
        total = 0.0
        if grouped:
            total, dp, dn = group_step(model, sampler.sample(), tensors, t, teacher)
            acc["pos"] += dp
            acc["neg"] += dn
        for _ in range(0 if grouped else t["pairs_per_step"]):
            b = sampler.sample()
            ta, tb = tensors.get(b.fa), tensors.get(b.fb)
            da = model.embed_descriptors(ta[0])
            db = model.embed_descriptors(tb[0])
            ea = model.embed_from(da, *ta[1:], rows=torch.from_numpy(b.anchors))
            rows_b = torch.from_numpy(np.concatenate([b.positives, b.pool]))
            eb = model.embed_from(db, *tb[1:], rows=rows_b)
            loss, dp, dn = contrastive_loss(
                ea, eb[: len(b.anchors)], eb[len(b.anchors) :], torch.from_numpy(b.anchor_ids),
                torch.from_numpy(b.pool_ids), t["margin"], t["hard_negatives"], gen,
            )
            (loss / t["pairs_per_step"]).backward()
            total += loss.item() / t["pairs_per_step"]
            acc["pos"] += dp / t["pairs_per_step"]
            acc["neg"] += dn / t["pairs_per_step"]
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        sched.step()
        if ema is not None:
            ema.update_parameters(model)
        acc["loss"] += total
        acc["n"] += 1
        bar.set_postfix(loss=f"{total:.3f}")
        done = step + 1
        if done % t["eval_every"] == 0 or done == stop:
            judged = model if ema is None else ema.module
            nn_prec = selection_precision(judged, sel_units, cfg["data"]["selection_max_queries"])
            ratio = selection_ratio_score(judged, sel_units)
            prec = ratio["f1"] if select_on == "ratio_f1" else nn_prec
            n = max(acc["n"], 1)
            row = {
                "step": done, "loss": acc["loss"] / n, "d_pos": acc["pos"] / n, "d_neg": acc["neg"] / n,
                "selection_precision": nn_prec, "freak_selection_precision": freak_sel,
                "selection_ratio": ratio, "freak_selection_ratio": freak_ratio, "selected_on": select_on,
                "lr": sched.get_last_lr()[0], "seconds": time.time() - t0,
            }
            log.append(row)
            with open(run_dir / "log.jsonl", "a") as fh:
                fh.write(json.dumps(row) + "\n")
            tqdm.write(json.dumps(row))
            plot_log(log, run_dir / "curves.png")
            acc = {"loss": 0.0, "pos": 0.0, "neg": 0.0, "n": 0}
            evaluated = {"model": judged.state_dict(), "config": cfg, "step": done, "selection_precision": nn_prec,
                         "selection_ratio": ratio, "selected_on": select_on}
            if t.get("keep_evaluated", False):
                torch.save(evaluated, run_dir / f"step-{done:05d}.pt")
            if prec > best:
                best = prec
                torch.save(evaluated, run_dir / "best.pt")
        if done % t["checkpoint_every"] == 0 or done == stop:
            ck = {
                "model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                "sampler_rng": sampler.rng.bit_generator.state, "gen": gen.get_state(),
                "step": done, "best": best, "log": log, "config": cfg,
            }
            if ema is not None:
                ck["ema"] = ema.state_dict()
            torch.save(ck, run_dir / "last.tmp")
            os.replace(run_dir / "last.tmp", last)
    return run_dir / "best.pt"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "configs" / "scone-ring-real.yaml"))
    ap.add_argument("--run-dir", default=None)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--set", action="append", default=[], help="override, e.g. train.hard_negatives=false")
    args = ap.parse_args()
    cfg = yaml.safe_load(Path(args.config).read_text())
    for kv in args.set:
        key, val = kv.split("=", 1)
        node = cfg
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = yaml.safe_load(val)
    run_dir = Path(args.run_dir) if args.run_dir else prefix_dir() / "runs" / cfg["name"]
    best = train(cfg, run_dir, args.steps)
    print(f"best checkpoint: {best}")


if __name__ == "__main__":
    main()
