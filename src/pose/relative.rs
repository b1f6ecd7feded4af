//! Relative pose of two cameras from their correspondences: the essential matrix (USAC or RANSAC on normalised
//! coordinates) and recoverPose, with copies of one correspondence left out of the estimation.

use nalgebra::{Matrix3, Rotation3, Vector3};
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;

use crate::camera::{validate_camera, Camera};
use crate::error::PoseError;
use crate::pose::ransac::RansacSettings;

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
pub(super) fn representatives(p1: &[(f32, f32)], p2: &[(f32, f32)], radius: f64) -> (Vec<usize>, Vec<usize>) {
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
