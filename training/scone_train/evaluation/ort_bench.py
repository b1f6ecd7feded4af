"""Where onnxruntime spends SConE's inference time (issues 29 and 40): the activation kernels alone, and graphs
side by side.

`python -m scone_train.evaluation.ort_bench [--threads 1] [GRAPH ...]` (from `training/`):
1. each candidate activation (`ACTIVATIONS`: Relu, Gelu, Silu, Tanh, Sigmoid, Selu for reference, Elu, Exp)
   alone and after a fully connected layer (Gemm 256 -> 256, which onnxruntime fuses with Relu), on 2,000
   keypoints (the ring network's widest layer), and alone on [1500, 20, 64], the shape of the constellation
   set encoder's per-member activations: median of 50 runs, one process, interleaved by repetition;
2. the shipped graph against the same graph with its Selu nodes replaced by Relu (wrong values: a bound on what a
   vectorised Selu kernel could save, for timing only) and against every GRAPH given, interleaved in one process
   over real training frames (`speed_figure.inference_ratios`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from ..model.quantize import feeds, frames_for
from ..paths import prefix_dir
from .speed_gate import SHIPPED

SELU_ALPHA = 1.6732632423543772
#: The activations issue 40 asks about, as ONNX nodes (Silu has no node of its own: x * Sigmoid(x)).
ACTIVATIONS = ("Relu", "Gelu", "Silu", "Tanh", "Sigmoid", "Selu", "Elu", "Exp")


def activation_nodes(op: str, x: str, y: str) -> list:
    """The ONNX nodes of activation `op` from tensor `x` to `y`."""
    from onnx import helper

    if op == "Silu":
        return [helper.make_node("Sigmoid", [x], [y + "_s"]), helper.make_node("Mul", [x, y + "_s"], [y])]
    attrs = {"alpha": SELU_ALPHA} if op == "Elu" else {}
    return [helper.make_node(op, [x], [y], **attrs)]


def activation_graph(op: str, shape, gemm: int = 0):
    """A graph of activation `op` on a float tensor of `shape` ([n, width] with `gemm`: after a Gemm width ->
    `gemm`, as a fully connected layer)."""
    from onnx import TensorProto, helper, numpy_helper

    nodes, inits, src = [], [], "x"
    out_shape = list(shape)
    if gemm:
        rng = np.random.default_rng(1)
        w = (rng.standard_normal((shape[1], gemm)) / np.sqrt(shape[1])).astype(np.float32)
        inits = [numpy_helper.from_array(w, "w"), numpy_helper.from_array(np.zeros(gemm, np.float32), "b")]
        nodes.append(helper.make_node("Gemm", ["x", "w", "b"], ["h"]))
        src, out_shape = "h", [shape[0], gemm]
    nodes += activation_nodes(op, src, "y")
    graph = helper.make_graph(nodes, op, [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, out_shape)], initializer=inits)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)], ir_version=9)


def one_node(op: str, threads: int, shape=(1500, 20, 64), runs: int = 50, gemm: int = 0) -> float:
    """Median milliseconds of activation `op` on a float tensor of `shape` (after a Gemm with `gemm`)."""
    import onnxruntime as ort

    model = activation_graph(op, shape, gemm)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    sess = ort.InferenceSession(model.SerializeToString(), opts)
    x = {"x": np.random.default_rng(0).standard_normal(shape).astype(np.float32)}
    sess.run(None, x)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        sess.run(None, x)
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def selu_as_relu(src: Path, dst: Path) -> int:
    """Writes `src` with every Selu node turned into Relu (timing only); returns how many were turned."""
    import onnx

    model = onnx.load(str(src))
    turned = 0
    for node in model.graph.node:
        if node.op_type == "Selu":
            node.op_type = "Relu"
            del node.attribute[:]
            turned += 1
    onnx.save(model, str(dst))
    return turned


def inference_ratios(graphs: list[Path], frames: int, threads: int, reps: int) -> list[float]:
    """Median time per frame of each graph over `reps` interleaved rounds, as ratios to the first graph's."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    sessions = [ort.InferenceSession(str(g), opts) for g in graphs]
    wanted = [{i.name for i in s.get_inputs()} for s in sessions]
    # A ring-context graph needs the context, which only the exports at issue 39's extraction (E1) hold: then
    # every graph runs on those frames (the same keypoints for all).
    ring = any("context" in w for w in wanted)
    cache = prefix_dir() / "data" / ("cache-levels8max-keypoints2000" if ring else "cache") / "real"
    chosen = frames_for(cache, frames, 0)
    base = feeds(chosen, 20)
    for feed, frame in zip(base, chosen):
        if ring:
            feed["context"] = frame.context
    inputs = [[{k: v for k, v in feed.items() if k in w} for feed in base] for w in wanted]
    for s, own in zip(sessions, inputs):
        for f in own[:3]:
            s.run(None, f)
    times = [[] for _ in sessions]
    for _ in range(reps):
        for s, own, t in zip(sessions, inputs, times):
            start = time.perf_counter()
            for f in own:
                s.run(None, f)
            t.append((time.perf_counter() - start) / len(own))
    med = [float(np.median(t)) for t in times]
    return [m / med[0] for m in med]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("graphs", nargs="*", type=Path)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=2, help="per training scene")
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args()
    cases = [("[2000, 256]", (2000, 256), 0), ("Gemm 256 -> 256 on 2000, then it", (2000, 256), 256),
             ("[1500, 20, 64]", (1500, 20, 64), 0)]
    print(f"| activation ({a.threads} thread), ms | " + " | ".join(c[0] for c in cases) + " |")
    print("|---|" + "---|" * len(cases))
    for op in ACTIVATIONS:
        print(f"| {op} | " + " | ".join(f"{one_node(op, a.threads, shape, gemm=g):.3f}" for _, shape, g in cases) + " |")
    shipped = SHIPPED.with_suffix(".onnx")
    with tempfile.TemporaryDirectory() as tmp:
        bound = Path(tmp) / "selu-as-relu.onnx"
        turned = selu_as_relu(shipped, bound)
        names = ["shipped", f"shipped, {turned} Selu nodes as Relu (timing only)", *map(str, a.graphs)]
        ratios = inference_ratios([shipped, bound, *a.graphs], a.frames, a.threads, a.reps)
    print(f"\n| graph ({a.threads} thread) | inference, ratio to shipped |\n|---|---|")
    for name, r in zip(names, ratios):
        print(f"| {name} | {r:.2f}x |")


if __name__ == "__main__":
    main()
