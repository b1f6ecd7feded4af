//! What a posed keyframe brings to map building: its pose, intrinsics, features and embeddings, and either a
//! depth image or the observations an external SfM made of it.

use nalgebra::Isometry3;
use opencv::core::Mat;
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::describe::features::Features;

/// An observation of a landmark given by an external SfM: where this keyframe sees it and where it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ExternalObservation {
    /// Pixel in this keyframe (x right, y down, (0, 0) the centre of the top-left pixel).
    pub x: f64,
    pub y: f64,
    /// The SfM's id of the 3D point (COLMAP's POINT3D_ID); one id across keyframes is one landmark.
    pub landmark_id: u64,
    /// The point in world coordinates.
    pub point: [f64; 3],
}

/// Depth for a keyframe: 16-bit image and the factor that turns raw values into metres.
pub struct Depth<'a> {
    pub image: &'a Mat,
    /// Metres per raw unit (TUM: [`crate::describe::decode::TUM_DEPTH_SCALE`]).
    pub scale: f64,
}

/// A keyframe to add.
pub struct KeyframeInput<'a> {
    pub id: u64,
    /// Camera-to-world.
    pub pose: Isometry3<f64>,
    pub camera: Camera,
    pub features: &'a Features,
    /// `[N, dim]` embeddings of the features' keypoints.
    pub embeddings: &'a [f32],
    pub depth: Option<Depth<'a>>,
    /// Landmarks given by an external SfM; `Some` (even empty) means this keyframe takes its landmarks from
    /// them only (see the module docs).
    pub external: Option<&'a [ExternalObservation]>,
}
