"""Localize throughput through nginx with 1 and then 2 `scone serve` replicas on one bucket, in one run.

The bucket is moto's server mode (an S3 *emulator* on loopback, not Amazon S3). The router is Debian's nginx
running deploy/nginx/scone-replicas.conf.template (consistent hash of the map id). The maps: MAPS maps of
real, different frames (consecutive blocks of sun3d-studyroom, every other frame a keyframe with its depth
and pose, written through the proxy); the queries: the other frames of each block, JPEG quality 90, sent by
wrk (Debian package) as raw Localize bodies with `x-scone-map-id`, cycling over every map.

Pinning (2 cores): replica A on core 0; replica B, nginx and wrk on core 1. So "1 replica" is one core of
scone with the proxy and the generator beside it on the other core, and "2 replicas" adds a scone on the
generator's core: the ratio is what a second replica buys on this machine, not what it buys on its own host.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import requests
from PIL import Image

ROOT = Path(__file__).resolve().parents[2]
PREFIX = Path(os.environ.get("SCONE_PREFIX", Path.home() / ".cache/scone"))
SCONE = os.environ.get("SCONE_BIN", str(PREFIX / "target/release/scone"))
KEY = "bench"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout: float = 90.0) -> None:
    t = time.time()
    while True:
        try:
            if requests.get(url, timeout=2).status_code == 200:
                return
        except requests.RequestException:
            pass
        if time.time() - t > timeout:
            raise SystemExit(f"replicas: {url} did not answer within {timeout:.0f} s")
        time.sleep(0.1)


def read_scene(scene: Path):
    def table(name: str) -> list[list[str]]:
        return [ln.split() for ln in (scene / name).read_text().splitlines() if ln and not ln.startswith("#")]

    cam = [float(x) for x in table("camera.txt")[0]]
    rgb = {s: scene / f for s, f in table("rgb.txt")}
    depth = {s: scene / f for s, f in table("depth.txt")}
    poses = {r[0]: [float(x) for x in r[1:]] for r in table("groundtruth.txt")}
    stamps = [s for s in rgb if s in depth and s in poses]
    return cam, [(s, rgb[s], depth[s], poses[s]) for s in stamps]


class Procs:
    """Processes started by the run, stopped (SIGTERM, then SIGKILL) in reverse order."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def start(self, cmd: list[str], cpu: str | None = None, **kw) -> subprocess.Popen:
        if cpu is not None:
            cmd = ["taskset", "-c", cpu, *cmd]
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, **kw)
        self.procs.append(p)
        return p

    def stop(self, p: subprocess.Popen) -> None:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def stop_all(self) -> None:
        while self.procs:
            self.stop(self.procs.pop())


def render_nginx(runtime: Path, http_port: int, grpc_port: int, replicas: list[tuple[int, int]]) -> Path:
    template = (ROOT / "deploy/nginx/scone-replicas.conf.template").read_text()

    def servers(i: int) -> str:
        return "\n".join(f"        server 127.0.0.1:{r[i]} max_fails=1 fail_timeout=10s;" for r in replicas)

    conf = (
        template.replace("@RUNTIME_DIR@", str(runtime))
        .replace("@HTTP_LISTEN@", f"127.0.0.1:{http_port}")
        .replace("@GRPC_LISTEN@", f"127.0.0.1:{grpc_port}")
        .replace("@HTTP_SERVERS@", servers(0))
        .replace("@GRPC_SERVERS@", servers(1))
        .replace("@USER@", "user root;" if os.geteuid() == 0 else "")
    )
    path = runtime / "nginx.conf"
    path.write_text(conf)
    return path


