//! What several bodies share: frames (an image or keypoints) with intrinsics, poses and their convention,
//! priors, points, similarities, the render switch.

use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

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

impl From<&crate::describe::features::Keypoint> for Keypoint {
    fn from(k: &crate::describe::features::Keypoint) -> Self {
        Self { x: k.x, y: k.y, size: k.size, angle: k.angle, response: k.response, octave: k.octave }
    }
}

impl From<&Keypoint> for crate::describe::features::Keypoint {
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

/// A 3D point in map units.
#[derive(Debug, Clone, Copy, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Point3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
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

/// Query of the routes that can answer with a picture.
#[derive(Debug, Default, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct RenderQuery {
    /// `png`: answer with a picture of the matches instead of JSON (as `Accept: image/png` does).
    pub render: Option<String>,
}
