"""End-to-end on tiny data: a rendered sequence -> Rust feature export -> geometric landmarks -> a few training
steps -> ONNX export -> onnxruntime parity. Plus unit checks of the correspondence and metric code."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
import yaml

from scone_train.data import correspondences as C
from scone_train.data.features import FrameFeatures
from scone_train.data.render import render_sequence
from scone_train.data.training_units import PairSampler, build_unit
from scone_train.evaluation import nn_precision as E
from scone_train.model import export as X
from scone_train.model.network import SconeNet, unpack_bits
from scone_train.paths import scone_binary
from scone_train.train import train

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "scone.yaml"
TINY_ROOT: list[Path] = []


@pytest.fixture(scope="module")
def tiny_unit(tmp_path_factory):
    if not scone_binary().exists():
        pytest.fail(f"{scone_binary()} missing: run scripts/setup")
    root = tmp_path_factory.mktemp("render")
    TINY_ROOT[:] = [root]
    render_sequence(root / "seq000", seed=3, frames=4, width=320, height=240)
    return build_unit(root / "seq000", root / "cache")


def test_rust_export_and_depth_landmarks(tiny_unit):
    assert len(tiny_unit.frames) == 4
    f = tiny_unit.frames[0]
    assert f.descriptors.dtype == np.uint8 and f.descriptors.shape[1] == 64
    assert f.neighbours.shape == (len(f), 20) and f.relative.shape == (len(f), 20, 4)
    assert len(f) > 100
    s = C.summary(tiny_unit.ids)
    assert s["landmarks"] > 20, s
    # No track holds two keypoints of one frame.
    for ids in tiny_unit.ids:
        valid = ids[ids >= 0]
        assert len(valid) == len(np.unique(valid))


def test_training_steps_export_and_parity(tiny_unit, tmp_path):
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["train"].update(steps=4, eval_every=2, checkpoint_every=2, pairs_per_step=2, anchors=32, pool=32, threads=1)
    best = train(cfg, tmp_path / "run", units=([tiny_unit], [tiny_unit]))
    assert best.exists() and (tmp_path / "run" / "log.jsonl").exists() and (tmp_path / "run" / "curves.png").exists()
    # Resuming at the end is a no-op that keeps the log.
    train(cfg, tmp_path / "run", units=([tiny_unit], [tiny_unit]))
    model = SconeNet()
    model.load_state_dict(torch.load(best, weights_only=False)["model"])
    path = X.export_onnx(model, tmp_path / "m.onnx")
    onnx.checker.check_model(onnx.load(str(path)))
    assert X.check_parity(model, path, n=137) <= 1e-4
    # Real features through onnxruntime equal PyTorch on the same features.
    f = tiny_unit.frames[1]
    got = X.run_onnx(X.session(path, 1), f.descriptors, f.keypoints[:, [3, 2]], f.neighbours, f.mask, f.relative)
    ref = E.embed_frames(model, [f])[0]
    assert np.abs(got - ref).max() <= 1e-4
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-4)


def test_ring_context_of_the_rust_export_equals_the_reference_and_a_ring_model_exports(tiny_unit, tmp_path):
    """The Rust export's ring contexts are byte for byte `ring_context.sample` on the frames' images; a RingNet
    trains a few steps on them, exports to ONNX, and onnxruntime agrees with PyTorch on real inputs."""
    import cv2

    from scone_train.data import ring_context as CX
    from scone_train.model.network import RingNet

    root = tiny_unit_root(tiny_unit)
    for k, f in enumerate(tiny_unit.frames[:2]):
        grey = cv2.imread(str(root / "rgb" / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert f.context is not None and f.context.shape == (len(f), CX.SAMPLES)
        assert np.array_equal(f.context, CX.sample(grey, f.keypoints[:, :4]))
    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["model"] = {"context": "ring", "k": 0, "embed_dim": 48, "desc_dim": 64, "lstm_hidden": 32}
    cfg["train"].update(steps=3, eval_every=3, checkpoint_every=3, anchors=32, threads=1, loss="triplet_frames",
                        frame_loss="softmax+triplet", group_frames=3, select_on="ratio_f1")
    best = train(cfg, tmp_path / "ring", units=([tiny_unit], [tiny_unit]))
    model = RingNet()
    model.load_state_dict(torch.load(best, weights_only=False)["model"])
    path = X.export_onnx(model, tmp_path / "ring.onnx")
    assert [i.name for i in onnx.load(str(path)).graph.input] == ["descriptors", "context"]
    assert X.check_parity(model, path, n=91) <= 1e-4
    f = tiny_unit.frames[1]
    got = X.run_onnx(X.session(path, 1), f.descriptors, f.context)
    assert np.abs(got - E.embed_frames(model, [f])[0]).max() <= 1e-4


def test_ring_gradients_are_their_definition_and_a_gradient_ring_model_trains_and_exports(tiny_unit, tmp_path):
    """`ring_context.gradients` is its definition from the pixels (box means by plain sums, turned by the angle's
    cosine and sine, halved and rounded half up), and a RingNet reading them trains, exports with a third
    input and keeps parity with onnxruntime."""
    import math

    from scone_train.data import features as D
    from scone_train.data import ring_context as CX
    from scone_train.model.network import RingNet

    h, w = 41, 67
    img = np.random.default_rng(0).integers(0, 256, (h, w)).astype(np.uint8)
    kps = np.array([[(i * 37 % w) + 0.3, (i * 53 % h) - 0.2, 5 + i % 7, i * 7.3] for i in range(40)])
    got = CX.gradients(img, kps)
    assert got.shape == (40, CX.GRADIENTS) and got.dtype == np.int8
    dx, dy, half = CX._TABLE

    def mean(x0, x1, y0, y1):
        x0, x1, y0, y1 = max(x0, 0), min(x1, w - 1), max(y0, 0), min(y1, h - 1)
        return None if x1 < x0 or y1 < y0 else float(img[y0:y1 + 1, x0:x1 + 1].astype(np.int64).mean())

    def diff(a, b):
        return 0.0 if a is None or b is None else a - b

    for k, (x, y, s, angle) in enumerate(kps):
        a = int(CX.angle_bin(angle))
        t = 2.0 * math.pi * a / CX.ANGLE_BINS
        for n in range(CX.SAMPLES):
            cx = min(max(math.floor(x + s * dx[a, n] + 0.5), 0), w - 1)
            cy = min(max(math.floor(y + s * dy[a, n] + 0.5), 0), h - 1)
            g = max(math.floor(half[n] * s + 0.5), 1)
            gx = diff(mean(cx + 1, cx + g, cy - g, cy + g), mean(cx - g, cx - 1, cy - g, cy + g))
            gy = diff(mean(cx - g, cx + g, cy + 1, cy + g), mean(cx - g, cx + g, cy - g, cy - 1))
            want = [max(-127, min(127, math.floor(v * 0.5 + 0.5))) for v in (gx * math.cos(t) + gy * math.sin(t),
                                                                                gy * math.cos(t) - gx * math.sin(t))]
            assert [got[k, n], got[k, CX.SAMPLES + n]] == want, (k, n)

    root = tiny_unit_root(tiny_unit)
    for k, f in enumerate(tiny_unit.frames):
        f.gradients = CX.gradients(D.grey_image(root / "rgb" / f"{k:06d}.png"), f.keypoints)
    try:
        cfg = yaml.safe_load(CONFIG.read_text())
        cfg["model"] = {"context": "ring", "ring_gradients": True, "k": 0, "embed_dim": 48, "desc_dim": 64,
                        "lstm_hidden": 32}
        cfg["train"].update(steps=3, eval_every=3, checkpoint_every=3, anchors=32, threads=1, loss="triplet_frames",
                            frame_loss="softmax+triplet", group_frames=3, select_on="ratio_f1")
        best = train(cfg, tmp_path / "grad", units=([tiny_unit], [tiny_unit]))
    finally:
        for f in tiny_unit.frames:
            f.gradients = None
    model = RingNet(gradients=True)
    model.load_state_dict(torch.load(best, weights_only=False)["model"])
    path = X.export_onnx(model, tmp_path / "grad.onnx")
    assert [i.name for i in onnx.load(str(path)).graph.input] == ["descriptors", "context", "gradients"]
    assert X.check_parity(model, path, n=91) <= 1e-4


def test_ring_invariants_ignore_a_turn_and_an_averaged_ring_model_resumes_and_exports(tiny_unit, tmp_path):
    """`RingInvariants` do not change when every ring turns by whole steps (what an error of the angle does),
    and a RingNet with them trains with averaged weights (`train.ema`), resumes with the average, saves the
    average as its checkpoint and exports with parity."""
    from scone_train.model.network import RingInvariants, build_model

    inv = RingInvariants()
    c = torch.randn(6, 113)
    turned = torch.cat([c[:, :1], c[:, 1:].reshape(6, 7, 16).roll(5, dims=2).reshape(6, 112)], dim=1)
    assert inv(c).shape == (6, RingInvariants.size)
    assert torch.allclose(inv(c), inv(turned), atol=1e-5)
    scrambled = torch.cat([c[:, :1], c[:, 1:].reshape(6, 7, 16)[:, :, torch.randperm(16)].reshape(6, 112)], dim=1)
    assert not torch.allclose(inv(c), inv(scrambled), atol=1e-3)

    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["model"] = {"context": "ring", "ring_invariants": True, "k": 0, "embed_dim": 48, "desc_dim": 64, "lstm_hidden": 32}
    cfg["train"].update(steps=4, eval_every=4, checkpoint_every=2, anchors=32, threads=1, loss="triplet_frames",
                        frame_loss="softmax+triplet", group_frames=3, select_on="ratio_f1", ema=0.5)
    run = tmp_path / "ema"
    train(cfg, run, steps=2, units=([tiny_unit], [tiny_unit]))
    assert "ema" in torch.load(run / "last.pt", weights_only=False)
    best = train(cfg, run, units=([tiny_unit], [tiny_unit]))
    last = torch.load(run / "last.pt", weights_only=False)
    saved = torch.load(best, weights_only=False)
    assert saved["step"] == 4  # the one evaluation
    # the average was restored on resume and updated at every step, and the checkpoint holds it, not the raw weights
    assert int(last["ema"]["n_averaged"]) == 4
    assert all(torch.equal(last["ema"][f"module.{k}"], v) for k, v in saved["model"].items())
    assert any(not torch.equal(last["model"][k], v) for k, v in saved["model"].items())
    model = build_model(cfg["model"])
    model.load_state_dict(saved["model"])
    path = X.export_onnx(model, tmp_path / "inv.onnx")
    assert X.check_parity(model, path, n=77) <= 1e-4


def test_stop_after_ends_a_run_early_on_its_own_schedule(tiny_unit, tmp_path):
    """`train.stop_after` ends the loop there, evaluates and checkpoints there, and leaves the learning rate on
    the cosine decay of the whole `steps`, not of a schedule as short as the run."""
    import math

    cfg = yaml.safe_load(CONFIG.read_text())
    cfg["model"] = {"context": "ring", "k": 0, "embed_dim": 48, "desc_dim": 64, "lstm_hidden": 32}
    cfg["train"].update(steps=10, stop_after=3, eval_every=100, checkpoint_every=100, anchors=32, threads=1,
                        loss="triplet_frames", frame_loss="softmax+triplet", group_frames=3, select_on="ratio_f1")
    run = tmp_path / "stopped"
    best = train(cfg, run, units=([tiny_unit], [tiny_unit]))
    last = torch.load(run / "last.pt", weights_only=False)
    assert last["step"] == 3 and torch.load(best, weights_only=False)["step"] == 3
    t = cfg["train"]
    lr = t["lr_final"] + 0.5 * (t["lr"] - t["lr_final"]) * (1 + math.cos(math.pi * 3 / 10))
    assert [row["step"] for row in last["log"]] == [3]
    assert math.isclose(last["log"][0]["lr"], lr, rel_tol=1e-6)
    for bad in (0, 11):
        cfg["train"]["stop_after"] = bad
        with pytest.raises(ValueError, match="stop_after"):
            train(cfg, tmp_path / f"bad-{bad}", units=([tiny_unit], [tiny_unit]))


def tiny_unit_root(unit) -> Path:
    """The rendered sequence a unit was built from (the fixture renders `seq000`)."""
    return Path(TINY_ROOT[0]) / "seq000"


def test_unpack_bits_order_matches_numpy():
    d = np.random.default_rng(0).integers(0, 256, (5, 64), dtype=np.uint8)
    ours = unpack_bits(torch.from_numpy(d)).numpy()
    ref = np.unpackbits(d, axis=1, bitorder="little").astype(np.float32) * 2 - 1
    assert np.array_equal(ours, ref)


def test_ties_count_against_unless_all_correct():
    # Query 0 of frame 0 (landmark 7) ties between a correct and a wrong keypoint of frame 1.
    v0 = np.array([[1.0, 0.0]], np.float32)
    v1 = np.array([[1.0, 0.0], [1.0, 0.0], [-1.0, 0.0]], np.float32)
    ids = [np.array([7]), np.array([7, 8, -1])]
    assert not E.nn_correct([v0, v1], ids, "l2")[0]
    ids_ok = [np.array([7]), np.array([7, 7, -1])]  # not a valid track, but checks the tie rule
    assert E.nn_correct([v0, v1], ids_ok, "l2")[0]


def _frame(kps: np.ndarray) -> FrameFeatures:
    n = len(kps)
    return FrameFeatures(kps.astype(np.float32), np.zeros((n, 64), np.uint8), np.zeros((n, 20), np.int32),
                         np.zeros((n, 20), np.uint8), np.zeros((n, 20, 4), np.float32))


def test_epipolar_landmarks_from_geometry_only():
    """Three cameras see random 3D points; keypoints are their exact projections plus clutter; geometry alone
    recovers tracks, and every track's keypoints are projections of one point."""
    from scone_train.data.scenes import Scene

    rng = np.random.default_rng(1)
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X3 = np.c_[rng.uniform(-2, 2, 60), rng.uniform(-1.5, 1.5, 60), rng.uniform(5, 9, 60)]
    poses = []
    for tx in (0.0, 0.6, 1.2):
        T = np.eye(4)
        T[0, 3] = tx
        poses.append(T)
    frames, truth = [], []
    for T in poses:
        Xc = X3 - T[:3, 3]
        uv = Xc[:, :2] / Xc[:, 2:] * 500 + [320, 240]
        clutter = np.c_[rng.uniform(0, 640, 40), rng.uniform(0, 480, 40)]
        pts = np.r_[uv, clutter]
        kps = np.c_[pts, np.full(len(pts), 7.0), np.zeros(len(pts)), np.ones(len(pts)), np.zeros(len(pts))]
        frames.append(_frame(kps))
        truth.append(np.r_[np.arange(60), np.full(40, -1)])
    scene = Scene(Path("."), "synthetic", K, 640, 480, ["0", "1", "2"], [Path("a")] * 3, poses, [None] * 3)
    ids = C.landmarks(scene, frames, C.GeometryParams(scale_tol=2.0))
    linked = 0
    for lm in np.unique(np.concatenate(ids)):
        if lm < 0:
            continue
        members = [truth[f][ids[f] == lm] for f in range(3)]
        points = np.concatenate(members)
        assert len(set(points.tolist())) == 1 and points[0] >= 0, "a track mixes different 3D points or clutter"
        linked += 1
    assert linked >= 20
    # `stats` accounts for every linked keypoint: kept, or dropped with a track that holds two keypoints of one
    # frame (also with a second keypoint of frame 0 on point 0's projection).
    doubled = [_frame(np.r_[frames[0].keypoints, frames[0].keypoints[:1]]), frames[1], frames[2]]
    for fs in (frames, doubled):
        stats = {}
        ids = C.landmarks(scene, fs, C.GeometryParams(scale_tol=2.0), stats)
        assert stats["kept"] == sum(int((i >= 0).sum()) for i in ids) >= 40
        assert stats["linked"] == stats["kept"] + stats["conflicted"]
        # Refusing conflicting links instead drops no track, and keeps at least what dropping kept.
        refused = {}
        kept = C.landmarks(scene, fs, C.GeometryParams(scale_tol=2.0, tracks="refuse"), refused)
        assert refused["conflicted"] == 0 and refused["kept"] >= stats["kept"]
        for lm in np.unique(np.concatenate(kept)):
            if lm >= 0:
                assert all(int((k == lm).sum()) <= 1 for k in kept)
    with pytest.raises(ValueError, match="tracks"):
        C.landmarks(scene, frames, C.GeometryParams(tracks="merge"))


