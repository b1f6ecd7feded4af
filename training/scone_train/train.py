"""Train SConE: `python -m scone_train.train --config configs/scone.yaml [--steps N] [--run-dir DIR]`.

Seeded, resumable (a checkpoint every `checkpoint_every` steps; rerunning the same command continues), with a
per-interval log of loss and selection-split precision (`log.jsonl`, `curves.png`). The best checkpoint on
the selection split is kept as `best.pt`; validation scenes are never read here.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm import tqdm

from . import correspondences as C
from . import evaluate as E
from .data import FrameFeatures, shared_data
from .dataset import PairSampler, Unit, build_unit
from .model import SconeNet


def prefix() -> Path:
    return Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))


def load_units(cfg: dict, rendered_root: Path | None = None) -> tuple[list[Unit], list[Unit]]:
    """(train units, selection units) as the config says; renders what is missing."""
    d = cfg["data"]
    cache = prefix() / "data" / "cache"
    rendered_root = rendered_root or prefix() / "data" / f"rendered-{d['rendered_seed']}"
    seqs = []
    if d["rendered_sequences"] > 0:
        from .render import render_dataset

        render_dataset(rendered_root, d["rendered_sequences"], d["rendered_frames"], d["rendered_seed"])
        seqs = sorted(p for p in rendered_root.iterdir() if p.is_dir())[: d["rendered_sequences"]]
    n_sel = d["selection_sequences"]
    train, select = [], []
    for k, s in enumerate(tqdm(seqs, desc="features + landmarks", leave=False)):
        unit = build_unit(s, cache / rendered_root.name)
        (select if k >= len(seqs) - n_sel else train).append(unit)
    if d.get("castle"):
        castle = shared_data() / "scenes" / d["castle"]
        if castle.is_dir():
            cut = d["castle_train_frames"]
            total = len([line for line in (castle / "rgb.txt").read_text().splitlines() if line and line[0] != "#"])
            train.append(build_unit(castle, cache / "real", list(range(cut)), C.GeometryParams(), "castle-train"))
            select.append(build_unit(castle, cache / "real", list(range(cut, total)), C.GeometryParams(), "castle-sel"))
    return train, select


class TensorCache:
    """Torch views of a frame's arrays, made once; constellations cut to the model's k (nearest first)."""

    def __init__(self, k: int):
        self.k = k
        self.cache: dict[int, tuple] = {}

    def get(self, f: FrameFeatures):
        key = id(f)
        if key not in self.cache:
            self.cache[key] = f.model_inputs(self.k)
        return self.cache[key]


def build_model(m: dict) -> SconeNet:
    """k = 0 is the ablation without neighbours (central descriptor only)."""
    return SconeNet(
        k=max(m["k"], 1), embed_dim=m["embed_dim"], desc_dim=m["desc_dim"], lstm_hidden=m["lstm_hidden"],
        use_neighbours=m["k"] > 0,
    )


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
    m = cfg["model"]
    model = build_model(m)
    opt = torch.optim.Adam(model.parameters(), lr=t["lr"], weight_decay=t["weight_decay"])
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: (t["lr_final"] + 0.5 * (t["lr"] - t["lr_final"]) * (1 + math.cos(math.pi * min(s, steps) / steps))) / t["lr"]
    )
    sampler = PairSampler(train_units, t["anchors"], t["pool"], seed=cfg["seed"], near=t.get("near_negatives", 0))
    gen = torch.Generator().manual_seed(cfg["seed"])
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
        print(f"resuming {run_dir} at step {start}")
    tensors = TensorCache(max(model.k, 1))
    acc = {"loss": 0.0, "pos": 0.0, "neg": 0.0, "n": 0}
    t0 = time.time()
    bar = tqdm(range(start, steps), initial=start, total=steps, desc=cfg["name"], mininterval=1 if sys.stderr.isatty() else 60)
    for step in bar:
        model.train()
        opt.zero_grad()
        total = 0.0
        for _ in range(t["pairs_per_step"]):
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
        acc["loss"] += total
        acc["n"] += 1
        bar.set_postfix(loss=f"{total:.3f}")
        done = step + 1
        if done % t["eval_every"] == 0 or done == steps:
            prec = selection_precision(model, sel_units, cfg["data"]["selection_max_queries"])
            n = max(acc["n"], 1)
            row = {
                "step": done, "loss": acc["loss"] / n, "d_pos": acc["pos"] / n, "d_neg": acc["neg"] / n,
                "selection_precision": prec, "freak_selection_precision": freak_sel,
                "lr": sched.get_last_lr()[0], "seconds": time.time() - t0,
            }
            log.append(row)
            with open(run_dir / "log.jsonl", "a") as fh:
                fh.write(json.dumps(row) + "\n")
            tqdm.write(json.dumps(row))
            plot_log(log, run_dir / "curves.png")
            acc = {"loss": 0.0, "pos": 0.0, "neg": 0.0, "n": 0}
            if prec > best:
                best = prec
                torch.save({"model": model.state_dict(), "config": cfg, "step": done, "selection_precision": prec}, run_dir / "best.pt")
        if done % t["checkpoint_every"] == 0 or done == steps:
            ck = {
                "model": model.state_dict(), "opt": opt.state_dict(), "sched": sched.state_dict(),
                "sampler_rng": sampler.rng.bit_generator.state, "gen": gen.get_state(),
                "step": done, "best": best, "log": log,
            }
            torch.save(ck, run_dir / "last.tmp")
            os.replace(run_dir / "last.tmp", last)
    return run_dir / "best.pt"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--config", default=str(Path(__file__).resolve().parents[1] / "configs" / "scone.yaml"))
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
    run_dir = Path(args.run_dir) if args.run_dir else prefix() / "runs" / cfg["name"]
    best = train(cfg, run_dir, args.steps)
    print(f"best checkpoint: {best}")


if __name__ == "__main__":
    main()