def requests_served(base: str) -> float:
    text = requests.get(f"{base}/metrics", timeout=10).text
    total = 0.0
    for line in text.splitlines():
        if line.startswith("scone_requests_total") and 'route="/v1/maps/{map_id}/localize"' in line:
            if 'status="200"' in line:
                total += float(line.rsplit(" ", 1)[1])
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=ROOT.parent / "shared/data/scenes/sun3d-studyroom")
    ap.add_argument("--maps", type=int, default=8)
    ap.add_argument("--block", type=int, default=12, help="consecutive frames per map")
    ap.add_argument("--duration", type=int, default=30, help="seconds of load per configuration")
    ap.add_argument("--connections", type=int, default=8)
    ap.add_argument("--out", type=Path, default=ROOT / "load-tests/results/replicas.md")
    args = ap.parse_args()
    if not (args.scene / "depth.txt").exists():
        raise SystemExit(f"replicas: {args.scene} (a scene with depth) is absent; nothing measured")
    cam, frames = read_scene(args.scene)
    fx, fy, cx, cy = cam[:4]
    if len(frames) < args.maps * args.block:
        raise SystemExit(f"replicas: {len(frames)} frames, need {args.maps * args.block}")

    work = Path(tempfile.mkdtemp(prefix="scone-replicas-load-"))
    procs = Procs()
    try:
        moto_port = free_port()
        procs.start([str(PREFIX / "venv-s3/bin/moto_server"), "-H", "127.0.0.1", "-p", str(moto_port)], cpu="1")
        endpoint = f"http://127.0.0.1:{moto_port}"
        wait_http(endpoint)
        bucket = "replicas-load"
        requests.put(f"{endpoint}/{bucket}", timeout=10).raise_for_status()
        env = dict(
            os.environ,
            SCONE_STORE__BACKEND__KIND="s3",
            SCONE_STORE__BACKEND__BUCKET=bucket,
            SCONE_STORE__BACKEND__PREFIX="load",
            SCONE_STORE__BACKEND__ENDPOINT=endpoint,
            SCONE_STORE__BACKEND__ALLOW_HTTP="true",
            SCONE_WORKERS__THREADS="1",
            SCONE_MODEL__INTRA_THREADS="1",
            AWS_REGION="us-east-1",
            AWS_ACCESS_KEY_ID=KEY,
            AWS_SECRET_ACCESS_KEY=KEY,
        )
        # Queries: JPEG quality 90 of the frames between keyframes.
        targets = []
        blocks = [frames[m * args.block : (m + 1) * args.block] for m in range(args.maps)]
        for m, block in enumerate(blocks):
            for j, (stamp, rgb, _, _) in enumerate(block):
                if j % 2 == 1:
                    path = work / f"q-{m}-{stamp}.jpg"
                    buf = io.BytesIO()
                    Image.open(rgb).convert("RGB").save(buf, "JPEG", quality=90)
                    path.write_bytes(buf.getvalue())
                    targets.append(f"/v1/maps/s{m}/localize?fx={fx}&fy={fy}&cx={cx}&cy={cy}|{path}")

        results = []
        built = False
        for n in (1, 2):
            ports = [(free_port(), free_port()) for _ in range(n)]
            servers = []
            for i, (hp, gp) in enumerate(ports):
                e = dict(env, SCONE_STORE__DATA_DIR=str(work / f"replica-{n}-{i}"))
                servers.append(
                    procs.start(
                        [SCONE, "serve", "--http-addr", f"127.0.0.1:{hp}", "--grpc-addr", f"127.0.0.1:{gp}"],
                        cpu=str(i),
                        env=e,
                    )
                )
            runtime = work / f"nginx-{n}"
            runtime.mkdir()
            proxy_port = free_port()
            conf = render_nginx(runtime, proxy_port, free_port(), ports)
            nginx = procs.start(["nginx", "-p", str(runtime), "-c", str(conf), "-g", "daemon off;"], cpu="1")
            proxy = f"http://127.0.0.1:{proxy_port}"
            for hp, _ in ports:
                wait_http(f"http://127.0.0.1:{hp}/readyz")
            wait_http(f"{proxy}/readyz")
            if not built:
                t = time.time()
                for m, block in enumerate(blocks):
                    r = requests.post(f"{proxy}/v1/maps", json={"map_id": f"s{m}"}, headers={"x-scone-map-id": f"s{m}"})
                    r.raise_for_status()
                    for j, (stamp, rgb, depth, p) in enumerate(block):
                        if j % 2 == 1:
                            continue
                        req = {
                            "keyframe_id": j,
                            "pose": dict(zip(["tx", "ty", "tz", "qx", "qy", "qz", "qw"], p)),
                            "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy},
                        }
                        files = {
                            "request": (None, json.dumps(req), "application/json"),
                            "image": ("rgb.png", rgb.read_bytes(), "image/png"),
                            "depth": ("depth.png", depth.read_bytes(), "image/png"),
                        }
                        r = requests.post(f"{proxy}/v1/maps/s{m}/keyframes", files=files, timeout=120)
                        r.raise_for_status()
                built = True
                listed = requests.get(f"{proxy}/v1/maps", timeout=30).json()["maps"]
                obs = sum(m["observations"] for m in listed)
                print(f"[replicas] {len(listed)} maps, {obs} observations, written in {time.time() - t:.0f} s")
            # Warm-up: every query once (each map loads on its owner), then the measured run.
            for tgt in targets:
                path, file = tgt.split("|")
                requests.post(
                    proxy + path,
                    data=Path(file).read_bytes(),
                    timeout=120,
                    headers={"content-type": "image/jpeg", "x-scone-map-id": path.split("/")[3]},
                )
            before = [requests_served(f"http://127.0.0.1:{hp}") for hp, _ in ports]
            wrk_env = dict(os.environ, SCONE_WRK_TARGETS=";".join(targets))
            out = subprocess.run(
                [
                    "taskset",
                    "-c",
                    "1",
                    "wrk",
                    "-t1",
                    f"-c{args.connections}",
                    f"-d{args.duration}s",
                    "--timeout",
                    "60s",
                    "-s",
                    str(ROOT / "load-tests/wrk/post-jpeg.lua"),
                    proxy,
                ],
                env=wrk_env,
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            figures = json.loads(re.search(r"SCONE-WRK-JSON (\{.*\})", out).group(1))
            after = [requests_served(f"http://127.0.0.1:{hp}") for hp, _ in ports]
            figures["per_replica"] = [a - b for a, b in zip(after, before)]
            figures["replicas"] = n
            results.append(figures)
            print(f"[replicas] {n} replica(s): {json.dumps(figures)}")
            procs.stop(nginx)
            for s in servers:
                procs.stop(s)
            procs.procs = [p for p in procs.procs if p.poll() is None]

        base = results[0]["rps"] - results[0]["non2xx"] / results[0]["duration_s"]
        lines = [
            f"Localize through nginx (consistent hash of the map id), {args.maps} maps of {args.block // 2} keyframes "
            f"from {args.scene.name}, {len(targets)} JPEG queries, wrk -c{args.connections}, {args.duration} s per row; "
            "moto (S3 emulator) on loopback. Replica A on core 0; replica B, nginx and wrk on core 1.",
            "",
            "| replicas | answered/s | vs 1 replica | p50 ms | p99 ms | non-2xx | answered per replica |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in results:
            answered = r["rps"] - r["non2xx"] / r["duration_s"]
            share = " / ".join(f"{x:.0f}" for x in r["per_replica"])
            lines.append(
                f"| {r['replicas']} | {answered:.2f} | {answered / base:.2f} | {r['p50_ms']:.0f} | {r['p99_ms']:.0f} "
                f"| {r['non2xx']} | {share} |"
            )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
    finally:
        procs.stop_all()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
