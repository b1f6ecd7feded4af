"""Distil the shipped SConE network into a cheaper student (issue 29: the network's shape).

`python -m scone_train.model.distill --name NAME [--activation relu] [--desc-hidden 256,256] [--set-hidden 64]
[--head-hidden 128] [--bits-skip 64] [--steps 3000]` (from `training/`): the student learns to give the
teacher's embeddings for the same inputs, on the Rust-exported features of the five real training scenes'
training frames (never their selection part, never a validation scene). No labels are used, so the student
can only be as good as the teacher; what it buys is speed.

The loss per step takes two frames of one scene:
- every keypoint of both frames: squared distance between the student's and the teacher's embeddings;
- `anchors` keypoints of the first frame against every keypoint of the second: the squared difference between
  the student's and the teacher's cosine similarities (what the matcher's nearest-neighbour and ratio tests read),
  weighted by `relational`.

Where a student's parameter has the teacher's shape it starts from the teacher's values. Every `eval_every`
steps the student is scored on the selection frames of the same scenes: the mean cosine to the teacher and the
share of queries whose nearest neighbour in another frame is the teacher's (`nn_agreement`); `best.pt` keeps the
highest `nn_agreement`. A tqdm bar on stderr counts the steps; each score is a JSON line on stdout and in
`log.jsonl`. The run lives in `<prefix>/runs/distill-NAME` and resumes from `last.pt`. `best.onnx`
is exported (with the parity check) at the end; whether it may ship is decided by issue 29's accuracy gate
(`scone_train.evaluation.speed_gate`, `scripts/speed`), not here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ..data.splits import exported_frames
from ..paths import REPO, prefix_dir
from .export import check_parity, export_onnx
from .network import build_model, load_checkpoint


class Embedded:
    """A frame's model inputs with the teacher's embeddings, computed once."""

    def __init__(self, frame, teacher, k: int):
        self.inputs = frame.model_inputs(k)
        with torch.no_grad():
            self.teacher = teacher(*self.inputs)


def nn_agreement(student, pairs: list[tuple[Embedded, Embedded]]) -> tuple[float, float]:
    """Mean cosine between student and teacher embeddings, and the share of the first frame's keypoints whose
    nearest neighbour (L2) in the second frame is the same under both networks."""
    cos, agree, total = [], 0, 0
    with torch.no_grad():
        for a, b in pairs:
            sa, sb = student(*a.inputs), student(*b.inputs)
            cos.append(float((sa * a.teacher).sum(1).mean()))
            agree += int(((sa @ sb.T).argmax(1) == (a.teacher @ b.teacher.T).argmax(1)).sum())
            total += len(sa)
    return float(np.mean(cos)), agree / max(total, 1)


def relational_loss(sa: torch.Tensor, sb: torch.Tensor, ta: torch.Tensor, tb: torch.Tensor, anchors) -> torch.Tensor:
    """Mean squared difference between the student's and the teacher's cosine similarities of the anchors of frame
    a to every keypoint of frame b: what the nearest-neighbour and ratio tests read, in the teacher's geometry,
    without asking the student for the teacher's embedding space."""
    return F.mse_loss(sa[anchors] @ sb.T, ta[anchors] @ tb.T)


