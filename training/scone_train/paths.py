"""Where things are: the repository, the `scone` binary, the prefix of data, caches and runs, the shared data."""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def scone_binary() -> Path:
    """Path of the release binary built by scripts/setup."""
    if "SCONE_BIN" in os.environ:
        return Path(os.environ["SCONE_BIN"])
    prefix = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))
    target = Path(os.environ.get("CARGO_TARGET_DIR", prefix / "target"))
    return target / "release" / "scone"


def prefix_dir() -> Path:
    """The prefix outside the clone where data, caches and runs live ($SCONE_PREFIX)."""
    return Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))


def shared_data() -> Path:
    return Path(os.environ.get("SCONE_DATA", REPO.parent / "shared" / "data"))
