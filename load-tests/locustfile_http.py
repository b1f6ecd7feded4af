"""HTTP users for scone (locust FastHttpUser: geventhttpclient, the lighter of locust's two clients).

Pick the users on the command line, e.g. `locust -f locustfile_http.py --headless --host http://127.0.0.1:18151
--users 4 --spawn-rate 4 --run-time 60s DescribeUser`. The run script sets the environment (see common.py).

- DescribeUser: POST /v1/describe with a 640x480 JPEG (raw body), cycling over the scene's frames.
- LocalizeUser: POST /v1/maps/$SCONE_LOAD_MAP/localize?fx=..&fy=..&cx=..&cy=.. with the same JPEGs; a 429 is
  followed by the next request at once (no back-off), and $SCONE_LOAD_MAX_REQUESTS bounds a user's requests.
- MatchUser: POST /v1/match, multipart (request JSON with both frames' intrinsics, image1, image2), cycling over
  every pair of the scene's frames; "localized" in the raw records means a relative pose came back.
- KeyframeWriter (fixed_count 1): multipart POST /v1/maps/$SCONE_LOAD_WRITE_MAP/keyframes (image, depth, pose)
  at $SCONE_LOAD_WRITE_RATE keyframes/s; each acknowledgement means the write is durable.

A 429 is recorded under "<name> 429" (outcome "rejected") so its latency is reported apart from the answers.
"""

import itertools
import json

from locust import task
from locust.contrib.fasthttp import FastHttpUser

import common

_kf_ids = itertools.count(1)


def _check(r, name, localize=False, posed=False):
    if r.status_code == 429:
        r.request_meta["name"] = f"{name} 429"
        r.request_meta["context"] = {"rejected": True}
        r.failure("429 Too Many Requests")
    elif r.status_code != 200:
        r.failure(f"HTTP {r.status_code}: {(r.text or '')[:80]}")
    elif localize or posed:
        try:
            j = r.json()
            r.request_meta["context"] = {"localized": bool(j.get("localized")) if localize else j.get("pose") is not None}
        except ValueError:
            r.failure("bad JSON")
        else:
            r.success()
    else:
        r.success()


class _HttpUser(FastHttpUser):
    abstract = True
    wait_time = common.wait_time()
    network_timeout = 60.0
    connection_timeout = 10.0


class DescribeUser(_HttpUser):

    def on_start(self):
        self.images = itertools.cycle(common.JPEGS)

    @task
    def describe(self):
        with self.client.post("/v1/describe", data=next(self.images), headers={"Content-Type": "image/jpeg"},
                              name="Describe", catch_response=True) as r:
            _check(r, "Describe")


class LocalizeUser(_HttpUser):

    def on_start(self):
        self.images = itertools.cycle(common.JPEGS)
        i = common.INTRINSICS
        self.path = f"/v1/maps/{common.MAP}/localize?fx={i['fx']}&fy={i['fy']}&cx={i['cx']}&cy={i['cy']}"
        self.budget = common.RequestBudget()

    @task
    def localize(self):
        self.budget.spend()
        with self.client.post(self.path, data=next(self.images), headers={"Content-Type": "image/jpeg"},
                              name="Localize", catch_response=True) as r:
            _check(r, "Localize", localize=True)


class MatchUser(_HttpUser):

    def on_start(self):
        self.pairs = itertools.cycle(common.PAIRS)
        i = common.INTRINSICS
        intr = {"fx": i["fx"], "fy": i["fy"], "cx": i["cx"], "cy": i["cy"]}
        self.request = json.dumps({"frame1": {"intrinsics": intr}, "frame2": {"intrinsics": intr}}).encode()

    @task
    def match(self):
        a, b = next(self.pairs)
        body, ctype = _multipart([("request", "application/json", self.request), ("image1", "image/jpeg", a),
                                  ("image2", "image/jpeg", b)])
        with self.client.post("/v1/match", data=body, headers={"Content-Type": ctype}, name="MatchPair",
                              catch_response=True) as r:
            _check(r, "MatchPair", posed=True)


class KeyframeWriter(_HttpUser):
    fixed_count = 1
    wait_time = common.write_wait_time()

    def on_start(self):
        self.intrinsics, frames = common.writes()
        self.frames = itertools.cycle(frames)

    @task
    def add_keyframe(self):
        image, depth, pose = next(self.frames)
        i = self.intrinsics
        request = {"keyframe_id": next(_kf_ids), "pose": pose,
                   "intrinsics": {"fx": i["fx"], "fy": i["fy"], "cx": i["cx"], "cy": i["cy"]}}
        body, ctype = _multipart([("request", "application/json", json.dumps(request).encode()),
                                  ("image", "image/png", image)] + ([("depth", "image/png", depth)] if depth else []))
        with self.client.post(f"/v1/maps/{common.WRITE_MAP}/keyframes", data=body,
                              headers={"Content-Type": ctype}, name="AddKeyframe", catch_response=True) as r:
            _check(r, "AddKeyframe")


def _multipart(parts):
    boundary = "scone-load-boundary-7d1f0c"
    out = bytearray()
    for name, ctype, data in parts:
        out += (f"--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}\"\r\n"
                f"Content-Type: {ctype}\r\n\r\n").encode()
        out += data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"
