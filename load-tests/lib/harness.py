"""Runs the load-test scenarios against a fresh scone server each and writes the figures.

Called by load-tests/run (which prepares the venv, wrk, the inputs and the ~100k-observation map); run it
through that script. Every server is pinned to core 0 and every load generator to core 1 (taskset); each
scenario and each run of a generator is bounded in time; the server is stopped (SIGTERM, then SIGKILL) on
every way out.

Results: load-tests/results/results.json (figures of every scenario run so far, merged), summary.md (the
tables), raw/ (locust CSVs and raw samples, wrk output, server logs and /metrics; not committed).
"""

import argparse
import datetime
import json
import os
import platform
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import psutil

HERE = os.path.dirname(os.path.abspath(__file__))
LOAD = os.path.dirname(HERE)
ROOT = os.path.dirname(LOAD)
sys.path.insert(0, HERE)
import report  # noqa: E402

SCENARIOS = ["describe", "localize", "match", "burst", "storm", "mixed", "soak", "settings"]
SERVER_CORE = os.environ.get("SCONE_LOAD_SERVER_CPU", "0")
GEN_CORE = os.environ.get("SCONE_LOAD_GEN_CPU", "1")


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def env_num(name, default, cast=float):
    v = os.environ.get(name)
    return cast(v) if v not in (None, "") else default


class Config:
    def __init__(self, quick):
        self.quick = quick
        self.bin = os.environ.get("SCONE_BIN", os.path.expanduser("~/.cache/scone/target/release/scone"))
        self.cache = os.environ["SCONE_LOAD_CACHE"]
        self.map_dir = os.environ["SCONE_LOAD_MAP_DIR"]
        self.venv_bin = os.path.dirname(sys.executable)
        self.results = os.environ.get("SCONE_LOAD_RESULTS", os.path.join(LOAD, "results"))
        self.raw = os.path.join(self.results, "raw")
        self.work = os.path.join(self.cache, "work")
        q = quick
        self.point_s = env_num("SCONE_LOAD_DURATION", 8 if q else 60, int)        # one concurrency level
        self.wrk_s = env_num("SCONE_LOAD_WRK_DURATION", 8 if q else 30, int)
        default_clients = "1,4" if q else "1,2,4,8"
        self.clients = [int(c) for c in os.environ.get("SCONE_LOAD_CLIENTS", default_clients).split(",")]
        self.grpc_clients = [int(c) for c in os.environ.get("SCONE_LOAD_GRPC_CLIENTS",
                                                             "4" if q else default_clients).split(",")]
        self.wrk_clients = [int(c) for c in os.environ.get("SCONE_LOAD_WRK_CLIENTS",
                                                            "4" if q else default_clients).split(",")]
        self.burst_users = env_num("SCONE_LOAD_BURST_USERS", 48, int)
        self.burst_s = env_num("SCONE_LOAD_BURST_DURATION", 10 if q else 30, int)
        self.burst_rounds = env_num("SCONE_LOAD_BURST_ROUNDS", 1 if q else 3, int)
        self.storm_users = env_num("SCONE_LOAD_STORM_USERS", 32, int)
        self.storm_base_users = env_num("SCONE_LOAD_STORM_BASE_USERS", 2, int)
        self.storm_s = env_num("SCONE_LOAD_STORM_DURATION", 10 if q else 30, int)
        self.storm_max_requests = env_num("SCONE_LOAD_STORM_MAX_REQUESTS", 100000, int)  # per client
        self.mixed_s = env_num("SCONE_LOAD_MIXED_DURATION", 12 if q else 60, int)
        self.mixed_readers = env_num("SCONE_LOAD_MIXED_READERS", 2, int)
        self.write_rate = env_num("SCONE_LOAD_WRITE_RATE", 2.0)
        self.soak_s = env_num("SCONE_LOAD_SOAK_DURATION", 30 if q else 600, int)
        self.soak_share = env_num("SCONE_LOAD_SOAK_SHARE", 0.7)
        self.soak_users = env_num("SCONE_LOAD_SOAK_USERS", 2, int)
        self.sample_s = env_num("SCONE_LOAD_SAMPLE_S", 2.0)
        self.settings_clients = [int(c) for c in os.environ.get("SCONE_LOAD_SETTINGS_CLIENTS", "2,4").split(",")]
        self.settings_s = env_num("SCONE_LOAD_SETTINGS_DURATION", 8 if q else 30, int)
        self.max_wait_build_s = env_num("SCONE_LOAD_MAX_WAIT_BUILD_S", 3600, int)
        self.max_other_cpu = env_num("SCONE_LOAD_MAX_OTHER_CPU", 15.0)  # % of a core, during a measurement
        self.attempts = env_num("SCONE_LOAD_ATTEMPTS", 3, int)


