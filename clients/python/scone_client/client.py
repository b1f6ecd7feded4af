"""gRPC calls of the scone service with frames built from images or from the client contract's keypoints."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import cv2
import grpc
import numpy as np

from scone_client._proto.scone.v1 import scone_pb2 as pb
from scone_client._proto.scone.v1 import scone_pb2_grpc as pb_grpc
from scone_client.contract import DESCRIPTOR_BYTES, RING_SAMPLES, ExtractorConfig, Features

__all__ = [
    "Camera",
    "SconeClient",
    "covariance",
    "features_from_describe",
    "image_frame",
    "keypoint_frame",
    "keypoint_set",
    "pb",
]


@dataclass(frozen=True)
class Camera:
    """Intrinsics, pixels ((0, 0) is the centre of the top-left pixel), with an optional lens model.

    ``fx = fy = 0`` leaves the focal length unknown: Localize then estimates it with the pose (every other call
    refuses it). ``cx = cy = 0`` is the image centre. ``distortion_model`` is ``pb.DISTORTION_MODEL_*`` with
    ``distortion`` its coefficients in OpenCV's order (radial-tangential k1, k2, p1, p2[, k3[, k4, k5, k6]];
    fisheye k1..k4): the server undistorts the keypoint positions."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion_model: int = pb.DISTORTION_MODEL_NONE
    distortion: tuple[float, ...] = field(default=())

    def to_proto(self) -> pb.Intrinsics:
        return pb.Intrinsics(
            fx=self.fx,
            fy=self.fy,
            cx=self.cx,
            cy=self.cy,
            width=self.width,
            height=self.height,
            distortion_model=self.distortion_model,
            distortion=list(self.distortion),
        )


def covariance(response: pb.LocalizeResponse) -> np.ndarray | None:
    """The 6x6 pose covariance of a Localize answer (translation, then rotation vector; in the request's pose
    convention), or None when it has none."""
    if len(response.covariance) != 36:
        return None
    return np.asarray(response.covariance, dtype=np.float64).reshape(6, 6)


def keypoint_set(features: Features, model_id: str = "") -> pb.KeypointSet:
    """A KeypointSet message from extracted features (descriptors as 64 bytes per keypoint, in order; the ring
    contexts, 113 bytes per keypoint, when the features carry them)."""
    desc = np.ascontiguousarray(features.descriptors, np.uint8)
    if desc.shape != (len(features), DESCRIPTOR_BYTES):
        raise ValueError(f"descriptors are {desc.shape}, expected ({len(features)}, {DESCRIPTOR_BYTES})")
    keypoints = [
        pb.Keypoint(x=float(x), y=float(y), size=float(s), angle=float(a), response=float(r), octave=int(o))
        for (x, y), s, a, r, o in zip(
            features.xy, features.size, features.angle, features.response, features.octave, strict=True
        )
    ]
    context = b""
    if features.context is not None:
        ctx = np.ascontiguousarray(features.context, np.uint8)
        if ctx.shape != (len(features), RING_SAMPLES):
            raise ValueError(f"ring contexts are {ctx.shape}, expected ({len(features)}, {RING_SAMPLES})")
        context = ctx.tobytes()
    return pb.KeypointSet(
        keypoints=keypoints,
        descriptors=desc.tobytes(),
        width=features.width,
        height=features.height,
        model_id=model_id,
        context=context,
    )


def keypoint_frame(features: Features, camera: Camera | None = None, model_id: str = "") -> pb.Frame:
    """A Frame carrying the client's keypoints instead of an image."""
    frame = pb.Frame(keypoints=keypoint_set(features, model_id))
    if camera is not None:
        frame.intrinsics.CopyFrom(camera.to_proto())
    return frame


def image_frame(data: bytes, camera: Camera | None = None) -> pb.Frame:
    """A Frame carrying an encoded PNG or JPEG (the server extracts the keypoints)."""
    frame = pb.Frame(image=pb.Image(data=data))
    if camera is not None:
        frame.intrinsics.CopyFrom(camera.to_proto())
    return frame


