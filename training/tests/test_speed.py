"""Issue 29's pieces that need no data: the exported set encoder's arithmetic, the students' options, the gate."""

import torch

from scone_train.evaluation.speed_gate import compare
from scone_train.model import export as X
from scone_train.model.distill import start_from_teacher
from scone_train.model.network import SconeNet


def reference_set_encoder(enc, d, neighbours, geo, m):
    """The set encoder as first written: advanced indexing on [n, k, hidden], -2 for padding in the max."""
    h = enc.desc_part(d)[neighbours] + enc.geo_part(geo)
    h = enc.act(enc.second(enc.act(h)))
    count = m.sum(1)
    pooled_max = (h * m + (m - 1.0) * 2.0).max(1).values
    pooled_mean = (h * m).sum(1) / count.clamp_min(1.0)
    return enc.read(torch.cat([pooled_max * (count > 0).to(h.dtype), pooled_mean], dim=-1))


def test_set_encoder_as_exported_computes_the_reference_for_every_activation():
    torch.manual_seed(0)
    for activation, member in (("selu", None), ("relu", None), ("selu", "relu")):
        model = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 32), bits_skip=8, activation=activation,
                         member_activation=member).eval()
        x = list(X.example_inputs(n=40, k=20, seed=5))
        x[3][:, 12:] = 0.0  # padding
        x[3][:4] = 0.0  # keypoints without neighbours
        with torch.no_grad():
            got = model(*x)
            enc = model.set_encoder
            enc.forward = lambda d, nb, geo, m, enc=enc: reference_set_encoder(enc, d, nb, geo, m)
            want = model(*x)
        assert torch.allclose(got, want, atol=1e-6), (activation, member, float((got - want).abs().max()))
        assert enc.nonnegative == ((member or activation) == "relu")


def test_set_encoder_takes_no_keypoints():
    model = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 32)).eval()
    x = (torch.zeros(0, 64, dtype=torch.uint8), torch.zeros(0, 2), torch.zeros(0, 20, dtype=torch.int64),
         torch.zeros(0, 20), torch.zeros(0, 20, 4))
    with torch.no_grad():
        assert model(*x).shape == (0, 48)


def test_student_starts_from_every_teacher_parameter_of_its_shape():
    torch.manual_seed(0)
    teacher = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 32), bits_skip=8)
    same = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 32), bits_skip=8, activation="relu")
    slim = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 16), bits_skip=8, activation="relu")
    assert start_from_teacher(same, teacher) == len(teacher.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(same.state_dict().values(), teacher.state_dict().values()))
    copied = start_from_teacher(slim, teacher)
    assert 0 < copied < len(teacher.state_dict())
    assert torch.equal(slim.desc_mlp[0].weight, teacher.desc_mlp[0].weight)


def report(auc10, scores):
    pairs = [{"method": "scone", "reference": "a", "frame": str(i), "errors_deg": [10.0 * (1.0 - s)]}
             for i, s in enumerate(scores)]
    return {"summaries": [{"auc10": auc10}], "pairs": pairs}


def test_gate_allows_the_tolerance_and_no_more_on_every_part():
    shipped = {"p": report(0.500, [0.5, 0.5]), "q": report(0.300, [0.3, 0.3])}
    near = {"p": report(0.496, [0.49, 0.502]), "q": report(0.320, [0.3, 0.34])}
    rows, ok = compare(shipped, near, 0.005)
    assert ok and [r["passes"] for r in rows] == [True, True]
    far = {"p": report(0.494, [0.49, 0.498]), "q": report(0.900, [0.9, 0.9])}
    rows, ok = compare(shipped, far, 0.005)
    assert not ok and [r["passes"] for r in rows] == [False, True]
    lo, hi = rows[0]["delta_ci95"]
    assert lo <= -0.002 - 1e-9 and hi <= 0.0  # both pairs lost: the interval lies below zero
