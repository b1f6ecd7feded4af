//! The HTTP API's JSON: every request and response body, typed, with the conversions from the service's
//! domain types. The OpenAPI document's schemas are generated from these structs (their doc comments are the
//! descriptions), so what is documented is what is parsed and sent.
//!
//! Conventions: poses are camera-to-world with quaternions (x, y, z, w) and OpenCV camera axes (x right, y
//! down, z forward); pixels have (0, 0) at the centre of the top-left pixel; binary data in JSON is base64.

use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use crate::service::MapSummary;

/// Pinhole intrinsics, pixels, with an optional lens distortion model. Left out: `fy` takes `fx`; a principal
/// point left out (or (0, 0)) is the image centre. Localize alone accepts intrinsics without `fx` and `fy`
/// (or none at all): it estimates the focal length with the pose and returns it.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}))]
pub struct Intrinsics {
    /// Focal length, pixels (absent: unknown; Localize only).
    #[serde(default)]
    pub fx: f64,
    /// Focal length, pixels (absent: `fx`).
    #[serde(default)]
    pub fy: f64,
    /// Principal point, pixels (absent with `cy`: the image centre).
    #[serde(default)]
    pub cx: f64,
    #[serde(default)]
    pub cy: f64,
    /// Defaults to the image's (or the keypoint set's) width.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width: Option<u32>,
    /// Defaults to the image's (or the keypoint set's) height.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height: Option<u32>,
    /// The lens model of the frame's pixels (default none). With a model, keypoint positions are undistorted
    /// (OpenCV) before constellations, triangulation and PnP; refused with depth and without a focal length.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub distortion_model: Option<DistortionModel>,
    /// The model's coefficients in OpenCV's order: `radial_tangential` k1, k2, p1, p2[, k3[, k4, k5, k6]]
    /// (4, 5 or 8); `fisheye` k1, k2, k3, k4.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub distortion: Vec<f64>,
}

impl Intrinsics {
    /// The lens model, checked.
    pub fn lens(&self) -> Result<crate::service::Distortion, crate::error::PoseError> {
        crate::service::Distortion::new(self.distortion_model.unwrap_or_default().into(), &self.distortion)
    }
}

/// A lens distortion model, OpenCV's definitions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum DistortionModel {
    /// A pinhole camera (or keypoints the client undistorted).
    #[default]
    None,
    /// OpenCV's default model (Brown-Conrady; Kalibr `radtan`).
    RadialTangential,
    /// OpenCV's `cv::fisheye` (Kalibr `equidistant`).
    Fisheye,
}

impl From<DistortionModel> for crate::service::DistortionModel {
    fn from(m: DistortionModel) -> Self {
        match m {
            DistortionModel::None => Self::None,
            DistortionModel::RadialTangential => Self::RadialTangential,
            DistortionModel::Fisheye => Self::Fisheye,
        }
    }
}

/// A FAST keypoint as the service extracts it (the client contract of `proto/scone/v1/scone.proto`).
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Keypoint {
    pub x: f32,
    pub y: f32,
    /// Diameter of the FREAK pattern at this keypoint's pyramid level, pixels of the full image.
    pub size: f32,
    /// Orientation, degrees.
    pub angle: f32,
    #[serde(default)]
    pub response: f32,
    /// Pyramid level.
    #[serde(default)]
    pub octave: i32,
}

