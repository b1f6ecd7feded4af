//! Where a query is lost: the stages of a relocalisation followed with the query's ground truth, so a query
//! that is not localised is charged to the first stage that left it too little to work with.
//!
//! The counts follow the correct correspondences down the pipeline:
//! 1. **map**: query keypoints that some landmark of the evaluated scene projects to (within the precision
//!    radius, under the true pose, in front of the camera and seen from within [`VISIBLE_WITHIN_DEG`] of the
//!    direction a map keyframe saw it from): what the map holds of this view, whatever the descriptor;
//! 2. **candidates**: the same for the landmarks of the keyframes that stage 1's covisibility vote chooses;
//! 3. **matches**: correct 2D-3D matches passed to the estimator (`correct_matches` of the record), and among
//!    its first [`RANSAC_HEAD`], the ones it draws hypotheses from;
//! 4. **estimator**: matches within the RANSAC threshold of the true pose (what a perfect estimator would find
//!    as inliers), and the estimator's own answer on the same matches without the inlier floor.
//!
//! A query that is not placed within the success threshold is charged to the first of these below
//! `min_inliers`: `map`, `candidates`, `matching` (the correct matches, or those within the RANSAC threshold of
//! the truth), then `estimator` (enough true inliers, no right pose found) or `floor` (the estimator found the
//! right pose with fewer inliers than the floor asks). A pose that was accepted but wrong is `wrong-pose`.
//! Occlusion is not modelled, so the first two counts are upper bounds.

use std::collections::HashSet;

use nalgebra::{Isometry3, Point3};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::describe::features::Keypoint;
use crate::map::localize::{LandmarkMatch, Localization, LocalizeSettings};
use crate::map::model::MapData;
use crate::pose::{absolute_pose, rotation_error_deg, RANSAC_HEAD};

/// A landmark counts as visible from the query when the query sees it within this angle of the direction one
/// of its map keyframes saw it from (a descriptor cannot be expected to match beyond it, and the back of an
/// object orbited all round is left out).
pub const VISIBLE_WITHIN_DEG: f64 = 60.0;

/// Keyframe ids from here on are distractor scenes' (`stages::add_distractors`), never the evaluated scene's.
const FIRST_DISTRACTOR_ID: u64 = 1_000_000;

/// The stage a query was lost at (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LostAt {
    Localised,
    Map,
    Candidates,
    Matching,
    Estimator,
    Floor,
    WrongPose,
}

impl LostAt {
    pub fn name(self) -> &'static str {
        match self {
            Self::Localised => "localised",
            Self::Map => "map",
            Self::Candidates => "candidates",
            Self::Matching => "matching",
            Self::Estimator => "estimator",
            Self::Floor => "floor",
            Self::WrongPose => "wrong-pose",
        }
    }
}

/// One query's counts down the pipeline (module docs).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Diagnosis {
    pub reachable_map: usize,
    pub reachable_candidates: usize,
    pub stage1_matches: usize,
    pub stage1_correct: usize,
    /// Matches the estimator drew hypotheses from, and the correct ones among them.
    pub head: usize,
    pub head_correct: usize,
    /// Matches within the RANSAC threshold of the true pose.
    pub true_inliers: usize,
    /// The estimator's answer on the same matches without the floor: its inliers (0 without a pose) and
    /// whether it is within the success threshold.
    pub unfloored_inliers: usize,
    pub unfloored_within: bool,
    pub lost_at: LostAt,
}

/// What the diagnosis reads of the query beside the localisation.
pub(super) struct QueryTruth<'a> {
    /// Camera-to-world ground truth.
    pub truth: &'a Isometry3<f64>,
    pub camera: &'a Camera,
    pub keypoints: &'a [Keypoint],
    pub precision_px: f64,
    /// Success thresholds: translation (scene units) and rotation (degrees).
    pub within: (f64, f64),
}

impl QueryTruth<'_> {
    /// Pixels between the match's keypoint and where the truth projects its landmark (infinite behind the
    /// camera).
    pub fn error_px(&self, data: &MapData, m: &LandmarkMatch) -> f64 {
        let p = Point3::from(data.landmarks[&m.landmark].point);
        let k = &self.keypoints[m.keypoint];
        let seen = self.camera.project(&(self.truth.inverse() * p));
        seen.map_or(f64::INFINITY, |(u, v)| (u - f64::from(k.x)).hypot(v - f64::from(k.y)))
    }
}

