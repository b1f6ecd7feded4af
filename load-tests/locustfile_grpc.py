"""gRPC users for scone: locust Users calling the grpcio stubs and firing locust request events, so locust's
stats, CSV and the raw recorder include them like HTTP requests.

Stubs are generated from proto/scone/v1/scone.proto by lib/prepare.py into $SCONE_LOAD_CACHE/grpc (not
committed). Target: $SCONE_LOAD_GRPC (host:port). Pick the users on the command line (DescribeGrpcUser,
LocalizeGrpcUser, MatchPairGrpcUser). RESOURCE_EXHAUSTED is recorded under "<name> RESOURCE_EXHAUSTED" (outcome "rejected").
Each user has its own channel and its own HTTP/2 connection (local subchannel pool), like one device each.
"""

import itertools
import os
import sys
import time

import gevent
import grpc
import grpc.experimental.gevent as grpc_gevent
from locust import User, task

import common

grpc_gevent.init_gevent()  # grpcio's completion queue cooperating with locust's gevent loop
# In gevent mode every blocking call waits in a thread of gevent's hub threadpool, 10 threads by default: with
# more users than that, calls queue in the client (measured: RESOURCE_EXHAUSTED answers took ~260 ms instead
# of ~5 ms with 48 users). One thread per user, with room to spare.
gevent.get_hub().threadpool.maxsize = 1024

sys.path.insert(0, os.path.join(common.CACHE, "grpc"))
from scone.v1 import scone_pb2, scone_pb2_grpc  # noqa: E402

TARGET = os.environ.get("SCONE_LOAD_GRPC", "127.0.0.1:50151")
CHANNEL_OPTIONS = [
    ("grpc.use_local_subchannel_pool", 1),
    ("grpc.max_receive_message_length", 64 << 20),
    ("grpc.max_send_message_length", 64 << 20),
]


class _GrpcUser(User):
    abstract = True
    wait_time = common.wait_time()

    def on_start(self):
        self.channel = grpc.insecure_channel(TARGET, options=CHANNEL_OPTIONS)
        grpc.channel_ready_future(self.channel).result(timeout=10)
        self.matching = scone_pb2_grpc.MatchingStub(self.channel)
        i = common.INTRINSICS
        intr = scone_pb2.Intrinsics(fx=i["fx"], fy=i["fy"], cx=i["cx"], cy=i["cy"], width=i["width"], height=i["height"])
        self.frames = itertools.cycle([scone_pb2.Frame(image=scone_pb2.Image(data=j), intrinsics=intr)
                                       for j in common.JPEGS])
        self.pairs = itertools.cycle([(scone_pb2.Frame(image=scone_pb2.Image(data=a), intrinsics=intr),
                                       scone_pb2.Frame(image=scone_pb2.Image(data=b), intrinsics=intr))
                                      for a, b in common.PAIRS])

    def on_stop(self):
        self.channel.close()

    def _call(self, name, method, request, localize=False, posed=False):
        context = {}
        exc = None
        length = 0
        t0 = time.perf_counter()
        try:
            resp = method(request, timeout=60)
            length = resp.ByteSize()
            if localize:
                context["localized"] = resp.localized
            elif posed:
                context["localized"] = resp.HasField("pose")
        except grpc.RpcError as e:
            exc = RuntimeError(f"{e.code().name}: {e.details()}")  # str(e) has a timestamp: one failure row each
            if e.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
                name = f"{name} RESOURCE_EXHAUSTED"
                context["rejected"] = True
        self.environment.events.request.fire(request_type="grpc", name=name,
                                             response_time=(time.perf_counter() - t0) * 1000,
                                             response_length=length, exception=exc, context=context)


class DescribeGrpcUser(_GrpcUser):
    @task
    def describe(self):
        self._call("Describe", self.matching.Describe, scone_pb2.DescribeRequest(frame=next(self.frames)))


class LocalizeGrpcUser(_GrpcUser):
    """RESOURCE_EXHAUSTED is followed by the next call at once; $SCONE_LOAD_MAX_REQUESTS bounds a user's calls."""

    def on_start(self):
        super().on_start()
        self.budget = common.RequestBudget()

    @task
    def localize(self):
        self.budget.spend()
        self._call("Localize", self.matching.Localize,
                   scone_pb2.LocalizeRequest(map_id=common.MAP, frame=next(self.frames)), localize=True)


class MatchPairGrpcUser(_GrpcUser):
    @task
    def match_pair(self):
        a, b = next(self.pairs)
        self._call("MatchPair", self.matching.MatchPair, scone_pb2.MatchPairRequest(frame1=a, frame2=b), posed=True)
