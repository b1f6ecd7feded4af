//! Pose estimation with OpenCV: relative pose from an essential matrix (USAC or RANSAC + recoverPose) and absolute
//! camera pose from 2D-3D matches (solvePnPRansac + Levenberg-Marquardt refinement on the inliers).
//!
//! Conventions: a relative pose `(R, t)` maps points of camera 1 into camera 2, `X2 = R X1 + t`, with `t` of
//! unit length (the scale is unobservable); absolute poses are camera-to-world, as in the map and the scenes.

use nalgebra::{Isometry3, Matrix3, Matrix6, Rotation3, Translation3, UnitQuaternion, Vector3, Vector6};
use opencv::core::{Mat, Point2d, Point2f, Point3f, Vector};
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::{validate_camera, Camera, PoseConvention};
use crate::error::PoseError;

/// RANSAC settings shared by both estimators.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RansacSettings {
    /// Inlier threshold in pixels.
    pub threshold_px: f64,
    pub confidence: f64,
    pub max_iters: i32,
    /// The essential-matrix estimator (relative pose only; PnP always refines its inliers).
    pub essential: EssentialMethod,
    /// Relative pose only: a correspondence within this many pixels of an earlier one in both images (one
    /// corner matched again through its copies on other pyramid levels) is left out of the estimation and
    /// takes that one's inlier flag. 0 = off.
    pub duplicate_px: f64,
}

/// The relative-pose defaults: 1 px, USAC_ACCURATE, and a search of up to 10,000 iterations at confidence
/// 0.9999. OpenCV's own defaults (1,000 at 0.999) stop short on wide baselines: at 30 % inliers a 5-point
/// search needs about 2,800 iterations for 0.999, and on the selection split (5 standard scenes + 4
/// wide-orbit sequences) the larger budget raised mean AUC@10 from 0.678 to 0.694 for SConE and from 0.684 to
/// 0.707 for FREAK. Relocalisation sets its own PnP parameters (`map::localize`).
impl Default for RansacSettings {
    fn default() -> Self {
        Self {
            threshold_px: 1.0,
            confidence: 0.9999,
            max_iters: 10_000,
            essential: EssentialMethod::UsacAccurate,
            duplicate_px: 0.0,
        }
    }
}

impl RansacSettings {
    /// A finite positive threshold, a confidence strictly between 0 and 1 and at least one iteration.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.threshold_px.is_finite() && self.threshold_px > 0.0) {
            return Err(format!("threshold_px must be a positive number, got {}", self.threshold_px));
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(format!("confidence must lie strictly between 0 and 1, got {}", self.confidence));
        }
        if self.max_iters < 1 {
            return Err(format!("max_iters must be at least 1, got {}", self.max_iters));
        }
        if !(self.duplicate_px.is_finite() && self.duplicate_px >= 0.0) {
            return Err(format!("duplicate_px must be a number >= 0, got {}", self.duplicate_px));
        }
        Ok(())
    }

    /// OpenCV's `findEssentialMat` defaults (plain RANSAC, 1,000 iterations, confidence 0.999) at `threshold_px`:
    /// the data README's baseline pipeline.
    pub fn opencv(threshold_px: f64) -> Self {
        Self { threshold_px, confidence: 0.999, max_iters: 1000, essential: EssentialMethod::Ransac, duplicate_px: 0.0 }
    }
}

/// How `findEssentialMat` searches. The default is `UsacAccurate`: on the selection split (rendered
/// sequences 36-39 and castle frames 20-29) it raised pair AUC@10 from 0.676 to 0.806 for FREAK and from 0.629
/// to 0.796 for SConE over `Ransac`, because the plain estimator returns an unrefined 5-point model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum EssentialMethod {
    /// Classic RANSAC over 5-point samples; the best sample's model is returned as it is (OpenCV's `RANSAC`,
    /// the data README's configuration).
    Ransac,
    /// OpenCV's USAC with local optimisation of the best model on its inliers (`USAC_ACCURATE`).
    UsacAccurate,
    /// OpenCV's USAC with MAGSAC++ scoring (`USAC_MAGSAC`).
    UsacMagsac,
}

impl EssentialMethod {
    fn flag(self) -> i32 {
        match self {
            EssentialMethod::Ransac => opencv::calib3d::RANSAC,
            EssentialMethod::UsacAccurate => opencv::calib3d::USAC_ACCURATE,
            EssentialMethod::UsacMagsac => opencv::calib3d::USAC_MAGSAC,
        }
    }
}

