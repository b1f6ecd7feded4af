//! What a homography does to an image: where it sends a pixel, its zoom, rotation and tilt at a point, how
//! far a fitted homography sends the image's corners from the true one's, and the fit itself (MAGSAC++).

use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Where `h` sends `(x, y)`; None behind the camera (w <= 0).
pub fn apply(h: &Matrix3<f64>, x: f64, y: f64) -> Option<(f64, f64)> {
    let p = h * Vector3::new(x, y, 1.0);
    (p.z > 1e-12).then(|| (p.x / p.z, p.y / p.z))
}

/// What `h` does around one point: zoom, in-plane rotation and tilt.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalGeometry {
    /// `max(s, 1/s)` with `s` the larger singular value of the Jacobian: the scale along the axis the tilt
    /// leaves alone, so that a tilt alone is no zoom (the area scale, `sqrt(det)`, would make a 55 degree tilt
    /// a zoom of 1.3).
    pub zoom: f64,
    /// Angle of the Jacobian's nearest similarity, degrees, 0..=180.
    pub rotation_deg: f64,
    /// Out-of-plane angle, `acos(s2 / s1)` of the Jacobian's singular values, degrees, 0..90.
    pub tilt_deg: f64,
}

/// The zoom, in-plane rotation and tilt of `h` at `(x, y)` ([`LocalGeometry`]).
pub fn local_geometry(h: &Matrix3<f64>, x: f64, y: f64) -> LocalGeometry {
    let d = 0.5;
    let (Some(c), Some(px), Some(py)) = (apply(h, x, y), apply(h, x + d, y), apply(h, x, y + d)) else {
        return LocalGeometry { zoom: f64::INFINITY, rotation_deg: 0.0, tilt_deg: 90.0 };
    };
    let (a, cc) = ((px.0 - c.0) / d, (px.1 - c.1) / d);
    let (b, dd) = ((py.0 - c.0) / d, (py.1 - c.1) / d);
    let sv = nalgebra::Matrix2::new(a, b, cc, dd).singular_values();
    let (s1, s2) = (sv[0].max(sv[1]), sv[0].min(sv[1]));
    let zoom = if s1 > 0.0 { s1.max(1.0 / s1) } else { f64::INFINITY };
    let rotation_deg = (cc - b).atan2(a + dd).to_degrees().abs();
    let tilt_deg = if s1 > 0.0 { (s2 / s1).clamp(0.0, 1.0).acos().to_degrees() } else { 90.0 };
    LocalGeometry { zoom, rotation_deg, tilt_deg }
}

/// Mean distance between where `est` and `truth` send the corners of a `w` x `h` image.
pub fn corner_error(est: &Matrix3<f64>, truth: &Matrix3<f64>, w: u32, h: u32) -> f64 {
    let (w, h) = (w as f64 - 1.0, h as f64 - 1.0);
    let corners = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)];
    let mut sum = 0.0;
    for (x, y) in corners {
        match (apply(est, x, y), apply(truth, x, y)) {
            (Some(e), Some(t)) => sum += (e.0 - t.0).hypot(e.1 - t.1),
            _ => return f64::INFINITY,
        }
    }
    sum / 4.0
}

/// MAGSAC++ homography of the correspondences, None when there are fewer than 4 or none is found.
pub fn fit_homography(
    src: &[(f32, f32)],
    dst: &[(f32, f32)],
    ransac_px: f64,
) -> Result<Option<Matrix3<f64>>, BoxError> {
    if src.len() < 4 {
        return Ok(None);
    }
    let s: Vector<Point2f> = src.iter().map(|p| Point2f::new(p.0, p.1)).collect();
    let d: Vector<Point2f> = dst.iter().map(|p| Point2f::new(p.0, p.1)).collect();
    let mut mask = Mat::default();
    let h = opencv::calib3d::find_homography_ext(
        &s,
        &d,
        opencv::calib3d::USAC_MAGSAC,
        ransac_px,
        &mut mask,
        10_000,
        0.9999,
    )?;
    if h.empty() || h.rows() != 3 || h.cols() != 3 {
        return Ok(None);
    }
    let mut m = Matrix3::zeros();
    for r in 0..3 {
        for c in 0..3 {
            m[(r, c)] = *h.at_2d::<f64>(r as i32, c as i32)?;
        }
    }
    Ok((m.iter().all(|x| x.is_finite()) && m.determinant().abs() > 1e-12).then_some(m))
}
