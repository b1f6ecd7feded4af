"""Shared by the locustfiles: inputs, pacing, and a raw recorder of every request.

Environment (set by load-tests/run):
  SCONE_LOAD_CACHE   cache with queries/, writes/ and grpc/ (from lib/prepare.py)
  SCONE_LOAD_MAP     map the Localize users query (default "big")
  SCONE_LOAD_WRITE_MAP  map the keyframe writer fills (default "writes")
  SCONE_LOAD_RATE    requests/s per user (locust constant_throughput); unset or 0: back-to-back (closed loop)
  SCONE_LOAD_WRITE_RATE  keyframes/s of the writer (default 2)
  SCONE_LOAD_MAX_REQUESTS  requests per user after which it stops (Localize users; unset or 0: no limit)
  SCONE_LOAD_RAW     JSON file receiving every request (end time, ms, name, outcome, localized) when locust
                     quits, for exact percentiles (locust's CSV rounds times above 100 ms to 10 ms)
"""

import json
import os
import time

from locust import constant, constant_throughput, events
from locust.exception import StopUser

CACHE = os.environ.get("SCONE_LOAD_CACHE", os.path.expanduser("~/.cache/scone/load-tests"))
MAP = os.environ.get("SCONE_LOAD_MAP", "big")
WRITE_MAP = os.environ.get("SCONE_LOAD_WRITE_MAP", "writes")


def _queries():
    m = json.load(open(os.path.join(CACHE, "queries", "manifest.json")))
    return m["intrinsics"], [open(f, "rb").read() for f in m["files"]]


INTRINSICS, JPEGS = _queries()
# MatchPair inputs: every pair of query frames (i < j), so baselines from neighbouring frames to the widest mix.
PAIRS = [(JPEGS[i], JPEGS[j]) for i in range(len(JPEGS)) for j in range(i + 1, len(JPEGS))]


def writes():
    m = json.load(open(os.path.join(CACHE, "writes", "manifest.json")))
    frames = []
    for f in m["frames"]:
        depth = open(f["depth"], "rb").read() if f["depth"] else None
        frames.append((open(f["image"], "rb").read(), depth, f["pose"]))
    return m["intrinsics"], frames


def wait_time():
    rate = float(os.environ.get("SCONE_LOAD_RATE", "0") or 0)
    return constant_throughput(rate) if rate > 0 else constant(0)


class RequestBudget:
    """At most $SCONE_LOAD_MAX_REQUESTS requests of one user (a storm stays bounded in count, not only in time)."""

    def __init__(self):
        self.left = int(os.environ.get("SCONE_LOAD_MAX_REQUESTS", "0") or 0) or None

    def spend(self):
        if self.left is not None:
            if self.left <= 0:
                raise StopUser()
            self.left -= 1


def write_wait_time():
    return constant_throughput(float(os.environ.get("SCONE_LOAD_WRITE_RATE", "2")))


# Every request: (end time s, response time ms, name, outcome, localized) with outcome "ok", "rejected" (429 /
# RESOURCE_EXHAUSTED) or an error string; localized is true/false for a Localize answer (for MatchPair: whether
# a relative pose came back), else null.
_RAW = []


@events.request.add_listener
def _record(request_type, name, response_time, response_length, exception, context, **_kw):
    if exception is None:
        outcome = "ok"
    elif (context or {}).get("rejected"):
        outcome = "rejected"
    else:
        outcome = str(exception)[:120]
    _RAW.append((time.time(), round(response_time, 3), name, outcome, (context or {}).get("localized")))


@events.quitting.add_listener
def _dump(environment, **_kw):
    path = os.environ.get("SCONE_LOAD_RAW")
    if path:
        with open(path, "w") as f:
            json.dump({"requests": _RAW}, f)
