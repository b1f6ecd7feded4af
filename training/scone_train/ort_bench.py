"""Where onnxruntime spends SConE's inference time (issue 29): the activation kernels alone, and graphs side by side.

`python -m scone_train.ort_bench [--threads 1] [GRAPH ...]` (from `training/`):
1. each activation node alone (Selu, Elu, Relu, Exp) on a [1500, 20, 64] float tensor, the shape of the set
   encoder's per-member activations for 1,500 keypoints: median of 50 runs;
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

from .speed_figure import inference_ratios
from .speed_gate import SHIPPED

SELU_ALPHA = 1.6732632423543772


def one_node(op: str, threads: int, shape=(1500, 20, 64), runs: int = 50) -> float:
    """Median milliseconds of a graph holding the single node `op` on a float tensor of `shape`."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    attrs = {"alpha": SELU_ALPHA} if op == "Elu" else {}
    graph = helper.make_graph([helper.make_node(op, ["x"], ["y"], **attrs)], op,
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, list(shape))],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, list(shape))])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("graphs", nargs="*", type=Path)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=2, help="per training scene")
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args()
    print("| node on [1500, 20, 64] | ms |\n|---|---|")
    for op in ("Selu", "Elu", "Relu", "Exp"):
        print(f"| {op} | {one_node(op, a.threads):.2f} |")
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