# ---------------------------------------------------------------------------------------------------------
# Processes
# ---------------------------------------------------------------------------------------------------------


def proc_cpu_s(pid):
    """User + system CPU time of a process (all its threads, not its children), seconds; None once it is gone."""
    try:
        t = psutil.Process(pid).cpu_times()
        return t.user + t.system
    except psutil.Error:
        return None


def proc_rss_kib(pid):
    """Resident memory of a process, KiB; None once it is gone."""
    try:
        return psutil.Process(pid).memory_info().rss // 1024
    except psutil.Error:
        return None


def machine_busy_s():
    """CPU time spent by the whole machine (every core, every process), seconds: everything but idle and
    iowait."""
    t = psutil.cpu_times()
    return t.user + t.nice + t.system + t.irq + t.softirq + t.steal


def wait_for_quiet_machine(cfg, pids=()):
    """No rustc/cargo running and nothing else busy (a build or a test run on 2 cores distorts every figure):
    wait and retry. pids: our own processes, left out of the count."""
    waited = 0
    while True:
        busy = [n for n in ("rustc", "cargo") if subprocess.run(["pgrep", "-x", n], capture_output=True).returncode == 0]
        if not busy:
            own0 = sum(proc_cpu_s(p) or 0 for p in pids)
            m0 = machine_busy_s()
            time.sleep(2)
            other = (machine_busy_s() - m0 - (sum(proc_cpu_s(p) or 0 for p in pids) - own0)) / 2
            if other > 0.25:
                busy = [f"other processes ({100 * other:.0f} % of a core)"]
        if not busy:
            if waited:
                log(f"machine quiet again after {waited} s")
            return
        if waited >= cfg.max_wait_build_s:
            raise SystemExit(f"{'/'.join(busy)} still running after {waited} s: giving up (figures would be distorted)")
        if waited == 0:
            log(f"{'/'.join(busy)} running: waiting for it to finish before measuring")
        time.sleep(30 if "cargo" in busy or "rustc" in busy else 15)
        waited += 30 if "cargo" in busy or "rustc" in busy else 15


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def http(method, url, body=None, ctype=None, timeout=60):
    req = urllib.request.Request(url, data=body, method=method)
    if ctype:
        req.add_header("Content-Type", ctype)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()