/// A relative pose with its RANSAC support.
#[derive(Debug, Clone)]
pub struct RelativePose {
    pub rotation: Rotation3<f64>,
    /// Unit translation direction.
    pub translation: Vector3<f64>,
    /// One flag per input correspondence.
    pub inliers: Vec<bool>,
    pub inlier_count: usize,
}

/// Iterations a RANSAC with a minimal sample of `sample` points needs to find an all-inlier sample with
/// `confidence`, at inlier ratio `w`: `ln(1 - confidence) / ln(1 - w^sample)` (the adaptive stopping rule).
pub fn ransac_iterations_needed(w: f64, sample: i32, confidence: f64) -> f64 {
    if w <= 0.0 {
        return f64::INFINITY;
    }
    let p = w.powi(sample);
    if p >= 1.0 {
        return 1.0;
    }
    ((1.0 - confidence).ln() / (1.0 - p).ln()).max(1.0)
}

fn normalised(points: &[(f32, f32)], cam: &Camera) -> Vector<Point2d> {
    points.iter().map(|&(x, y)| Point2d::new((x as f64 - cam.cx) / cam.fx, (y as f64 - cam.cy) / cam.fy)).collect()
}

fn mat3(m: &Mat) -> Result<Matrix3<f64>, PoseError> {
    let mut out = Matrix3::zeros();
    for r in 0..3 {
        for c in 0..3 {
            out[(r, c)] = *m.at_2d::<f64>(r as i32, c as i32)?;
        }
    }
    Ok(out)
}

/// Essential matrix by `params.essential` on normalised coordinates (threshold converted by the mean focal
/// length), then recoverPose. `None` when fewer than 5 correspondences or no pose has support.
pub fn relative_pose(
    p1: &[(f32, f32)],
    p2: &[(f32, f32)],
    cam1: &Camera,
    cam2: &Camera,
    params: &RansacSettings,
) -> Result<Option<RelativePose>, PoseError> {
    validate_camera(cam1)?;
    validate_camera(cam2)?;
    if p1.len() != p2.len() {
        return Err(PoseError::Mismatch { what: "image 1", got: p1.len(), other: "image 2", expected: p2.len() });
    }
    if p1.len() < 5 {
        return Ok(None);
    }
    // rep[i]: the position in `kept` of correspondence i's representative.
    let (kept, rep) = representatives(p1, p2, params.duplicate_px);
    if kept.len() < 5 {
        return Ok(None);
    }
    let q1: Vec<(f32, f32)> = kept.iter().map(|&i| p1[i]).collect();
    let q2: Vec<(f32, f32)> = kept.iter().map(|&i| p2[i]).collect();
    let n1 = normalised(&q1, cam1);
    let n2 = normalised(&q2, cam2);
    let focal = (cam1.fx + cam1.fy + cam2.fx + cam2.fy) / 4.0;
    let mut mask = Mat::default();
    let e = opencv::calib3d::find_essential_mat_1(
        &n1,
        &n2,
        1.0,
        Point2d::new(0.0, 0.0),
        params.essential.flag(),
        params.confidence,
        params.threshold_px / focal,
        params.max_iters,
        &mut mask,
    )?;
    if e.rows() < 3 || e.cols() != 3 {
        return Ok(None);
    }
    let e3 = e.row_range(&opencv::core::Range::new(0, 3)?)?.try_clone()?;
    let mut r = Mat::default();
    let mut t = Mat::default();
    let identity = Mat::eye(3, 3, opencv::core::CV_64F)?.to_mat()?;
    let count = opencv::calib3d::recover_pose_estimated(&e3, &n1, &n2, &identity, &mut r, &mut t, &mut mask)?;
    if count < 5 {
        return Ok(None);
    }
    let rotation = Rotation3::from_matrix_unchecked(mat3(&r)?);
    let translation = Vector3::new(*t.at_2d::<f64>(0, 0)?, *t.at_2d::<f64>(1, 0)?, *t.at_2d::<f64>(2, 0)?);
    let kept_inlier: Vec<bool> =
        (0..kept.len()).map(|i| mask.at::<u8>(i as i32).map(|v| *v != 0)).collect::<Result<_, _>>()?;
    let inliers: Vec<bool> = rep.iter().map(|&r| kept_inlier[r]).collect();
    let inlier_count = inliers.iter().filter(|&&b| b).count();
    Ok(Some(RelativePose { rotation, translation: translation.normalize(), inliers, inlier_count }))
}

