"""A real scone server for the tests: the release binary on 127.0.0.1 with free ports and a temporary data dir.

The binary is $SCONE_BIN, else $CARGO_TARGET_DIR/release/scone, else $SCONE_PREFIX/target/release/scone
(scripts/env.sh's defaults), so CI finds the binary scripts/setup built.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from scone_client import configure_opencv
from scone_client.client import SconeClient

REPO = Path(__file__).resolve().parents[3]
FIXTURES = REPO / "tests" / "fixtures"


def server_binary() -> Path:
    if os.environ.get("SCONE_BIN"):
        return Path(os.environ["SCONE_BIN"])
    prefix = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache" / "scone"))
    target = Path(os.environ.get("CARGO_TARGET_DIR", prefix / "target"))
    return target / "release" / "scone"


@pytest.fixture(scope="session", autouse=True)
def _opencv() -> None:
    configure_opencv()


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory):
    """Starts `scone serve`, waits for /readyz, yields (grpc_target, http_url); SIGTERM at the end."""
    binary = server_binary()
    if not binary.is_file():
        pytest.fail(f"no scone binary at {binary} (build it with cargo build --release, or set SCONE_BIN)")
    data = tmp_path_factory.mktemp("data")
    log_path = data.parent / "server.log"
    env = dict(os.environ, SCONE_MODEL__INTRA_THREADS="1", RUST_LOG=os.environ.get("RUST_LOG", "warn"))
    env.pop("SCONE_CONFIG", None)
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            [str(binary), "serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--data-dir", str(data)],
            stdout=subprocess.PIPE,
            stderr=log,
            stdin=subprocess.DEVNULL,
            env=env,
        )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().decode()
        found = re.search(r"gRPC (\S+) HTTP (\S+)", line)
        if not found:
            proc.wait(timeout=10)
            pytest.fail(f"server did not start ({line!r}); log:\n{log_path.read_text()}")
        grpc_target, http_url = found.group(1), found.group(2)
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(f"{http_url}/readyz", timeout=2) as r:
                    if r.status == 200:
                        break
            except (urllib.error.URLError, ConnectionError):
                pass
            if time.monotonic() > deadline or proc.poll() is not None:
                pytest.fail(f"server not ready; log:\n{log_path.read_text()}")
            time.sleep(0.1)
        yield grpc_target, http_url
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture(scope="session")
def client(server):
    with SconeClient(server[0], timeout=120.0) as c:
        yield c