class Server:
    """One scone server pinned to SERVER_CORE, on free loopback ports, with its own copy of the data."""

    live = []  # for the signal handler

    def __init__(self, cfg, name, with_map, env=None):
        self.cfg, self.name, self.with_map, self.env = cfg, name, with_map, dict(env or {})
        self.proc = None

    def start(self):
        cfg = self.cfg
        self.data = os.path.join(cfg.work, self.name)
        shutil.rmtree(self.data, ignore_errors=True)
        if self.with_map:
            shutil.copytree(cfg.map_dir, self.data, ignore=shutil.ignore_patterns("BUILD_INFO"))
        else:
            os.makedirs(self.data)
        self.http_port, self.grpc_port = free_port(), free_port()
        self.url = f"http://127.0.0.1:{self.http_port}"
        self.grpc = f"127.0.0.1:{self.grpc_port}"
        env = dict(os.environ)
        env.update(self.env)
        self.log_path = os.path.join(cfg.raw, f"{self.name}.server.log")
        self.log_file = open(self.log_path, "w")
        cmd = ["taskset", "-c", SERVER_CORE, cfg.bin, "serve", "--data-dir", self.data,
               "--grpc-addr", self.grpc, "--http-addr", f"127.0.0.1:{self.http_port}"]
        self.proc = subprocess.Popen(cmd, stdout=self.log_file, stderr=subprocess.STDOUT, env=env,
                                     start_new_session=True)
        Server.live.append(self)
        with open(os.path.join(cfg.work, "server.pids"), "a") as f:
            f.write(f"{self.proc.pid}\n")
        t0 = time.time()
        while True:
            if self.proc.poll() is not None:
                raise SystemExit(f"server {self.name} exited with {self.proc.returncode}: see {self.log_path}")
            try:
                if http("GET", self.url + "/readyz", timeout=2)[0] == 200:
                    break
            except OSError:
                pass
            if time.time() - t0 > 180:
                raise SystemExit(f"server {self.name} not ready after 180 s: see {self.log_path}")
            time.sleep(0.2)
        self.ready_s = time.time() - t0
        if self.with_map:
            st, body = http("GET", self.url + "/v1/maps/big")
            if st != 200:
                raise SystemExit(f"map 'big' not served ({st}: {body[:200]!r}); delete {cfg.map_dir} to rebuild it")
            self.map_info = json.loads(body)
        log(f"server {self.name}: pid {self.proc.pid} ready in {self.ready_s:.1f} s "
            f"(HTTP {self.url}, gRPC {self.grpc}, env {self.env or 'defaults'})")
        return self

    @property
    def pid(self):
        return self.proc.pid

    def alive(self):
        if self.proc.poll() is not None:
            return False
        try:
            return http("GET", self.url + "/healthz", timeout=5)[0] == 200
        except OSError:
            return False

    def metrics(self):
        st, body = http("GET", self.url + "/metrics")
        text = body.decode()
        with open(os.path.join(self.cfg.raw, f"{self.name}.metrics.txt"), "w") as f:
            f.write(text)
        return report.parse_metrics(text)

    def stop(self):
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log_file.close()
        if self in Server.live:
            Server.live.remove(self)
        shutil.rmtree(self.data, ignore_errors=True)

    def __enter__(self):
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc):
        self.stop()


def _on_signal(signum, _frame):
    for s in list(Server.live):
        if s.proc and s.proc.poll() is None:
            s.proc.kill()
    sys.exit(128 + signum)


class Sampler(threading.Thread):
    """Every period: the server's RSS and CPU time, and the generator's CPU time."""

    def __init__(self, server_pid, gen_pid, period):
        super().__init__(daemon=True)
        self.server_pid, self.gen_pid, self.period = server_pid, gen_pid, period
        self.samples = []
        self.stop_event = threading.Event()
        self.t0 = time.time()

    def sample(self):
        self.samples.append({"t": round(time.time() - self.t0, 2), "rss_kib": proc_rss_kib(self.server_pid),
                             "server_cpu_s": proc_cpu_s(self.server_pid), "gen_cpu_s": proc_cpu_s(self.gen_pid)})

    def run(self):
        while not self.stop_event.wait(self.period):
            self.sample()

    def finish(self):
        self.stop_event.set()
        self.join()
        self.sample()
        return self.samples