impl From<&crate::features::Keypoint> for Keypoint {
    fn from(k: &crate::features::Keypoint) -> Self {
        Self { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
    }
}

impl From<&Keypoint> for crate::features::Keypoint {
    fn from(k: &Keypoint) -> Self {
        Self { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
    }
}

/// Keypoints computed on a device (FAST + FREAK by the client contract) instead of an image.
#[derive(Debug, Clone, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct KeypointSet {
    /// Size of the image the keypoints were detected in.
    pub width: u32,
    pub height: u32,
    pub keypoints: Vec<Keypoint>,
    /// 64 bytes of FREAK bits per keypoint, in keypoint order, base64.
    pub descriptors_base64: String,
    /// The model the client's contract targets; when given, it must be the server's.
    #[serde(default)]
    pub model_id: Option<String>,
    /// The ring context, 113 bytes per keypoint in keypoint order, base64 (the client contract's step 9):
    /// required when the server's model reads it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub context_base64: Option<String>,
}

/// One frame: exactly one of `image_base64` or `keypoints` (or, in multipart requests, a binary image part).
#[derive(Debug, Clone, Default, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Frame {
    /// A PNG or JPEG image, base64.
    #[serde(default)]
    pub image_base64: Option<String>,
    #[serde(default)]
    pub keypoints: Option<KeypointSet>,
    #[serde(default)]
    pub intrinsics: Option<Intrinsics>,
}

/// A camera-to-world pose: translation (map units) and unit quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0}))]
pub struct Pose {
    pub tx: f64,
    pub ty: f64,
    pub tz: f64,
    pub qx: f64,
    pub qy: f64,
    pub qz: f64,
    pub qw: f64,
}

impl Pose {
    pub fn from_isometry(p: &nalgebra::Isometry3<f64>) -> Self {
        let q = p.rotation.quaternion();
        let t = p.translation.vector;
        Self { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
    }

    pub fn domain(&self) -> crate::camera::Pose {
        crate::camera::Pose { translation: [self.tx, self.ty, self.tz], rotation: [self.qx, self.qy, self.qz, self.qw] }
    }
}

/// How the poses of a request and of its answer are expressed (default `opencv_camera_to_world`, as maps store
/// them). The world frame is the client's own in every convention.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum PoseConvention {
    /// Camera x right, y down, z forward (OpenCV); camera-to-world.
    OpencvCameraToWorld,
    /// OpenCV camera axes; world-to-camera (COLMAP, many SLAM exports).
    OpencvWorldToCamera,
    /// Camera x right, y up, z backward (OpenGL); camera-to-world: ARKit and ARCore poses.
    OpenglCameraToWorld,
}

impl From<PoseConvention> for crate::camera::PoseConvention {
    fn from(c: PoseConvention) -> Self {
        match c {
            PoseConvention::OpencvCameraToWorld => Self::OpencvCameraToWorld,
            PoseConvention::OpencvWorldToCamera => Self::OpencvWorldToCamera,
            PoseConvention::OpenglCameraToWorld => Self::OpenglCameraToWorld,
        }
    }
}

/// `?pose_convention=` on routes whose poses can come as a raw body or go out in a picture.
#[derive(Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ConventionQuery {
    /// How the answer's poses are expressed (default `opencv_camera_to_world`).
    pub pose_convention: Option<PoseConvention>,
}

/// Where the camera is believed to be: only landmarks within `radius` of (x, y, z) are matched.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Prior {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub radius: f64,
}

/// Describe: keypoints, FREAK descriptors and SConE embeddings of one frame.
#[derive(Debug, Default, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DescribeRequest {
    /// Absent when the image comes as a raw body or a multipart `image` part.
    #[serde(default)]
    pub frame: Option<Frame>,
}

/// How MatchPair picks its matches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum Matcher {
    /// The SConE embedding alone: L2 nearest neighbour with the ratio test.
    Plain,
    /// Plain SConE matches plus FREAK's where SConE has none.
    Union,
    /// FREAK's nearest candidates re-ranked by the SConE embedding.
    Rerank,
    /// `rerank`, or `union` when the two images differ in scale by 1.6x or more (the default).
    #[serde(rename = "scale-aware")]
    ScaleAware,
    /// FREAK alone (Hamming + ratio test): the baseline, for comparison on the same keypoints.
    Freak,
}

impl From<Matcher> for crate::matching::SconeMatcher {
    fn from(m: Matcher) -> Self {
        match m {
            Matcher::Plain => Self::Plain,
            Matcher::Union => Self::Union,
            Matcher::Rerank => Self::Rerank,
            Matcher::ScaleAware => Self::ScaleAware,
            Matcher::Freak => Self::Freak,
        }
    }
}