/// Greedy duplicate suppression: correspondence i is kept unless an earlier kept one lies within `radius` px of
/// it in both images. Returns the kept indices and, per input, the position in that list of its representative
/// (itself when kept). `radius <= 0` keeps everything.
fn representatives(p1: &[(f32, f32)], p2: &[(f32, f32)], radius: f64) -> (Vec<usize>, Vec<usize>) {
    if radius <= 0.0 {
        return ((0..p1.len()).collect(), (0..p1.len()).collect());
    }
    let r2 = (radius * radius) as f32;
    let near = |a: (f32, f32), b: (f32, f32)| (a.0 - b.0).powi(2) + (a.1 - b.1).powi(2) <= r2;
    let mut kept: Vec<usize> = Vec::new();
    let mut rep = Vec::with_capacity(p1.len());
    for i in 0..p1.len() {
        match kept.iter().position(|&k| near(p1[i], p1[k]) && near(p2[i], p2[k])) {
            Some(pos) => rep.push(pos),
            None => {
                rep.push(kept.len());
                kept.push(i);
            }
        }
    }
    (kept, rep)
}

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
    /// client's convention with [`pose_covariance`].
    pub covariance_w2c: Option<Matrix6<f64>>,
    /// The focal length the pose was estimated with, pixels: the camera's, or the estimate of
    /// [`absolute_pose_unknown_focal`].
    pub focal: f64,
}

/// The 95 % quantile of the χ² distribution with 6 degrees of freedom: a 6-d Gaussian error lies within the
/// ellipsoid `eᵀ Σ⁻¹ e <= 12.592` with probability 0.95.
pub const CHI2_6_95: f64 = 12.591587;

