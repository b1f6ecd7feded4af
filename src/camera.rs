//! Cameras and poses, shared by every part of the crate: pinhole intrinsics ([`Camera`]) and their checks,
//! camera-to-world poses as stored in maps and sent by clients ([`Pose`], translation + quaternion x, y, z, w),
//! and the quaternion conversions the transports use.

use nalgebra::{Isometry3, Quaternion, Rotation3, Translation3, UnitQuaternion};
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
    pub fn validate(&self) -> Result<(), String> {
        if !self.translation.iter().chain(self.rotation.iter()).all(|v| v.is_finite()) {
            return Err("pose has a non-finite value".into());
        }
        if let Some(t) = self.translation.iter().find(|t| t.abs() > MAX_COORDINATE) {
            return Err(format!("pose translation {t} is beyond {MAX_COORDINATE} map units"));
        }
        let n = self.rotation.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (n - 1.0).abs() > 1e-3 {
            return Err(format!("pose quaternion has norm {n:.6}, expected 1"));
        }
        Ok(())
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