/// MatchPair: matches between two frames and their relative pose.
#[derive(Debug, Default, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MatchRequest {
    /// Absent when its image is the multipart part `image1` (or `image`).
    #[serde(default)]
    pub frame1: Option<Frame>,
    /// Absent when its image is the multipart part `image2`.
    #[serde(default)]
    pub frame2: Option<Frame>,
    /// Ratio-test threshold in (0, 1]; default 0.8.
    #[serde(default)]
    pub ratio: Option<f32>,
    /// Keep only mutual nearest neighbours.
    #[serde(default)]
    pub mutual: bool,
    /// Absent: the server's default (`scale-aware`).
    #[serde(default)]
    pub matcher: Option<Matcher>,
    /// The camera axes of the answer's relative pose (OpenGL: y up, z backward); it maps camera 1 into camera 2
    /// in every convention.
    #[serde(default)]
    pub pose_convention: Option<PoseConvention>,
}

/// Localize: the camera-to-world pose of a frame against a map.
#[derive(Debug, Default, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct LocalizeRequest {
    /// Absent when the image comes as a raw body or a multipart `image` part.
    #[serde(default)]
    pub frame: Option<Frame>,
    /// The frame's intrinsics given outside it (they must agree with `frame.intrinsics` if both are given).
    #[serde(default)]
    pub intrinsics: Option<Intrinsics>,
    #[serde(default)]
    pub prior: Option<Prior>,
    /// The convention of the answer's pose (or give `?pose_convention=`; both must agree).
    #[serde(default)]
    pub pose_convention: Option<PoseConvention>,
}

/// A 3D point in map units.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Point3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// A landmark an external SfM (COLMAP and the like) gives for a pixel of the keyframe.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExternalObservation {
    pub x: f64,
    pub y: f64,
    /// The SfM's id of the 3D point; observations of one id in several keyframes are one landmark.
    pub landmark_id: u64,
    pub point: Point3,
}

/// AddKeyframes (one keyframe): a posed frame added to a map, acknowledged once durable.
#[derive(Debug, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct KeyframeRequest {
    pub keyframe_id: u64,
    /// In `pose_convention` (default OpenCV camera-to-world).
    pub pose: Pose,
    #[serde(default)]
    pub pose_convention: Option<PoseConvention>,
    /// Absent when the image comes as a multipart `image` part.
    #[serde(default)]
    pub frame: Option<Frame>,
    #[serde(default)]
    pub intrinsics: Option<Intrinsics>,
    /// A 16-bit PNG aligned with the image (or a multipart `depth` part).
    #[serde(default)]
    pub depth_png_base64: Option<String>,
    /// Metres per depth unit; default 1/5000 (TUM RGB-D).
    #[serde(default)]
    pub depth_scale: Option<f64>,
    /// Landmarks given by an external SfM; without them, depth or triangulation makes the landmarks.
    #[serde(default)]
    pub external_landmarks: Vec<ExternalObservation>,
}

/// CreateMap.
#[derive(Debug, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"map_id": "office"}))]
pub struct CreateMapRequest {
    /// 1-64 characters from `[A-Za-z0-9_-]`.
    pub map_id: String,
}

/// Keypoints, FREAK descriptors and SConE embeddings of a frame.
#[derive(Debug, Serialize, ToSchema)]
pub struct DescribeResponse {
    pub width: u32,
    pub height: u32,
    pub keypoints: Vec<Keypoint>,
    /// 64 bytes per keypoint, base64.
    pub descriptors_base64: String,
    /// `[keypoints, dim]`, row-major, unit norm.
    pub embeddings: Vec<f32>,
    pub dim: usize,
    pub model_id: String,
    /// The ring context, 113 bytes per keypoint, base64; empty when the model does not read it.
    pub context_base64: String,
}