/// The counts and the stage `out` was lost at.
pub(super) fn diagnose(
    data: &MapData,
    q: &QueryTruth,
    out: &Localization,
    correct_matches: usize,
    params: &LocalizeSettings,
) -> Result<Diagnosis, Box<dyn std::error::Error + Send + Sync>> {
    let scene_keyframes: Vec<u64> = data.keyframes.keys().copied().filter(|&k| k < FIRST_DISTRACTOR_ID).collect();
    let reachable_map = reachable(data, &scene_keyframes, q);
    // The keyframes stage 2 reads (the covisibility vote on stage 1's matches); a distractor's adds nothing.
    let voted = data.covisible_keyframes(out.stage1.iter().map(|m| m.landmark), |_| true, params.candidate_keyframes);
    let voted: Vec<u64> = voted.into_iter().filter(|&k| k < FIRST_DISTRACTOR_ID).collect();
    let reachable_candidates = reachable(data, &voted, q);
    let stage1_correct = out.stage1.iter().filter(|m| q.error_px(data, m) <= q.precision_px).count();
    let head = out.matches.len().min(RANSAC_HEAD);
    let head_correct = out.matches[..head].iter().filter(|m| q.error_px(data, m) <= q.precision_px).count();
    let threshold = params.ransac.threshold_px;
    let true_inliers = out.matches.iter().filter(|m| q.error_px(data, m) <= threshold).count();
    let within = |p: &Isometry3<f64>| {
        (p.translation.vector - q.truth.translation.vector).norm() <= q.within.0
            && rotation_error_deg(&p.rotation.to_rotation_matrix(), &q.truth.rotation.to_rotation_matrix())
                <= q.within.1
    };
    let (unfloored_inliers, unfloored_within) = if q.camera.focal_unknown() || out.matches.len() < 6 {
        (0, false)
    } else {
        let p2: Vec<(f32, f32)> =
            out.matches.iter().map(|m| (q.keypoints[m.keypoint].x, q.keypoints[m.keypoint].y)).collect();
        match absolute_pose(&out.points, &p2, q.camera, &params.ransac, 6)? {
            Some(p) => (p.inliers.len(), within(&p.camera_to_world)),
            None => (0, false),
        }
    };
    let floor = params.min_inliers;
    let lost_at = match &out.pose {
        Some(p) if within(&p.camera_to_world) => LostAt::Localised,
        Some(_) => LostAt::WrongPose,
        None if reachable_map < floor => LostAt::Map,
        None if correct_matches < floor && reachable_candidates < floor => LostAt::Candidates,
        None if correct_matches < floor || true_inliers < floor => LostAt::Matching,
        None if unfloored_within && unfloored_inliers < floor => LostAt::Floor,
        None => LostAt::Estimator,
    };
    Ok(Diagnosis {
        reachable_map,
        reachable_candidates,
        stage1_matches: out.stage1.len(),
        stage1_correct,
        head,
        head_correct,
        true_inliers,
        unfloored_inliers,
        unfloored_within,
        lost_at,
    })
}

/// Query keypoints that a landmark observed by `keyframes` projects to within the precision radius under the
/// truth, seen within [`VISIBLE_WITHIN_DEG`] of one of its map views.
fn reachable(data: &MapData, keyframes: &[u64], q: &QueryTruth) -> usize {
    let w2c = q.truth.inverse();
    let centre = Point3::from(q.truth.translation.vector);
    let cell = q.precision_px.max(1.0);
    let key = |x: f64, y: f64| ((x / cell).floor() as i64, (y / cell).floor() as i64);
    let mut grid: std::collections::HashMap<(i64, i64), Vec<usize>> = std::collections::HashMap::new();
    for (i, k) in q.keypoints.iter().enumerate() {
        grid.entry(key(f64::from(k.x), f64::from(k.y))).or_default().push(i);
    }
    let cos_limit = VISIBLE_WITHIN_DEG.to_radians().cos();
    let mut landmarks: Vec<u64> = data.observations_of_keyframes(keyframes).map(|o| o.landmark).collect();
    landmarks.sort_unstable();
    landmarks.dedup();
    let mut reached = HashSet::new();
    for lm in landmarks {
        let l = &data.landmarks[&lm];
        let p = Point3::from(l.point);
        let Some((u, v)) = q.camera.project(&(w2c * p)) else { continue };
        let to_query = (centre - p).normalize();
        let seen = l.observations.iter().map(|&o| &data.observations[o as usize]).any(|o| {
            o.live
                && data.keyframes.get(&o.keyframe).is_some_and(|kf| {
                    let c = Point3::from(kf.pose.isometry().translation.vector);
                    (c - p).normalize().dot(&to_query) >= cos_limit
                })
        });
        if !seen {
            continue;
        }
        let (cx, cy) = key(u, v);
        let mut best = (q.precision_px, usize::MAX);
        for gx in cx - 1..=cx + 1 {
            for gy in cy - 1..=cy + 1 {
                for &i in grid.get(&(gx, gy)).into_iter().flatten() {
                    let k = &q.keypoints[i];
                    let d = (u - f64::from(k.x)).hypot(v - f64::from(k.y));
                    if d <= best.0 {
                        best = (d, i);
                    }
                }
            }
        }
        if best.1 != usize::MAX {
            reached.insert(best.1);
        }
    }
    reached.len()
}
