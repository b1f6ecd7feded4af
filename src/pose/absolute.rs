//! Absolute camera pose from 2D-3D matches: solvePnPRansac on the best matches, then the inliers among all of
//! them refined with Levenberg-Marquardt; and the same for a camera whose focal length is unknown.

use nalgebra::{Isometry3, Matrix6, Vector3};
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use crate::camera::{validate_camera, Camera};
use crate::error::PoseError;
use crate::pose::covariance::{covariance_at, world_to_camera};
use crate::pose::ransac::{PnpMethod, RansacSettings};

/// An absolute camera pose with its RANSAC support.
#[derive(Debug, Clone)]
pub struct AbsolutePose {
    /// Camera-to-world.
    pub camera_to_world: Isometry3<f64>,
    pub inliers: Vec<usize>,
    /// Mean reprojection error of the inliers after refinement, pixels.
    pub reprojection_error: f64,
    /// Covariance of OpenCV's world-to-camera `(rvec, tvec)` from the refinement on the inliers,
    /// `σ² (JᵀJ)⁻¹` with `σ²` the inliers' residual variance; `None` when `JᵀJ` is singular. Express it in a
    /// client's convention with [`pose_covariance`](crate::pose::pose_covariance).
    pub covariance_w2c: Option<Matrix6<f64>>,
    /// The focal length the pose was estimated with, pixels: the camera's, or the estimate of
    /// [`absolute_pose_unknown_focal`].
    pub focal: f64,
}

/// Correspondences the RANSAC hypotheses are drawn from (the best ones; see [`absolute_pose`]).
pub const RANSAC_HEAD: usize = 300;

