//! Cameras and poses, shared by every part of the crate: pinhole intrinsics ([`Camera`]) and their checks, lens
//! distortion a client may declare ([`Distortion`]: keypoints are undistorted with OpenCV before anything else
//! uses them), camera-to-world poses as stored in maps and sent by clients ([`Pose`], translation + quaternion
//! x, y, z, w), and the quaternion conversions the transports use.

use nalgebra::{Isometry3, Quaternion, Rotation3, Translation3, UnitQuaternion};
use opencv::prelude::MatTraitConst;
use serde::{Deserialize, Serialize};

use crate::error::PoseError;

/// Pinhole intrinsics without distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// The 3x3 calibration matrix, row-major.
    pub fn k(&self) -> [[f64; 3]; 3] {
        [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
    }

    /// Pixel of a point given in this camera's coordinates; `None` when it is not in front (z <= 0).
    pub fn project(&self, p: &nalgebra::Point3<f64>) -> Option<(f64, f64)> {
        (p.z > 0.0).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy))
    }

    /// Whether the focal length is unknown (`fx` and `fy` both 0: not given). Only Localize accepts such a
    /// camera; it estimates the focal length with the pose.
    pub fn focal_unknown(&self) -> bool {
        self.fx == 0.0 && self.fy == 0.0
    }

    /// Intrinsics as a client may leave them out: `fy` absent (0) takes `fx`, and a principal point of (0, 0)
    /// (absent) is the image centre, `((width - 1) / 2, (height - 1) / 2)` in this API's pixel convention.
    pub fn with_defaults(mut self) -> Self {
        if self.fy == 0.0 && self.fx != 0.0 {
            self.fy = self.fx;
        }
        if self.cx == 0.0 && self.cy == 0.0 {
            self.cx = (f64::from(self.width) - 1.0) / 2.0;
            self.cy = (f64::from(self.height) - 1.0) / 2.0;
        }
        self
    }

    /// This camera with focal length `f` (both axes).
    pub fn with_focal(self, f: f64) -> Self {
        Self { fx: f, fy: f, ..self }
    }
}

/// A lens distortion model with its coefficients, OpenCV's definitions.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub enum Distortion {
    /// No distortion (the keypoints are those of a pinhole camera).
    #[default]
    None,
    /// OpenCV's radial-tangential model (Kalibr's `radtan`): `k1, k2, p1, p2`, optionally `k3`, optionally
    /// `k4, k5, k6` (4, 5 or 8 coefficients).
    RadialTangential(Vec<f64>),
    /// OpenCV's fisheye model (Kalibr's `equidistant`): `k1, k2, k3, k4`.
    Fisheye([f64; 4]),
}

/// Largest absolute distortion coefficient accepted: real lenses stay within single digits; beyond this a
/// value is a unit or ordering mistake.
pub const MAX_DISTORTION_COEFFICIENT: f64 = 100.0;

impl Distortion {
    /// The model from its wire name and coefficients, checked: the count the model takes, finite values
    /// within [`MAX_DISTORTION_COEFFICIENT`].
    pub fn new(model: DistortionModel, coefficients: &[f64]) -> Result<Self, PoseError> {
        let bad = |reason: String| Err(PoseError::Intrinsics { reason });
        if let Some(c) = coefficients.iter().find(|c| !(c.is_finite() && c.abs() <= MAX_DISTORTION_COEFFICIENT)) {
            return bad(format!(
                "distortion coefficients must be finite and within ±{MAX_DISTORTION_COEFFICIENT} (got {c})"
            ));
        }
        match model {
            DistortionModel::None if coefficients.is_empty() => Ok(Self::None),
            DistortionModel::None => {
                bad(format!("{} distortion coefficients given without a distortion model", coefficients.len()))
            }
            DistortionModel::RadialTangential if matches!(coefficients.len(), 4 | 5 | 8) => {
                Ok(Self::RadialTangential(coefficients.to_vec()))
            }
            DistortionModel::RadialTangential => bad(format!(
                "the radial-tangential model takes 4, 5 or 8 coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6]]), got {}",
                coefficients.len()
            )),
            DistortionModel::Fisheye => match coefficients {
                &[a, b, c, d] => Ok(Self::Fisheye([a, b, c, d])),
                _ => {
                    bad(format!("the fisheye model takes 4 coefficients (k1, k2, k3, k4), got {}", coefficients.len()))
                }
            },
        }
    }