/// One putative match: keypoint `index1` of frame 1 and `index2` of frame 2.
#[derive(Debug, Serialize, ToSchema)]
pub struct PairMatch {
    pub index1: usize,
    pub index2: usize,
    pub distance: f32,
    /// Whether the relative pose's RANSAC kept it.
    pub inlier: bool,
}

/// Frame 1's camera into frame 2's: `X2 = R X1 + t`, `t` of unit length (the scale is unobservable).
#[derive(Debug, Serialize, ToSchema)]
pub struct RelativePose {
    pub qx: f64,
    pub qy: f64,
    pub qz: f64,
    pub qw: f64,
    pub tx: f64,
    pub ty: f64,
    pub tz: f64,
}

/// Matches and the relative pose (null when too few matches support one).
#[derive(Debug, Serialize, ToSchema)]
pub struct MatchResponse {
    pub matches: Vec<PairMatch>,
    pub pose: Option<RelativePose>,
    pub inliers: usize,
}

/// A pose, or `localized: false`.
#[derive(Debug, Serialize, ToSchema)]
pub struct LocalizeResponse {
    pub localized: bool,
    /// Camera-to-world, in the map's frame.
    pub pose: Option<Pose>,
    /// 2D-3D matches found.
    pub matches: usize,
    pub inliers: usize,
    /// Mean reprojection error of the inliers, pixels.
    pub reprojection_error: f64,
    /// In [0, 1]: the probability, under the pose's covariance, that the pose is within 2° and within 5 % of
    /// the inliers' median depth of the truth; 0 without a pose. As calibrated as the covariance is.
    pub confidence: f64,
    /// The focal length of the pose, pixels: the request's `fx`, or the estimate when it left it out; 0 when
    /// not localised.
    pub focal_length: f64,
    /// Whether `focal_length` is the server's estimate.
    pub focal_estimated: bool,
    /// When localised: the pose's 6x6 covariance, row-major (36 values), in the request's convention, over
    /// (tx, ty, tz, rx, ry, rz): translation in map units, then a rotation vector in radians perturbing the
    /// returned rotation on the left (`R_true = exp([r]x) R`). Scaled so that about 95 % of true errors lie in
    /// its 95 % ellipsoid (calibrated on real scenes); empty when it cannot be computed.
    pub covariance: Vec<f64>,
}

/// A similarity between two maps' world frames, `X_target = scale * R * X_source + t` (R a unit quaternion x,
/// y, z, w within 1e-3; scale in (1e-6, 1e6)).
#[derive(Debug, Clone, Copy, PartialEq, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(example = json!({"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0, "scale": 1.0}))]
pub struct Similarity {
    pub tx: f64,
    pub ty: f64,
    pub tz: f64,
    pub qx: f64,
    pub qy: f64,
    pub qz: f64,
    pub qw: f64,
    pub scale: f64,
}

impl From<Similarity> for crate::service::Similarity {
    fn from(s: Similarity) -> Self {
        Self { translation: [s.tx, s.ty, s.tz], rotation: [s.qx, s.qy, s.qz, s.qw], scale: s.scale }
    }
}

impl From<crate::service::Similarity> for Similarity {
    fn from(s: crate::service::Similarity) -> Self {
        let ([tx, ty, tz], [qx, qy, qz, qw]) = (s.translation, s.rotation);
        Self { tx, ty, tz, qx, qy, qz, qw, scale: s.scale }
    }
}

/// Merge another map into this one (rpc Maps.MergeMaps).
#[derive(Debug, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct MergeMapsRequest {
    /// The map merged into this one; read, never changed.
    pub source_map_id: String,
    /// Source to target coordinates; estimated from the source keyframes localised in the target when absent.
    #[serde(default)]
    pub transform: Option<Similarity>,
}