def run_generator(cfg, server, cmd, env, timeout_s, label, sample_s=None):
    """Runs one load generator pinned to GEN_CORE; returns its output and the CPU/RSS figures."""
    out_path = os.path.join(cfg.raw, f"{label}.out")
    full_env = dict(os.environ)
    full_env.update(env)
    rss0 = proc_rss_kib(server.pid)
    srv_cpu0 = proc_cpu_s(server.pid)
    own0 = proc_cpu_s(os.getpid())
    m0 = machine_busy_s()
    t0 = time.time()
    with open(out_path, "w") as out:
        proc = subprocess.Popen(["taskset", "-c", GEN_CORE] + cmd, stdout=out, stderr=subprocess.STDOUT,
                                env=full_env, cwd=LOAD, start_new_session=True)
        sampler = Sampler(server.pid, proc.pid, sample_s or cfg.sample_s)
        sampler.sample()
        sampler.start()
        deadline = t0 + timeout_s
        status = None
        while True:
            pid, status, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.time() > deadline:
                log(f"{label}: generator over its time limit ({timeout_s} s): killing it")
                os.killpg(proc.pid, signal.SIGKILL)
                pid, status, ru = os.wait4(proc.pid, 0)
                break
            time.sleep(0.2)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.time() - t0
    m1 = machine_busy_s()
    samples = sampler.finish()
    srv_cpu1 = proc_cpu_s(server.pid)
    gen_cpu = ru.ru_utime + ru.ru_stime
    # CPU used by anything else on the machine meanwhile (another build, test run...): flags distorted figures
    other = (m1 - m0) - (srv_cpu1 - srv_cpu0) - gen_cpu - (proc_cpu_s(os.getpid()) - own0)
    rss = [s["rss_kib"] for s in samples if s["rss_kib"]]
    return {
        "rc": proc.returncode,
        "output": open(out_path).read(),
        "wall_s": round(wall, 2),
        "gen_cpu_s": round(gen_cpu, 2),
        "gen_cpu_pct": round(100 * gen_cpu / wall, 1),
        "server_cpu_pct": round(100 * (srv_cpu1 - srv_cpu0) / wall, 1) if srv_cpu1 is not None else None,
        "other_cpu_pct": round(max(0.0, 100 * other / wall), 1),
        "rss_start_mib": round(rss0 / 1024, 1) if rss0 else None,
        "rss_end_mib": round(rss[-1] / 1024, 1) if rss else None,
        "rss_max_mib": round(max(rss) / 1024, 1) if rss else None,
        "samples": samples,
    }


def measured(cfg, server, label, once):
    """Runs one measurement; runs it again (up to cfg.attempts in all) when other processes used more than
    cfg.max_other_cpu % of a core meanwhile, and keeps the least disturbed run."""
    best = None
    for attempt in range(1, cfg.attempts + 1):
        wait_for_quiet_machine(cfg, [server.pid])
        r = once()
        r["attempt"] = attempt
        if best is None or r["other_cpu_pct"] < best["other_cpu_pct"]:
            best = r
        if r["other_cpu_pct"] <= cfg.max_other_cpu:
            return r
        log(f"{label}: other processes used {r['other_cpu_pct']} % of a core meanwhile: measuring again")
    log(f"{label}: still disturbed after {cfg.attempts} attempts: keeping the least disturbed run")
    return best


def locust(cfg, server, locustfile, classes, users, run_s, label, env=None, sample_s=None):
    """One headless locust run (closed loop unless SCONE_LOAD_RATE is set); figures from its raw record."""
    return measured(cfg, server, label, lambda: _locust(cfg, server, locustfile, classes, users, run_s, label, env, sample_s))


def _locust(cfg, server, locustfile, classes, users, run_s, label, env, sample_s):
    raw_path = os.path.join(cfg.raw, f"{label}.raw.json")
    csv_prefix = os.path.join(cfg.raw, label)
    cmd = [os.path.join(cfg.venv_bin, "locust"), "-f", locustfile, "--headless", "--host", server.url,
           "--users", str(users), "--spawn-rate", str(users), "--run-time", f"{run_s}s", "--stop-timeout", "0",
           "--csv", csv_prefix, "--only-summary", "--loglevel", "WARNING", "--exit-code-on-error", "0"] + classes
    e = {"SCONE_LOAD_RAW": raw_path, "SCONE_LOAD_GRPC": server.grpc}
    e.update(env or {})
    log(f"{label}: locust {' '.join(classes)}, {users} users, {run_s} s")
    r = run_generator(cfg, server, cmd, e, run_s + 60, label, sample_s)
    if r["rc"] != 0 or not os.path.exists(raw_path):
        raise SystemExit(f"{label}: locust failed (rc {r['rc']}): {r['output'][-2000:]}")
    r["by_name"] = report.summarise_raw(json.load(open(raw_path))["requests"])
    del r["output"]
    return r


def wrk(cfg, server, path, conns, run_s, label, env=None):
    return measured(cfg, server, label, lambda: _wrk(cfg, server, path, conns, run_s, label, env))