def test_tracks_refuse_a_link_that_would_hold_two_keypoints_of_one_frame():
    """Keypoints 0, 1 in frame 0, 2 in frame 1, 3 in frame 2: 0-2 and 2-3 join; 1-3 would put 0 and 1 (both of
    frame 0) in one track, so it is refused, and without refusal it joins."""
    frame_of = np.array([0, 0, 1, 2])
    for refuse, together, refused in ((True, False, 1), (False, True, 0)):
        t = C.Tracks(frame_of, refuse)
        for a, b in ((0, 2), (2, 3), (1, 3)):
            t.join(a, b)
        assert t.uf.find(0) == t.uf.find(3)
        assert (t.uf.find(1) == t.uf.find(0)) == together and t.refused == refused


def test_pair_sampler_gives_consistent_positives(tiny_unit):
    s = PairSampler([tiny_unit], anchors=16, pool=16, seed=0, min_shared=4)
    b = s.sample()
    ida = next(u for u in [tiny_unit]).ids
    fa = [i for i, f in enumerate(tiny_unit.frames) if f is b.fa][0]
    fb = [i for i, f in enumerate(tiny_unit.frames) if f is b.fb][0]
    assert np.array_equal(ida[fa][b.anchors], ida[fb][b.positives])
    assert np.array_equal(ida[fb][b.pool], b.pool_ids)


