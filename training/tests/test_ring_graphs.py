"""The embedded ring graph read back as a network (the teacher of a run), its bits-input rewrite, and the teacher's
loss."""

import hashlib

import numpy as np
import onnx
import pytest
import torch

from scone_train.model import bits_input as B
from scone_train.model import export as X
from scone_train.model.distill import relational_loss
from scone_train.model.network import RingNet, ring_from_onnx, unpack_bits
from scone_train.paths import REPO

SHIPPED = REPO / "models" / "scone-ring-e1-real.onnx"


def test_the_shipped_graph_read_back_as_a_network_gives_its_embeddings():
    model = ring_from_onnx(SHIPPED)
    descriptors, context = model.example_inputs(n=400, seed=3)
    with torch.no_grad():
        ours = model(descriptors, context).numpy()
    theirs = X.run_onnx(X.session(SHIPPED, threads=1), descriptors.numpy(), context.numpy())
    assert np.abs(ours - theirs).max() < 1e-5


def test_the_bits_input_graph_gives_the_same_bytes_and_declares_its_source(tmp_path):
    out = tmp_path / "bits.onnx"
    result = B.write(SHIPPED, out)
    assert result["same_bytes"]
    assert result[B.EMBEDS_AS_KEY] == "sha256:" + hashlib.sha256(SHIPPED.read_bytes()).hexdigest()
    graph = onnx.load(str(out))
    assert [i.name for i in graph.graph.input] == ["bits", "context"]
    assert not any(n.op_type.startswith("Gather") for n in graph.graph.node)
    props = {p.key: p.value for p in graph.metadata_props}
    shipped = {p.key: p.value for p in onnx.load(str(SHIPPED)).metadata_props}
    assert props == {**shipped, B.EMBEDS_AS_KEY: result[B.EMBEDS_AS_KEY]}
    # the committed bits graph is this one, byte for byte
    assert (REPO / "models" / "scone-ring-e1-real-bits.onnx").read_bytes() == out.read_bytes()


def test_a_graph_without_descriptors_is_not_rewritten(tmp_path):
    out = tmp_path / "bits.onnx"
    B.write(SHIPPED, out)
    with pytest.raises(ValueError, match="not an exported ring graph"):
        B.rewrite(onnx.load(str(out)))


def test_unpacking_is_the_networks():
    descriptors = torch.randint(0, 256, (50, 64), dtype=torch.uint8, generator=torch.Generator().manual_seed(1))
    assert np.array_equal(B.unpack(descriptors.numpy()), unpack_bits(descriptors).numpy())


def test_the_teachers_loss_is_zero_for_the_teacher_and_grows_away_from_it():
    model = RingNet()
    a, b = model.example_inputs(n=120, seed=1), model.example_inputs(n=90, seed=2)
    with torch.no_grad():
        ta, tb = model(*a), model(*b)
    anchors = torch.arange(0, 120, 3)
    assert relational_loss(ta, tb, ta, tb, anchors).item() == 0.0
    other = torch.nn.functional.normalize(
        ta + 0.3 * torch.randn(ta.shape, generator=torch.Generator().manual_seed(0)), dim=1
    )
    assert relational_loss(other, tb, ta, tb, anchors).item() > 1e-3
