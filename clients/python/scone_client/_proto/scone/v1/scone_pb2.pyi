from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class DistortionModel(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DISTORTION_MODEL_NONE: _ClassVar[DistortionModel]
    DISTORTION_MODEL_RADIAL_TANGENTIAL: _ClassVar[DistortionModel]
    DISTORTION_MODEL_FISHEYE: _ClassVar[DistortionModel]

class PoseConvention(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    POSE_CONVENTION_OPENCV_CAMERA_TO_WORLD: _ClassVar[PoseConvention]
    POSE_CONVENTION_OPENCV_WORLD_TO_CAMERA: _ClassVar[PoseConvention]
    POSE_CONVENTION_OPENGL_CAMERA_TO_WORLD: _ClassVar[PoseConvention]

class PairMatcher(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PAIR_MATCHER_DEFAULT: _ClassVar[PairMatcher]
    PAIR_MATCHER_PLAIN: _ClassVar[PairMatcher]
    PAIR_MATCHER_UNION: _ClassVar[PairMatcher]
    PAIR_MATCHER_RERANK: _ClassVar[PairMatcher]
    PAIR_MATCHER_FREAK: _ClassVar[PairMatcher]
    PAIR_MATCHER_SCALE_AWARE: _ClassVar[PairMatcher]
    PAIR_MATCHER_JOINT: _ClassVar[PairMatcher]
    PAIR_MATCHER_BOTH: _ClassVar[PairMatcher]
DISTORTION_MODEL_NONE: DistortionModel
DISTORTION_MODEL_RADIAL_TANGENTIAL: DistortionModel
DISTORTION_MODEL_FISHEYE: DistortionModel
POSE_CONVENTION_OPENCV_CAMERA_TO_WORLD: PoseConvention
POSE_CONVENTION_OPENCV_WORLD_TO_CAMERA: PoseConvention
POSE_CONVENTION_OPENGL_CAMERA_TO_WORLD: PoseConvention
PAIR_MATCHER_DEFAULT: PairMatcher
PAIR_MATCHER_PLAIN: PairMatcher
PAIR_MATCHER_UNION: PairMatcher
PAIR_MATCHER_RERANK: PairMatcher
PAIR_MATCHER_FREAK: PairMatcher
PAIR_MATCHER_SCALE_AWARE: PairMatcher
PAIR_MATCHER_JOINT: PairMatcher
PAIR_MATCHER_BOTH: PairMatcher

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy", "width", "height", "distortion_model", "distortion")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_MODEL_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion_model: DistortionModel
    distortion: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., distortion_model: _Optional[_Union[DistortionModel, str]] = ..., distortion: _Optional[_Iterable[float]] = ...) -> None: ...

class Pose(_message.Message):
    __slots__ = ("tx", "ty", "tz", "qx", "qy", "qz", "qw")
    TX_FIELD_NUMBER: _ClassVar[int]
    TY_FIELD_NUMBER: _ClassVar[int]
    TZ_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    tx: float
    ty: float
    tz: float
    qx: float
    qy: float
    qz: float
    qw: float
    def __init__(self, tx: _Optional[float] = ..., ty: _Optional[float] = ..., tz: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ...) -> None: ...

class Image(_message.Message):
    __slots__ = ("data",)
    DATA_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    def __init__(self, data: _Optional[bytes] = ...) -> None: ...

class Keypoint(_message.Message):
    __slots__ = ("x", "y", "size", "angle", "response", "octave")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    ANGLE_FIELD_NUMBER: _ClassVar[int]
    RESPONSE_FIELD_NUMBER: _ClassVar[int]
    OCTAVE_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    size: float
    angle: float
    response: float
    octave: int
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., size: _Optional[float] = ..., angle: _Optional[float] = ..., response: _Optional[float] = ..., octave: _Optional[int] = ...) -> None: ...

class KeypointSet(_message.Message):
    __slots__ = ("keypoints", "descriptors", "width", "height", "model_id", "context")
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_FIELD_NUMBER: _ClassVar[int]
    keypoints: _containers.RepeatedCompositeFieldContainer[Keypoint]
    descriptors: bytes
    width: int
    height: int
    model_id: str
    context: bytes
    def __init__(self, keypoints: _Optional[_Iterable[_Union[Keypoint, _Mapping]]] = ..., descriptors: _Optional[bytes] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., model_id: _Optional[str] = ..., context: _Optional[bytes] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("image", "keypoints", "intrinsics")
    IMAGE_FIELD_NUMBER: _ClassVar[int]
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    image: Image
    keypoints: KeypointSet
    intrinsics: Intrinsics
    def __init__(self, image: _Optional[_Union[Image, _Mapping]] = ..., keypoints: _Optional[_Union[KeypointSet, _Mapping]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ...) -> None: ...

class CreateMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class GetMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class MapInfo(_message.Message):
    __slots__ = ("map_id", "model_id", "keyframes", "landmarks", "observations", "live_observations", "version", "approximate_index", "loaded", "load_note")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    LIVE_OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    APPROXIMATE_INDEX_FIELD_NUMBER: _ClassVar[int]
    LOADED_FIELD_NUMBER: _ClassVar[int]
    LOAD_NOTE_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    model_id: str
    keyframes: int
    landmarks: int
    observations: int
    live_observations: int
    version: int
    approximate_index: bool
    loaded: bool
    load_note: str
    def __init__(self, map_id: _Optional[str] = ..., model_id: _Optional[str] = ..., keyframes: _Optional[int] = ..., landmarks: _Optional[int] = ..., observations: _Optional[int] = ..., live_observations: _Optional[int] = ..., version: _Optional[int] = ..., approximate_index: _Optional[bool] = ..., loaded: _Optional[bool] = ..., load_note: _Optional[str] = ...) -> None: ...

class ListMapsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListMapsResponse(_message.Message):
    __slots__ = ("maps", "held_back")
    MAPS_FIELD_NUMBER: _ClassVar[int]
    HELD_BACK_FIELD_NUMBER: _ClassVar[int]
    maps: _containers.RepeatedCompositeFieldContainer[MapInfo]
    held_back: _containers.RepeatedCompositeFieldContainer[HeldBackMap]
    def __init__(self, maps: _Optional[_Iterable[_Union[MapInfo, _Mapping]]] = ..., held_back: _Optional[_Iterable[_Union[HeldBackMap, _Mapping]]] = ...) -> None: ...

class HeldBackMap(_message.Message):
    __slots__ = ("map_id", "reason")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    reason: str
    def __init__(self, map_id: _Optional[str] = ..., reason: _Optional[str] = ...) -> None: ...

class DeleteMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class DeleteMapResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class AddKeyframeRequest(_message.Message):
    __slots__ = ("map_id", "keyframe_id", "frame", "pose", "depth_png", "depth_scale", "external_landmarks", "pose_convention")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    DEPTH_PNG_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    POSE_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    keyframe_id: int
    frame: Frame
    pose: Pose
    depth_png: bytes
    depth_scale: float
    external_landmarks: _containers.RepeatedCompositeFieldContainer[ExternalObservation]
    pose_convention: PoseConvention
    def __init__(self, map_id: _Optional[str] = ..., keyframe_id: _Optional[int] = ..., frame: _Optional[_Union[Frame, _Mapping]] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., depth_png: _Optional[bytes] = ..., depth_scale: _Optional[float] = ..., external_landmarks: _Optional[_Iterable[_Union[ExternalObservation, _Mapping]]] = ..., pose_convention: _Optional[_Union[PoseConvention, str]] = ...) -> None: ...

class Point3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class ExternalObservation(_message.Message):
    __slots__ = ("x", "y", "landmark_id", "point")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    LANDMARK_ID_FIELD_NUMBER: _ClassVar[int]
    POINT_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    landmark_id: int
    point: Point3
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., landmark_id: _Optional[int] = ..., point: _Optional[_Union[Point3, _Mapping]] = ...) -> None: ...

class KeyframeAck(_message.Message):
    __slots__ = ("keyframe_id", "new_landmarks", "observations", "map_version", "external_rejected", "external_unassociated")
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    NEW_LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    OBSERVATIONS_FIELD_NUMBER: _ClassVar[int]
    MAP_VERSION_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_REJECTED_FIELD_NUMBER: _ClassVar[int]
    EXTERNAL_UNASSOCIATED_FIELD_NUMBER: _ClassVar[int]
    keyframe_id: int
    new_landmarks: int
    observations: int
    map_version: int
    external_rejected: int
    external_unassociated: int
    def __init__(self, keyframe_id: _Optional[int] = ..., new_landmarks: _Optional[int] = ..., observations: _Optional[int] = ..., map_version: _Optional[int] = ..., external_rejected: _Optional[int] = ..., external_unassociated: _Optional[int] = ...) -> None: ...

class RemoveKeyframeRequest(_message.Message):
    __slots__ = ("map_id", "keyframe_id")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    keyframe_id: int
    def __init__(self, map_id: _Optional[str] = ..., keyframe_id: _Optional[int] = ...) -> None: ...

class Similarity(_message.Message):
    __slots__ = ("tx", "ty", "tz", "qx", "qy", "qz", "qw", "scale")
    TX_FIELD_NUMBER: _ClassVar[int]
    TY_FIELD_NUMBER: _ClassVar[int]
    TZ_FIELD_NUMBER: _ClassVar[int]
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    tx: float
    ty: float
    tz: float
    qx: float
    qy: float
    qz: float
    qw: float
    scale: float
    def __init__(self, tx: _Optional[float] = ..., ty: _Optional[float] = ..., tz: _Optional[float] = ..., qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ..., scale: _Optional[float] = ...) -> None: ...

class MergeMapsRequest(_message.Message):
    __slots__ = ("target_map_id", "source_map_id", "transform")
    TARGET_MAP_ID_FIELD_NUMBER: _ClassVar[int]
    SOURCE_MAP_ID_FIELD_NUMBER: _ClassVar[int]
    TRANSFORM_FIELD_NUMBER: _ClassVar[int]
    target_map_id: str
    source_map_id: str
    transform: Similarity
    def __init__(self, target_map_id: _Optional[str] = ..., source_map_id: _Optional[str] = ..., transform: _Optional[_Union[Similarity, _Mapping]] = ...) -> None: ...

class MergeMapsResponse(_message.Message):
    __slots__ = ("target", "transform", "transform_estimated", "source_keyframes", "keyframes_localised", "transform_inliers", "keyframe_id_offset", "landmarks_fused", "landmarks_added")
    TARGET_FIELD_NUMBER: _ClassVar[int]
    TRANSFORM_FIELD_NUMBER: _ClassVar[int]
    TRANSFORM_ESTIMATED_FIELD_NUMBER: _ClassVar[int]
    SOURCE_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_LOCALISED_FIELD_NUMBER: _ClassVar[int]
    TRANSFORM_INLIERS_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_ID_OFFSET_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FUSED_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_ADDED_FIELD_NUMBER: _ClassVar[int]
    target: MapInfo
    transform: Similarity
    transform_estimated: bool
    source_keyframes: int
    keyframes_localised: int
    transform_inliers: int
    keyframe_id_offset: int
    landmarks_fused: int
    landmarks_added: int
    def __init__(self, target: _Optional[_Union[MapInfo, _Mapping]] = ..., transform: _Optional[_Union[Similarity, _Mapping]] = ..., transform_estimated: _Optional[bool] = ..., source_keyframes: _Optional[int] = ..., keyframes_localised: _Optional[int] = ..., transform_inliers: _Optional[int] = ..., keyframe_id_offset: _Optional[int] = ..., landmarks_fused: _Optional[int] = ..., landmarks_added: _Optional[int] = ...) -> None: ...

class ExportMapRequest(_message.Message):
    __slots__ = ("map_id",)
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    def __init__(self, map_id: _Optional[str] = ...) -> None: ...

class MapChunk(_message.Message):
    __slots__ = ("map_id", "data")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    data: bytes
    def __init__(self, map_id: _Optional[str] = ..., data: _Optional[bytes] = ...) -> None: ...

class DescribeRequest(_message.Message):
    __slots__ = ("frame",)
    FRAME_FIELD_NUMBER: _ClassVar[int]
    frame: Frame
    def __init__(self, frame: _Optional[_Union[Frame, _Mapping]] = ...) -> None: ...

class DescribeResponse(_message.Message):
    __slots__ = ("keypoints", "descriptors", "embeddings", "dim", "model_id", "context", "extraction")
    KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    DESCRIPTORS_FIELD_NUMBER: _ClassVar[int]
    EMBEDDINGS_FIELD_NUMBER: _ClassVar[int]
    DIM_FIELD_NUMBER: _ClassVar[int]
    MODEL_ID_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_FIELD_NUMBER: _ClassVar[int]
    EXTRACTION_FIELD_NUMBER: _ClassVar[int]
    keypoints: _containers.RepeatedCompositeFieldContainer[Keypoint]
    descriptors: bytes
    embeddings: _containers.RepeatedScalarFieldContainer[float]
    dim: int
    model_id: str
    context: bytes
    extraction: Extraction
    def __init__(self, keypoints: _Optional[_Iterable[_Union[Keypoint, _Mapping]]] = ..., descriptors: _Optional[bytes] = ..., embeddings: _Optional[_Iterable[float]] = ..., dim: _Optional[int] = ..., model_id: _Optional[str] = ..., context: _Optional[bytes] = ..., extraction: _Optional[_Union[Extraction, _Mapping]] = ...) -> None: ...

class Extraction(_message.Message):
    __slots__ = ("fast_threshold", "max_keypoints", "levels", "scale_factor", "grid_cell")
    FAST_THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    MAX_KEYPOINTS_FIELD_NUMBER: _ClassVar[int]
    LEVELS_FIELD_NUMBER: _ClassVar[int]
    SCALE_FACTOR_FIELD_NUMBER: _ClassVar[int]
    GRID_CELL_FIELD_NUMBER: _ClassVar[int]
    fast_threshold: int
    max_keypoints: int
    levels: int
    scale_factor: float
    grid_cell: int
    def __init__(self, fast_threshold: _Optional[int] = ..., max_keypoints: _Optional[int] = ..., levels: _Optional[int] = ..., scale_factor: _Optional[float] = ..., grid_cell: _Optional[int] = ...) -> None: ...

class Match(_message.Message):
    __slots__ = ("index1", "index2", "distance", "inlier")
    INDEX1_FIELD_NUMBER: _ClassVar[int]
    INDEX2_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    INLIER_FIELD_NUMBER: _ClassVar[int]
    index1: int
    index2: int
    distance: float
    inlier: bool
    def __init__(self, index1: _Optional[int] = ..., index2: _Optional[int] = ..., distance: _Optional[float] = ..., inlier: _Optional[bool] = ...) -> None: ...

class MatchPairRequest(_message.Message):
    __slots__ = ("frame1", "frame2", "ratio", "mutual", "matcher", "pose_convention")
    FRAME1_FIELD_NUMBER: _ClassVar[int]
    FRAME2_FIELD_NUMBER: _ClassVar[int]
    RATIO_FIELD_NUMBER: _ClassVar[int]
    MUTUAL_FIELD_NUMBER: _ClassVar[int]
    MATCHER_FIELD_NUMBER: _ClassVar[int]
    POSE_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    frame1: Frame
    frame2: Frame
    ratio: float
    mutual: bool
    matcher: PairMatcher
    pose_convention: PoseConvention
    def __init__(self, frame1: _Optional[_Union[Frame, _Mapping]] = ..., frame2: _Optional[_Union[Frame, _Mapping]] = ..., ratio: _Optional[float] = ..., mutual: _Optional[bool] = ..., matcher: _Optional[_Union[PairMatcher, str]] = ..., pose_convention: _Optional[_Union[PoseConvention, str]] = ...) -> None: ...

class RelativePose(_message.Message):
    __slots__ = ("qx", "qy", "qz", "qw", "tx", "ty", "tz")
    QX_FIELD_NUMBER: _ClassVar[int]
    QY_FIELD_NUMBER: _ClassVar[int]
    QZ_FIELD_NUMBER: _ClassVar[int]
    QW_FIELD_NUMBER: _ClassVar[int]
    TX_FIELD_NUMBER: _ClassVar[int]
    TY_FIELD_NUMBER: _ClassVar[int]
    TZ_FIELD_NUMBER: _ClassVar[int]
    qx: float
    qy: float
    qz: float
    qw: float
    tx: float
    ty: float
    tz: float
    def __init__(self, qx: _Optional[float] = ..., qy: _Optional[float] = ..., qz: _Optional[float] = ..., qw: _Optional[float] = ..., tx: _Optional[float] = ..., ty: _Optional[float] = ..., tz: _Optional[float] = ...) -> None: ...

class MatchPairResponse(_message.Message):
    __slots__ = ("matches", "pose", "inliers", "matcher")
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    MATCHER_FIELD_NUMBER: _ClassVar[int]
    matches: _containers.RepeatedCompositeFieldContainer[Match]
    pose: RelativePose
    inliers: int
    matcher: PairMatcher
    def __init__(self, matches: _Optional[_Iterable[_Union[Match, _Mapping]]] = ..., pose: _Optional[_Union[RelativePose, _Mapping]] = ..., inliers: _Optional[int] = ..., matcher: _Optional[_Union[PairMatcher, str]] = ...) -> None: ...

class PosePrior(_message.Message):
    __slots__ = ("x", "y", "z", "radius")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    RADIUS_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    radius: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., radius: _Optional[float] = ...) -> None: ...

class LocalizeRequest(_message.Message):
    __slots__ = ("map_id", "frame", "prior", "pose_convention")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    PRIOR_FIELD_NUMBER: _ClassVar[int]
    POSE_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    frame: Frame
    prior: PosePrior
    pose_convention: PoseConvention
    def __init__(self, map_id: _Optional[str] = ..., frame: _Optional[_Union[Frame, _Mapping]] = ..., prior: _Optional[_Union[PosePrior, _Mapping]] = ..., pose_convention: _Optional[_Union[PoseConvention, str]] = ...) -> None: ...

class TrackFrame(_message.Message):
    __slots__ = ("frame", "pose")
    FRAME_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    frame: Frame
    pose: Pose
    def __init__(self, frame: _Optional[_Union[Frame, _Mapping]] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ...) -> None: ...

class LocalizeTrackRequest(_message.Message):
    __slots__ = ("map_id", "frames", "estimate_scale", "prior", "pose_convention", "tracker_error")
    MAP_ID_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    ESTIMATE_SCALE_FIELD_NUMBER: _ClassVar[int]
    PRIOR_FIELD_NUMBER: _ClassVar[int]
    POSE_CONVENTION_FIELD_NUMBER: _ClassVar[int]
    TRACKER_ERROR_FIELD_NUMBER: _ClassVar[int]
    map_id: str
    frames: _containers.RepeatedCompositeFieldContainer[TrackFrame]
    estimate_scale: bool
    prior: PosePrior
    pose_convention: PoseConvention
    tracker_error: TrackerError
    def __init__(self, map_id: _Optional[str] = ..., frames: _Optional[_Iterable[_Union[TrackFrame, _Mapping]]] = ..., estimate_scale: _Optional[bool] = ..., prior: _Optional[_Union[PosePrior, _Mapping]] = ..., pose_convention: _Optional[_Union[PoseConvention, str]] = ..., tracker_error: _Optional[_Union[TrackerError, _Mapping]] = ...) -> None: ...

class TrackerError(_message.Message):
    __slots__ = ("translation_share", "degrees_per_frame")
    TRANSLATION_SHARE_FIELD_NUMBER: _ClassVar[int]
    DEGREES_PER_FRAME_FIELD_NUMBER: _ClassVar[int]
    translation_share: float
    degrees_per_frame: float
    def __init__(self, translation_share: _Optional[float] = ..., degrees_per_frame: _Optional[float] = ...) -> None: ...

class TrackFrameResult(_message.Message):
    __slots__ = ("pose", "matches", "inliers", "dropped", "localized_alone")
    POSE_FIELD_NUMBER: _ClassVar[int]
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    LOCALIZED_ALONE_FIELD_NUMBER: _ClassVar[int]
    pose: Pose
    matches: int
    inliers: int
    dropped: bool
    localized_alone: bool
    def __init__(self, pose: _Optional[_Union[Pose, _Mapping]] = ..., matches: _Optional[int] = ..., inliers: _Optional[int] = ..., dropped: _Optional[bool] = ..., localized_alone: _Optional[bool] = ...) -> None: ...

class LocalizeTrackResponse(_message.Message):
    __slots__ = ("localized", "map_from_track", "frames", "inliers", "reprojection_error", "confidence", "covariance", "single_frame")
    LOCALIZED_FIELD_NUMBER: _ClassVar[int]
    MAP_FROM_TRACK_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_ERROR_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    SINGLE_FRAME_FIELD_NUMBER: _ClassVar[int]
    localized: bool
    map_from_track: Similarity
    frames: _containers.RepeatedCompositeFieldContainer[TrackFrameResult]
    inliers: int
    reprojection_error: float
    confidence: float
    covariance: _containers.RepeatedScalarFieldContainer[float]
    single_frame: int
    def __init__(self, localized: _Optional[bool] = ..., map_from_track: _Optional[_Union[Similarity, _Mapping]] = ..., frames: _Optional[_Iterable[_Union[TrackFrameResult, _Mapping]]] = ..., inliers: _Optional[int] = ..., reprojection_error: _Optional[float] = ..., confidence: _Optional[float] = ..., covariance: _Optional[_Iterable[float]] = ..., single_frame: _Optional[int] = ...) -> None: ...

class LocalizeResponse(_message.Message):
    __slots__ = ("localized", "pose", "matches", "inliers", "reprojection_error", "confidence", "focal_length", "focal_estimated", "covariance")
    LOCALIZED_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    MATCHES_FIELD_NUMBER: _ClassVar[int]
    INLIERS_FIELD_NUMBER: _ClassVar[int]
    REPROJECTION_ERROR_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    FOCAL_LENGTH_FIELD_NUMBER: _ClassVar[int]
    FOCAL_ESTIMATED_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    localized: bool
    pose: Pose
    matches: int
    inliers: int
    reprojection_error: float
    confidence: float
    focal_length: float
    focal_estimated: bool
    covariance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, localized: _Optional[bool] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., matches: _Optional[int] = ..., inliers: _Optional[int] = ..., reprojection_error: _Optional[float] = ..., confidence: _Optional[float] = ..., focal_length: _Optional[float] = ..., focal_estimated: _Optional[bool] = ..., covariance: _Optional[_Iterable[float]] = ...) -> None: ...