SET_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "scone-set.yaml"


def test_set_encoder_training_steps_export_and_parity(tiny_unit, tmp_path):
    """The committed configuration (set encoder, bits skip, whole-frame loss over frame groups) trains, resumes,
    exports with the same five-input contract and matches onnxruntime on real features."""
    from scone_train.model.network import build_model

    cfg = yaml.safe_load(SET_CONFIG.read_text())
    cfg["train"].update(steps=4, eval_every=2, checkpoint_every=2, anchors=32, threads=1, group_frames=3)
    best = train(cfg, tmp_path / "run", units=([tiny_unit], [tiny_unit]))
    rows = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert rows[-1]["step"] == 4 and np.isfinite(rows[-1]["loss"]) and rows[-1]["loss"] > 0
    assert 0.0 <= rows[-1]["selection_ratio"]["precision"] <= 1.0
    model = build_model(cfg["model"])
    model.load_state_dict(torch.load(best, weights_only=False)["model"])
    path = X.export_onnx(model, tmp_path / "set.onnx")
    assert [i.name for i in onnx.load(str(path)).graph.input] == X.INPUT_NAMES
    assert X.check_parity(model, path, n=211) <= 1e-4
    f = tiny_unit.frames[2]
    got = X.run_onnx(X.session(path, 1), f.descriptors, f.keypoints[:, [3, 2]], f.neighbours, f.mask, f.relative)
    assert np.abs(got - E.embed_frames(model, [f])[0]).max() <= 1e-4


