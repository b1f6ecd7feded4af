"""Export the SConE network to ONNX (one pass per image, dynamic N) and check it with onnx and onnxruntime."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from .model import SconeNet

INPUT_NAMES = ["descriptors", "keypoints", "neighbours", "mask", "relative"]
OUTPUT_NAME = "embeddings"


def example_inputs(n: int = 64, k: int = 20, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randint(0, 256, (n, 64), dtype=torch.uint8, generator=g),
        torch.cat([torch.rand(n, 1, generator=g) * 360, 7 * 1.2 ** torch.randint(0, 6, (n, 1), generator=g)], 1),
        torch.randint(0, n, (n, k), generator=g),
        torch.ones(n, k),
        torch.randn(n, k, 4, generator=g),
    )


def export_onnx(model: SconeNet, path: Path, opset: int = 18) -> Path:
    model = model.eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = torch.export.Dim("n", min=1, max=100_000)
    shapes = {name: {0: n} for name in INPUT_NAMES}
    with torch.no_grad():
        torch.onnx.export(
            model,
            example_inputs(k=model.k),
            str(path),
            input_names=INPUT_NAMES,
            output_names=[OUTPUT_NAME],
            dynamic_shapes=shapes,
            opset_version=opset,
            dynamo=True,
            external_data=False,
        )
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    return path


def session(path: Path, threads: int = 2) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def run_onnx(sess: ort.InferenceSession, descriptors, keypoints, neighbours, mask, relative) -> np.ndarray:
    feeds = {
        "descriptors": np.ascontiguousarray(descriptors, dtype=np.uint8),
        "keypoints": np.ascontiguousarray(keypoints, dtype=np.float32),
        "neighbours": np.ascontiguousarray(neighbours, dtype=np.int64),
        "mask": np.ascontiguousarray(mask, dtype=np.float32),
        "relative": np.ascontiguousarray(relative, dtype=np.float32),
    }
    return sess.run([OUTPUT_NAME], feeds)[0]


def check_parity(model: SconeNet, path: Path, n: int = 300, tol: float = 1e-4) -> float:
    """Max abs difference between PyTorch and onnxruntime on random inputs of a size unlike the export's."""
    x = example_inputs(n=n, k=model.k, seed=1)
    with torch.no_grad():
        ref = model.eval()(*x).numpy()
    got = run_onnx(session(path), *[t.numpy() for t in x])
    diff = float(np.abs(ref - got).max())
    if diff > tol:
        raise AssertionError(f"onnxruntime differs from PyTorch by {diff} > {tol}")
    return diff


def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def main() -> None:
    """`python -m scone_train.export --checkpoint RUN/best.pt --out CANDIDATE.onnx`: a candidate checkpoint as
    ONNX for scoring (`scone eval pairs --model`), with the parity check; the shipped model goes through
    scone_train.release instead."""
    import argparse
    import json

    from .validate import load_checkpoint

    ap = argparse.ArgumentParser()
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    torch.set_num_threads(1)
    model = load_checkpoint(Path(a.checkpoint))
    export_onnx(model, Path(a.out))
    step = torch.load(a.checkpoint, weights_only=False)["step"]
    print(json.dumps({"step": step, "parity": check_parity(model, Path(a.out)), "sha256": sha256(Path(a.out))}))


if __name__ == "__main__":
    main()
