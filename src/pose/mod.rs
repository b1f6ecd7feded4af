//! Pose estimation with OpenCV: relative pose from an essential matrix (USAC or RANSAC + recoverPose) and absolute
//! camera pose from 2D-3D matches (solvePnPRansac + Levenberg-Marquardt refinement on the inliers).
//!
//! Conventions: a relative pose `(R, t)` maps points of camera 1 into camera 2, `X2 = R X1 + t`, with `t` of
//! unit length (the scale is unobservable); absolute poses are camera-to-world, as in the map and the scenes.
//!
//! Rooms: `ransac.rs` (the settings both estimators share), `relative.rs` (essential matrix), `absolute.rs`
//! (PnP, also with the focal length unknown), `covariance.rs` (how sure an absolute pose is, in a client's
//! convention), `track.rs` (several frames with known relative poses located together); here, the comparisons
//! of two poses that evaluations and tests make.

use nalgebra::{Isometry3, Rotation3, Vector3};

mod absolute;
mod covariance;
mod ransac;
mod relative;
#[cfg(test)]
mod tests;
mod track;

pub use absolute::{
    absolute_pose, absolute_pose_unknown_focal, focal_candidates, AbsolutePose, CANDIDATE_ITERATIONS, RANSAC_HEAD,
};
pub use covariance::{pose_covariance, pose_difference, CHI2_6_95};
pub use ransac::{ransac_iterations_needed, EssentialMethod, PnpMethod, RansacSettings};
pub use relative::{relative_pose, RelativePose};
pub use track::{track_pose, FrameOutcome, TrackFrame, TrackPose, TrackScale, TrackerError};

/// Angle between two rotations, degrees: acos((tr(R1ᵀ R2) − 1) / 2).
pub fn rotation_error_deg(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    let m = a.matrix().transpose() * b.matrix();
    ((m.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Angle between two translation directions, degrees.
pub fn translation_angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    let (na, nb) = (a.norm(), b.norm());
    if na < 1e-12 || nb < 1e-12 {
        return 0.0;
    }
    (a.dot(b) / (na * nb)).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Ground-truth relative motion from camera 1 to camera 2 given camera-to-world poses: `X2 = R X1 + t`.
pub fn relative_motion(t_w1: &Isometry3<f64>, t_w2: &Isometry3<f64>) -> Isometry3<f64> {
    t_w2.inverse() * t_w1
}