def _wrk(cfg, server, path, conns, run_s, label, env=None):
    files = json.load(open(os.path.join(cfg.cache, "queries", "manifest.json")))["files"]
    cmd = ["wrk", "-t1", f"-c{conns}", f"-d{run_s}s", "--timeout", "60s", "-s",
           os.path.join(LOAD, "wrk", "post-jpeg.lua"), server.url + path]
    log(f"{label}: wrk -t1 -c{conns} {run_s} s {path.split('?')[0]}")
    e = {"SCONE_WRK_FILES": ":".join(files)}
    e.update(env or {})
    r = run_generator(cfg, server, cmd, e, run_s + 60, label)
    m = re.search(r"SCONE-WRK-JSON (\{.*\})", r["output"])
    if r["rc"] != 0 or not m:
        raise SystemExit(f"{label}: wrk failed (rc {r['rc']}): {r['output'][-2000:]}")
    r["wrk"] = json.loads(m.group(1))
    del r["output"]
    return r


def warm_up(server, localize):
    q = json.load(open(os.path.join(os.environ["SCONE_LOAD_CACHE"], "queries", "manifest.json")))
    i = q["intrinsics"]
    for f in q["files"]:
        body = open(f, "rb").read()
        st, out = http("POST", server.url + "/v1/describe", body, "image/jpeg")
        if st != 200:
            raise SystemExit(f"warm-up Describe: HTTP {st}: {out[:300]!r}")
        if localize:
            st, out = http("POST", server.url + localize_path(i), body, "image/jpeg")
            if st != 200:
                raise SystemExit(f"warm-up Localize: HTTP {st}: {out[:300]!r}")


def localize_path(i, map_id="big"):
    return f"/v1/maps/{map_id}/localize?fx={i['fx']}&fy={i['fy']}&cx={i['cx']}&cy={i['cy']}"


def intrinsics(cfg):
    return json.load(open(os.path.join(cfg.cache, "queries", "manifest.json")))["intrinsics"]


def strip(r):
    """A run's figures without the per-sample series (kept only for the soak)."""
    r = dict(r)
    r.pop("samples", None)
    return r


# ---------------------------------------------------------------------------------------------------------
# Scenarios
# ---------------------------------------------------------------------------------------------------------


SWEEP_USERS = {
    "describe": ("DescribeUser", "DescribeGrpcUser"),
    "localize": ("LocalizeUser", "LocalizeGrpcUser"),
    "match": ("MatchUser", "MatchPairGrpcUser"),
}


def sweep(cfg, op):
    """Describe, Localize or MatchPair at each concurrency: locust HTTP, locust gRPC, and wrk (not for
    MatchPair, whose body is a two-image multipart that wrk/post-jpeg.lua does not build); one fresh server per
    tool."""
    with_map = op == "localize"
    http_class, grpc_class = SWEEP_USERS[op]
    path = localize_path(intrinsics(cfg)) if with_map else "/v1/describe"
    out = {"op": op, "locust_http": {}, "locust_grpc": {}, "wrk": {}, "durations_s": {"locust": cfg.point_s, "wrk": cfg.wrk_s}}
    tools = (("locust_http", cfg.clients), ("locust_grpc", cfg.grpc_clients), ("wrk", cfg.wrk_clients))
    for tool, clients in tools if op != "match" else tools[:2]:
        if not clients:
            continue
        with Server(cfg, f"{op}-{tool}", with_map) as srv:
            warm_up(srv, with_map)
            for n in clients:
                label = f"{op}-{tool}-c{n}"
                if tool == "wrk":
                    r = wrk(cfg, srv, path, n, cfg.wrk_s, label)
                elif tool == "locust_http":
                    r = locust(cfg, srv, "locustfile_http.py", [http_class], n, cfg.point_s, label)
                else:
                    r = locust(cfg, srv, "locustfile_grpc.py", [grpc_class], n, cfg.point_s, label)
                out[tool][str(n)] = strip(r)
                log(f"{label}: {report.one_line(r)}")
                time.sleep(3)  # let interrupted requests drain
            out[tool + "_metrics"] = srv.metrics()
            if with_map:
                out["map"] = srv.map_info
    return out