/// solvePnPRansac (the estimator of `params.pnp`) on the best [`RANSAC_HEAD`] correspondences (pass them best
/// first), then the inliers among all correspondences by reprojection error, refined with Levenberg-Marquardt.
/// `None` when fewer than `min_inliers` inliers support the pose.
pub fn absolute_pose(
    points3d: &[[f64; 3]],
    points2d: &[(f32, f32)],
    cam: &Camera,
    params: &RansacSettings,
    min_inliers: usize,
) -> Result<Option<AbsolutePose>, PoseError> {
    validate_camera(cam)?;
    if points3d.len() != points2d.len() {
        return Err(PoseError::Mismatch {
            what: "3D points",
            got: points3d.len(),
            other: "2D points",
            expected: points2d.len(),
        });
    }
    if points3d.len() < min_inliers.max(4) {
        return Ok(None);
    }
    let obj: Vector<Point3f> = points3d.iter().map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32)).collect();
    let img: Vector<Point2f> = points2d.iter().map(|&(x, y)| Point2f::new(x, y)).collect();
    let k = Mat::from_slice_2d(&[[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])?;
    let dist = Mat::default();
    let mut rvec = Mat::default();
    let mut tvec = Mat::default();
    let mut inliers = Vector::<i32>::new();
    // Hypotheses come from the best correspondences only (callers pass them best first): the head of the list
    // has a far higher inlier ratio, so RANSAC needs fewer iterations and scores fewer points. On a
    // relocalisation query with ~20 % inliers among ~900 matches, the full set ran into the iteration cap
    // (~90 ms); the inlier set is then taken from all correspondences below.
    let head = points3d.len().min(RANSAC_HEAD);
    let head_obj: Vector<Point3f> = obj.iter().take(head).collect();
    let head_img: Vector<Point2f> = img.iter().take(head).collect();
    let found = match params.pnp.flag() {
        Some(flags) => opencv::calib3d::solve_pnp_ransac(
            &head_obj,
            &head_img,
            &k,
            &dist,
            &mut rvec,
            &mut tvec,
            false,
            params.max_iters,
            params.threshold_px as f32,
            params.confidence,
            &mut inliers,
            flags,
        )?,
        None => {
            let mut k_used = k.clone();
            let usac = PnpMethod::usac_params(params)?;
            opencv::calib3d::solve_pnp_ransac_1(
                &head_obj,
                &head_img,
                &mut k_used,
                &dist,
                &mut rvec,
                &mut tvec,
                &mut inliers,
                usac,
            )?
        }
    };
    if !found || inliers.len() < 6 {
        return Ok(None);
    }
    // The inlier set is decided here, by our own threshold on the reprojection error of every correspondence,
    // not by the sampler's: select, refine (Levenberg-Marquardt), select again, refine again.
    let select = |rvec: &Mat, tvec: &Mat| -> Result<Vec<usize>, PoseError> {
        let mut projected = Vector::<Point2f>::new();
        opencv::calib3d::project_points_def(&obj, rvec, tvec, &k, &dist, &mut projected)?;
        Ok(projected
            .iter()
            .zip(img.iter())
            .enumerate()
            .filter(|(_, (a, b))| ((a.x - b.x) as f64).hypot((a.y - b.y) as f64) <= params.threshold_px)
            .map(|(i, _)| i)
            .collect())
    };
    let mut chosen: Vec<usize> = inliers.iter().map(|i| i as usize).collect();
    for _ in 0..2 {
        if chosen.len() < min_inliers.max(4) {
            return Ok(None);
        }
        let (in_obj, in_img) = inlier_points(points3d, points2d, &chosen);
        opencv::calib3d::solve_pnp_refine_lm_def(&in_obj, &in_img, &k, &dist, &mut rvec, &mut tvec)?;
        chosen = select(&rvec, &tvec)?;
    }
    if chosen.len() < min_inliers {
        return Ok(None);
    }
    let (in_obj, in_img) = inlier_points(points3d, points2d, &chosen);
    let mut projected = Vector::<Point2f>::new();
    opencv::calib3d::project_points_def(&in_obj, &rvec, &tvec, &k, &dist, &mut projected)?;
    let err =
        projected.iter().zip(in_img.iter()).map(|(a, b)| ((a.x - b.x) as f64).hypot((a.y - b.y) as f64)).sum::<f64>()
            / in_img.len().max(1) as f64;
    let rv = Vector3::new(*rvec.at::<f64>(0)?, *rvec.at::<f64>(1)?, *rvec.at::<f64>(2)?);
    let tv = Vector3::new(*tvec.at::<f64>(0)?, *tvec.at::<f64>(1)?, *tvec.at::<f64>(2)?);
    if !rv.iter().chain(tv.iter()).all(|v| v.is_finite()) {
        return Ok(None);
    }
    let covariance_w2c = covariance_at(&world_to_camera(&rv, &tv), &in_obj, &in_img, &k, false)?;
    // OpenCV returns world-to-camera; invert to camera-to-world.
    Ok(Some(AbsolutePose {
        camera_to_world: world_to_camera(&rv, &tv).inverse(),
        inliers: chosen,
        reprojection_error: err,
        covariance_w2c,
        focal: cam.fx,
    }))
}

/// Focal lengths tried when a query's is unknown, as multiples of the image's larger side: a geometric grid
/// from 0.42 to 8 (fields of view across the larger side from about 100° down to 7°), four steps per octave.
pub fn focal_candidates(cam: &Camera) -> Vec<f64> {
    let side = f64::from(cam.width.max(cam.height));
    (-5..=12).map(|i| side * 2f64.powf(f64::from(i) / 4.0)).collect()
}

/// RANSAC iterations per focal-length candidate: at the right focal length the best correspondences hold
/// mostly inliers and few iterations find them; at a wrong one the full budget would only be spent on failing.
pub const CANDIDATE_ITERATIONS: i32 = 300;