    pub fn is_none(&self) -> bool {
        matches!(self, Self::None)
    }

    fn matrices(&self, cam: &Camera) -> opencv::Result<(opencv::core::Mat, opencv::core::Mat)> {
        let k = opencv::core::Mat::from_slice_2d(&cam.k())?;
        let d = match self {
            Self::None => opencv::core::Mat::default(),
            Self::RadialTangential(c) => opencv::core::Mat::from_slice(c)?.try_clone()?,
            Self::Fisheye(c) => opencv::core::Mat::from_slice(c)?.try_clone()?,
        };
        Ok((k, d))
    }

    /// Pixels of a camera with this distortion, as the pinhole camera `cam` would see them (OpenCV
    /// `undistortPoints` with `P = K`, iterated to 1e-10 normalised units; the fisheye model with its own
    /// `fisheye::undistortPoints`).
    pub fn undistort(&self, cam: &Camera, points: &[(f32, f32)]) -> Result<Vec<(f32, f32)>, PoseError> {
        use opencv::core::{Mat, Point2d, TermCriteria, TermCriteria_Type, Vector};
        if self.is_none() || points.is_empty() {
            return Ok(points.to_vec());
        }
        let (k, d) = self.matrices(cam)?;
        let src: Vector<Point2d> = points.iter().map(|&(x, y)| Point2d::new(x.into(), y.into())).collect();
        let mut dst = Vector::<Point2d>::new();
        let criteria = TermCriteria::new(TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32, 100, 1e-10)?;
        match self {
            Self::None => unreachable!(),
            Self::RadialTangential(_) => {
                opencv::calib3d::undistort_points_iter(&src, &mut dst, &k, &d, &Mat::default(), &k, criteria)?
            }
            Self::Fisheye(_) => {
                opencv::calib3d::fisheye_undistort_points(&src, &mut dst, &k, &d, &Mat::default(), &k, criteria)?
            }
        }
        Ok(dst.iter().map(|p| (p.x as f32, p.y as f32)).collect())
    }

    /// The inverse of [`Distortion::undistort`]: where a pinhole pixel of `cam` lands through this lens
    /// (OpenCV `projectPoints` / `fisheye::distortPoints`). For tests and synthetic data.
    pub fn distort(&self, cam: &Camera, points: &[(f64, f64)]) -> Result<Vec<(f64, f64)>, PoseError> {
        use opencv::core::{Mat, Point2d, Point3d, Vector};
        if self.is_none() || points.is_empty() {
            return Ok(points.to_vec());
        }
        let (k, d) = self.matrices(cam)?;
        let normalised = points.iter().map(|&(x, y)| ((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy));
        let mut out = Vector::<Point2d>::new();
        match self {
            Self::None => unreachable!(),
            Self::RadialTangential(_) => {
                let rays: Vector<Point3d> = normalised.map(|(x, y)| Point3d::new(x, y, 1.0)).collect();
                let zero = Mat::from_slice(&[0.0f64; 3])?.try_clone()?;
                opencv::calib3d::project_points_def(&rays, &zero, &zero, &k, &d, &mut out)?;
            }
            Self::Fisheye(_) => {
                let src: Vector<Point2d> = normalised.map(|(x, y)| Point2d::new(x, y)).collect();
                opencv::calib3d::fisheye_distort_points_def(&src, &mut out, &k, &d)?;
            }
        }
        Ok(out.iter().map(|p| (p.x, p.y)).collect())
    }
}

/// The distortion models a client may name (the wire enums of both transports).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DistortionModel {
    #[default]
    None,
    RadialTangential,
    Fisheye,
}

/// Largest focal length accepted, pixels (a 100-megapixel sensor behind a long lens stays far below).
pub const MAX_FOCAL_PX: f64 = 1e6;
/// Largest absolute coordinate of a position (pose translation, prior), map units: 10^8 m holds geocentric
/// coordinates with room to spare; beyond it a value is a client's bug, and squares of it lose precision.
pub const MAX_COORDINATE: f64 = 1e8;