def burst(cfg):
    """Far more closed-loop clients than workers + queue: most requests must be refused at once, not queued.

    Each tool gets a fresh server and cfg.burst_rounds bursts in a row (figures of the first; RSS after each:
    growth in the first round only is the allocator's high-water mark, growth in every round a leak)."""
    out = {"users": cfg.burst_users, "duration_s": cfg.burst_s, "rounds": cfg.burst_rounds}
    q = json.load(open(os.path.join(cfg.cache, "queries", "manifest.json")))
    path = localize_path(q["intrinsics"])
    # wrk: the same burst from a generator that stays far from saturating its core (locust's HTTP client
    # nearly does at 48 users, since refusals come back in milliseconds). Its latencies mix answers and 429s.
    for tool in ("http", "grpc", "wrk"):
        with Server(cfg, f"burst-{tool}", True) as srv:
            warm_up(srv, True)
            rss = [proc_rss_kib(srv.pid)]
            first = None
            for k in range(cfg.burst_rounds):
                label = f"burst-{tool}" + (f"-r{k + 1}" if k else "")
                if tool == "wrk":
                    r = wrk(cfg, srv, path, cfg.burst_users, cfg.burst_s, label)
                else:
                    lf, cls = (("locustfile_http.py", "LocalizeUser") if tool == "http"
                               else ("locustfile_grpc.py", "LocalizeGrpcUser"))
                    r = locust(cfg, srv, lf, [cls], cfg.burst_users, cfg.burst_s, label, sample_s=1.0)
                time.sleep(3)
                rss.append(proc_rss_kib(srv.pid))
                first = first or r
                log(f"{label}: " + (str(r["wrk"]) if tool == "wrk" else report.one_line(r)))
            st, _ = http("POST", srv.url + path, open(q["files"][0], "rb").read(), "image/jpeg")
            r = first
            r["alive_after"] = srv.alive() and st == 200
            r["rss_before_mib"] = round(rss[0] / 1024, 1)
            r["rss_after_mib"] = round(rss[1] / 1024, 1)
            r["rss_after_rounds_mib"] = [round(x / 1024, 1) for x in rss[1:]]
            r["metrics"] = srv.metrics()
            out[tool] = strip(r)
            log(f"burst-{tool}: alive after: {r['alive_after']}; RSS before and after each round "
                f"{[round(x / 1024, 1) for x in rss]} MiB")
            time.sleep(2)
    return out


def answered_rps(r):
    """Answered (2xx / OK) Localize requests per second of a locust or wrk run."""
    if "wrk" in r:
        w = r["wrk"]
        return (w["requests"] - w["non2xx"] - w["socket_errors"]) / w["duration_s"]
    return r["by_name"].get("Localize", {}).get("rps", 0.0)


def storm(cfg):
    """Clients that do not back off (issue 16, item 3): cfg.storm_users closed-loop clients that send their next
    Localize at once after a 429 / RESOURCE_EXHAUSTED, against the unloaded rate (cfg.storm_base_users clients)
    measured on the same server just before, and again just after (drift check). Per tool a fresh server with
    the default pool (2 workers, 8 waiting slots). Bounded in time (cfg.storm_s per phase) and in count
    (cfg.storm_max_requests per client)."""
    out = {"users": cfg.storm_users, "base_users": cfg.storm_base_users, "duration_s": cfg.storm_s,
           "max_requests_per_client": cfg.storm_max_requests}
    path = localize_path(intrinsics(cfg))
    phases = (("base", cfg.storm_base_users), ("storm", cfg.storm_users), ("after", cfg.storm_base_users))
    for tool in ("http", "grpc", "wrk"):
        with Server(cfg, f"storm-{tool}", True) as srv:
            warm_up(srv, True)
            runs = {}
            for phase, users in phases:
                label = f"storm-{tool}-{phase}"
                if tool == "wrk":
                    # One wrk thread drives every connection: its cap is the clients' caps together. wrk
                    # reports the configured duration even when the cap stopped it early, so that is flagged.
                    cap = cfg.storm_max_requests * users
                    r = wrk(cfg, srv, path, users, cfg.storm_s, label, env={"SCONE_WRK_MAX_REQUESTS": str(cap)})
                    r["stopped_by_cap"] = r["wrk"]["requests"] >= cap
                else:
                    lf, cls = (("locustfile_http.py", "LocalizeUser") if tool == "http"
                               else ("locustfile_grpc.py", "LocalizeGrpcUser"))
                    r = locust(cfg, srv, lf, [cls], users, cfg.storm_s, label,
                               env={"SCONE_LOAD_MAX_REQUESTS": str(cfg.storm_max_requests)})
                runs[phase] = strip(r)
                log(f"{label}: answered {answered_rps(r):.2f} req/s; " +
                    (str(r["wrk"]) if tool == "wrk" else report.one_line(r)))
                time.sleep(3)  # let refused and interrupted requests drain
            runs["ratio"] = round(answered_rps(runs["storm"]) / max(answered_rps(runs["base"]), 1e-9), 3)
            runs["ratio_after"] = round(answered_rps(runs["storm"]) / max(answered_rps(runs["after"]), 1e-9), 3)
            runs["alive_after"] = srv.alive()
            runs["metrics"] = srv.metrics()
            out[tool] = runs
            log(f"storm-{tool}: answered under storm / unloaded = {runs['ratio']} (against the run after: "
                f"{runs['ratio_after']})")
    return out


