//! How sure an absolute pose is: the covariance of the refinement on the inliers, and that covariance expressed
//! in a client's pose convention.

use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use crate::camera::PoseConvention;
use crate::error::PoseError;

/// The 95 % quantile of the χ² distribution with 6 degrees of freedom: a 6-d Gaussian error lies within the
/// ellipsoid `eᵀ Σ⁻¹ e <= 12.592` with probability 0.95.
pub const CHI2_6_95: f64 = 12.591587;

pub(super) fn world_to_camera(rvec: &Vector3<f64>, tvec: &Vector3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(*tvec), UnitQuaternion::from_scaled_axis(*rvec))
}

/// The difference of two poses as a 6-vector: translation difference, then the rotation vector of
/// `Ra Rbᵀ` (a perturbation on the left, in the pose's outer frame: the world for camera-to-world poses).
pub fn pose_difference(a: &Isometry3<f64>, b: &Isometry3<f64>) -> Vector6<f64> {
    let dt = a.translation.vector - b.translation.vector;
    let dr = (a.rotation * b.rotation.inverse()).scaled_axis();
    Vector6::new(dt.x, dt.y, dt.z, dr.x, dr.y, dr.z)
}

/// The covariance of a pose as `convention` expresses it, over [`pose_difference`]'s parameters (translation
/// x, y, z in map units, then a rotation vector in radians), from the covariance of OpenCV's world-to-camera
/// `(rvec, tvec)` at `camera_to_world` (first-order propagation, central differences).
pub fn pose_covariance(
    convention: PoseConvention,
    camera_to_world: &Isometry3<f64>,
    covariance_w2c: &Matrix6<f64>,
) -> Matrix6<f64> {
    let w2c = camera_to_world.inverse();
    let (r0, t0) = (w2c.rotation.scaled_axis(), w2c.translation.vector);
    let express =
        |r: Vector3<f64>, t: Vector3<f64>| convention.from_opencv_camera_to_world(&world_to_camera(&r, &t).inverse());
    let at = express(r0, t0);
    let mut g = Matrix6::zeros();
    let h = 1e-6;
    for j in 0..6 {
        let (mut rp, mut tp, mut rm, mut tm) = (r0, t0, r0, t0);
        if j < 3 {
            rp[j] += h;
            rm[j] -= h;
        } else {
            tp[j - 3] += h;
            tm[j - 3] -= h;
        }
        let d = (pose_difference(&express(rp, tp), &at) - pose_difference(&express(rm, tm), &at)) / (2.0 * h);
        g.set_column(j, &d);
    }
    g * covariance_w2c * g.transpose()
}

/// `σ² (JᵀJ)⁻¹` of the reprojection residuals at `(rvec, tvec)` (world-to-camera), over those 6 parameters.
/// With `focal_free`, the focal length (square pixels) is a seventh parameter and the pose's block of the
/// 7x7 covariance is returned: the pose's uncertainty with the focal length's marginalised out (a focal
/// length estimated with the pose trades against the distance along the optical axis).
fn refinement_covariance(
    obj: &Vector<Point3f>,
    img: &Vector<Point2f>,
    rvec: &Mat,
    tvec: &Mat,
    k: &Mat,
    focal_free: bool,
) -> Result<Option<Matrix6<f64>>, PoseError> {
    let n = obj.len();
    let params = if focal_free { 7 } else { 6 };
    if 2 * n <= params {
        return Ok(None);
    }
    let mut projected = Vector::<Point2f>::new();
    let mut jacobian = Mat::default();
    opencv::calib3d::project_points(obj, rvec, tvec, k, &Mat::default(), &mut projected, &mut jacobian, 0.0)?;
    // OpenCV's columns: rvec (3), tvec (3), fx, fy, cx, cy, then the distortion coefficients.
    let mut jtj = nalgebra::DMatrix::<f64>::zeros(params, params);
    for row in 0..(2 * n) as i32 {
        let at = |c: i32| jacobian.at_2d::<f64>(row, c).copied().unwrap_or(0.0);
        let mut j = nalgebra::DVector::<f64>::from_fn(params, |c, _| if c < 6 { at(c as i32) } else { 0.0 });
        if focal_free {
            j[6] = at(6) + at(7);
        }
        jtj += &j * j.transpose();
    }
    let sq: f64 = projected
        .iter()
        .zip(img.iter())
        .map(|(a, b)| ((a.x - b.x) as f64).powi(2) + ((a.y - b.y) as f64).powi(2))
        .sum();
    let sigma2 = sq / (2 * n - params) as f64;
    let Some(inverse) = jtj.try_inverse() else { return Ok(None) };
    let c: Matrix6<f64> = inverse.fixed_view::<6, 6>(0, 0).into_owned() * sigma2;
    Ok(c.iter().all(|v| v.is_finite()).then_some(c))
}

/// [`refinement_covariance`] at a world-to-camera pose, parametrised as [`pose_covariance`] expects: the
/// rotation vector of nalgebra (angle at most π), not OpenCV's `rvec` after refinement (which may exceed π and
/// is then another parametrisation of the same rotation).
pub(super) fn covariance_at(
    w2c: &Isometry3<f64>,
    obj: &Vector<Point3f>,
    img: &Vector<Point2f>,
    k: &Mat,
    focal_free: bool,
) -> Result<Option<Matrix6<f64>>, PoseError> {
    let rvec = Mat::from_slice(w2c.rotation.scaled_axis().as_slice())?.try_clone()?;
    let tvec = Mat::from_slice(w2c.translation.vector.as_slice())?.try_clone()?;
    refinement_covariance(obj, img, &rvec, &tvec, k, focal_free)
}
