"""Figures from raw request records and /metrics, and the markdown summary of results.json."""

import os
import re

SUFFIXES = (" 429", " RESOURCE_EXHAUSTED")


def pct(sorted_vals, p):
    """Percentile with linear interpolation between closest ranks (numpy's default)."""
    if not sorted_vals:
        return None
    k = (len(sorted_vals) - 1) * p / 100
    lo = int(k)
    hi = min(lo + 1, len(sorted_vals) - 1)
    return sorted_vals[lo] + (sorted_vals[hi] - sorted_vals[lo]) * (k - lo)


def r1(x):
    return None if x is None else round(x, 1)


def summarise_raw(requests):
    """Per operation (rejections folded back into their operation): counts, RPS and latency percentiles.

    requests: [end_time_s, response_ms, name, outcome, localized]. RPS counts answered requests (outcome ok)
    over the span from the first request's start to the last one's end."""
    if not requests:
        return {}
    start = min(t - ms / 1000 for t, ms, *_ in requests)
    end = max(t for t, *_ in requests)
    span = max(end - start, 1e-9)
    ops = {}
    for t, ms, name, outcome, localized in requests:
        base = name
        for s in SUFFIXES:
            if base.endswith(s):
                base = base[: -len(s)]
        o = ops.setdefault(base, {"ok": [], "rejected": [], "errors": {}, "localized": 0, "answers": 0})
        if outcome == "ok":
            o["ok"].append(ms)
            if localized is not None:
                o["answers"] += 1
                o["localized"] += bool(localized)
        elif outcome == "rejected":
            o["rejected"].append(ms)
        else:
            o["errors"][outcome] = o["errors"].get(outcome, 0) + 1
    out = {}
    for base, o in ops.items():
        ok, rej = sorted(o["ok"]), sorted(o["rejected"])
        nerr = sum(o["errors"].values())
        total = len(ok) + len(rej) + nerr
        out[base] = {
            "total": total,
            "ok": len(ok),
            "rejected": len(rej),
            "errors": nerr,
            "error_rate": round((len(rej) + nerr) / total, 4),
            "rejected_share": round(len(rej) / total, 4),
            "span_s": round(span, 2),
            "rps": round(len(ok) / span, 2),
            "attempts_per_s": round(total / span, 2),
            "p50_ms": r1(pct(ok, 50)),
            "p95_ms": r1(pct(ok, 95)),
            "p99_ms": r1(pct(ok, 99)),
            "max_ms": r1(ok[-1] if ok else None),
            "mean_ms": r1(sum(ok) / len(ok) if ok else None),
            "rejected_p50_ms": r1(pct(rej, 50)),
            "rejected_p95_ms": r1(pct(rej, 95)),
            "rejected_p99_ms": r1(pct(rej, 99)),
            "localized_share": round(o["localized"] / o["answers"], 3) if o["answers"] else None,
            "error_kinds": dict(sorted(o["errors"].items(), key=lambda kv: -kv[1])[:5]),
        }
    return out


_SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(?:[^"}]|"[^"]*")*\})?\s+(\S+)')  # label values may hold braces


def parse_metrics(text):
    """The figures of interest from scone's /metrics: pool rejections and queue, mean time per stage."""
    stages = {}
    out = {"pool_rejected": 0.0, "requests": {}}
    for line in text.splitlines():
        m = _SAMPLE.match(line)
        if not m:
            continue
        name, labels, value = m.group(1), m.group(2) or "", m.group(3)
        try:
            v = float(value)
        except ValueError:
            continue
        lab = dict(re.findall(r'(\w+)="([^"]*)"', labels))
        if name == "scone_pool_rejected_total":
            out["pool_rejected"] += v
        elif name.startswith("scone_stage_duration_seconds_sum"):
            stages.setdefault(lab.get("stage", "?"), [0.0, 0.0])[0] += v
        elif name.startswith("scone_stage_duration_seconds_count"):
            stages.setdefault(lab.get("stage", "?"), [0.0, 0.0])[1] += v
        elif name.startswith("scone_requests_total"):
            key = f"{lab.get('transport', '')} {lab.get('route') or lab.get('method') or lab.get('operation', '')} {lab.get('code') or lab.get('status', '')}".strip()
            out["requests"][key] = out["requests"].get(key, 0) + v
    out["stage_mean_ms"] = {s: round(1000 * a / c, 2) for s, (a, c) in stages.items() if c}
    out["stage_count"] = {s: int(c) for s, (a, c) in stages.items()}
    return out


