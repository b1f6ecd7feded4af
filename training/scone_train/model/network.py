"""The SConE network, written as the one-pass graph that is exported.

Two readings of the constellation: the paper's Table 1 (a 2-layer BiLSTM over the nearest-first members,
`encoder="lstm"`) and a permutation-invariant set encoder (`encoder="set"`, the committed model; see
`SetEncoder` and the experiments in BENCHMARKS.md). Both take the same inputs and give the same output.

Inputs are those of a whole image, as the Rust service builds them (`src/describe/constellation.rs`):

| name | dtype | shape | meaning |
|---|---|---|---|
| descriptors | uint8 | [N, 64] | FREAK bits, bit i in byte i // 8 at position i % 8 (LSB first) |
| keypoints | float32 | [N, 2] | central orientation (degrees) and size (pixels) |
| neighbours | int64 | [N, k] | constellation member indices, nearest first (padding = own index) |
| mask | float32 | [N, k] | 1 real neighbour, 0 padding |
| relative | float32 | [N, k, 4] | u, v (in central sizes), dθ (rad), ln size ratio |

Output `embeddings` float32 [N, 48], L2-normalised.

Every normalisation happens in here, so the Rust side passes raw values and cannot drift from training:
bits become ±1 (one table lookup per byte); angles become (sin, cos); u, v are divided by `UV_SCALE`; sizes become pyramid levels
(log base 1.2 of size / 7). The descriptor MLP runs once per keypoint and neighbours are gathered by index
(not embedded 21 times per keypoint). SELU (ReLU in the students of issue 29) follows every hidden fully
connected layer; the last layer of each block is linear (the head's output is L2-normalised, the neighbourhood block feeds the head).

`RingNet` is the ring-context network (the service's embedded model). `build_model` makes either network from a
config's `model` section, `load_checkpoint` from a training checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

UV_SCALE = 8.0
LEVEL_LOG = math.log(1.2)
FAST_SIZE = 7.0


ACTIVATIONS = {"selu": nn.SELU, "relu": nn.ReLU}


def mlp(sizes: list[int], last_activation: bool, activation: str = "selu") -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        lin = nn.Linear(a, b)
        # LeCun normal initialisation, as SELU's self-normalising property assumes.
        nn.init.normal_(lin.weight, std=1.0 / math.sqrt(a))
        nn.init.zeros_(lin.bias)
        layers.append(lin)
        if i < len(sizes) - 2 or last_activation:
            layers.append(ACTIVATIONS[activation]())
    return nn.Sequential(*layers)


# Row v holds the 8 bits of the byte value v as ±1, least significant first.
_BIT_TABLE = (torch.remainder(torch.div(torch.arange(256)[:, None], 2 ** torch.arange(8), rounding_mode="floor"), 2) * 2 - 1).to(torch.float32)


def unpack_bits(descriptors: torch.Tensor) -> torch.Tensor:
    """uint8 [N, 64] -> float [N, 512] of ±1, bit order LSB first.

    One table lookup per byte (a Gather in ONNX): exact, and about 10x cheaper in ONNX Runtime than the
    integer div/mod chain it replaces, which took a quarter of the whole graph's time at 1,000 keypoints.
    """
    table = _BIT_TABLE.to(descriptors.device)
    return table[descriptors.to(torch.int64)].reshape(descriptors.shape[0], 512)


class SetEncoder(nn.Module):
    """Permutation-invariant reading of a constellation (the alternative to the paper's BiLSTM).

    Each member j becomes phi([d_j, geometry_j]) (two layers, SELU); the members are pooled by a masked max
    and a masked mean and read by FC 2h -> 64 -> 32. The first layer is split: its descriptor part
    W_d d_j is computed once per keypoint and gathered by index (as the descriptor MLP itself), so only the
    5-d geometry part and the second layer run per member. Unlike the nearest-first sequence, the result does
    not change when two members swap places in the distance order, and a member that the detector missed in
    the other view removes one element of a set instead of shifting every later step of a sequence.
    """

    def __init__(self, desc_dim: int, geo_dim: int, hidden: int, activation: str = "selu", member_activation: str | None = None):
        super().__init__()
        member_activation = member_activation or activation
        self.desc_part = nn.Linear(desc_dim, hidden)
        self.geo_part = nn.Linear(geo_dim, hidden, bias=False)
        self.second = nn.Linear(hidden, hidden)
        for lin, fan_in in ((self.desc_part, desc_dim + geo_dim), (self.geo_part, desc_dim + geo_dim), (self.second, hidden)):
            nn.init.normal_(lin.weight, std=1.0 / math.sqrt(fan_in))
        nn.init.zeros_(self.desc_part.bias)
        nn.init.zeros_(self.second.bias)
        # The per-member layers' activation may differ from the rest of the network's (`member_activation`):
        # they run on [N, k, hidden], the largest activations of the graph.
        self.act = ACTIVATIONS[member_activation]()
        self.nonnegative = member_activation == "relu"
        self.read = mlp([2 * hidden, 64, 32], last_activation=True, activation=activation)

    def forward(self, d: torch.Tensor, neighbours: torch.Tensor, geo: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        n, k = neighbours.shape
        hidden = self.second.out_features
        # Written for the exported graph, with the same arithmetic as `desc_part(d)[neighbours] + geo_part(geo)`
        # on [n, k, hidden]: rows gathered by index_select export as one Gather (advanced indexing exports as
        # GatherND, slower), and the per-member layers run on a 2-D [n * k, hidden] matrix, which onnxruntime
        # fuses with its bias and activation into one Gemm.
        h = self.desc_part(d).index_select(0, neighbours.reshape(-1)) + self.geo_part(geo.reshape(n * k, geo.shape[-1]))
        h = self.act(self.second(self.act(h))).reshape(n, k, hidden)
        count = m.sum(1)
        if self.nonnegative:
            # ReLU's outputs are >= 0, so zeroed padding never wins the max against a real member.
            pooled_max = (h * m).max(1).values
        else:
            # SELU is bounded below by -1.7581, so -2 never wins the max against a real member.
            pooled_max = (h * m + (m - 1.0) * 2.0).max(1).values
        pooled_mean = (h * m).sum(1) / count.clamp_min(1.0)
        any_real = (count > 0).to(h.dtype)
        return self.read(torch.cat([pooled_max * any_real, pooled_mean], dim=-1))


class SconeNet(nn.Module):
    """The constellation network (the paper's context: detected neighbours)."""

    INPUT_NAMES = ["descriptors", "keypoints", "neighbours", "mask", "relative"]

    def __init__(
        self,
        k: int = 20,
        embed_dim: int = 48,
        desc_dim: int = 32,
        lstm_hidden: int = 32,
        use_neighbours: bool = True,
        encoder: str = "lstm",
        desc_hidden: tuple[int, int] = (512, 256),
        set_hidden: int = 64,
        head_hidden: int = 64,
        bits_skip: int = 0,
        central_orientation: bool = True,
        activation: str = "selu",
        member_activation: str | None = None,
    ):
        super().__init__()
        for a in (activation, member_activation or activation):
            if a not in ACTIVATIONS:
                raise ValueError(f"unknown activation {a!r} ({' or '.join(ACTIVATIONS)})")
        self.k = k
        self.use_neighbours = use_neighbours
        self.encoder = encoder
        self.desc_mlp = mlp([512, *desc_hidden, desc_dim], last_activation=True, activation=activation)
        geo_dim = 5  # u, v, sin dθ, cos dθ, Δlevel
        if encoder == "lstm":
            self.lstm = nn.LSTM(desc_dim + geo_dim, lstm_hidden, num_layers=2, bidirectional=True, batch_first=True)
            self.neigh_mlp = mlp([2 * lstm_hidden, 64, 64, 32], last_activation=True, activation=activation)
        elif encoder == "set":
            self.set_encoder = SetEncoder(desc_dim, geo_dim, set_hidden, activation, member_activation)
        else:
            raise ValueError(f"unknown neighbourhood encoder {encoder!r} (lstm or set)")
        # Optional linear path from the central keypoint's bits to the head (bits_skip dimensions), beside the
        # SELU MLP: a linear projection of the ±1 bits keeps their Hamming geometry more faithfully.
        self.bits_skip = bits_skip
        if bits_skip:
            self.skip = nn.Linear(512, bits_skip, bias=False)
            nn.init.normal_(self.skip.weight, std=1.0 / math.sqrt(512))
        # The paper gives the head the central keypoint's orientation (sin, cos) and scale; without the
        # orientation the embedding cannot change with in-plane rotation of the whole image.
        self.central_orientation = central_orientation
        self.head = mlp([32 + desc_dim + bits_skip + (3 if central_orientation else 1), head_hidden, head_hidden, embed_dim], last_activation=False, activation=activation)

    def frame_inputs(self, f) -> tuple:
        """The network's inputs for one exported frame (`data.FrameFeatures`)."""
        return f.model_inputs(self.k)

    @staticmethod
    def example_inputs(n: int = 64, k: int = 20, seed: int = 0) -> tuple:
        """Random inputs of `n` keypoints, for export and parity checks."""
        g = torch.Generator().manual_seed(seed)
        return (
            torch.randint(0, 256, (n, 64), dtype=torch.uint8, generator=g),
            torch.cat([torch.rand(n, 1, generator=g) * 360, 7 * 1.2 ** torch.randint(0, 6, (n, 1), generator=g)], 1),
            torch.randint(0, n, (n, k), generator=g),
            torch.ones(n, k),
            torch.randn(n, k, 4, generator=g),
        )

    def embed_descriptors(self, descriptors: torch.Tensor) -> torch.Tensor:
        """Per keypoint: the descriptor MLP's output, followed by the linear skip path when there is one."""
        bits = unpack_bits(descriptors)
        d = self.desc_mlp(bits)
        return torch.cat([d, self.skip(bits)], dim=1) if self.bits_skip else d

    def forward(
        self,
        descriptors: torch.Tensor,
        keypoints: torch.Tensor,
        neighbours: torch.Tensor,
        mask: torch.Tensor,
        relative: torch.Tensor,
    ) -> torch.Tensor:
        d = self.embed_descriptors(descriptors)
        return self.embed_from(d, keypoints, neighbours, mask, relative)

    def embed_from(self, d, keypoints, neighbours, mask, relative, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Embeddings of keypoints `rows` (all when None), given every keypoint's descriptor embedding `d`."""
        full = d
        if self.bits_skip:
            d = full[:, : full.shape[1] - self.bits_skip]
        if rows is not None:
            keypoints, neighbours, mask, relative = keypoints[rows], neighbours[rows], mask[rows], relative[rows]
            central = full[rows]
        else:
            central = full
        angle = keypoints[:, 0:1] * (math.pi / 180.0)
        level = torch.log(keypoints[:, 1:2] / FAST_SIZE) / LEVEL_LOG
        if self.central_orientation:
            central_geo = torch.cat([torch.sin(angle), torch.cos(angle), level / 5.0], dim=1)
        else:
            central_geo = level / 5.0
        m = mask.unsqueeze(-1)
        if self.use_neighbours:
            rel = relative
            geo = torch.cat(
                [rel[..., 0:2] / UV_SCALE, torch.sin(rel[..., 2:3]), torch.cos(rel[..., 2:3]), rel[..., 3:4] / LEVEL_LOG / 5.0],
                dim=-1,
            )
            if self.encoder == "set":
                neigh = self.set_encoder(d, neighbours, geo, m)
            else:
                nd = d[neighbours]  # gather: [n, k, desc_dim]
                seq = torch.cat([nd, geo], dim=-1) * m
                _, (h, _) = self.lstm(seq)
                neigh = self.neigh_mlp(torch.cat([h[-2], h[-1]], dim=-1))
        else:
            neigh = torch.zeros(central.shape[0], 32, dtype=central.dtype, device=central.device)
        out = self.head(torch.cat([neigh, central, central_geo], dim=-1))
        return F.normalize(out, dim=-1)


def relu_mlp(sizes: list[int], last_activation: bool) -> nn.Sequential:
    """Fully connected layers with ReLU (He initialisation); onnxruntime fuses each with its Gemm."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        lin = nn.Linear(a, b)
        nn.init.kaiming_normal_(lin.weight, nonlinearity="relu")
        nn.init.zeros_(lin.bias)
        layers.append(lin)
        if i < len(sizes) - 2 or last_activation:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


class RingInvariants(nn.Module):
    """Features of the normalised ring that a turn of the keypoint's angle does not change.

    An error of the FREAK angle turns every ring of the context by the same amount: its 16 samples shift
    cyclically. The discrete Fourier transform of each ring turns that shift into a phase, so these do not change
    under a shift by whole steps (22.5°), and change less than the samples under a fraction of a step: each ring's
    amplitude at harmonics 1..8 (7 x 8), and, for harmonics 1 and 2, the product of a ring's coefficient with the
    next ring's conjugate (real and imaginary parts, 6 x 2 x 2), which keeps the rings' relative phase. Harmonic 0
    is each ring's mean, which the raw samples already give linearly. A fixed matrix product and element-wise
    arithmetic: one MatMul and a few cheap nodes in ONNX.
    """

    RINGS = 7
    ANGLES = 16
    HARMONICS = 8
    CROSS = 2
    size = RINGS * HARMONICS + (RINGS - 1) * CROSS * 2

    def __init__(self):
        super().__init__()
        j = torch.arange(self.ANGLES, dtype=torch.float64)[:, None]
        k = torch.arange(1, self.HARMONICS + 1, dtype=torch.float64)[None, :]
        t = 2.0 * math.pi * j * k / self.ANGLES
        # [16, 16]: the cosine then minus the sine of each harmonic, divided by the ring's length (a mean)
        basis = torch.cat([torch.cos(t), -torch.sin(t)], dim=1) / self.ANGLES
        self.register_buffer("basis", basis.to(torch.float32), persistent=False)

    def forward(self, c: torch.Tensor) -> torch.Tensor:
        n = c.shape[0]
        rings = c[:, 1:].reshape(n, self.RINGS, self.ANGLES)
        z = rings @ self.basis
        re, im = z[..., : self.HARMONICS], z[..., self.HARMONICS :]
        amplitude = torch.sqrt(re * re + im * im + 1e-4)
        a_re, a_im = re[:, :-1, : self.CROSS], im[:, :-1, : self.CROSS]
        b_re, b_im = re[:, 1:, : self.CROSS], im[:, 1:, : self.CROSS]
        cross = torch.stack([a_re * b_re + a_im * b_im, a_im * b_re - a_re * b_im], dim=-1)
        # the products are of two amplitudes: times 4 keeps them near the amplitudes' range
        return torch.cat([amplitude.reshape(n, -1), 4.0 * cross.reshape(n, -1)], dim=1)


class RingNet(nn.Module):
    """A keypoint's FREAK bits and its ring context (`context.py`: the image around it at fixed places in its
    own frame) -> a unit-length embedding.

    Two branches, each run once per keypoint: the bits (as ±1) through an MLP, the ring's 113 grey levels,
    normalised for gain and offset (minus their mean, over their standard deviation plus 4 grey levels, so a
    flat patch stays near zero), through another; their outputs joined by a head. ReLU everywhere, so every
    layer is one fused Gemm in onnxruntime. No absolute orientation or scale goes in: the embedding does not
    change when the whole image turns or zooms, as far as the keypoint's own angle and size follow.
    """

    INPUT_NAMES = ["descriptors", "context"]

    def __init__(self, embed_dim: int = 48, bits_hidden: tuple = (256,), bits_dim: int = 128, ring_hidden: tuple = (256,),
                 ring_dim: int = 128, head_hidden: tuple = (128,), samples: int = 113, invariants: bool = False,
                 gradients: bool = False):
        super().__init__()
        self.k = 0
        self.samples = samples
        self.invariants = RingInvariants() if invariants else None
        # With `gradients`, a third input: the ring's gradients in the keypoint's frame (`context.gradients`,
        # 2 x samples int8), scaled by the same normaliser as the grey levels and read by the ring branch.
        self.gradients = gradients
        if gradients:
            self.INPUT_NAMES = [*RingNet.INPUT_NAMES, "gradients"]
        ring_in = samples + (self.invariants.size if invariants else 0) + (2 * samples if gradients else 0)
        self.bits = relu_mlp([512, *bits_hidden, bits_dim], last_activation=True)
        self.ring = relu_mlp([ring_in, *ring_hidden, ring_dim], last_activation=True)
        self.head = relu_mlp([bits_dim + ring_dim, *head_hidden, embed_dim], last_activation=False)

    def frame_inputs(self, f) -> tuple:
        if f.context is None:
            raise ValueError("a ring-context model needs the frames' ring contexts (export format 2)")
        if not self.gradients:
            return torch.from_numpy(f.descriptors), torch.from_numpy(f.context)
        if f.gradients is None:
            raise ValueError("this ring model reads the ring's gradients too (load_units with model.ring_gradients loads them)")
        return torch.from_numpy(f.descriptors), torch.from_numpy(f.context), torch.from_numpy(f.gradients)

    def example_inputs(self, n: int = 64, k: int = 0, seed: int = 0) -> tuple:
        g = torch.Generator().manual_seed(seed)
        x = (
            torch.randint(0, 256, (n, 64), dtype=torch.uint8, generator=g),
            torch.randint(0, 256, (n, self.samples), dtype=torch.uint8, generator=g),
        )
        if self.gradients:
            x += (torch.randint(-127, 128, (n, 2 * self.samples), dtype=torch.int8, generator=g),)
        return x

    def forward(self, descriptors: torch.Tensor, context: torch.Tensor, gradients: torch.Tensor | None = None) -> torch.Tensor:
        c = context.to(torch.float32)
        mean = c.mean(1, keepdim=True)
        std = ((c - mean) ** 2).mean(1, keepdim=True).sqrt()
        scale = std + 4.0
        c = (c - mean) / scale
        if self.invariants is not None:
            c = torch.cat([c, self.invariants(c)], dim=1)
        if self.gradients:
            c = torch.cat([c, gradients.to(torch.float32) / scale], dim=1)
        x = torch.cat([self.bits(unpack_bits(descriptors)), self.ring(c)], dim=1)
        return F.normalize(self.head(x), dim=-1)


def build_model(m: dict):
    """`context: ring` is the ring-context network (`RingNet`); otherwise the constellation network, where k = 0
    is the ablation without neighbours (central descriptor only)."""
    if m.get("context") == "ring":
        return RingNet(
            embed_dim=m["embed_dim"], bits_hidden=tuple(m.get("bits_hidden", [256])), bits_dim=m.get("bits_dim", 128),
            ring_hidden=tuple(m.get("ring_hidden", [256])), ring_dim=m.get("ring_dim", 128),
            head_hidden=tuple(m.get("head_hidden_layers", [128])), invariants=m.get("ring_invariants", False),
            gradients=m.get("ring_gradients", False),
        )
    return SconeNet(
        k=max(m["k"], 1), embed_dim=m["embed_dim"], desc_dim=m["desc_dim"], lstm_hidden=m["lstm_hidden"],
        use_neighbours=m["k"] > 0, encoder=m.get("encoder", "lstm"), desc_hidden=tuple(m.get("desc_hidden", [512, 256])),
        set_hidden=m.get("set_hidden", 64), head_hidden=m.get("head_hidden", 64), bits_skip=m.get("bits_skip", 0),
        central_orientation=m.get("central_orientation", True), activation=m.get("activation", "selu"),
        member_activation=m.get("member_activation"),
    )


def ring_from_onnx(path: Path) -> RingNet:
    """The ring network an exported graph holds (`export_onnx` names its initializers by the PyTorch parameters,
    `bits.0.weight` and so on, and keeps the [out, in] layout), in eval mode: a frozen teacher for a run whose
    checkpoint is not at hand. The widths are read from the weights; a graph with the ring's invariants or
    gradients fails to load (its first ring layer is wider than the 113 samples)."""
    import onnx
    from onnx import numpy_helper

    weights = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in onnx.load(str(path)).graph.initializer}
    widths = {name: [int(weights[f"{name}.{k}.weight"].shape[0]) for k in range(0, 16, 2) if f"{name}.{k}.weight" in weights]
              for name in ("bits", "ring", "head")}
    model = RingNet(embed_dim=widths["head"][-1], bits_hidden=tuple(widths["bits"][:-1]), bits_dim=widths["bits"][-1],
                    ring_hidden=tuple(widths["ring"][:-1]), ring_dim=widths["ring"][-1], head_hidden=tuple(widths["head"][:-1]))
    own = set(model.state_dict())
    unread = sorted(k for k in weights if k.split(".")[0] in widths and k not in own)
    if unread:
        raise ValueError(f"{path}: the ring network built from its widths leaves weights unread: {unread}")
    model.load_state_dict({k: weights[k] for k in own})
    return model.eval()


def load_checkpoint(path: Path) -> SconeNet:
    """The network of a training checkpoint (`best.pt`, `last.pt`), built from the config it holds, in eval mode."""
    ck = torch.load(path, weights_only=False)
    model = build_model(ck["config"]["model"])
    model.load_state_dict(ck["model"])
    return model.eval()
