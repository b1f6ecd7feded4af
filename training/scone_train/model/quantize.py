"""Static int8 quantisation of an exported SConE model (onnxruntime's QDQ tooling), calibrated on real frames.

`python -m scone_train.model.quantize --model ../models/scone-freak-k20.onnx --out DIR/scone-int8.onnx` (from
`training/`): the matrix products (MatMul / Gemm) get int8 weights (per channel) and uint8 activations,
calibrated on the Rust-exported features of training frames of the five real training scenes (never the
selection or validation frames); every other operator stays fp32. It prints the cosine between the int8 and
the fp32 embeddings on other training frames. Whether the faster model may ship is decided by the accuracy gate
of issue 29 (`scone eval pairs` and NN precision on the validation scenes), not here.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..paths import prefix_dir
from .export import INPUT_NAMES


def frames_for(cache: Path, per_scene: int, skip: int) -> list:
    """`per_scene` training frames (`splits.SPLIT`'s train part) of each real training scene's exported
    features, with a step of len(part) // (2 * per_scene) from `skip`, so another `skip` gives other frames."""
    from ..data.splits import exported_frames

    return [f for frames in exported_frames(cache, "train", per_scene, skip, spread=2).values() for f in frames]


def feeds(frames: list, k: int) -> list[dict]:
    return [dict(zip(INPUT_NAMES, (t.numpy() for t in f.model_inputs(k)))) for f in frames]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--k", type=int, default=20)
    ap.add_argument("--calibration-frames", type=int, default=8, help="per scene")
    ap.add_argument("--cache", type=Path, default=None, help="exported features (default: <prefix>/data/cache/real)")
    args = ap.parse_args()
    import onnxruntime as ort
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    cache = args.cache or prefix_dir() / "data" / "cache" / "real"
    calib = feeds(frames_for(cache, args.calibration_frames, 0), args.k)
    check = feeds(frames_for(cache, 4, 1), args.k)

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(calib)

        def get_next(self):
            return next(self.it, None)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    pre = args.out.with_suffix(".pre.onnx")
    quant_pre_process(str(args.model), str(pre), skip_symbolic_shape=True)
    quantize_static(str(pre), str(args.out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                    activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, op_types_to_quantize=["MatMul", "Gemm"])
    pre.unlink()
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    fp32 = ort.InferenceSession(str(args.model), opts)
    int8 = ort.InferenceSession(str(args.out), opts)
    cos = []
    for f in check:
        a, b = fp32.run(None, f)[0], int8.run(None, f)[0]
        cos.append((a * b).sum(1))
    c = np.concatenate(cos)
    print(f"{args.out}: {len(check)} check frames, cosine int8 vs fp32 mean {c.mean():.4f}, 1st percentile "
          f"{np.percentile(c, 1):.4f}")


if __name__ == "__main__":
    main()