def _op(r):
    """(rps, p50, p95, p99, error rate) of a locust or wrk run."""
    if "wrk" in r:
        w = r["wrk"]
        err = (w["non2xx"] + w["socket_errors"]) / max(w["requests"], 1)
        return w["rps"], w["p50_ms"], w["p95_ms"], w["p99_ms"], err
    (o,) = [v for k, v in r["by_name"].items() if k != "AddKeyframe"][:1] or [None]
    return o["rps"], o["p50_ms"], o["p95_ms"], o["p99_ms"], o["error_rate"]


def one_line(r):
    rps, p50, p95, p99, err = _op(r)
    return (f"{rps:.1f} req/s, p50 {_ms(p50)} p95 {_ms(p95)} p99 {_ms(p99)} ms, errors {100 * err:.1f} %, "
            f"generator CPU {r['gen_cpu_pct']} %, server CPU {r['server_cpu_pct']} %, other CPU {r.get('other_cpu_pct')} %")


def _ms(x):
    if x is None:
        return "-"
    return f"{x:.0f}" if x >= 100 else f"{x:.1f}"


def _rounds(r):
    return f"{r['rss_before_mib']} -> " + ", ".join(str(x) for x in r.get("rss_after_rounds_mib", [r["rss_after_mib"]]))


def _other(r):
    v = r.get("other_cpu_pct")
    return "-" if v is None else f"{v:.0f} %"


def _pct(x):
    return "-" if x is None else f"{100 * x:.1f} %"


TOOLS = [("locust_http", "locust HTTP"), ("locust_grpc", "locust gRPC"), ("wrk", "wrk HTTP")]


