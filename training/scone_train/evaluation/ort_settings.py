"""ONNX Runtime's session settings against SConE's inference time (issue 61): does any setting the service does
not use make a ring graph faster?

`python -m scone_train.evaluation.ort_settings [--rounds 30] [GRAPH ...]` (from `training/`; default: the
embedded model): for each graph, one session per setting (one intra-op thread, spinning off, as the service runs
them): the service's own (`ORT_ENABLE_ALL`), the memory pattern off, the CPU arena off, basic and extended graph
optimisation, denormals flushed to zero. Each round runs every session once, in turn, on the same real frame
(the training frame of the five real training scenes with the most keypoints, at the E1 extraction); printed:
the median time and the median within-round ratio to the service's setting.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..model.quantize import RING_CACHE
from ..paths import REPO, prefix_dir


def settings(ort) -> dict:
    level = ort.GraphOptimizationLevel
    return {
        "service (all optimisations)": {},
        "memory pattern off": {"enable_mem_pattern": False},
        "CPU arena off": {"enable_cpu_mem_arena": False},
        "basic optimisation": {"graph_optimization_level": level.ORT_ENABLE_BASIC},
        "extended optimisation": {"graph_optimization_level": level.ORT_ENABLE_EXTENDED},
        "denormals as zero": {"config": ("session.set_denormal_as_zero", "1")},
    }


def session(ort, graph: Path, setting: dict):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    for k, v in setting.items():
        if k == "config":
            opts.add_session_config_entry(*v)
        else:
            setattr(opts, k, v)
    return ort.InferenceSession(str(graph), opts, providers=["CPUExecutionProvider"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("graphs", nargs="*", type=Path, default=[REPO / "models" / "scone-ring-e1-real.onnx"])
    ap.add_argument("--rounds", type=int, default=30)
    args = ap.parse_args()
    import onnxruntime as ort

    from ..data.splits import exported_frames

    frames = [f for v in exported_frames(prefix_dir() / "data" / RING_CACHE / "real", "train", 20).values() for f in v]
    frame = max(frames, key=lambda f: len(f.descriptors))
    feed = {"descriptors": frame.descriptors, "context": frame.context}
    for graph in args.graphs:
        sessions = {name: session(ort, graph, s) for name, s in settings(ort).items()}
        times = {name: [] for name in sessions}
        for _ in range(args.rounds):
            for name, s in sessions.items():
                start = time.perf_counter()
                s.run(None, feed)
                times[name].append(time.perf_counter() - start)
        base = np.array(times["service (all optimisations)"])
        print(f"{graph.name}, {len(frame.descriptors)} keypoints, {args.rounds} rounds")
        for name, t in times.items():
            print(f"  {name:28s} {np.median(t) * 1e3:6.2f} ms  {np.median(np.array(t) / base):.3f}x")


if __name__ == "__main__":
    main()
