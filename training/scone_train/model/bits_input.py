"""A ring model's graph that reads FREAK's bits already unpacked: the same embeddings, byte for byte, without the
unpacking inside ONNX Runtime.

    python -m scone_train.model.bits_input --model ../models/scone-ring-e1-real.onnx \\
        --out ../models/scone-ring-e1-real-bits.onnx        (from training/)

The exported ring graph turns `descriptors` (uint8 [N, 64]) into ±1 floats with a GatherND of a 256 x 8 table
(`network.unpack_bits`): about 1.1 ms of its 12 ms for 2,000 keypoints on one thread, the largest part of the
graph that does not shrink with its widths. The graph written here takes `bits` (float32 [N, 512], bit i of byte
i // 8 at position i % 8, least significant first, as -1 or +1) in place of `descriptors`, which the service
fills from the FREAK bytes (`src/describe/embedding.rs`); every other node, weight and input is the source's.
Its first matrix product reads the very floats the source's unpacking made, so its output is the same bytes:
checked here on random keypoints, and in the Rust suite on the golden fixture.

The new file declares the embedding space it computes (`scone.embeds_as`: the source's id, `sha256:` and the
source file's sha256, or the source's own declaration), so the service reports that id and maps built with the
source are served by it. The source's other metadata (extraction, matcher) is copied.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from .export import OUTPUT_NAME, declare, session, sha256
from .network import _BIT_TABLE

#: The metadata key of the embedding space a graph computes when it is not its own file's (the service's model id).
EMBEDS_AS_KEY = "scone.embeds_as"
BITS = "bits"
FIRST_WEIGHT = "bits.0.weight"


def rewrite(model: onnx.ModelProto) -> onnx.ModelProto:
    """`model` with the input `bits` in place of `descriptors` and the nodes that unpacked it removed."""
    g = model.graph
    first = [n for n in g.node if n.op_type == "Gemm" and len(n.input) > 1 and n.input[1] == FIRST_WEIGHT]
    if len(first) != 1 or "descriptors" not in {i.name for i in g.input}:
        raise ValueError("not an exported ring graph: expected an input 'descriptors' and one Gemm on bits.0.weight")
    unpacked = first[0].input[0]
    producers = {o: n for n in g.node for o in n.output}
    drop, stack = set(), [unpacked]
    while stack:
        n = producers.get(stack.pop())
        if n is not None and id(n) not in drop:
            drop.add(id(n))
            stack.extend(n.input)
    keep = [n for n in g.node if id(n) not in drop]
    for n in keep:
        # `descriptors` also gave the graph its N (a Shape); `bits` has the same first dimension.
        n.input[:] = [BITS if name in (unpacked, "descriptors") else name for name in n.input]
    used = {name for n in keep for name in n.input}
    if "context" not in used:
        raise ValueError("the graph's unpacking reached its context input: not an exported ring graph")
    del g.node[:]
    g.node.extend(keep)
    inputs = [i for i in g.input if i.name != "descriptors"]
    del g.input[:]
    g.input.extend([helper.make_tensor_value_info(BITS, TensorProto.FLOAT, ["n", 512]), *inputs])
    initializers = [i for i in g.initializer if i.name in used]
    del g.initializer[:]
    g.initializer.extend(initializers)
    onnx.checker.check_model(model, full_check=True)
    return model


#: Row v holds the 8 bits of byte value v as ±1, least significant first: the network's own table.
_TABLE = _BIT_TABLE.numpy()


def unpack(descriptors: np.ndarray) -> np.ndarray:
    """uint8 [N, 64] -> float32 [N, 512] of ±1, the input `bits`."""
    return _TABLE[descriptors].reshape(len(descriptors), 512)


def write(source: Path, out: Path) -> dict:
    """Writes the bits-input graph of `source` to `out` and checks it gives the same bytes on 3,000 random
    keypoints; returns what it declares and the check."""
    model = onnx.load(str(source))
    props = {p.key: p.value for p in model.metadata_props}
    props.setdefault(EMBEDS_AS_KEY, f"sha256:{sha256(source)}")
    onnx.save(rewrite(model), str(out))
    declare(out, props)
    rng = np.random.default_rng(0)
    descriptors = rng.integers(0, 256, (3000, 64), dtype=np.uint8)
    context = rng.integers(0, 256, (3000, 113), dtype=np.uint8)
    ref = session(source, threads=1).run([OUTPUT_NAME], {"descriptors": descriptors, "context": context})[0]
    got = session(out, threads=1).run([OUTPUT_NAME], {BITS: unpack(descriptors), "context": context})[0]
    if not np.array_equal(ref, got):
        raise AssertionError(f"the bits-input graph differs from its source by {float(np.abs(ref - got).max())}")
    return {"out": str(out), "sha256": sha256(out), EMBEDS_AS_KEY: props[EMBEDS_AS_KEY], "same_bytes": True}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, required=True, help="an exported ring graph (input descriptors)")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    print(json.dumps(write(a.model, a.out)))


if __name__ == "__main__":
    main()