def start_from_teacher(student, teacher) -> int:
    """Copy every teacher parameter whose name and shape the student shares; returns how many were copied."""
    own = student.state_dict()
    same = {k: v for k, v in teacher.state_dict().items() if k in own and own[k].shape == v.shape}
    own.update(same)
    student.load_state_dict(own)
    return len(same)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--name", required=True)
    ap.add_argument("--teacher", type=Path, default=REPO / "models" / "scone-freak-k20.pt")
    ap.add_argument("--activation", default="relu")
    ap.add_argument("--member-activation", default=None, help="the set encoder's per-member layers (default: --activation)")
    ap.add_argument("--desc-hidden", default=None, help="comma-separated widths (default: the teacher's)")
    ap.add_argument("--set-hidden", type=int, default=None)
    ap.add_argument("--head-hidden", type=int, default=None)
    ap.add_argument("--bits-skip", type=int, default=None)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--lr-final", type=float, default=1e-5)
    ap.add_argument("--anchors", type=int, default=256)
    ap.add_argument("--relational", type=float, default=4.0)
    ap.add_argument("--train-frames", type=int, default=60, help="per scene")
    ap.add_argument("--select-frames", type=int, default=6, help="per scene")
    ap.add_argument("--eval-every", type=int, default=250)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cache", type=Path, default=None, help="exported features (default: <prefix>/data/cache/real)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    rng = np.random.default_rng(a.seed)

    teacher_ck = torch.load(a.teacher, weights_only=False)
    teacher = load_checkpoint(a.teacher)
    config = json.loads(json.dumps(teacher_ck["config"]))
    m = config["model"]
    m["activation"] = a.activation
    if a.member_activation:
        m["member_activation"] = a.member_activation
    if a.desc_hidden:
        m["desc_hidden"] = [int(w) for w in a.desc_hidden.split(",")]
    for key, value in (("set_hidden", a.set_hidden), ("head_hidden", a.head_hidden), ("bits_skip", a.bits_skip)):
        if value is not None:
            m[key] = value
    config["name"] = f"distill-{a.name}"
    config["distill"] = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()}
    student = build_model(m)
    copied = start_from_teacher(student, teacher)
    k = m["k"]

    run = prefix_dir() / "runs" / f"distill-{a.name}"
    run.mkdir(parents=True, exist_ok=True)
    opt = torch.optim.Adam(student.parameters(), lr=a.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=a.steps, eta_min=a.lr_final)
    step, best = 0, -1.0
    if (run / "last.pt").exists():
        ck = torch.load(run / "last.pt", weights_only=False)
        if ck.get("model_config") != m or ck.get("steps") != a.steps:
            raise SystemExit(f"{run} holds a run of another network or length ({ck.get('model_config')}, "
                             f"{ck.get('steps')} steps): pick another --name, or remove the directory")
        student.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        sched.load_state_dict(ck["scheduler"])
        step, best = ck["step"], ck["best"]
        rng = np.random.default_rng([a.seed, step])
    print(json.dumps({"run": str(run), "copied_from_teacher": copied, "resumed_at": step, "model": m}))

    cache = a.cache or prefix_dir() / "data" / "cache" / "real"
    def embedded(which: str, per_scene: int) -> dict[str, list[Embedded]]:
        return {s: [Embedded(f, teacher, k) for f in fs if len(f) >= 50]
                for s, fs in exported_frames(cache, which, per_scene).items()}

    train = embedded("train", a.train_frames)
    select = [(fs[i], fs[i + 1]) for fs in embedded("select", a.select_frames).values() for i in range(len(fs) - 1)]
    scenes = sorted(train)
    log = open(run / "log.jsonl", "a")
    t0 = time.time()
    bar = tqdm(total=a.steps, initial=step, desc=config["name"], mininterval=1 if sys.stderr.isatty() else 60)
    while step < a.steps:
        student.train()
        frames = train[scenes[rng.integers(len(scenes))]]
        i, j = rng.choice(len(frames), 2, replace=False)
        fa, fb = frames[i], frames[j]
        sa, sb = student(*fa.inputs), student(*fb.inputs)
        loss = ((sa - fa.teacher) ** 2).sum(1).mean() / 2 + ((sb - fb.teacher) ** 2).sum(1).mean() / 2
        anchors = torch.from_numpy(rng.choice(len(sa), min(a.anchors, len(sa)), replace=False))
        rel = relational_loss(sa, sb, fa.teacher, fb.teacher, anchors)
        total = loss + a.relational * rel
        opt.zero_grad()
        total.backward()
        opt.step()
        sched.step()
        step += 1
        bar.update(1)
        bar.set_postfix(loss=f"{total.item():.4f}", refresh=False)
        if step % a.eval_every == 0 or step == a.steps:
            student.eval()
            cos, agree = nn_agreement(student, select)
            row = {"step": step, "loss": float(loss), "relational": float(rel), "select_cosine": cos,
                   "nn_agreement": agree, "lr": sched.get_last_lr()[0], "seconds": time.time() - t0}
            tqdm.write(json.dumps(row), file=sys.stdout)
            sys.stdout.flush()
            log.write(json.dumps(row) + "\n")
            log.flush()
            if agree > best:
                best = agree
                torch.save({"model": student.state_dict(), "config": config, "step": step, "nn_agreement": agree,
                            "select_cosine": cos}, run / "best.pt")
            torch.save({"model": student.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                        "step": step, "best": best, "model_config": m, "steps": a.steps}, run / "last.pt")
    bar.close()
    best_model = load_checkpoint(run / "best.pt")
    export_onnx(best_model, run / "best.onnx")
    print(json.dumps({"onnx": str(run / "best.onnx"), "parity": check_parity(best_model, run / "best.onnx"),
                      "best_nn_agreement": best}))


if __name__ == "__main__":
    main()