/// What a merge did.
#[derive(Debug, Serialize, ToSchema)]
pub struct MergeMapsResponse {
    /// The target after the merge.
    pub target: MapInfo,
    /// Given or estimated.
    pub transform: Similarity,
    pub transform_estimated: bool,
    pub source_keyframes: usize,
    /// Source keyframes localised in the target.
    pub keyframes_localised: usize,
    /// Of those, the ones the estimated transform agrees with (0 when given).
    pub transform_inliers: usize,
    /// Added to every source keyframe id (0 when none collided with the target's).
    pub keyframe_id_offset: u64,
    /// Source landmarks fused with a target landmark.
    pub landmarks_fused: usize,
    /// Source landmarks added as new.
    pub landmarks_added: usize,
}

/// A keyframe write, durable when this is answered.
#[derive(Debug, Serialize, ToSchema)]
pub struct KeyframeAck {
    pub keyframe_id: u64,
    pub new_landmarks: usize,
    pub observations: usize,
    pub map_version: u64,
    /// External landmarks refused: behind the camera, reprojecting too far from their pixel, or a second
    /// view of one id.
    pub external_rejected: usize,
    /// External landmarks that were valid but found no free keypoint within the radius.
    pub external_unassociated: usize,
}

/// A map's statistics.
#[derive(Debug, Serialize, ToSchema)]
pub struct MapInfo {
    pub map_id: String,
    /// The model the map's embeddings were made with.
    pub model_id: String,
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    /// Observations whose keyframe was not removed.
    pub live_observations: usize,
    /// Records applied since creation.
    pub version: u64,
    /// Whether the index is approximate (HNSW) rather than exact.
    pub approximate_index: bool,
    /// Whether the answering server holds the map in memory (with object storage, maps are loaded on
    /// demand and listings name every stored map; the counts of one not loaded are its manifest's).
    pub loaded: bool,
    /// Present when loading the map found something to tell: its log ended inside a record and those bytes
    /// were cut off (after a crash, the one write in flight, never acknowledged; otherwise damage).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub load_note: Option<String>,
}

impl From<MapSummary> for MapInfo {
    fn from(s: MapSummary) -> Self {
        Self {
            map_id: s.id,
            model_id: s.model_id,
            keyframes: s.keyframes,
            landmarks: s.landmarks,
            observations: s.observations,
            live_observations: s.live_observations,
            version: s.version,
            approximate_index: s.approximate_index,
            loaded: s.loaded,
            load_note: s.load_note,
        }
    }
}

/// A stored map that could not be loaded, and why.
#[derive(Debug, Serialize, ToSchema)]
pub struct HeldBack {
    pub map_id: String,
    pub reason: String,
}

/// ListMaps: the loaded maps, and those held back.
#[derive(Debug, Serialize, ToSchema)]
pub struct MapList {
    pub maps: Vec<MapInfo>,
    pub held_back: Vec<HeldBack>,
}

/// A landmark for viewers.
#[derive(Debug, Serialize, ToSchema)]
pub struct LandmarkView {
    pub id: u64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
    /// Keyframes that see it.
    pub observations: usize,
}

/// A keyframe for viewers.
#[derive(Debug, Serialize, ToSchema)]
pub struct KeyframeView {
    pub keyframe_id: u64,
    /// Camera-to-world.
    pub pose: Pose,
    pub intrinsics: Intrinsics,
}

/// A map's contents for viewers: keyframe poses and intrinsics, and landmarks (an even subsample when the map
/// has more than `max_landmarks`).
#[derive(Debug, Serialize, ToSchema)]
pub struct MapContents {
    pub map_id: String,
    pub version: u64,
    pub keyframes: Vec<KeyframeView>,
    pub landmarks: Vec<LandmarkView>,
    /// Landmarks in the map (`landmarks` may hold fewer).
    pub landmarks_total: usize,
}

/// Query of the contents route.
#[derive(Debug, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct ContentsQuery {
    /// Landmarks returned at most (default 20,000; at most 200,000).
    pub max_landmarks: Option<usize>,
    /// How the keyframe poses are expressed (default `opencv_camera_to_world`).
    pub pose_convention: Option<PoseConvention>,
}

