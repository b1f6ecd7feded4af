"""Static int8 quantisation of an exported SConE model (onnxruntime's QDQ tooling), calibrated on real frames.

`python -m scone_train.model.quantize --model ../models/scone-freak-k20.onnx --out DIR/scone-int8.onnx` (from
`training/`): the matrix products (MatMul / Gemm) get int8 weights (per channel) and uint8 activations,
calibrated on the Rust-exported features of training frames of the five real training scenes (never the
selection or validation frames); every other operator stays fp32. It prints the cosine between the int8 and
the fp32 embeddings on other training frames. Whether the faster model may ship is decided by the accuracy gate
of issue 29 (`scone eval pairs` and NN precision on the validation scenes), not here.

`--ring bits-int8|int8` (a ring-context model, `models/scone-ring-e1-real.onnx`): the candidates of
`docs/results/speed/int8/RULE.md`. `bits-int8` rewrites the first layer (512 x 256 on FREAK's bits) as
`MatMulInteger` on the bits as exact 0/1 bytes with int8 weights, one scale per output, the ±1 of the fp32 graph
folded into scale and bias; `int8` also makes the other matrix products static int8 (QDQ, per-channel weights
with `reduce_range`, uint8 activations with MinMax ranges from the training frames of the five real training
scenes at the E1 extraction). Both declare `scone.approximates`, the fp32 graph's id (`sha256:...` of its file):
what they stand for, which the service does not read. They must not declare `scone.embeds_as`, which tells the
service that a graph's embeddings are another file's byte for byte and so takes that file's id (their embeddings
differ from the fp32 graph's). It prints the cosine to the fp32 embeddings on 4 selection frames of each of those scenes.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np

from ..paths import prefix_dir
from .export import INPUT_NAMES


def frames_for(cache: Path, per_scene: int, skip: int) -> list:
    """`per_scene` training frames (`splits.SPLIT`'s train part) of each real training scene's exported
    features, with a step of len(part) // (2 * per_scene) from `skip`, so another `skip` gives other frames."""
    from ..data.splits import exported_frames

    return [f for frames in exported_frames(cache, "train", per_scene, skip, spread=2).values() for f in frames]


def calibration_reader(calibration: list[dict]):
    """onnxruntime's calibration reader over `calibration`, the graph's feeds."""
    from onnxruntime.quantization import CalibrationDataReader

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(calibration)

        def get_next(self):
            return next(self.it, None)

    return Reader()


def cosines(fp32: Path, candidate: Path, check: list[dict]) -> np.ndarray:
    """The cosine of every keypoint's embedding by `candidate` to its fp32 one, over the feeds `check` (one
    intra-op thread)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    a, b = (ort.InferenceSession(str(p), opts, providers=["CPUExecutionProvider"]) for p in (fp32, candidate))
    return np.concatenate([(a.run(None, f)[0] * b.run(None, f)[0]).sum(1) for f in check])


def feeds(frames: list, k: int) -> list[dict]:
    return [dict(zip(INPUT_NAMES, (t.numpy() for t in f.model_inputs(k)))) for f in frames]


#: What an approximate graph stands for (not `scone.embeds_as`, which claims the same bytes).
APPROXIMATES_KEY = "scone.approximates"
RING_CACHE = "cache-levels8max-keypoints2000"


def bits_int8(model):
    """`model` (an fp32 `RingNet` graph, onnx.ModelProto) with its first layer on int8 weights read by
    `MatMulInteger` on the bits as 0/1 bytes; changed in place and returned."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    g = model.graph
    init = {t.name: t for t in g.initializer}
    first = next(n for n in g.node if n.op_type == "Gemm" and n.input[1] == "bits.0.weight")
    if not any(a.name == "transB" and a.i == 1 for a in first.attribute):
        raise ValueError("expected the first layer as Gemm(x, W, b) with transB = 1")
    w = numpy_helper.to_array(init["bits.0.weight"]).astype(np.float64).T  # [512, 256]
    b = numpy_helper.to_array(init["bits.0.bias"]).astype(np.float64)
    scale = np.abs(w).max(0) / 127.0
    q = np.clip(np.round(w / scale), -127, 127).astype(np.int8)
    # W x + b with x = 2 u - 1 (u the 0/1 bits): 2 s (q^T u) + (b - s sum(q)).
    mul = (2.0 * scale).astype(np.float32)
    add = (b - scale * q.astype(np.float64).sum(0)).astype(np.float32)
    table = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.uint8)  # LSB first, as FREAK's
    # What fed the first layer (the ±1 unpacking) and the layer itself go; their replacement takes their place.
    feed = first.input[0]
    producers = {o: n for n in g.node for o in n.output}
    dropped, todo = {id(first)}, [feed]
    while todo:
        n = producers.get(todo.pop())
        if n is not None and "descriptors" not in n.output and id(n) not in dropped:
            dropped.add(id(n))
            todo.extend(i for i in n.input if i in producers)
    new = [
        helper.make_node("Cast", ["descriptors"], ["bits_index"], to=TensorProto.INT32),
        helper.make_node("Gather", ["bits_table", "bits_index"], ["bits_u8"], axis=0),
        helper.make_node("Reshape", ["bits_u8", "bits_shape"], ["bits_flat"]),
        helper.make_node("MatMulInteger", ["bits_flat", "bits_weight_q"], ["bits_acc"]),
        helper.make_node("Cast", ["bits_acc"], ["bits_accf"], to=TensorProto.FLOAT),
        helper.make_node("Mul", ["bits_accf", "bits_scale"], ["bits_scaled"]),
        helper.make_node("Add", ["bits_scaled", "bits_offset"], [first.output[0]]),
    ]
    at = next(i for i, n in enumerate(g.node) if id(n) == id(first))
    kept = [n for i, n in enumerate(g.node) if id(n) not in dropped]
    before = sum(1 for i, n in enumerate(g.node) if i < at and id(n) not in dropped)
    del g.node[:]
    g.node.extend(kept[:before] + new + kept[before:])
    used = {i for n in g.node for i in n.input}
    for t in [t for t in g.initializer if t.name not in used]:
        g.initializer.remove(t)
    g.initializer.extend([
        numpy_helper.from_array(table, "bits_table"),
        numpy_helper.from_array(np.array([-1, 512], np.int64), "bits_shape"),
        numpy_helper.from_array(q, "bits_weight_q"),
        numpy_helper.from_array(mul, "bits_scale"),
        numpy_helper.from_array(add, "bits_offset"),
    ])
    del g.value_info[:]
    onnx.checker.check_model(model)
    return model


