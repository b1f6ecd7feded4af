"""How closely a client's extraction reproduces the server's on the same image."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from scone_client import contract
from scone_client.contract import Features


@dataclass(frozen=True)
class Agreement:
    server: int
    client: int
    #: Server keypoints with a client keypoint within 1 px.
    within_1px: int
    #: Server keypoints with a client keypoint within 1 px whose FREAK bytes are identical.
    within_1px_same_bytes: int
    #: Same count and every keypoint field and descriptor byte equal, in the same order.
    bit_exact: bool

    @property
    def fraction(self) -> float:
        """The contract's figure: within_1px_same_bytes / server keypoints."""
        return self.within_1px_same_bytes / self.server if self.server else 1.0

    def __str__(self) -> str:
        return (
            f"{self.within_1px_same_bytes}/{self.server} server keypoints matched within 1 px with identical "
            f"descriptor bytes ({100 * self.fraction:.2f} %), {self.within_1px} within 1 px, "
            f"{self.client} client keypoints, bit-exact: {self.bit_exact}"
        )


def _fields(f: Features) -> np.ndarray:
    return np.column_stack([f.xy, f.size, f.angle, f.response, f.octave.astype(np.float32)])


def compare(server: Features, client: Features, radius: float = 1.0) -> Agreement:
    near = same = 0
    for i in range(len(server)):
        d2 = ((client.xy - server.xy[i]) ** 2).sum(axis=1)
        candidates = np.nonzero(d2 <= radius * radius)[0]
        if len(candidates):
            near += 1
            if (client.descriptors[candidates] == server.descriptors[i]).all(axis=1).any():
                same += 1
    exact = (
        len(server) == len(client)
        and np.array_equal(_fields(server), _fields(client))
        and np.array_equal(server.descriptors, client.descriptors)
    )
    return Agreement(len(server), len(client), near, same, exact)


# -- Deviations: each rule of the contract done the other way, to measure what it is worth ----------------


def _floor_level_size(w, h, level, scale_factor=1.2):
    s = contract.powi(scale_factor, level)
    return math.floor(w / s), math.floor(h / s)


def _bankers_level_size(w, h, level, scale_factor=1.2):
    s = contract.powi(scale_factor, level)
    return round(w / s), round(h / s)


def _double_mapping(level_xy, w, h, lw, lh):
    xy = level_xy.astype(np.float64)
    return np.column_stack([(xy[:, 0] + 0.5) * w / lw - 0.5, (xy[:, 1] + 0.5) * h / lh - 0.5]).astype(np.float32)


def _spread_last_round_by_cell(level_xy, response, budget, cell):
    """Round-robin as the contract, but the last partial round in cell order instead of strength order."""
    n = len(response)
    if cell == 0 or n <= budget:
        return _SELECT(level_xy, response, budget, cell)
    full = _SELECT(level_xy, response, n, cell)  # every keypoint, in round order
    order = list(full)
    rank = {}
    seen: dict[tuple[int, int], int] = {}
    for i in sorted(range(n), key=lambda i: (-float(response[i]), float(level_xy[i, 1]), float(level_xy[i, 0]))):
        key = (int(level_xy[i, 1]) // cell, int(level_xy[i, 0]) // cell)
        rank[i] = seen.get(key, 0)
        seen[key] = rank[i] + 1
    last = rank[order[budget - 1]]
    done = [i for i in order if rank[i] < last]
    partial = sorted(
        (i for i in order if rank[i] == last), key=lambda i: (int(level_xy[i, 1]) // cell, int(level_xy[i, 0]) // cell)
    )
    return np.asarray((done + partial)[:budget], dtype=np.int64)


_SELECT = contract.select_spread


@contextlib.contextmanager
def deviation(name: str) -> Iterator[None]:
    """Within the block, ``contract`` follows one rule the other way (see DEVIATIONS)."""
    patches = {
        "floor for W_l": ("level_size", _floor_level_size),
        "half-to-even rounding for W_l": ("level_size", _bankers_level_size),
        "coordinates in double": ("to_full_resolution", _double_mapping),
        "pow() instead of binary powers": ("powi", lambda b, e: b**e),
        "last partial round in cell order": ("select_spread", _spread_last_round_by_cell),
    }
    if name not in patches:
        yield
        return
    attr, replacement = patches[name]
    saved = getattr(contract, attr)
    setattr(contract, attr, replacement)
    try:
        yield
    finally:
        setattr(contract, attr, saved)


def grey_for(name: str, data: bytes) -> np.ndarray:
    """The grey image the deviation ``name`` uses (decoded straight to grey for that deviation)."""
    if name == "decoded straight to grey":
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    return contract.decode_grey(data)


DEVIATIONS = [
    "decoded straight to grey",
    "floor for W_l",
    "half-to-even rounding for W_l",
    "coordinates in double",
    "pow() instead of binary powers",
    "last partial round in cell order",
]