/// Checks intrinsics a client or a file gave: finite focal lengths in (0, [`MAX_FOCAL_PX`]], a non-empty
/// image, and a principal point within one image size of the image (`cx` in [-width, 2 width], `cy` alike).
pub fn validate_camera(cam: &Camera) -> Result<(), PoseError> {
    let bad = |reason: String| Err(PoseError::Intrinsics { reason });
    for (name, v) in [("fx", cam.fx), ("fy", cam.fy)] {
        if !(v.is_finite() && v > 0.0) {
            return bad(format!("{name} must be finite and positive (got {v})"));
        }
        if v > MAX_FOCAL_PX {
            return bad(format!("{name} must be at most {MAX_FOCAL_PX} pixels (got {v})"));
        }
    }
    if cam.width == 0 || cam.height == 0 {
        return bad(format!("width and height must be positive (got {}x{})", cam.width, cam.height));
    }
    for (name, v, size) in [("cx", cam.cx, cam.width), ("cy", cam.cy, cam.height)] {
        let size = f64::from(size);
        if !(v.is_finite() && (-size..=2.0 * size).contains(&v)) {
            return bad(format!(
                "{name} must be finite and within [{}, {}] for this image size (got {v})",
                -size,
                2.0 * size
            ));
        }
    }
    Ok(())
}

/// A camera-to-world pose as translation + unit quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

impl Pose {
    pub fn from_isometry(p: &Isometry3<f64>) -> Self {
        let q = p.rotation.quaternion();
        Self { translation: p.translation.vector.into(), rotation: [q.i, q.j, q.k, q.w] }
    }

    pub fn isometry(&self) -> Isometry3<f64> {
        let [x, y, z, w] = self.rotation;
        Isometry3::from_parts(
            Translation3::new(self.translation[0], self.translation[1], self.translation[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        )
    }

    /// Finite values, a translation within [`MAX_COORDINATE`] on each axis, and a quaternion of unit length
    /// (within 1e-3).
    pub fn validate(&self) -> Result<(), PoseProblem> {
        if !self.translation.iter().chain(self.rotation.iter()).all(|v| v.is_finite()) {
            return Err(PoseProblem::NonFinite);
        }
        if let Some(t) = self.translation.iter().find(|t| t.abs() > MAX_COORDINATE) {
            return Err(PoseProblem::TooFar { coordinate: *t });
        }
        let n = self.rotation.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-3 {
            return Err(PoseProblem::NotUnit { norm: n });
        }
        Ok(())
    }
}

/// Why a pose (or the rotation and translation of a transform) is refused; the caller names the field.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PoseProblem {
    #[error("has a non-finite value")]
    NonFinite,
    #[error("translation {coordinate} is beyond {MAX_COORDINATE} map units")]
    TooFar { coordinate: f64 },
    #[error("quaternion has norm {norm:.6}, expected 1")]
    NotUnit { norm: f64 },
}

/// A similarity between two world frames, `X_to = scale * R * X_from + t` (R a unit quaternion x, y, z, w):
/// how a client gives the transform of a map merge, and how the answer reports it. World frames are the
/// same in every pose convention, so it has none.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
    pub scale: f64,
}

/// Scales a merge transform may have: (1e-6, 1e6). Map units differ (metres, an SfM's arbitrary units), but
/// not by more than that.
pub const SCALE_RANGE: (f64, f64) = (1e-6, 1e6);

impl Similarity {
    /// As [`Pose::validate`] for the rotation and translation, and a finite scale within [`SCALE_RANGE`].
    pub fn checked(&self) -> Result<nalgebra::Similarity3<f64>, String> {
        let pose = Pose { translation: self.translation, rotation: self.rotation };
        pose.validate().map_err(|problem| format!("transform {problem}"))?;
        if !(self.scale.is_finite() && self.scale > SCALE_RANGE.0 && self.scale < SCALE_RANGE.1) {
            return Err(format!(
                "transform scale must lie in ({}, {}) (got {})",
                SCALE_RANGE.0, SCALE_RANGE.1, self.scale
            ));
        }
        let iso = pose.isometry();
        Ok(nalgebra::Similarity3::from_isometry(iso, self.scale))
    }

    pub fn from_nalgebra(s: &nalgebra::Similarity3<f64>) -> Self {
        let p = Pose::from_isometry(&s.isometry);
        Self { translation: p.translation, rotation: p.rotation, scale: s.scaling() }
    }
}

