//! The bodies of the frame routes: Describe, MatchPair, Localize and LocalizeTrack.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::common::{Frame, Intrinsics, Keypoint, Pose, PoseConvention, Prior, Similarity};

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
    /// Every plain SConE match and every FREAK match; the pose's robust estimate decides between them, and a
    /// keypoint may count twice among the inliers.
    Both,
    /// FREAK's nearest candidates re-ranked by the SConE embedding.
    Rerank,
    /// `rerank`, or `union` when the two images differ in scale by 1.6x or more (the default of models that
    /// declare none).
    #[serde(rename = "scale-aware")]
    ScaleAware,
    /// One descriptor of both: the unit embedding and FREAK's bits, by L2 with the ratio test.
    Joint,
    /// FREAK alone (Hamming + ratio test): the baseline, for comparison on the same keypoints.
    Freak,
}

impl From<crate::matching::SconeMatcher> for Matcher {
    fn from(m: crate::matching::SconeMatcher) -> Self {
        use crate::matching::SconeMatcher as S;
        match m {
            S::Plain => Self::Plain,
            S::Union => Self::Union,
            S::Both => Self::Both,
            S::Rerank => Self::Rerank,
            S::ScaleAware => Self::ScaleAware,
            S::Joint => Self::Joint,
            S::Freak => Self::Freak,
        }
    }
}

impl From<Matcher> for crate::matching::SconeMatcher {
    fn from(m: Matcher) -> Self {
        match m {
            Matcher::Plain => Self::Plain,
            Matcher::Union => Self::Union,
            Matcher::Both => Self::Both,
            Matcher::Rerank => Self::Rerank,
            Matcher::ScaleAware => Self::ScaleAware,
            Matcher::Joint => Self::Joint,
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
    /// Absent: the model's (`union` for the embedded model; `matcher` in the answer names it).
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
    /// The extraction this server runs: what a keypoint set must be extracted with.
    pub extraction: Extraction,
}

/// The numbers of the client contract a server runs: the model's declared extraction with the server's
/// `[extractor]` over it (revision 3: 20, 2000, 8, 1.2, 32; revision 2, the constellation model's: 20, 1500, 6,
/// 1.2, 32).
#[derive(Debug, Serialize, ToSchema)]
pub struct Extraction {
    pub fast_threshold: i32,
    pub max_keypoints: usize,
    pub levels: u32,
    pub scale_factor: f64,
    pub grid_cell: u32,
}

impl From<&crate::describe::features::ExtractorSettings> for Extraction {
    fn from(e: &crate::describe::features::ExtractorSettings) -> Self {
        Self {
            fast_threshold: e.fast_threshold,
            max_keypoints: e.max_keypoints,
            levels: e.levels,
            scale_factor: e.scale_factor,
            grid_cell: e.grid_cell,
        }
    }
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
    /// The matcher that picked the matches: the request's, or the model's default.
    pub matcher: Matcher,
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

/// One frame of a track: the frame (or a multipart part `trackN` with its image, N its position) and its
/// pose in the track's frame.
#[derive(Debug, Clone, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackFrame {
    /// Absent when the image comes as the multipart part `trackN`; its intrinsics are then given here with no
    /// image: `{"intrinsics": {...}}`.
    #[serde(default)]
    pub frame: Option<Frame>,
    /// The frame's pose in the track's frame (camera-to-track in the default convention): the tracker's pose.
    pub pose: Pose,
}

/// 2-10 frames with their poses relative to each other, located together (rpc LocalizeTrack).
#[derive(Debug, Clone, Default, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct LocalizeTrackRequest {
    pub frames: Vec<TrackFrame>,
    /// False: rigid (a metric track against a metric map); true: the scale between track and map is estimated.
    #[serde(default)]
    pub estimate_scale: bool,
    #[serde(default)]
    pub prior: Option<Prior>,
    /// The convention of the frames' poses and of the answer's.
    #[serde(default)]
    pub pose_convention: Option<PoseConvention>,
    /// How far the frames' poses may be off (it widens the answer's covariance). Absent: a phone's tracker, 1 %
    /// of the distance from frame 0 and 0.5 degrees per frame; zeros: a rig's calibrated extrinsics.
    #[serde(default)]
    pub tracker_error: Option<TrackerError>,
}

/// The error of a track's relative poses, as root mean square sizes in no preferred direction.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TrackerError {
    /// Frame f's position relative to frame 0 is off by this share of their distance, in [0, 1].
    pub translation_share: f64,
    /// Its orientation is off by this many degrees per frame between it and frame 0 in the request's order,
    /// in [0, 45].
    pub degrees_per_frame: f64,
}

/// What became of one frame of a track.
#[derive(Debug, Serialize, ToSchema)]
pub struct TrackFrameResult {
    /// When localised: the frame's camera in the map, in the request's convention.
    pub pose: Option<Pose>,
    pub matches: usize,
    pub inliers: usize,
    /// Left out of the estimate: its own pose disagreed with the other frames' (blur, a wrong relative pose).
    pub dropped: bool,
    /// Whether Localize of this frame alone found a pose.
    pub localized_alone: bool,
}

/// A track's transform into the map, or `localized: false`.
#[derive(Debug, Serialize, ToSchema)]
pub struct LocalizeTrackResponse {
    pub localized: bool,
    /// Track to map: `X_map = scale * R * X_track + t` (scale 1 when rigid).
    pub map_from_track: Option<Similarity>,
    /// In the request's order.
    pub frames: Vec<TrackFrameResult>,
    /// Over all frames.
    pub inliers: usize,
    pub reprojection_error: f64,
    /// As Localize's, for frame 0's pose.
    pub confidence: f64,
    /// Frame 0's pose covariance, as Localize's.
    pub covariance: Vec<f64>,
    /// The frame whose own pose is the answer (no joint estimate had more inliers than it alone); absent for
    /// the joint estimate.
    pub single_frame: Option<usize>,
}
