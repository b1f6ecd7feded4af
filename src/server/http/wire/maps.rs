//! The bodies of the map routes: create, keyframes, merge, info, listings and contents.

use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::common::{Frame, Intrinsics, Point3, Pose, PoseConvention, Similarity};
use crate::service::MapSummary;

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