def test_set_encoder_ignores_padding_and_member_order():
    """Padding slots change nothing, and neither does the order of the members (the LSTM's weak point)."""
    torch.manual_seed(0)
    model = SconeNet(encoder="set", desc_dim=16, desc_hidden=(32, 32), bits_skip=8).eval()
    x = list(X.example_inputs(n=30, k=20, seed=3))
    x[3][:, 15:] = 0.0  # last five slots are padding
    with torch.no_grad():
        ref = model(*x)
        y = [t.clone() for t in x]
        y[2][:, 15:] = torch.arange(30)[:, None]  # padding points anywhere: still ignored
        y[4][:, 15:] = 123.0
        assert torch.allclose(model(*y), ref, atol=1e-6)
        perm = torch.randperm(15)
        z = [t.clone() for t in x]
        z[2][:, :15], z[3][:, :15], z[4][:, :15] = x[2][:, perm], x[3][:, perm], x[4][:, perm]
        assert torch.allclose(model(*z), ref, atol=1e-5)
        x[3][:3] = 0.0  # keypoints without any neighbour still get a finite, unit embedding
        e = model(*x)
        assert torch.isfinite(e).all() and torch.allclose(e.norm(dim=1), torch.ones(30), atol=1e-5)


def test_group_sampler_pairs_share_landmarks(tiny_unit):
    from scone_train.data.training_units import GroupSampler

    s = GroupSampler([tiny_unit], size=3, seed=0, min_shared=4)
    for _ in range(5):
        g = s.sample()
        assert 2 <= len(g.frames) <= 3 and len(set(g.frames)) == len(g.frames) and g.pairs
        for i, j in g.pairs:
            a, b = tiny_unit.ids[g.frames[i]], tiny_unit.ids[g.frames[j]]
            assert len(np.intersect1d(a[a >= 0], b)) >= 4