fn world_to_camera(rvec: &Vector3<f64>, tvec: &Vector3<f64>) -> Isometry3<f64> {
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
fn covariance_at(
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

/// Correspondences the RANSAC hypotheses are drawn from (the best ones; see [`absolute_pose`]).
pub const RANSAC_HEAD: usize = 300;

/// solvePnPRansac (EPnP inside RANSAC) on the best [`RANSAC_HEAD`] correspondences (pass them best first),
/// then the inliers among all correspondences by reprojection error, refined with Levenberg-Marquardt.
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
    let found = opencv::calib3d::solve_pnp_ransac(
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
        opencv::calib3d::SOLVEPNP_EPNP,
    )?;
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

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
    }

    fn project(cam: &Camera, t_cw: &Isometry3<f64>, p: &Vector3<f64>) -> Option<(f32, f32)> {
        let c = t_cw * nalgebra::Point3::from(*p);
        (c.z > 0.1).then(|| ((cam.fx * c.x / c.z + cam.cx) as f32, (cam.fy * c.y / c.z + cam.cy) as f32))
    }

    /// Camera 2's pose (camera-to-world) in the relative-pose tests; camera 1 is at the origin.
    fn second_camera() -> Isometry3<f64> {
        Isometry3::new(Vector3::new(0.5, 0.05, 0.1), Vector3::new(0.02, -0.15, 0.03))
    }

    /// A point's index and its pixel positions in cameras 1 and 2.
    type Seen = (usize, (f32, f32), (f32, f32));

    /// Point `i` of `n` spread 4-9 m in front of camera 1, projected into both cameras, for the points both
    /// cameras see.
    fn two_views(n: usize) -> Vec<Seen> {
        let (c, t_w2) = (cam(), second_camera());
        (0..n)
            .filter_map(|i| {
                let x = Vector3::new(
                    ((i * 37) % 100) as f64 / 25.0 - 2.0,
                    ((i * 53) % 100) as f64 / 33.0 - 1.5,
                    4.0 + ((i * 71) % 100) as f64 / 20.0,
                );
                Some((i, project(&c, &Isometry3::identity(), &x)?, project(&c, &t_w2.inverse(), &x)?))
            })
            .collect()
    }

    /// Points spread in front of both cameras, a known motion, 30 % outliers: the pose comes back.
    #[test]
    fn relative_pose_recovers_a_known_motion() {
        let c = cam();
        let (mut p1, mut p2) = (Vec::new(), Vec::new());
        for (i, a, b) in two_views(200) {
            p1.push(a);
            p2.push(if i % 10 < 3 { (b.0 + 40.0 + (i % 7) as f32 * 9.0, b.1 - 25.0) } else { b });
        }
        let pose = relative_pose(&p1, &p2, &c, &c, &RansacSettings::default()).unwrap().unwrap();
        let gt = relative_motion(&Isometry3::identity(), &second_camera());
        assert!(rotation_error_deg(&pose.rotation, &gt.rotation.to_rotation_matrix()) < 0.5);
        assert!(translation_angle_deg(&pose.translation, &gt.translation.vector) < 2.0);
        assert!(pose.inlier_count >= p1.len() * 6 / 10);
    }

    #[test]
    fn duplicates_are_left_out_of_the_estimate_and_share_their_representative_flag() {
        let p1 = [(10.0, 10.0), (11.0, 10.5), (10.5, 10.0), (50.0, 50.0), (11.0, 10.0)];
        let p2 = [(20.0, 20.0), (21.0, 20.0), (40.0, 20.0), (60.0, 60.0), (20.5, 21.0)];
        // 1 and 4 copy 0 in both images; 2 is near 0 in image 1 only, so it stays.
        let (kept, rep) = representatives(&p1, &p2, 2.0);
        assert_eq!(kept, vec![0, 2, 3]);
        assert_eq!(rep, vec![0, 0, 1, 2, 0]);
        assert_eq!(representatives(&p1, &p2, 0.0).0.len(), 5);
        // The same motion as above with every correspondence given three times, 1 px apart: the pose is the
        // same, and each input gets a flag, copies included.
        let c = cam();
        let (mut p1, mut p2) = (Vec::new(), Vec::new());
        for (_, a, b) in two_views(120) {
            for d in [0.0, 0.7, -0.7] {
                p1.push((a.0 + d, a.1));
                p2.push((b.0, b.1 + d));
            }
        }
        let params = RansacSettings { duplicate_px: 2.0, threshold_px: 2.0, ..Default::default() };
        let pose = relative_pose(&p1, &p2, &c, &c, &params).unwrap().unwrap();
        let gt = relative_motion(&Isometry3::identity(), &second_camera());
        assert!(rotation_error_deg(&pose.rotation, &gt.rotation.to_rotation_matrix()) < 0.5);
        assert_eq!(pose.inliers.len(), p1.len());
        assert!(pose.inlier_count >= p1.len() * 9 / 10, "{} of {}", pose.inlier_count, p1.len());
        assert!(RansacSettings { duplicate_px: f64::NAN, ..Default::default() }.validate().is_err());
    }

    #[test]
    fn absolute_pose_recovers_a_known_camera() {
        let c = cam();
        let t_wc = Isometry3::new(Vector3::new(0.3, -0.2, -1.0), Vector3::new(0.1, 0.2, -0.05));
        let (mut p3, mut p2) = (Vec::new(), Vec::new());
        for i in 0..150 {
            let x = Vector3::new(
                ((i * 37) % 100) as f64 / 25.0 - 2.0,
                ((i * 53) % 100) as f64 / 33.0 - 1.5,
                3.0 + ((i * 71) % 100) as f64 / 30.0,
            );
            if let Some(uv) = project(&c, &t_wc.inverse(), &x) {
                p3.push([x.x, x.y, x.z]);
                p2.push(if i % 5 == 0 { (uv.0 + 50.0, uv.1 + 30.0) } else { uv });
            }
        }
        let pose = absolute_pose(&p3, &p2, &c, &RansacSettings { threshold_px: 2.0, ..Default::default() }, 10)
            .unwrap()
            .unwrap();
        let d = pose.camera_to_world.inverse() * t_wc;
        assert!(d.translation.vector.norm() < 1e-3, "{d:?}");
        assert!(d.rotation.angle() < 1e-3);
        assert!(pose.reprojection_error < 0.01);
    }

    #[test]
    fn too_few_points_give_no_pose() {
        let c = cam();
        let p = vec![(1.0, 2.0); 4];
        assert!(relative_pose(&p, &p, &c, &c, &RansacSettings::default()).unwrap().is_none());
        assert!(absolute_pose(&[[0.0; 3]; 4], &p, &c, &RansacSettings::default(), 10).unwrap().is_none());
    }

    #[test]
    fn nan_intrinsics_are_refused() {
        let bad = Camera { fx: f64::NAN, ..cam() };
        let p = vec![(1.0, 2.0); 8];
        assert!(matches!(
            relative_pose(&p, &p, &bad, &cam(), &RansacSettings::default()),
            Err(PoseError::Intrinsics { .. })
        ));
    }

    #[test]
    fn iterations_needed_follows_the_formula() {
        assert!((ransac_iterations_needed(0.5, 5, 0.999) - 217.6).abs() < 1.0);
        assert!(ransac_iterations_needed(0.0, 5, 0.999).is_infinite());
        assert_eq!(ransac_iterations_needed(1.0, 5, 0.999), 1.0);
    }

    /// Points 4-9 m in front of a camera, seen with Gaussian pixel noise of 1 px: the refinement's covariance
    /// is a covariance of the answer. In each convention, the true pose lies within the 95 % ellipsoid in
    /// about 95 % of trials, and the focal length estimated without intrinsics is close to the truth.
    #[test]
    fn the_covariance_covers_the_truth_in_every_convention_and_the_focal_length_is_estimated() {
        use rand::{Rng, SeedableRng};
        let c = cam();
        let truth = Isometry3::new(Vector3::new(0.3, -0.2, 0.1), Vector3::new(0.05, 0.2, -0.1));
        let mut rng = rand::rngs::StdRng::seed_from_u64(28);
        let mut gauss = move || {
            let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        let points: Vec<Vector3<f64>> = (0..150)
            .map(|i| {
                truth
                    * nalgebra::Point3::new(
                        ((i * 37) % 100) as f64 / 25.0 - 2.0,
                        ((i * 53) % 100) as f64 / 33.0 - 1.5,
                        4.0 + ((i * 71) % 100) as f64 / 20.0,
                    )
            })
            .map(|p| p.coords)
            .collect();
        let conventions = [
            PoseConvention::OpencvCameraToWorld,
            PoseConvention::OpencvWorldToCamera,
            PoseConvention::OpenglCameraToWorld,
        ];
        let trials = 400;
        let mut inside = [0usize; 3];
        let params = RansacSettings { threshold_px: 4.0, confidence: 0.999, max_iters: 2000, ..Default::default() };
        for _ in 0..trials {
            let (mut p3, mut p2) = (Vec::new(), Vec::new());
            for p in &points {
                if let Some((u, v)) = project(&c, &truth.inverse(), p) {
                    p3.push([p.x, p.y, p.z]);
                    p2.push((u + gauss() as f32, v + gauss() as f32));
                }
            }
            let pose = absolute_pose(&p3, &p2, &c, &params, 15).unwrap().unwrap();
            let cov = pose.covariance_w2c.unwrap();
            for (n, conv) in conventions.iter().enumerate() {
                let sigma = pose_covariance(*conv, &pose.camera_to_world, &cov);
                let e = pose_difference(
                    &conv.from_opencv_camera_to_world(&truth),
                    &conv.from_opencv_camera_to_world(&pose.camera_to_world),
                );
                let d2 = (e.transpose() * sigma.try_inverse().unwrap() * e)[0];
                inside[n] += usize::from(d2 <= CHI2_6_95);
            }
        }
        for (n, k) in inside.iter().enumerate() {
            let share = *k as f64 / trials as f64;
            assert!(
                (0.91..=0.99).contains(&share),
                "{:?}: {share} of the truths in the 95 % ellipsoid",
                conventions[n]
            );
        }

        // Without intrinsics (principal point known): the focal length comes back, and the covariance with it
        // marginalised covers the truth as well (the focal length's uncertainty is in it).
        let unknown = Camera { fx: 0.0, fy: 0.0, ..c };
        let (mut covered, trials) = (0, 120);
        for _ in 0..trials {
            let (mut p3, mut p2) = (Vec::new(), Vec::new());
            for p in &points {
                if let Some((u, v)) = project(&c, &truth.inverse(), p) {
                    p3.push([p.x, p.y, p.z]);
                    p2.push((u + gauss() as f32, v + gauss() as f32));
                }
            }
            let pose = absolute_pose_unknown_focal(&p3, &p2, &unknown, &params, 15).unwrap().unwrap();
            assert!((pose.focal - c.fx).abs() < 0.05 * c.fx, "focal {}", pose.focal);
            let sigma =
                pose_covariance(PoseConvention::default(), &pose.camera_to_world, &pose.covariance_w2c.unwrap());
            let e = pose_difference(&truth, &pose.camera_to_world);
            covered += usize::from((e.transpose() * sigma.try_inverse().unwrap() * e)[0] <= CHI2_6_95);
        }
        let share = covered as f64 / trials as f64;
        eprintln!("unknown focal length: {share} of the truths in the 95 % ellipsoid");
        assert!((0.88..=0.995).contains(&share), "unknown focal length: {share} of the truths in the 95 % ellipsoid");
    }
}