/// Query of the routes that can answer with a picture.
#[derive(Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RenderQuery {
    /// `png`: answer with a picture of the matches instead of JSON (as `Accept: image/png` does).
    pub render: Option<String>,
}

/// The documented example requests (the OpenAPI test sends each of them and checks the answer against the
/// documented schema): small keypoint sets, so the examples carry no image.
pub mod examples {
    use base64::Engine;
    use serde_json::{json, Value};

    /// Twelve keypoints of a 640x480 frame on a 4x3 grid, shifted by `dx` pixels, with made-up descriptors.
    pub fn keypoint_set(dx: f32) -> Value {
        let keypoints: Vec<Value> = (0..12)
            .map(|i| {
                let (col, row) = ((i % 4) as f32, (i / 4) as f32);
                json!({"x": 120.0 + 110.0 * col + dx, "y": 110.0 + 120.0 * row, "size": 7.0,
                       "angle": (i * 29 % 360) as f32, "response": 20.0, "octave": 0})
            })
            .collect();
        let descriptors: Vec<u8> = (0..12 * 64).map(|i: u32| (i.wrapping_mul(2_654_435_761) >> 24) as u8).collect();
        json!({"width": 640, "height": 480, "keypoints": keypoints,
               "descriptors_base64": base64::engine::general_purpose::STANDARD.encode(descriptors)})
    }

    fn intrinsics() -> Value {
        json!({"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5})
    }

    pub fn describe() -> Value {
        json!({"frame": {"keypoints": keypoint_set(0.0)}})
    }

    pub fn match_pair() -> Value {
        json!({
            "frame1": {"keypoints": keypoint_set(0.0), "intrinsics": intrinsics()},
            "frame2": {"keypoints": keypoint_set(6.0), "intrinsics": intrinsics()},
            "ratio": 0.8,
            "matcher": "rerank"
        })
    }

    pub fn localize() -> Value {
        json!({"frame": {"keypoints": keypoint_set(0.0)}, "intrinsics": intrinsics()})
    }

    pub fn keyframe() -> Value {
        json!({
            "keyframe_id": 1,
            "pose": {"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0},
            "frame": {"keypoints": keypoint_set(0.0)},
            "intrinsics": intrinsics()
        })
    }

    pub fn create_map() -> Value {
        json!({"map_id": "office"})
    }

    pub fn merge_maps() -> Value {
        json!({"source_map_id": "office-copy",
               "transform": {"tx": 0.0, "ty": 0.0, "tz": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0, "scale": 1.0}})
    }
}

/// Raw bytes: an image (PNG or JPEG), a picture the service drew (PNG), or a map file.
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)] // Documentation of a binary body; the bytes are read and sent as they are.
pub struct Binary(Vec<u8>);

/// A one-frame request as `multipart/form-data`: the JSON fields in a part named `request`, the image as a
/// file part.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct FrameForm {
    /// The request's JSON fields (as the `application/json` body), optional when the image is all.
    request: Option<String>,
    /// PNG or JPEG.
    #[schema(value_type = Option<String>, format = Binary)]
    image: Option<Vec<u8>>,
}

/// A MatchPair request as `multipart/form-data`.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct PairForm {
    /// The request's JSON fields (as the `application/json` body: intrinsics of each frame, ratio, ...).
    request: Option<String>,
    /// Frame 1's image (the part may also be named `image`).
    #[schema(value_type = Option<String>, format = Binary)]
    image1: Option<Vec<u8>>,
    /// Frame 2's image.
    #[schema(value_type = Option<String>, format = Binary)]
    image2: Option<Vec<u8>>,
}

/// An AddKeyframe request as `multipart/form-data`.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct KeyframeForm {
    /// The request's JSON fields (keyframe_id, pose, intrinsics, ...).
    request: String,
    /// PNG or JPEG.
    #[schema(value_type = Option<String>, format = Binary)]
    image: Option<Vec<u8>>,
    /// 16-bit PNG depth aligned with the image.
    #[schema(value_type = Option<String>, format = Binary)]
    depth: Option<Vec<u8>>,
}
