"""Export the SConE network to ONNX (one pass per image, dynamic N) and check it with onnx and onnxruntime."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from ..data.features import REVISION_2_EXTRACTION
from .network import SconeNet, load_checkpoint

INPUT_NAMES = SconeNet.INPUT_NAMES
OUTPUT_NAME = "embeddings"
_DTYPES = {"descriptors": np.uint8, "keypoints": np.float32, "neighbours": np.int64, "mask": np.float32,
           "relative": np.float32, "context": np.uint8, "gradients": np.int8}


def example_inputs(n: int = 64, k: int = 20, seed: int = 0):
    """Random inputs of the constellation network (`SconeNet.example_inputs`)."""
    return SconeNet.example_inputs(n, k, seed)


def export_onnx(model: torch.nn.Module, path: Path, opset: int = 18) -> Path:
    """Either network (`SconeNet`, `RingNet`) as ONNX, its inputs named by its `INPUT_NAMES`."""
    model = model.eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = torch.export.Dim("n", min=1, max=100_000)
    names = model.INPUT_NAMES
    shapes = {name: {0: n} for name in names}
    with torch.no_grad():
        torch.onnx.export(
            model,
            model.example_inputs(k=model.k),
            str(path),
            input_names=names,
            output_names=[OUTPUT_NAME],
            dynamic_shapes=shapes,
            opset_version=opset,
            dynamo=True,
            external_data=False,
        )
    onnx.checker.check_model(onnx.load(str(path)), full_check=True)
    return path


# The metadata keys the service reads (src/describe/embedding.rs, "What a model declares").
EXTRACTION_KEY = "scone.extraction"
MATCHER_KEY = "scone.matcher"


def declaration(cfg: dict, matcher: str) -> dict[str, str]:
    """What a model trained under `cfg` declares: its full extraction (revision 2 with the config's
    `data.extractor` over it) and the MatchPair matcher it ships with."""
    given = cfg["data"].get("extractor") or {}
    extraction = {key: given.get(key, value) for key, value in REVISION_2_EXTRACTION.items()}
    return {EXTRACTION_KEY: json.dumps(extraction, sort_keys=True), MATCHER_KEY: matcher}


def declare(path: Path, props: dict[str, str]) -> None:
    """Writes `props` into the ONNX file's metadata (the graph and its weights are untouched)."""
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for key, value in sorted(props.items()):
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.checker.check_model(model, full_check=True)
    onnx.save(model, str(path))


def session(path: Path, threads: int = 2) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def run_onnx(sess: ort.InferenceSession, *inputs) -> np.ndarray:
    """The graph's output for its inputs, in the order of its input names."""
    names = [i.name for i in sess.get_inputs()]
    feeds = {name: np.ascontiguousarray(x, dtype=_DTYPES[name]) for name, x in zip(names, inputs)}
    return sess.run([OUTPUT_NAME], feeds)[0]


def check_parity(model: torch.nn.Module, path: Path, n: int = 300, tol: float = 1e-4) -> float:
    """Max abs difference between PyTorch and onnxruntime on random inputs of a size unlike the export's."""
    x = model.example_inputs(n=n, k=model.k, seed=1)
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
    """`python -m scone_train.model.export --checkpoint RUN/best.pt --out CANDIDATE.onnx`: a candidate checkpoint as
    ONNX for scoring (`scone eval pairs --model`), with the parity check. The embedded ring model was exported
    with it (`--matcher union`); scone_train.release is the constellation model's recipe. `--matcher` names the MatchPair matcher the model ships with; the model
    declares it and its extraction in its metadata."""
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--matcher", default="scale-aware", choices=["plain", "union", "both", "rerank", "scale-aware", "freak"])
    a = ap.parse_args()
    torch.set_num_threads(1)
    model = load_checkpoint(Path(a.checkpoint))
    export_onnx(model, Path(a.out))
    ckpt = torch.load(a.checkpoint, weights_only=False)
    step = ckpt["step"]
    declare(Path(a.out), declaration(ckpt["config"], a.matcher))
    print(json.dumps({"step": step, "parity": check_parity(model, Path(a.out)), "sha256": sha256(Path(a.out))}))


if __name__ == "__main__":
    main()
