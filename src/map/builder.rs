//! Map building from posed keyframes: which landmarks a new keyframe observes and which it creates.
//!
//! For a keyframe with a known camera-to-world pose, intrinsics, keypoints and their embeddings:
//!
//! 1. Candidates: the `candidates` existing keyframes whose camera centres are nearest and whose viewing
//!    directions differ by less than 90 degrees (they can see the same area).
//! 2. Each candidate is matched to the new keyframe (L2 nearest neighbour, ratio test, mutual check). A match
//!    to a keypoint that already observes a landmark adds an observation when the landmark reprojects into
//!    the new keyframe within `reproj_px` of the keypoint, in front of the camera.
//! 3. With a depth image: every remaining keypoint with a reading in `[min_depth, max_depth]` is
//!    back-projected into a new landmark.
//!    Without depth: remaining matches to unobserved keypoints are triangulated with the known poses (OpenCV
//!    `triangulatePoints`); a point is kept when it lies in front of both cameras, reprojects within
//!    `reproj_px` in both, and the rays meet at `min_parallax_deg` or more. It becomes a landmark observed by
//!    both keyframes; a keypoint is used by at most one landmark.
//!
//! The result is a [`Record`]: applying it (and logging it) is the store's job. Nothing here depends on what
//! the embeddings are, so the evaluation runs the same code for FREAK (bits as ±1, where L2 ranks exactly as
//! Hamming) and SIFT.

use std::collections::{HashMap, HashSet};

use nalgebra::{Isometry3, Point3, Vector3};
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::features::Features;
use crate::map::model::{Keyframe, MapData, NewObservation, Pose, Record};
use crate::matching::match_l2;
use crate::scene::Camera;

/// Settings of map building.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BuildParams {
    /// Ratio test between new and candidate keyframes.
    pub ratio: f32,
    /// Reprojection tolerance in pixels.
    pub reproj_px: f64,
    /// Smallest angle between the two viewing rays of a triangulated point.
    pub min_parallax_deg: f64,
    /// Earlier keyframes matched against a new one.
    pub candidates: usize,
    /// Valid depth readings, metres.
    pub min_depth: f64,
    pub max_depth: f64,
}

impl Default for BuildParams {
    fn default() -> Self {
        Self { ratio: 0.8, reproj_px: 3.0, min_parallax_deg: 1.0, candidates: 5, min_depth: 0.1, max_depth: 40.0 }
    }
}

/// Depth for a keyframe: 16-bit image and the factor that turns raw values into metres.
pub struct Depth<'a> {
    pub image: &'a Mat,
    /// Metres per raw unit (TUM: 1 / 5000).
    pub scale: f64,
}

/// A keyframe to add.
pub struct KeyframeInput<'a> {
    pub id: u64,
    /// Camera-to-world.
    pub pose: Isometry3<f64>,
    pub camera: Camera,
    pub features: &'a Features,
    /// `[N, dim]` embeddings of the features' keypoints.
    pub embeddings: &'a [f32],
    pub depth: Option<Depth<'a>>,
}

/// Pixel of a world point in a keyframe, with its depth (None when behind the camera).
fn project(pose_wc: &Isometry3<f64>, cam: &Camera, x: &Point3<f64>) -> Option<(f64, f64, f64)> {
    let c = pose_wc.inverse_transform_point(x);
    if c.z <= 1e-6 {
        return None;
    }
    cam.project(&c).map(|(u, v)| (u, v, c.z))
}