def test_frame_loss_prefers_the_true_positive():
    """The whole-frame loss is lower when each anchor's embedding equals its positive's than when the
    positives are shuffled, for every loss kind (so a broken positive index would show)."""
    from scone_train.train import frame_triplet_loss

    rng = np.random.default_rng(0)
    n = 40
    emb = torch.nn.functional.normalize(torch.randn(n, 48), dim=1)
    kps = np.c_[rng.uniform(0, 300, (n, 2)), np.full((n, 4), 1.0)].astype(np.float32)
    fa = fb = _frame(kps)
    ids = np.arange(n)
    ia = np.arange(0, 20)
    for kind in ("softmax", "triplet", "softmax+triplet"):
        good, _, _ = frame_triplet_loss(emb, emb, fa, fb, ia, ia, ids[ia], ids, ids, 0.5, 0.0, kind)
        shuffled = np.roll(ia, 1)
        bad, _, _ = frame_triplet_loss(emb, emb, fa, fb, ia, shuffled, ids[ia], ids, ids, 0.5, 0.0, kind)
        assert good.item() < bad.item(), kind


def test_pair_weights_shared_or_uniform(tiny_unit):
    # anchors (the cap on a pair's weight) above every pair's shared count: weights follow the shared landmarks
    shared = PairSampler([tiny_unit], anchors=10**6, pool=0, seed=0, min_shared=4)
    uniform = PairSampler([tiny_unit], anchors=10**6, pool=0, seed=0, min_shared=4, weight="uniform")
    assert len(shared.pairs) == len(uniform.pairs) > 1
    assert np.allclose(uniform.weights, 1.0 / len(uniform.pairs))
    counts = np.array([len(np.intersect1d(u.ids[a][u.ids[a] >= 0], u.ids[b])) for u, a, b in shared.pairs], float)
    assert np.allclose(shared.weights, counts / counts.sum()) and counts.std() > 0
    with pytest.raises(ValueError):
        PairSampler([tiny_unit], anchors=128, pool=0, seed=0, weight="angle")


