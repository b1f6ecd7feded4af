//! The geometry of posed keyframes: where a world point lands in one, how far from a keypoint, which way a
//! keyframe looks, and pixel pairs of two keyframes triangulated (OpenCV).

use nalgebra::{Isometry3, Point3, Vector3};
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;

use crate::camera::Camera;
use crate::error::MapError;

/// Pixel of a world point in a keyframe, with its depth (None when behind the camera).
pub(super) fn project(pose_wc: &Isometry3<f64>, cam: &Camera, x: &Point3<f64>) -> Option<(f64, f64, f64)> {
    let c = pose_wc.inverse_transform_point(x);
    if c.z <= 1e-6 {
        return None;
    }
    cam.project(&c).map(|(u, v)| (u, v, c.z))
}

pub(super) fn reproj_err(pose_wc: &Isometry3<f64>, cam: &Camera, x: &Point3<f64>, kp: (f32, f32)) -> Option<f64> {
    project(pose_wc, cam, x).map(|(u, v, _)| (u - kp.0 as f64).hypot(v - kp.1 as f64))
}

fn projection_matrix(pose_wc: &Isometry3<f64>, cam: &Camera) -> Result<Mat, MapError> {
    let cw = pose_wc.inverse().to_homogeneous();
    let k = cam.k();
    let mut rows = [[0.0f64; 4]; 3];
    for (r, row) in rows.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|i| k[r][i] * cw[(i, c)]).sum();
        }
    }
    Ok(Mat::from_slice_2d(&rows).map_err(crate::error::FeatureError::from)?)
}

/// A pixel in one keyframe and its match in another.
pub(super) type PixelPair = ((f32, f32), (f32, f32));

/// Triangulates pixel pairs with OpenCV; returns world points (None where the result is at infinity).
pub(super) fn triangulate(
    a: (&Isometry3<f64>, &Camera),
    b: (&Isometry3<f64>, &Camera),
    pairs: &[PixelPair],
) -> Result<Vec<Option<Point3<f64>>>, MapError> {
    if pairs.is_empty() {
        return Ok(Vec::new());
    }
    let pa: Vector<Point2d> = pairs.iter().map(|p| Point2d::new(p.0 .0 as f64, p.0 .1 as f64)).collect();
    let pb: Vector<Point2d> = pairs.iter().map(|p| Point2d::new(p.1 .0 as f64, p.1 .1 as f64)).collect();
    let mut out = Mat::default();
    let fe = crate::error::FeatureError::from;
    opencv::calib3d::triangulate_points(
        &projection_matrix(a.0, a.1)?,
        &projection_matrix(b.0, b.1)?,
        &pa,
        &pb,
        &mut out,
    )
    .map_err(fe)?;
    let mut pts = Vec::with_capacity(pairs.len());
    for i in 0..pairs.len() as i32 {
        let w = *out.at_2d::<f64>(3, i).map_err(fe)?;
        if w.abs() < 1e-12 {
            pts.push(None);
            continue;
        }
        let p = Point3::new(
            *out.at_2d::<f64>(0, i).map_err(fe)? / w,
            *out.at_2d::<f64>(1, i).map_err(fe)? / w,
            *out.at_2d::<f64>(2, i).map_err(fe)? / w,
        );
        pts.push(p.coords.iter().all(|v| v.is_finite()).then_some(p));
    }
    Ok(pts)
}

pub(super) fn viewing_direction(pose: &Isometry3<f64>) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}