def ring_candidate(src: Path, out: Path, which: str, calibration: list[dict]) -> None:
    """`which` ("bits-int8" or "int8") of the fp32 ring graph `src`, written to `out`, declaring `scone.approximates`."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    fp32_id = "sha256:" + hashlib.sha256(src.read_bytes()).hexdigest()
    model = bits_int8(onnx.load(src))
    out.parent.mkdir(parents=True, exist_ok=True)
    if which == "int8":
        stage = out.with_suffix(".bits.onnx")
        onnx.save(model, stage)
        gemms = [n.name for n in model.graph.node if n.op_type == "Gemm"]
        quantize_static(str(stage), str(out), calibration_reader(calibration), quant_format=QuantFormat.QDQ, per_channel=True,
                        reduce_range=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_quantize=gemms, calibrate_method=CalibrationMethod.MinMax)
        stage.unlink()
        model = onnx.load(out)
    meta = {p.key: p.value for p in model.metadata_props if p.key != "onnx.infer"}
    meta[APPROXIMATES_KEY] = fp32_id
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=v)
    onnx.save(model, out)


def ring_main(args) -> None:
    from ..data.splits import exported_frames

    cache = args.cache or prefix_dir() / "data" / RING_CACHE / "real"
    pick = lambda per_scene, which, spread: [  # noqa: E731
        {"descriptors": f.descriptors, "context": f.context}
        for frames in exported_frames(cache, which, per_scene, 0, spread=spread).values() for f in frames]
    ring_candidate(args.model, args.out, args.ring, pick(args.calibration_frames, "train", 2))
    c = cosines(args.model, args.out, pick(4, "select", 1))
    print(f"{args.out}: cosine to the fp32 embeddings on 4 selection frames per scene: min {c.min():.5f}, "
          f"1st percentile {np.percentile(c, 1):.5f}, mean {c.mean():.6f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--calibration-frames", type=int, default=None, help="per scene (default 8; 6 with --ring)")
    ap.add_argument("--cache", type=Path, default=None, help="exported features (default: <prefix>/data/cache/real)")
    ap.add_argument("--ring", choices=["bits-int8", "int8"], default=None, help="a ring model's candidate (see above)")
    args = ap.parse_args()
    if args.ring:
        args.calibration_frames = args.calibration_frames or 6
        return ring_main(args)
    args.calibration_frames = args.calibration_frames or 8
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    cache = args.cache or prefix_dir() / "data" / "cache" / "real"
    calib = feeds(frames_for(cache, args.calibration_frames, 0), args.k)
    check = feeds(frames_for(cache, 4, 1), args.k)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    pre = args.out.with_suffix(".pre.onnx")
    quant_pre_process(str(args.model), str(pre), skip_symbolic_shape=True)
    quantize_static(str(pre), str(args.out), calibration_reader(calib), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, op_types_to_quantize=["MatMul", "Gemm"])
    pre.unlink()
    c = cosines(args.model, args.out, check)
    print(f"{args.out}: {len(check)} check frames, cosine int8 vs fp32 mean {c.mean():.4f}, 1st percentile "
          f"{np.percentile(c, 1):.4f}")


if __name__ == "__main__":
    main()