def _sweep_table(s):
    lines = ["| tool | clients | req/s | p50 ms | p95 ms | p99 ms | errors | generator CPU | server CPU | other CPU |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key, label in TOOLS:
        for n, r in sorted((s.get(key) or {}).items(), key=lambda kv: int(kv[0])):
            rps, p50, p95, p99, err = _op(r)
            lines.append(f"| {label} | {n} | {rps:.1f} | {_ms(p50)} | {_ms(p95)} | {_ms(p99)} | {_pct(err)} | "
                         f"{r['gen_cpu_pct']:.0f} % | {r['server_cpu_pct']:.0f} % | {_other(r)} |")
    return lines


def _stages(s, key):
    m = s.get(key) or {}
    st = m.get("stage_mean_ms") or {}
    if not st:
        return []
    return ["", "Mean server time per stage (from `/metrics`, " + key.replace("_metrics", "").replace("_", " ") + " server): " +
            ", ".join(f"{k} {v} ms" for k, v in sorted(st.items()))]


def _header(s):
    m = s.get("machine", {})
    d = s.get("durations_s")
    per_level = f"locust {d['locust']} s and wrk {d['wrk']} s per level, " if d else ""
    cmd = f" Command: `{s['command']}`." if s.get("command") else ""
    binary = os.path.basename(m.get("binary", "?"))
    return (f"_{s.get('finished', '?')}, {'QUICK smoke run, ' if s.get('quick') else ''}{per_level}binary {binary} built "
            f"{m.get('binary_mtime', '?')}, git {m.get('git', '?')} (of the load tests), took {s.get('elapsed_s', '?')} s.{cmd}_")


def markdown(results):
    sc = results.get("scenarios", {})
    any_s = next(iter(sc.values()), {})
    m = any_s.get("machine", {})
    out = ["# Load-test results", "",
           "Generated by `load-tests/run` (see `load-tests/README.md`); every figure comes from "
           "`load-tests/results/results.json`.", "",
           f"Machine: {m.get('nproc', '?')} cores, {m.get('cpu', '?')}, {m.get('mem_gib', '?')} GiB, "
           f"{m.get('os', '?')} (kernel {m.get('kernel', '?')}), shared. Server pinned to one core and every load "
           f"generator to the other ({m.get('pinning', '?')}); loopback only. Server settings are the defaults "
           "(2 worker threads, queue 8, ONNX Runtime 2 intra-op threads, 1 session) unless a table says otherwise.",
           "",
           "Columns: req/s = answered requests per second (2xx); p50/p95/p99 = latency of answered requests, "
           "measured by the client; errors = share of requests not answered with 2xx (429 / RESOURCE_EXHAUSTED "
           "included); generator CPU = the load generator's own CPU time / wall time (100 % = its whole core); "
           "server CPU = the server's (100 % = its whole core); other CPU = what every other process on the machine "
           "used meanwhile (a build or test run elsewhere: figures with more than a few % are distorted).", ""]
    for op, title in (("describe", "Describe (640x480 JPEG, the model's extraction: 2,000 keypoints for the embedded one)"),
                      ("localize", "Localize (640x480 JPEG against a map of ~100k observations)"),
                      ("match", "MatchPair (two 640x480 JPEGs: every pair of the scene's frames in turn)")):
        s = sc.get(op)
        if not s:
            continue
        out += [f"## {title}", "", _header(s), ""]
        if op == "localize" and s.get("map"):
            mp = s["map"]
            out += [f"Map: {mp.get('keyframes')} keyframes, {mp.get('landmarks')} landmarks, "
                    f"{mp.get('observations')} observations, approximate (HNSW) index: {mp.get('approximate_index')}.", ""]
        out += _sweep_table(s)
        loc = [r["by_name"]["Localize"].get("localized_share") for k in ("locust_http", "locust_grpc")
               for r in (s.get(k) or {}).values() if "Localize" in r.get("by_name", {})]
        if loc and None not in loc:
            out += ["", f"Queries localised: {100 * min(loc):.0f}-{100 * max(loc):.0f} % of answers."]
        posed = [r["by_name"]["MatchPair"].get("localized_share") for k in ("locust_http", "locust_grpc")
                 for r in (s.get(k) or {}).values() if "MatchPair" in r.get("by_name", {})]
        if posed and None not in posed:
            out += ["", f"Answers with a relative pose: {100 * min(posed):.0f}-{100 * max(posed):.0f} %."]
        for k, _ in TOOLS:
            out += _stages(s, k + "_metrics")
        out.append("")
    b = sc.get("burst")
    if b:
        out += ["## Burst above capacity", "", _header(b), "",
                f"{b['users']} closed-loop clients (no pause between requests, Retry-After ignored) send Localize for "
                f"{b['duration_s']} s to a server with the default 2 workers and 8 waiting slots; {b.get('rounds', 1)} such "
                "bursts in a row against one server per tool (figures: the first; RSS: after each).", "",
                "| transport | answered req/s | answered p50 / p99 ms | refused share | refused p50 / p99 ms | other errors | "
                "alive after | RSS before -> after each round MiB | generator CPU |",
                "|---|---|---|---|---|---|---|---|---|"]
        for t, label in (("http", "HTTP (429)"), ("grpc", "gRPC (RESOURCE_EXHAUSTED)")):
            r = b.get(t)
            if not r:
                continue
            o = r["by_name"].get("Localize", {})
            out.append(f"| {label} | {o.get('rps', 0):.1f} | {_ms(o.get('p50_ms'))} / {_ms(o.get('p99_ms'))} | "
                       f"{_pct(o.get('rejected_share'))} | {_ms(o.get('rejected_p50_ms'))} / {_ms(o.get('rejected_p99_ms'))} | "
                       f"{o.get('errors', 0)} | {'yes' if r.get('alive_after') else 'NO'} | "
                       f"{_rounds(r)} | {r['gen_cpu_pct']:.0f} % |")
        r = b.get("wrk")
        if r:
            w = r["wrk"]
            ans = w["requests"] - w["non2xx"]
            out.append(f"| wrk HTTP (429) | {ans / w['duration_s']:.1f} | - | {_pct(w['non2xx'] / max(w['requests'], 1))} | "
                       f"{_ms(w['p50_ms'])} / {_ms(w['p99_ms'])} (all responses) | {w['socket_errors']} | "
                       f"{'yes' if r.get('alive_after') else 'NO'} | "
                       f"{_rounds(r)} | {r['gen_cpu_pct']:.0f} % |")
        out += ["", "Attempts per second (answered + refused): " + ", ".join(
            f"{t} {v}" for t, v in (("HTTP", (b.get("http") or {}).get("by_name", {}).get("Localize", {}).get("attempts_per_s")),
                                    ("gRPC", (b.get("grpc") or {}).get("by_name", {}).get("Localize", {}).get("attempts_per_s")),
                                    ("wrk", round(b["wrk"]["wrk"]["rps"], 1) if b.get("wrk") else None)) if v is not None) + "."]
        out.append("")
    stm = sc.get("storm")
    if stm:
        out += ["## Storm: clients that do not back off", "", _header(stm), "",
                f"{stm['users']} closed-loop clients send Localize and, on 429 / RESOURCE_EXHAUSTED, the next request at "
                f"once, for {stm['duration_s']} s (at most {stm['max_requests_per_client']} requests each), against "
                f"{stm['base_users']} clients just before and just after on the same server (default pool: 2 workers, 8 "
                "waiting slots). Ratio = answered req/s under the storm / answered req/s of the run before.", "",
                f"| tool | {stm['base_users']} clients: req/s | {stm['users']} clients: answered req/s | ratio | refused/s | "
                "refused p50 / p99 ms | other errors | after: req/s | generator CPU (storm) | server CPU (storm) | other CPU |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        for t, label in (("http", "locust HTTP (429)"), ("grpc", "locust gRPC (RESOURCE_EXHAUSTED)"), ("wrk", "wrk HTTP (429)")):
            r = stm.get(t)
            if not r:
                continue
            rates = []
            for phase in ("base", "storm", "after"):
                x = r[phase]
                if "wrk" in x:
                    w = x["wrk"]
                    rates.append((w["requests"] - w["non2xx"] - w["socket_errors"]) / w["duration_s"])
                else:
                    rates.append(x["by_name"].get("Localize", {}).get("rps", 0.0))
            x = r["storm"]
            if "wrk" in x:
                w = x["wrk"]
                refused = f"{w['non2xx'] / w['duration_s']:.0f}" + (" (stopped by the cap: not comparable)" if x.get("stopped_by_cap") else "")
                lat = f"{_ms(w['p50_ms'])} / {_ms(w['p99_ms'])} (all responses)"
                errors = w["socket_errors"]
            else:
                o = x["by_name"].get("Localize", {})
                refused = f"{o.get('rejected', 0) / max(o.get('span_s', 1), 1e-9):.0f}"
                lat = f"{_ms(o.get('rejected_p50_ms'))} / {_ms(o.get('rejected_p99_ms'))}"
                errors = o.get("errors", 0)
            out.append(f"| {label} | {rates[0]:.2f} | {rates[1]:.2f} | {r['ratio']:.2f} | {refused} | {lat} | {errors} | "
                       f"{rates[2]:.2f} | {x['gen_cpu_pct']:.0f} % | {x['server_cpu_pct']:.0f} % | {_other(x)} |")
        out.append("")
    mx = sc.get("mixed")
    if mx:
        out += ["## Mixed: keyframe writes while others localise", "", _header(mx), "",
                f"One writer adds keyframes (HTTP multipart, image + depth, target {mx['write_rate_target']}/s, each "
                f"acknowledged once durable) to map `writes` while {mx['readers']} closed-loop clients Localize against "
                f"the ~100k-observation map, for {mx.get('duration_s', '?')} s.", "",
                "| operation | req/s | p50 ms | p95 ms | p99 ms | errors |", "|---|---|---|---|---|---|"]
        for name in ("Localize", "AddKeyframe"):
            o = mx["by_name"].get(name)
            if o:
                out.append(f"| {name} | {o['rps']:.2f} | {_ms(o['p50_ms'])} | {_ms(o['p95_ms'])} | {_ms(o['p99_ms'])} | "
                           f"{_pct(o['error_rate'])} |")
        wm = mx.get("writes_map") or {}
        out += ["", f"Map `writes` afterwards: {wm.get('keyframes')} keyframes, {wm.get('observations')} observations. "
                f"Generator CPU {mx['gen_cpu_pct']:.0f} %, server CPU {mx['server_cpu_pct']:.0f} %, other CPU {_other(mx)}, RSS "
                f"{mx['rss_start_mib']} -> {mx['rss_end_mib']} MiB."]
        st = (mx.get("metrics") or {}).get("stage_mean_ms") or {}
        if st:
            out.append("Mean server time per stage: " + ", ".join(f"{k} {v} ms" for k, v in sorted(st.items())) + ".")
        loc = (sc.get("localize") or {}).get("locust_http", {}).get(str(mx["readers"]))
        if loc:
            o = loc["by_name"]["Localize"]
            out.append(f"Localize alone at {mx['readers']} clients (sweep above): {o['rps']:.1f} req/s, "
                       f"p50 {_ms(o['p50_ms'])} ms, p95 {_ms(o['p95_ms'])} ms.")
        out.append("")
    so = sc.get("soak")
    if so:
        o = so["by_name"].get("Localize", {})
        series = so.get("rss_series") or []
        third = len(series) // 3 or 1
        first = [v for _, v in series[:third]]
        last = [v for _, v in series[-third:]]
        out += [f"## Soak: steady Localize for {so['wall_s'] / 60:.1f} minutes", "", _header(so), "",
                f"{so['users']} clients at a constant {so['target_rps']} req/s in total "
                f"({int(round(100 * so['target_rps'] / so['capacity_rps']))} % of the measured capacity "
                f"{so['capacity_rps']} req/s, {so['capacity_source']}); server RSS sampled every 5 s.", "",
                "| achieved req/s | p50 ms | p95 ms | p99 ms | errors | RSS start MiB | RSS end MiB | RSS max MiB | "
                "mean RSS first third -> last third MiB | generator CPU | server CPU | other CPU |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|",
                f"| {o.get('rps', 0):.2f} | {_ms(o.get('p50_ms'))} | {_ms(o.get('p95_ms'))} | {_ms(o.get('p99_ms'))} | "
                f"{_pct(o.get('error_rate'))} | {so['rss_start_mib']} | {so['rss_end_mib']} | {so['rss_max_mib']} | "
                f"{sum(first) / len(first):.1f} -> {sum(last) / len(last):.1f} | {so['gen_cpu_pct']:.0f} % | "
                f"{so['server_cpu_pct']:.0f} % | {_other(so)} |", ""]
    st = sc.get("settings")
    if st:
        out += ["## ONNX Runtime threading: Describe with wrk", "", _header(st), "",
                f"wrk, {st.get('duration_s', '?')} s per level, one fresh server per setting.", "",
                "| settings | clients | req/s | p50 ms | p95 ms | p99 ms | errors | server CPU | other CPU |", "|---|---|---|---|---|---|---|---|---|"]
        for v in st["variants"]:
            for n, r in sorted(v["wrk"].items(), key=lambda kv: int(kv[0])):
                rps, p50, p95, p99, err = _op(r)
                out.append(f"| {v['name']} | {n} | {rps:.1f} | {_ms(p50)} | {_ms(p95)} | {_ms(p99)} | {_pct(err)} | "
                           f"{r['server_cpu_pct']:.0f} % | {_other(r)} |")
        out.append("")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    # Re-renders summary.md from results.json: python lib/report.py [load-tests/results]
    import json
    import os
    import sys

    d = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "results")
    with open(os.path.join(d, "summary.md"), "w") as f:
        f.write(markdown(json.load(open(os.path.join(d, "results.json")))))