def test_constellation_augmentation_distorts_offsets_and_drops_only_real_members():
    from scone_train.train import augment_constellations

    rng = np.random.default_rng(0)
    n, k = 50, 20
    rel = torch.from_numpy(rng.normal(size=(n, k, 4)).astype(np.float32))
    mask = torch.ones(n, k)
    mask[:, 15:] = 0
    rel[:, 15:] = 0
    x = (torch.zeros(n, 64, dtype=torch.uint8), torch.zeros(n, 2), torch.zeros(n, k, dtype=torch.int64), mask, rel)
    same = augment_constellations(x, 0.0, 0.0, np.random.default_rng(1))
    assert torch.equal(same[4], rel) and torch.equal(same[3], mask)
    out = augment_constellations(x, 0.4, 0.2, np.random.default_rng(1))
    assert torch.equal(x[4], rel) and torch.equal(x[3], mask), "inputs must not change (they are cached)"
    ratio = out[4][:, :15, :2].norm(dim=-1) / rel[:, :15, :2].norm(dim=-1)
    assert ratio.min() >= np.exp(-0.4) - 1e-5 and ratio.max() <= np.exp(0.4) + 1e-5 and ratio.std() > 0.05
    assert torch.equal(out[4][..., 2:], rel[..., 2:]) and torch.equal(out[4][:, 15:], rel[:, 15:])
    assert torch.all(out[3][:, 15:] == 0) and 0.7 < out[3][:, :15].mean() < 0.9


def test_group_sampler_real_share(tiny_unit):
    from dataclasses import replace

    from scone_train.data.training_units import GroupSampler

    real = replace(tiny_unit, name="real", real=True)
    s = GroupSampler([tiny_unit, real], size=3, seed=0, min_shared=4, real_share=0.25)
    share = np.mean([s.sample().unit.real for _ in range(2000)])
    assert 0.2 < share < 0.3
    with pytest.raises(ValueError):
        GroupSampler([tiny_unit], size=3, seed=0, min_shared=4, real_share=0.25)
