"""How closely a client's extraction reproduces the server's on the same image."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