def mixed(cfg):
    """Keyframe writes to one map (HTTP multipart, durable acks) while other clients Localize against 'big'."""
    with Server(cfg, "mixed", True) as srv:
        warm_up(srv, True)
        st, body = http("POST", srv.url + "/v1/maps", json.dumps({"map_id": "writes"}).encode(), "application/json")
        if st not in (201, 409):
            raise SystemExit(f"mixed: creating map 'writes': HTTP {st}: {body[:200]!r}")
        r = locust(cfg, srv, "locustfile_http.py", ["LocalizeUser", "KeyframeWriter"], cfg.mixed_readers + 1,
                   cfg.mixed_s, "mixed", env={"SCONE_LOAD_WRITE_MAP": "writes", "SCONE_LOAD_WRITE_RATE": str(cfg.write_rate)})
        r["readers"] = cfg.mixed_readers
        r["duration_s"] = cfg.mixed_s
        r["write_rate_target"] = cfg.write_rate
        r["writes_map"] = json.loads(http("GET", srv.url + "/v1/maps/writes")[1])
        r["metrics"] = srv.metrics()
        log(f"mixed: {report.one_line(r)}")
        return strip(r)


def capacity(cfg, results):
    """Localize capacity (RPS) from this run's or a previous sweep, else a short measurement."""
    loc = (results.get("localize") or {}).get("locust_http") or {}
    best = max((v["by_name"].get("Localize", {}).get("rps", 0) for v in loc.values()), default=0)
    if best > 0:
        return best, "locust HTTP Localize sweep (best RPS)"
    with Server(cfg, "soak-capacity", True) as srv:
        warm_up(srv, True)
        r = locust(cfg, srv, "locustfile_http.py", ["LocalizeUser"], 4, min(cfg.point_s, 20), "soak-capacity")
    return r["by_name"]["Localize"]["rps"], "20 s closed loop, 4 users"


def soak(cfg, results):
    cap, source = capacity(cfg, results)
    rate = round(cfg.soak_share * cap, 2)
    cfg.attempts = min(cfg.attempts, 2)  # 10 minutes each
    with Server(cfg, "soak", True) as srv:
        warm_up(srv, True)
        r = locust(cfg, srv, "locustfile_http.py", ["LocalizeUser"], cfg.soak_users, cfg.soak_s, "soak",
                   env={"SCONE_LOAD_RATE": str(rate / cfg.soak_users)}, sample_s=5.0)
        r["capacity_rps"] = round(cap, 2)
        r["capacity_source"] = source
        r["target_rps"] = rate
        r["users"] = cfg.soak_users
        r["rss_series"] = [(s["t"], round(s["rss_kib"] / 1024, 1)) for s in r.pop("samples") if s["rss_kib"]]
        r["metrics"] = srv.metrics()
        log(f"soak: {report.one_line(r)}; RSS start {r['rss_start_mib']} end {r['rss_end_mib']} max {r['rss_max_mib']} MiB")
        return r