/// How a client expresses a pose. Maps store and compute OpenCV camera-to-world poses (camera x right, y down,
/// z forward); the transports convert what a client sends and what they answer, so a client never converts by
/// hand. The world frame is the client's own in every convention (ARKit and ARCore worlds are y-up: a map
/// made from their poses is y-up as well).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseConvention {
    /// OpenCV axes, camera-to-world (the default, as stored).
    #[default]
    OpencvCameraToWorld,
    /// OpenCV axes, world-to-camera (COLMAP, many SLAM exports).
    OpencvWorldToCamera,
    /// OpenGL axes (x right, y up, z backward), camera-to-world: ARKit and ARCore.
    OpenglCameraToWorld,
}

/// The camera axes of OpenGL in OpenCV's, and back: a half turn about x (its own inverse).
fn flip_yz() -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), std::f64::consts::PI)
}

impl PoseConvention {
    /// A pose given in this convention, as OpenCV camera-to-world.
    pub fn to_opencv_camera_to_world(self, pose: &Isometry3<f64>) -> Isometry3<f64> {
        match self {
            Self::OpencvCameraToWorld => *pose,
            Self::OpencvWorldToCamera => pose.inverse(),
            Self::OpenglCameraToWorld => pose * flip_yz(),
        }
    }

    /// An OpenCV camera-to-world pose, in this convention.
    pub fn from_opencv_camera_to_world(self, pose: &Isometry3<f64>) -> Isometry3<f64> {
        match self {
            Self::OpencvCameraToWorld => *pose,
            Self::OpencvWorldToCamera => pose.inverse(),
            Self::OpenglCameraToWorld => pose * flip_yz(),
        }
    }

    /// A relative pose between two cameras (points of camera 1 into camera 2) in OpenCV axes, in this
    /// convention's camera axes (the direction camera 1 into camera 2 is kept in every convention).
    pub fn relative_from_opencv(
        self,
        rotation: &Rotation3<f64>,
        translation: &nalgebra::Vector3<f64>,
    ) -> (Rotation3<f64>, nalgebra::Vector3<f64>) {
        match self {
            Self::OpencvCameraToWorld | Self::OpencvWorldToCamera => (*rotation, *translation),
            Self::OpenglCameraToWorld => {
                let f = flip_yz().to_rotation_matrix();
                (f * rotation * f, f * translation)
            }
        }
    }
}

/// (x, y, z, w) of a rotation.
pub fn quaternion_xyzw(r: &Rotation3<f64>) -> [f64; 4] {
    let q = UnitQuaternion::from_rotation_matrix(r);
    [q.i, q.j, q.k, q.w]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conventions_round_trip_and_match_their_definitions() {
        let p =
            Isometry3::from_parts(Translation3::new(1.0, -2.0, 0.5), UnitQuaternion::from_euler_angles(0.3, -0.7, 1.1));
        for c in [
            PoseConvention::OpencvCameraToWorld,
            PoseConvention::OpencvWorldToCamera,
            PoseConvention::OpenglCameraToWorld,
        ] {
            let back = c.to_opencv_camera_to_world(&c.from_opencv_camera_to_world(&p));
            assert!((back.to_homogeneous() - p.to_homogeneous()).abs().max() < 1e-12, "{c:?}");
        }
        // World-to-camera maps the camera centre to the origin.
        let w2c = PoseConvention::OpencvWorldToCamera.from_opencv_camera_to_world(&p);
        assert!((w2c * nalgebra::Point3::from(p.translation.vector)).coords.norm() < 1e-12);
        // OpenGL camera-to-world: same centre; its camera looks down -z, OpenCV's down +z, the same ray.
        let gl = PoseConvention::OpenglCameraToWorld.from_opencv_camera_to_world(&p);
        assert_eq!(gl.translation, p.translation);
        let forward_cv = p.rotation * nalgebra::Vector3::z();
        let forward_gl = gl.rotation * -nalgebra::Vector3::z();
        assert!((forward_cv - forward_gl).norm() < 1e-12);
        let up_gl = gl.rotation * nalgebra::Vector3::y();
        assert!((up_gl + p.rotation * nalgebra::Vector3::y()).norm() < 1e-12, "OpenGL y is OpenCV -y");
    }
}