class SconeClient:
    """Both services of scone.v1 on one channel. ``api_key`` is sent as ``authorization: Bearer <key>``."""

    def __init__(self, target: str, *, api_key: str | None = None, timeout: float = 30.0) -> None:
        self.channel = grpc.insecure_channel(target)
        self.maps = pb_grpc.MapsStub(self.channel)
        self.matching = pb_grpc.MatchingStub(self.channel)
        self.timeout = timeout
        self._metadata = (("authorization", f"Bearer {api_key}"),) if api_key else ()

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> SconeClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _call(self, method, request):
        return method(request, timeout=self.timeout, metadata=self._metadata)

    # -- Matching ---------------------------------------------------------------------------------------

    def describe(self, frame: pb.Frame) -> pb.DescribeResponse:
        return self._call(self.matching.Describe, pb.DescribeRequest(frame=frame))

    def localize(
        self,
        map_id: str,
        frame: pb.Frame,
        prior: pb.PosePrior | None = None,
        *,
        pose_convention: int = pb.POSE_CONVENTION_OPENCV_CAMERA_TO_WORLD,
    ) -> pb.LocalizeResponse:
        """Localizes a frame; the answer's pose is in ``pose_convention`` (e.g. ``POSE_CONVENTION_OPENGL_CAMERA_TO_WORLD``
        for ARKit / ARCore)."""
        request = pb.LocalizeRequest(map_id=map_id, frame=frame, pose_convention=pose_convention)
        if prior is not None:
            request.prior.CopyFrom(prior)
        return self._call(self.matching.Localize, request)

    def localize_track(
        self,
        map_id: str,
        frames: list[tuple[pb.Frame, pb.Pose]],
        *,
        estimate_scale: bool = False,
        prior: pb.PosePrior | None = None,
        pose_convention: int = pb.POSE_CONVENTION_OPENCV_CAMERA_TO_WORLD,
        tracker_error: tuple[float, float] | None = None,
    ) -> pb.LocalizeTrackResponse:
        """Localizes a short track: 2-10 (frame, pose) pairs, each pose the frame's in the track's own frame (what a
        phone's tracker or a rig's extrinsics give), in ``pose_convention``. ``estimate_scale`` when the track's
        units are not the map's. ``tracker_error`` is how far the poses may be off, ``(translation_share,
        degrees_per_frame)``: None for a phone's tracker (the server's 1 % and 0.5 degrees), ``(0, 0)`` for a rig;
        it widens the answer's covariance. The answer holds the track-to-map transform and every frame's pose in
        the map."""
        request = pb.LocalizeTrackRequest(
            map_id=map_id,
            frames=[pb.TrackFrame(frame=f, pose=p) for f, p in frames],
            estimate_scale=estimate_scale,
            pose_convention=pose_convention,
        )
        if prior is not None:
            request.prior.CopyFrom(prior)
        if tracker_error is not None:
            share, degrees = tracker_error
            request.tracker_error.CopyFrom(pb.TrackerError(translation_share=share, degrees_per_frame=degrees))
        return self._call(self.matching.LocalizeTrack, request)

    def match_pair(
        self,
        frame1: pb.Frame,
        frame2: pb.Frame,
        *,
        ratio: float = 0.0,
        mutual: bool = False,
        matcher: int = pb.PAIR_MATCHER_DEFAULT,
        pose_convention: int = pb.POSE_CONVENTION_OPENCV_CAMERA_TO_WORLD,
    ) -> pb.MatchPairResponse:
        """Matches two frames; ``ratio`` 0 means the server's default (0.8); the relative pose is in the camera
        axes of ``pose_convention``."""
        request = pb.MatchPairRequest(
            frame1=frame1, frame2=frame2, ratio=ratio, mutual=mutual, matcher=matcher, pose_convention=pose_convention
        )
        return self._call(self.matching.MatchPair, request)

    # -- Maps -------------------------------------------------------------------------------------------

    def create_map(self, map_id: str) -> pb.MapInfo:
        return self._call(self.maps.CreateMap, pb.CreateMapRequest(map_id=map_id))

    def get_map(self, map_id: str) -> pb.MapInfo:
        return self._call(self.maps.GetMap, pb.GetMapRequest(map_id=map_id))

    def add_keyframes(self, requests: Iterable[pb.AddKeyframeRequest]) -> Iterator[pb.KeyframeAck]:
        """Streams keyframes; yields one acknowledgement per keyframe once it is durable."""
        return self.maps.AddKeyframes(iter(requests), timeout=self.timeout, metadata=self._metadata)

    def merge_maps(
        self, target_map_id: str, source_map_id: str, transform: pb.Similarity | None = None
    ) -> pb.MergeMapsResponse:
        """Merges map ``source_map_id`` into ``target_map_id``; without ``transform`` (source to target
        coordinates) the server estimates it from the source keyframes it localises in the target."""
        request = pb.MergeMapsRequest(target_map_id=target_map_id, source_map_id=source_map_id)
        if transform is not None:
            request.transform.CopyFrom(transform)
        return self._call(self.maps.MergeMaps, request)

    def model_id(self) -> str:
        """The server's model id (from Describe of a blank image), for KeypointSet.model_id."""
        ok, png = cv2.imencode(".png", np.zeros((32, 32), np.uint8))
        if not ok:
            raise RuntimeError("could not encode a blank PNG")
        return self.describe(image_frame(png.tobytes())).model_id


def extractor_config(response: pb.DescribeResponse) -> ExtractorConfig:
    """The extraction the server runs (any Describe answer carries it): pass it to ``extract`` so that keypoint
    sets match what the server would compute from the image."""
    e = response.extraction
    return ExtractorConfig(e.fast_threshold, e.max_keypoints, e.levels, e.scale_factor, e.grid_cell)


def features_from_describe(response: pb.DescribeResponse, width: int, height: int) -> Features:
    """The keypoints, FREAK descriptors and (when the model reads them) ring contexts of a Describe response as
    Features (to compare with a client's)."""
    kps = response.keypoints
    n = len(kps)
    return Features(
        width=width,
        height=height,
        xy=np.array([(k.x, k.y) for k in kps], np.float32).reshape(n, 2),
        size=np.array([k.size for k in kps], np.float32),
        angle=np.array([k.angle for k in kps], np.float32),
        response=np.array([k.response for k in kps], np.float32),
        octave=np.array([k.octave for k in kps], np.int32),
        descriptors=np.frombuffer(response.descriptors, np.uint8).reshape(n, DESCRIPTOR_BYTES).copy(),
        context=np.frombuffer(response.context, np.uint8).reshape(n, RING_SAMPLES).copy() if response.context else None,
    )