/// [`absolute_pose`] for a camera whose focal length is unknown (`cam.fx`, `cam.fy` ignored; square pixels,
/// the principal point as given). Each of [`focal_candidates`] is tried (at most [`CANDIDATE_ITERATIONS`]
/// RANSAC iterations each); the one with the most inliers seeds OpenCV's `calibrateCamera` on those inliers,
/// which refines the focal length together with the pose (principal point and aspect ratio fixed, no
/// distortion). The pose is estimated again at that focal length, the focal length refined once more on the
/// new inliers, and the pose estimated at it: that answer's inliers give the covariance, with the focal length
/// as a seventh parameter marginalised out. `None` when no candidate reaches `min_inliers`, or the focal length
/// leaves the candidates' range.
pub fn absolute_pose_unknown_focal(
    points3d: &[[f64; 3]],
    points2d: &[(f32, f32)],
    cam: &Camera,
    params: &RansacSettings,
    min_inliers: usize,
) -> Result<Option<AbsolutePose>, PoseError> {
    let candidates = focal_candidates(cam);
    let (lo, hi) = (candidates[0], candidates[candidates.len() - 1]);
    let scan = RansacSettings { max_iters: params.max_iters.min(CANDIDATE_ITERATIONS), ..*params };
    let mut best: Option<AbsolutePose> = None;
    for &f in &candidates {
        if let Some(p) = absolute_pose(points3d, points2d, &cam.with_focal(f), &scan, min_inliers)? {
            let better = best
                .as_ref()
                .is_none_or(|b| (p.inliers.len(), -p.reprojection_error) > (b.inliers.len(), -b.reprojection_error));
            if better {
                best = Some(p);
            }
        }
    }
    let Some(mut pose) = best else { return Ok(None) };
    for _ in 0..2 {
        let f = refine_focal(points3d, points2d, &pose, cam)?;
        if !(f.is_finite() && (lo..=hi).contains(&f)) {
            return Ok(None);
        }
        match absolute_pose(points3d, points2d, &cam.with_focal(f), params, min_inliers)? {
            Some(p) => pose = p,
            None => return Ok(None),
        }
    }
    // The covariance with the focal length free, on the answer's inliers.
    let (in_obj, in_img) = inlier_points(points3d, points2d, &pose.inliers);
    let k = Mat::from_slice_2d(&cam.with_focal(pose.focal).k())?;
    pose.covariance_w2c = covariance_at(&pose.camera_to_world.inverse(), &in_obj, &in_img, &k, true)?;
    Ok(Some(pose))
}

fn inlier_points(
    points3d: &[[f64; 3]],
    points2d: &[(f32, f32)],
    inliers: &[usize],
) -> (Vector<Point3f>, Vector<Point2f>) {
    let obj = inliers.iter().map(|&i| points3d[i]).map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32));
    let img = inliers.iter().map(|&i| points2d[i]).map(|(x, y)| Point2f::new(x, y));
    (obj.collect(), img.collect())
}

/// The focal length that OpenCV's `calibrateCamera` fits, with the pose, to `pose`'s inliers, starting from
/// `pose.focal` (principal point and aspect ratio fixed, no distortion).
fn refine_focal(
    points3d: &[[f64; 3]],
    points2d: &[(f32, f32)],
    pose: &AbsolutePose,
    cam: &Camera,
) -> Result<f64, PoseError> {
    use opencv::calib3d as c;
    let (obj, img) = inlier_points(points3d, points2d, &pose.inliers);
    let objects: Vector<Vector<Point3f>> = std::iter::once(obj).collect();
    let images: Vector<Vector<Point2f>> = std::iter::once(img).collect();
    let mut k = Mat::from_slice_2d(&cam.with_focal(pose.focal).k())?;
    let mut dist = Mat::zeros(5, 1, opencv::core::CV_64F)?.to_mat()?;
    let (mut rvecs, mut tvecs) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let flags = c::CALIB_USE_INTRINSIC_GUESS
        | c::CALIB_FIX_PRINCIPAL_POINT
        | c::CALIB_FIX_ASPECT_RATIO
        | c::CALIB_ZERO_TANGENT_DIST
        | c::CALIB_FIX_K1
        | c::CALIB_FIX_K2
        | c::CALIB_FIX_K3;
    let criteria = opencv::core::TermCriteria::new(
        opencv::core::TermCriteria_Type::COUNT as i32 + opencv::core::TermCriteria_Type::EPS as i32,
        100,
        1e-12,
    )?;
    let size = opencv::core::Size::new(cam.width as i32, cam.height as i32);
    c::calibrate_camera(&objects, &images, size, &mut k, &mut dist, &mut rvecs, &mut tvecs, flags, criteria)?;
    Ok(*k.at_2d::<f64>(0, 0)?)
}