fn reproj_err(pose_wc: &Isometry3<f64>, cam: &Camera, x: &Point3<f64>, kp: (f32, f32)) -> Option<f64> {
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
type PixelPair = ((f32, f32), (f32, f32));

/// Triangulates pixel pairs with OpenCV; returns world points (None where the result is at infinity).
fn triangulate(
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

fn viewing_direction(pose: &Isometry3<f64>) -> Vector3<f64> {
    pose.rotation * Vector3::z()
}

/// Plans the record that adds `input` to `data`.
pub fn plan_keyframe(data: &MapData, input: &KeyframeInput, params: &BuildParams) -> Result<Record, MapError> {
    let dim = data.meta.dim;
    let n = input.features.len();
    if input.embeddings.len() != n * dim {
        return Err(MapError::InvalidInput {
            field: "embeddings".into(),
            reason: format!("{} values for {n} keypoints of dimension {dim}", input.embeddings.len()),
        });
    }
    if data.keyframes.contains_key(&input.id) {
        return Err(MapError::KeyframeExists { map: data.meta.id.clone(), keyframe: input.id });
    }
    let pose = Pose::from_isometry(&input.pose);
    pose.validate().map_err(|reason| MapError::InvalidInput { field: "pose".into(), reason })?;
    crate::pose::validate_camera(&input.camera)?;
    let kp = |i: usize| (input.features.keypoints[i].x, input.features.keypoints[i].y);

    let observed = data.observed_keypoints();
    let centre = input.pose.translation.vector;
    let dir = viewing_direction(&input.pose);
    let mut candidates: Vec<&Keyframe> =
        data.keyframes.values().filter(|k| viewing_direction(&k.pose.isometry()).dot(&dir) > 0.0).collect();
    candidates.sort_by(|a, b| {
        let da = (a.pose.isometry().translation.vector - centre).norm();
        let db = (b.pose.isometry().translation.vector - centre).norm();
        da.total_cmp(&db).then(a.id.cmp(&b.id))
    });
    candidates.truncate(params.candidates);

    let mut assigned: HashMap<u32, u64> = HashMap::new(); // keypoint of the new keyframe -> landmark
    let mut used_old: HashSet<(u64, u32)> = HashSet::new();
    let mut new_landmarks: Vec<(u64, [f64; 3])> = Vec::new();
    let mut observations: Vec<NewObservation> = Vec::new();
    let mut next = data.next_landmark;
    let mut to_triangulate: Vec<(&Keyframe, usize, usize)> = Vec::new();

    for cand in &candidates {
        let matches = match_l2(input.embeddings, &cand.embeddings, dim, params.ratio, true)?;
        for m in matches {
            let (a, b) = (m.query, m.train as u32);
            if assigned.contains_key(&(a as u32)) {
                continue;
            }
            if let Some(&lm) = observed.get(&(cand.id, b)) {
                let point = Point3::from(data.landmarks[&lm].point);
                if reproj_err(&input.pose, &input.camera, &point, kp(a)).is_some_and(|e| e <= params.reproj_px)
                    && !assigned.values().any(|&l| l == lm)
                {
                    assigned.insert(a as u32, lm);
                    observations.push(NewObservation { landmark: lm, keyframe: input.id, keypoint: a as u32 });
                }
            } else if input.depth.is_none() {
                to_triangulate.push((cand, a, b as usize));
            }
        }
    }

    if let Some(depth) = &input.depth {
        let inv = input.pose;
        for a in 0..n {
            if assigned.contains_key(&(a as u32)) {
                continue;
            }
            let (x, y) = kp(a);
            let (xi, yi) = (x.round() as i32, y.round() as i32);
            if xi < 0 || yi < 0 || xi >= depth.image.cols() || yi >= depth.image.rows() {
                continue;
            }
            let raw = *depth.image.at_2d::<u16>(yi, xi).map_err(crate::error::FeatureError::from)?;
            let z = raw as f64 * depth.scale;
            if raw == 0 || z < params.min_depth || z > params.max_depth {
                continue;
            }
            let cam = &input.camera;
            let pc = Point3::new((x as f64 - cam.cx) / cam.fx * z, (y as f64 - cam.cy) / cam.fy * z, z);
            let pw = inv * pc;
            let id = next;
            next += 1;
            new_landmarks.push((id, [pw.x, pw.y, pw.z]));
            assigned.insert(a as u32, id);
            observations.push(NewObservation { landmark: id, keyframe: input.id, keypoint: a as u32 });
        }
    } else {
        // Group by candidate to triangulate in batches.
        let mut by_cand: HashMap<u64, Vec<(usize, usize)>> = HashMap::new();
        for (cand, a, b) in &to_triangulate {
            by_cand.entry(cand.id).or_default().push((*a, *b));
        }
        for cand in &candidates {
            let Some(pairs) = by_cand.get(&cand.id) else { continue };
            let cpose = cand.pose.isometry();
            let pix: Vec<_> = pairs.iter().map(|&(a, b)| (kp(a), (cand.keypoints[b].x, cand.keypoints[b].y))).collect();
            let points = triangulate((&input.pose, &input.camera), (&cpose, &cand.camera), &pix)?;
            for ((a, b), point) in pairs.iter().zip(points) {
                let Some(point) = point else { continue };
                if assigned.contains_key(&(*a as u32)) || used_old.contains(&(cand.id, *b as u32)) {
                    continue;
                }
                let ea = reproj_err(&input.pose, &input.camera, &point, kp(*a));
                let eb = reproj_err(&cpose, &cand.camera, &point, (cand.keypoints[*b].x, cand.keypoints[*b].y));
                let (Some(ea), Some(eb)) = (ea, eb) else { continue };
                if ea > params.reproj_px || eb > params.reproj_px {
                    continue;
                }
                let ra = (point.coords - input.pose.translation.vector).normalize();
                let rb = (point.coords - cpose.translation.vector).normalize();
                if ra.dot(&rb).clamp(-1.0, 1.0).acos().to_degrees() < params.min_parallax_deg {
                    continue;
                }
                let id = next;
                next += 1;
                new_landmarks.push((id, [point.x, point.y, point.z]));
                assigned.insert(*a as u32, id);
                used_old.insert((cand.id, *b as u32));
                observations.push(NewObservation { landmark: id, keyframe: input.id, keypoint: *a as u32 });
                observations.push(NewObservation { landmark: id, keyframe: cand.id, keypoint: *b as u32 });
            }
        }
    }

    let keyframe = Keyframe {
        id: input.id,
        pose,
        camera: input.camera,
        keypoints: input.features.keypoints.clone(),
        descriptors: input.features.descriptors.as_flattened().to_vec(),
        embeddings: input.embeddings.to_vec(),
    };
    Ok(Record::AddKeyframe { keyframe, new_landmarks, observations })
}