def settings(cfg):
    """Describe throughput with ONNX Runtime's threads split differently (wrk, light on the generator)."""
    variants = [
        ("defaults (intra_threads 2, sessions 1)", {}),
        ("intra_threads 1, sessions 2", {"SCONE_MODEL__INTRA_THREADS": "1", "SCONE_MODEL__SESSIONS": "2"}),
    ]
    out = {"variants": [], "duration_s": cfg.settings_s}
    for i, (name, env) in enumerate(variants):
        v = {"name": name, "env": env, "wrk": {}}
        with Server(cfg, f"settings-{i}", False, env) as srv:
            warm_up(srv, False)
            for n in cfg.settings_clients:
                r = wrk(cfg, srv, "/v1/describe", n, cfg.settings_s, f"settings-{i}-c{n}")
                v["wrk"][str(n)] = strip(r)
                log(f"settings {name} c{n}: {report.one_line(r)}")
                time.sleep(2)
            v["metrics"] = srv.metrics()
        out["variants"].append(v)
    return out


# ---------------------------------------------------------------------------------------------------------


def machine(cfg):
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next((line.split(":", 1)[1].strip() for line in lscpu.splitlines() if line.startswith("Model name")), "?")
    try:
        rev = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--", "src", "Cargo.toml"],
                               capture_output=True, text=True).stdout.strip() != ""
    except OSError:
        rev, dirty = "?", False
    st = os.stat(cfg.bin)
    return {
        "nproc": os.cpu_count(),
        "cpu": model,
        "mem_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "kernel": platform.release(),
        "os": next((line.split("=", 1)[1].strip().strip('"') for line in open("/etc/os-release") if line.startswith("PRETTY_NAME")), "?"),
        "git": rev + ("+dirty" if dirty else ""),
        "binary": cfg.bin,
        "binary_mtime": datetime.datetime.fromtimestamp(st.st_mtime).isoformat(timespec="seconds"),
        "reloc_fast_marker": os.path.exists("/tmp/scone-reloc-fast"),
        "pinning": f"server taskset -c {SERVER_CORE}, generators taskset -c {GEN_CORE}",
    }


def command(a):
    """The command line that reproduces this run (its SCONE_LOAD_* settings included)."""
    internal = {"SCONE_LOAD_CACHE", "SCONE_LOAD_MAP_DIR"}
    env = [f"{k}={v}" for k, v in sorted(os.environ.items()) if k.startswith("SCONE_LOAD_") and k not in internal]
    return " ".join(env + ["load-tests/run"] + (["--quick"] if a.quick else []) + a.scenarios)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scenarios", nargs="*", default=["all"])
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    names = SCENARIOS if a.scenarios in (["all"], []) else a.scenarios
    for n in names:
        if n not in SCENARIOS:
            raise SystemExit(f"unknown scenario {n!r}: pick from {', '.join(SCENARIOS)} or all")
    cfg = Config(a.quick)
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    os.makedirs(cfg.raw, exist_ok=True)
    os.makedirs(cfg.work, exist_ok=True)
    res_path = os.path.join(cfg.results, "results.json")
    results = json.load(open(res_path)) if os.path.exists(res_path) else {}
    results.setdefault("scenarios", {})
    try:
        for n in names:
            t0 = time.time()
            log(f"=== scenario {n}{' (quick)' if cfg.quick else ''}")
            scen = results["scenarios"]
            if n == "describe":
                r = sweep(cfg, "describe")
            elif n == "localize":
                r = sweep(cfg, "localize")
            elif n == "match":
                r = sweep(cfg, "match")
            elif n == "burst":
                r = burst(cfg)
            elif n == "storm":
                r = storm(cfg)
            elif n == "mixed":
                r = mixed(cfg)
            elif n == "soak":
                r = soak(cfg, scen)
            else:
                r = settings(cfg)
            r["machine"] = machine(cfg)
            r["command"] = command(a)
            r["quick"] = cfg.quick
            r["finished"] = datetime.datetime.now().isoformat(timespec="seconds")
            r["elapsed_s"] = round(time.time() - t0, 1)
            scen[n] = r
            results["updated"] = r["finished"]
            with open(res_path, "w") as f:
                json.dump(results, f, indent=1)
            with open(os.path.join(cfg.results, "summary.md"), "w") as f:
                f.write(report.markdown(results))
            log(f"=== scenario {n} done in {r['elapsed_s']} s")
    finally:
        for s in list(Server.live):
            s.stop()
    log(f"results: {res_path} and {os.path.join(cfg.results, 'summary.md')}")


if __name__ == "__main__":
    main()
