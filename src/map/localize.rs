//! Relocalisation: a query's keypoints and embeddings against a map -> camera-to-world pose, in three stages,
//! each a setting of [`LocalizeSettings`]. The defaults were chosen by a rule fixed before scoring on the
//! selection scenes (`docs/history/benchmarks-log.md`; their figures: BENCHMARKS.md, "Relocalisation on the
//! validation scenes"): stages 1 and 2 on, FREAK's join and stage 3 off.
//!
//! 1. **Index search.** Each of the query's `max_query_keypoints` strongest keypoints (100 by default) takes
//!    its `knn` nearest observations in the map's index (optionally only those whose landmark lies within a
//!    prior's radius). The nearest landmark is accepted when its distance is below `ratio` times the distance
//!    to the nearest *other* landmark (several observations of one landmark do not make it ambiguous); when all
//!    `knn` hits belong to one landmark it is accepted. One query keypoint per landmark is kept (the closest). The keyframes observing the matched
//!    landmarks then vote (covisibility): the `candidate_keyframes` with the most votes are the candidates.
//!    A query whose pose after the stages below has fewer than `full_search_below_inliers` inliers (100 by
//!    default) has its other keypoints searched too, and is answered as if every keypoint had been searched.
//! 2. **Candidate matching** (`candidate_matching`). The query is matched against the candidates' landmarks
//!    alone (every live observation of a landmark a candidate sees, at most [`VIEWS_PER_LANDMARK`] each), by
//!    exact search with the looser `candidate_ratio` and a mutual check (the keypoint must be the nearest one
//!    to one of the landmark's views). With `candidate_freak`, FREAK's bits (which the keyframe payload keeps)
//!    are matched the same way by Hamming distance and their matches join the embedding's. Skipped when stage
//!    1's matches already give a pose with `candidate_skip_inliers` inliers (a query's cost stays bounded).
//! 3. **Guided search** (`guided_search`). From a pose with at least `min_inliers` inliers, the landmarks of
//!    the keyframes that see its inliers most are projected into the query; each takes the query keypoint
//!    within `guided_radius_px` whose embedding is nearest to one of its views, when that distance is within
//!    the distances of the pose's own inliers (their 90th percentile) and below `guided_ratio` times the next
//!    keypoint's in the window. The pose is estimated again on all matches and kept when it has at least as
//!    many inliers. Stage 3 only refines a pose that was already accepted: it never turns a query that was
//!    not localised into a localised one.
//!
//! The 2D-3D matches go to solvePnPRansac + refinement, best first (PROSAC), ranked by their ratio to the
//! runner-up (comparable across Hamming and L2); fewer than `min_inliers` inliers means "not localised": no
//! pose rather than a wrong one. A camera without a focal length ([`Camera::focal_unknown`]) has it estimated
//! with the pose (`pose::absolute_pose_unknown_focal`). The pose comes with the covariance of its refinement,
//! scaled by `covariance_scale`.
//!
//! Confidence in [0, 1] is the probability, under the pose's scaled covariance, that the pose lies within
//! [`CONFIDENCE_ROTATION_DEG`] and within [`CONFIDENCE_DEPTH_FRACTION`] of the inliers' median depth of the
//! truth ([`confidence`]): it is as calibrated as the covariance is (`docs/history/benchmarks-log.md`, "Clients
//! without calibration, and how sure a pose is", has both on real scenes),
//! and, like the covariance, it does not see a wrong pose that many inliers support.

use serde::{Deserialize, Serialize};

use std::collections::{HashMap, HashSet};

use opencv::core::{Mat, NORM_HAMMING, NORM_L2};
use opencv::prelude::*;

use crate::camera::Camera;
use crate::describe::features::{bits_mat, Features};
use crate::error::MapError;
use crate::map::index::{l2_squared, EmbeddingIndex};
use crate::map::model::MapData;
use crate::matching::embedding_mat;
use crate::matching::nearest::nearest_both_ways;
use crate::pose::{absolute_pose, absolute_pose_unknown_focal, AbsolutePose, RansacSettings};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocalizeSettings {
    pub ratio: f32,
    pub knn: usize,
    /// PnP's settings ([`RansacSettings::relocalisation`]).
    pub ransac: RansacSettings,
    pub min_inliers: usize,
    /// Only this many of the query's keypoints, the strongest by detector response, are searched in the
    /// index by stage 1 (all of them are still embedded). Stages 2 and 3 read every keypoint: stage 1 only has
    /// to find the candidate keyframes, and stage 2 matches the whole query against their landmarks, at a
    /// cost that does not grow with the map. The index search is the largest stage on a large map and grows
    /// with the number of queries. Default 100, with `full_search_below_inliers` = 100: chosen by a rule
    /// written before scoring, with caps and every keypoint compared on one graph
    /// (`docs/history/benchmarks-log.md`, "Caps compared on one graph"); a cap of at least the query's keypoints
    /// (say 1000000000) searches every keypoint. A cap alone, without the fallback, lost far queries on the
    /// validation scenes (800: KITTI 5 -> 3 of 25 within (0.25 m, 2°)).
    /// Keypoints of equal response keep their order, so client keypoints without responses are searched in
    /// the order sent.
    pub max_query_keypoints: usize,
    /// With stage 1 capped (`max_query_keypoints`), a query whose pose after the other stages has fewer than
    /// this many inliers (or none) has its other keypoints searched too and is answered exactly as without
    /// the cap, so the cap loses no query it could not place; 0 = off (a capped query is answered from its
    /// capped search alone). Default 100, the inlier count at which stage 2 is skipped
    /// (`candidate_skip_inliers`): a query placed that firmly by the capped search pays 100 searches and
    /// stage 2, and one that is not pays the capped attempt and then every keypoint's search (far queries
    /// took 1.05-1.4x as long on the validation scenes).
    pub full_search_below_inliers: usize,
    /// Multiplies the pose covariance of the refinement (`σ² (JᵀJ)⁻¹`), which counts only the query's pixel
    /// noise: the map's landmarks have errors of their own, so the raw ellipsoid is too small. 26: the 95th
    /// percentile of the raw squared Mahalanobis distance over 17 localised far-map queries of the training
    /// scenes with pixel-accurate ground truth, over χ²₆(0.95) (`docs/history/benchmarks-log.md`, "Clients
    /// without calibration, and how sure a pose is").
    pub covariance_scale: f64,
    /// Stage 1's covisibility vote: how many keyframes become candidates for stages 2 and 3.
    pub candidate_keyframes: usize,
    /// Stage 2: match the query against the candidates' landmarks alone.
    pub candidate_matching: bool,
    /// Stage 2's ratio test (looser than stage 1's: the candidates hold few look-alikes).
    pub candidate_ratio: f32,
    /// Stage 2: FREAK's matches (Hamming distance, the same ratio) join the embedding's.
    pub candidate_freak: bool,
    /// Stage 2 is skipped when stage 1's matches give a pose with at least this many inliers.
    pub candidate_skip_inliers: usize,
    /// Stage 3: guided search by projection from the pose, and the pose estimated again.
    pub guided_search: bool,
    /// Stage 3's search window around a projected landmark, pixels.
    pub guided_radius_px: f64,
    /// Stage 3's ratio between the nearest and the next keypoint in the window.
    pub guided_ratio: f32,
}

impl Default for LocalizeSettings {
    fn default() -> Self {
        Self {
            ratio: crate::matching::DEFAULT_RATIO,
            knn: 4,
            ransac: RansacSettings::relocalisation(),
            min_inliers: 15,
            max_query_keypoints: 100,
            full_search_below_inliers: 100,
            covariance_scale: 26.0,
            candidate_keyframes: 5,
            candidate_matching: true,
            candidate_ratio: 0.9,
            candidate_freak: false,
            candidate_skip_inliers: 100,
            guided_search: false,
            guided_radius_px: 8.0,
            guided_ratio: 0.9,
        }
    }
}

impl LocalizeSettings {
    /// Checks the settings a configuration file can get wrong.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_query_keypoints < self.min_inliers.max(1) {
            return Err(format!(
                "max_query_keypoints ({}) is below min_inliers ({}): no pose could ever be found",
                self.max_query_keypoints, self.min_inliers
            ));
        }
        if !(self.covariance_scale.is_finite() && self.covariance_scale > 0.0) {
            return Err(format!("covariance_scale must be a positive number, got {}", self.covariance_scale));
        }
        for (name, r) in [("candidate_ratio", self.candidate_ratio), ("guided_ratio", self.guided_ratio)] {
            if !(r > 0.0 && r <= 1.0) {
                return Err(format!("{name} must lie in (0, 1], got {r}"));
            }
        }
        if !(self.guided_radius_px > 0.0 && self.guided_radius_px <= 64.0) {
            return Err(format!("guided_radius_px must lie in (0, 64], got {}", self.guided_radius_px));
        }
        if (self.candidate_matching || self.guided_search) && self.candidate_keyframes == 0 {
            return Err("candidate_keyframes is 0 while stage 2 or 3 is on: they need candidate keyframes".into());
        }
        Ok(())
    }

    /// The pipeline without stages 2 and 3: stage 1 alone, every query keypoint searched (the baseline of the
    /// benchmarks; a cap leans on stage 2 to match the keypoints it does not search).
    pub fn stage_one_only(self) -> Self {
        Self {
            candidate_matching: false,
            candidate_freak: false,
            guided_search: false,
            max_query_keypoints: usize::MAX,
            full_search_below_inliers: 0,
            ..self
        }
    }
}

/// Stage 2 reads at most this many live views of each candidate landmark, and stage 3 compares with as many
/// (a landmark seen from many keyframes is described well enough by a few; the cost stays bounded).
pub const VIEWS_PER_LANDMARK: usize = 6;

/// Restricts the search to landmarks within `radius` of `position` (world units).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Prior {
    pub position: [f64; 3],
    pub radius: f64,
}

/// A 2D-3D correspondence.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LandmarkMatch {
    pub keypoint: usize,
    pub landmark: u64,
    pub distance: f32,
}

/// The outcome of a relocalisation.
#[derive(Debug, Clone)]
pub struct Localization {
    pub pose: Option<AbsolutePose>,
    pub matches: Vec<LandmarkMatch>,
    pub confidence: f64,
    /// The matched landmarks' positions, in the order of `matches`.
    pub points: Vec<[f64; 3]>,
    /// Stage 1's matches of the search the answer came from, which stage 2's covisibility vote read.
    pub stage1: Vec<LandmarkMatch>,
    /// Wall time of the index search (with the ratio test), of PnP (every estimate), and of stages 2 and 3's
    /// own matching, seconds.
    pub search_s: f64,
    pub pnp_s: f64,
    pub stages_s: f64,
}

/// Whether the landmark lies within the prior's radius (always, without a prior).
fn within_prior(data: &MapData, landmark: u64, prior: Option<&Prior>) -> bool {
    let Some(p) = prior else { return true };
    let l = &data.landmarks[&landmark].point;
    ((l[0] - p.position[0]).powi(2) + (l[1] - p.position[1]).powi(2) + (l[2] - p.position[2]).powi(2)).sqrt()
        <= p.radius
}

/// A 2D-3D match with its rank for PROSAC: its distance over the runner-up's (1 when it had none), which
/// compares across descriptors (L2 embeddings, Hamming bits).
#[derive(Debug, Clone, Copy)]
struct Ranked {
    m: LandmarkMatch,
    ratio: f32,
}

/// Stage 1: the index's accepted 2D-3D matches of the query keypoints `rows` (every one when `rows` is all of
/// them), in `rows` order, before one match per landmark is kept.
fn index_hits(
    data: &MapData,
    index: &EmbeddingIndex,
    embeddings: &[f32],
    rows: &[usize],
    prior: Option<&Prior>,
    params: &LocalizeSettings,
) -> Vec<Ranked> {
    let dim = data.meta.dim;
    let all = rows.len() * dim == embeddings.len();
    let subset: std::borrow::Cow<[f32]> = if all {
        embeddings.into()
    } else {
        rows.iter().flat_map(|&i| embeddings[i * dim..(i + 1) * dim].iter().copied()).collect()
    };
    let near = |obs: usize| within_prior(data, data.observations[obs].landmark, prior);
    let accept: crate::map::index::Accept = if prior.is_some() { Some(&near) } else { None };
    let all_hits = index.search_many(data, &subset, params.knn.max(2), accept);
    let mut found = Vec::new();
    for (i, hits) in all_hits.iter().enumerate() {
        let Some(first) = hits.first() else { continue };
        let lm = data.observations[first.observation].landmark;
        let other = hits.iter().find(|h| data.observations[h.observation].landmark != lm);
        // Without another landmark among the hits, its runner-up lies beyond the last hit: that bound ranks it.
        let runner_up = other.or(hits.last()).map_or(f32::MIN_POSITIVE, |h| h.distance.max(f32::MIN_POSITIVE));
        let ratio = first.distance / runner_up;
        if other.is_some() && first.distance >= params.ratio * other.map_or(0.0, |o| o.distance) {
            continue;
        }
        found.push(Ranked { m: LandmarkMatch { keypoint: rows[i], landmark: lm, distance: first.distance }, ratio });
    }
    found
}

/// Keeps one match per landmark (the closest), in keypoint order.
fn one_per_landmark(found: Vec<Ranked>) -> Vec<Ranked> {
    let mut best: HashMap<u64, Ranked> = HashMap::new();
    for r in found {
        best.entry(r.m.landmark)
            .and_modify(|b| {
                if r.m.distance < b.m.distance {
                    *b = r
                }
            })
            .or_insert(r);
    }
    let mut out: Vec<Ranked> = best.into_values().collect();
    out.sort_by_key(|r| r.m.keypoint);
    out
}

/// Live views (observation ids) of the landmarks the keyframes `candidates` observe (within the prior), at most
/// [`VIEWS_PER_LANDMARK`] per landmark, grouped by landmark in landmark order.
fn candidate_views(data: &MapData, candidates: &[u64], prior: Option<&Prior>) -> Vec<usize> {
    let mut landmarks: Vec<u64> = data
        .observations_of_keyframes(candidates)
        .filter(|o| within_prior(data, o.landmark, prior))
        .map(|o| o.landmark)
        .collect();
    landmarks.sort_unstable();
    landmarks.dedup();
    landmark_views(data, &landmarks)
}

fn landmark_views(data: &MapData, landmarks: &[u64]) -> Vec<usize> {
    let mut views = Vec::new();
    for lm in landmarks {
        let Some(l) = data.landmarks.get(lm) else { continue };
        views.extend(
            l.observations.iter().map(|&o| o as usize).filter(|&o| data.observations[o].live).take(VIEWS_PER_LANDMARK),
        );
    }
    views
}

/// Matches of the query's rows `query` against the rows `views` (one per observation id in `views`) by exact
/// search in `norm` (OpenCV's brute-force answer, from [`nearest_both_ways`]): the nearest view's landmark
/// when its distance is below `ratio` times the nearest view of another landmark, and the keypoint is the
/// nearest query row to one of that landmark's views (mutual). `distance` is left to the caller; the rank is the ratio.
fn mutual_landmark_matches(
    data: &MapData,
    query: &Mat,
    train: &Mat,
    views: &[usize],
    norm: i32,
    ratio: f32,
) -> Result<Vec<Ranked>, MapError> {
    if query.rows() < 1 || train.rows() < 1 {
        return Ok(Vec::new());
    }
    let both = nearest_both_ways(query, train, norm, VIEWS_PER_LANDMARK + 1, &Mat::default())?;
    let landmark = |t: usize| data.observations[views[t]].landmark;
    let nearest_of: HashSet<(u64, usize)> =
        both.back.iter().enumerate().filter_map(|(t, q)| q.map(|q| (landmark(t), q))).collect();
    let mut found = Vec::new();
    for (q, hits) in both.forward.iter().enumerate() {
        let Some(&(first, d0)) = hits.first() else { continue };
        let lm = landmark(first);
        let other = hits.iter().find(|h| landmark(h.0) != lm).map(|h| h.1);
        if other.is_some_and(|d1| d0 >= ratio * d1) || !nearest_of.contains(&(lm, q)) {
            continue;
        }
        let r = other.map_or(1.0, |d1| d0 / d1.max(f32::MIN_POSITIVE));
        found.push(Ranked { m: LandmarkMatch { keypoint: q, landmark: lm, distance: d0 }, ratio: r });
    }
    Ok(found)
}

/// Stage 2: the query's keypoints `rows` (embeddings `embeddings`, in `rows` order) against the landmarks of
/// the candidate keyframes.
fn candidate_matches(
    data: &MapData,
    candidates: &[u64],
    features: &Features,
    rows: &[usize],
    embeddings: &[f32],
    prior: Option<&Prior>,
    params: &LocalizeSettings,
) -> Result<Vec<Ranked>, MapError> {
    let dim = data.meta.dim;
    let views = candidate_views(data, candidates, prior);
    if views.is_empty() || rows.is_empty() {
        return Ok(Vec::new());
    }
    let train: Vec<f32> = views.iter().flat_map(|&o| data.embeddings[o * dim..(o + 1) * dim].iter().copied()).collect();
    let train = embedding_mat(&train, dim)?;
    let query = embedding_mat(embeddings, dim)?;
    let mut found = mutual_landmark_matches(data, &query, &train, &views, NORM_L2, params.candidate_ratio)?;
    let bits = match params.candidate_freak && features.descriptors.len() == features.len() {
        true => data.observation_descriptors(&views)?,
        false => None,
    };
    if let Some(bytes) = bits {
        let train = bits_mat(&bytes)?;
        let qbytes: Vec<u8> = rows.iter().flat_map(|&i| features.descriptors[i].iter().copied()).collect();
        let query = bits_mat(&qbytes)?;
        let mut freak = mutual_landmark_matches(data, &query, &train, &views, NORM_HAMMING, params.candidate_ratio)?;
        // A FREAK match reports the embedding distance to the landmark's nearest view, as every other match.
        for r in &mut freak {
            let e = &embeddings[r.m.keypoint * dim..(r.m.keypoint + 1) * dim];
            r.m.distance = nearest_view_distance(data, r.m.landmark, e);
        }
        found.extend(freak);
    }
    for r in &mut found {
        r.m.keypoint = rows[r.m.keypoint];
    }
    Ok(found)
}

/// L2 distance from `e` to the nearest of the landmark's first [`VIEWS_PER_LANDMARK`] live views.
fn nearest_view_distance(data: &MapData, landmark: u64, e: &[f32]) -> f32 {
    let dim = data.meta.dim;
    landmark_views(data, &[landmark])
        .into_iter()
        .map(|o| l2_squared(e, &data.embeddings[o * dim..(o + 1) * dim]))
        .fold(f32::INFINITY, f32::min)
        .sqrt()
}

/// Joins match sets: one landmark per keypoint and one keypoint per landmark, the better ranked first; the
/// result is in PROSAC's order (best first).
fn join(sets: impl IntoIterator<Item = Ranked>) -> Vec<Ranked> {
    let mut all: Vec<Ranked> = sets.into_iter().collect();
    all.sort_by(|a, b| {
        a.ratio.total_cmp(&b.ratio).then(a.m.distance.total_cmp(&b.m.distance)).then(a.m.keypoint.cmp(&b.m.keypoint))
    });
    let (mut keypoints, mut landmarks) = (HashSet::new(), HashSet::new());
    all.retain(|r| {
        let fresh = !keypoints.contains(&r.m.keypoint) && !landmarks.contains(&r.m.landmark);
        if fresh {
            keypoints.insert(r.m.keypoint);
            landmarks.insert(r.m.landmark);
        }
        fresh
    });
    all
}

/// What stage 3 reads of the query: every keypoint with its embedding, the camera and the prior.
#[derive(Clone, Copy)]
struct Query<'a> {
    features: &'a Features,
    embeddings: &'a [f32],
    camera: &'a Camera,
    prior: Option<&'a Prior>,
}

/// Stage 3: landmarks of the keyframes that see the pose's inliers most, projected with the pose, matched to
/// the query keypoint in the window (module docs). `matched` are the matches the pose was estimated from.
fn guided_matches(
    data: &MapData,
    pose: &AbsolutePose,
    query: &Query,
    matched: &[Ranked],
    params: &LocalizeSettings,
) -> Vec<Ranked> {
    let Query { features, embeddings, camera, prior } = *query;
    let dim = data.meta.dim;
    let inliers: Vec<&Ranked> = pose.inliers.iter().map(|&i| &matched[i]).collect();
    let mut gate: Vec<f32> = inliers.iter().map(|r| r.m.distance).collect();
    gate.sort_by(f32::total_cmp);
    let Some(&gate) = gate.get(gate.len() * 9 / 10).or(gate.last()) else { return Vec::new() };
    let candidates =
        data.covisible_keyframes(inliers.iter().map(|r| r.m.landmark), |_| true, params.candidate_keyframes);
    let taken_landmarks: HashSet<u64> = matched.iter().map(|r| r.m.landmark).collect();
    let taken_keypoints: HashSet<usize> = matched.iter().map(|r| r.m.keypoint).collect();
    let mut landmarks: Vec<u64> = data
        .observations_of_keyframes(&candidates)
        .filter(|o| !taken_landmarks.contains(&o.landmark) && within_prior(data, o.landmark, prior))
        .map(|o| o.landmark)
        .collect();
    landmarks.sort_unstable();
    landmarks.dedup();
    let radius = params.guided_radius_px;
    let key = |x: f64, y: f64| ((x / radius).floor() as i64, (y / radius).floor() as i64);
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (k, p) in features.keypoints.iter().enumerate() {
        if !taken_keypoints.contains(&k) {
            grid.entry(key(f64::from(p.x), f64::from(p.y))).or_default().push(k);
        }
    }
    let camera = if camera.focal_unknown() { camera.with_focal(pose.focal) } else { *camera };
    let w2c = pose.camera_to_world.inverse();
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    // Per keypoint, the landmark that claims it with the smallest distance.
    let mut claims: HashMap<usize, Ranked> = HashMap::new();
    for lm in landmarks {
        let point = nalgebra::Point3::from(data.landmarks[&lm].point);
        let Some((u, v)) = camera.project(&(w2c * point)) else { continue };
        if !(u > -radius && v > -radius && u < w + radius && v < h + radius) {
            continue;
        }
        let views = landmark_views(data, &[lm]);
        let (cx, cy) = key(u, v);
        let (mut best, mut second) = ((f32::INFINITY, usize::MAX), f32::INFINITY);
        for gx in cx - 1..=cx + 1 {
            for gy in cy - 1..=cy + 1 {
                for &k in grid.get(&(gx, gy)).into_iter().flatten() {
                    let p = &features.keypoints[k];
                    if (f64::from(p.x) - u).hypot(f64::from(p.y) - v) > radius {
                        continue;
                    }
                    let e = &embeddings[k * dim..(k + 1) * dim];
                    let d = views
                        .iter()
                        .map(|&o| l2_squared(e, &data.embeddings[o * dim..(o + 1) * dim]))
                        .fold(f32::INFINITY, f32::min)
                        .sqrt();
                    if d < best.0 {
                        second = best.0;
                        best = (d, k);
                    } else if d < second {
                        second = d;
                    }
                }
            }
        }
        let (d, k) = best;
        if k == usize::MAX || d > gate || d >= params.guided_ratio * second {
            continue;
        }
        let r = Ranked {
            m: LandmarkMatch { keypoint: k, landmark: lm, distance: d },
            // A runner-up beyond the gate, or none in the window, counts as the gate.
            ratio: d / second.min(gate).max(f32::MIN_POSITIVE),
        };
        claims
            .entry(k)
            .and_modify(|c| {
                if d < c.m.distance {
                    *c = r
                }
            })
            .or_insert(r);
    }
    let mut out: Vec<Ranked> = claims.into_values().collect();
    out.sort_by_key(|r| r.m.keypoint);
    out
}

/// The rotation tolerance of [`confidence`], degrees.
pub const CONFIDENCE_ROTATION_DEG: f64 = 2.0;
/// The position tolerance of [`confidence`], as a fraction of the inliers' median depth (scale-free: 5 cm at
/// 1 m, 50 cm at 10 m).
pub const CONFIDENCE_DEPTH_FRACTION: f64 = 0.05;
/// Draws of [`confidence`]'s estimate (deterministic: the same pose always gets the same confidence).
pub const CONFIDENCE_DRAWS: usize = 512;

/// The inliers' median depth in the camera of `pose` (the landmarks `points`, indexed by the inliers).
pub fn median_inlier_depth(pose: &AbsolutePose, points: &[[f64; 3]]) -> f64 {
    let w2c = pose.camera_to_world.inverse();
    let mut z: Vec<f64> =
        pose.inliers.iter().map(|&i| (w2c * nalgebra::Point3::from(points[i])).z).filter(|z| z.is_finite()).collect();
    z.sort_by(f64::total_cmp);
    z.get(z.len() / 2).copied().unwrap_or(0.0)
}

/// Whether `truth` (camera-to-world) lies within the tolerances [`confidence`] is the probability of.
pub fn within_confidence_tolerance(pose: &AbsolutePose, points: &[[f64; 3]], truth: &nalgebra::Isometry3<f64>) -> bool {
    let tolerance = CONFIDENCE_DEPTH_FRACTION * median_inlier_depth(pose, points);
    (pose.camera_to_world.translation.vector - truth.translation.vector).norm() <= tolerance
        && pose.camera_to_world.rotation.angle_to(&truth.rotation).to_degrees() <= CONFIDENCE_ROTATION_DEG
}

/// The probability that the true pose lies within [`CONFIDENCE_ROTATION_DEG`] and
/// [`CONFIDENCE_DEPTH_FRACTION`] of the median inlier depth, under the pose's covariance (camera-to-world
/// translation and rotation vector), estimated from [`CONFIDENCE_DRAWS`] seeded draws. 0 without a covariance.
pub fn confidence(pose: &AbsolutePose, points: &[[f64; 3]]) -> f64 {
    use rand::{Rng, SeedableRng};
    let Some(c) = &pose.covariance_w2c else { return 0.0 };
    let sigma = crate::pose::pose_covariance(crate::camera::PoseConvention::default(), &pose.camera_to_world, c);
    let Some(l) = sigma.cholesky().map(|ch| ch.l()) else { return 0.0 };
    let tolerance = CONFIDENCE_DEPTH_FRACTION * median_inlier_depth(pose, points);
    let (rotation, mut rng) = (CONFIDENCE_ROTATION_DEG.to_radians(), rand::rngs::StdRng::seed_from_u64(28));
    // Box-Muller: two uniforms give a standard normal.
    let mut normal = move || {
        let (a, b): (f64, f64) = (rng.random::<f64>().max(f64::MIN_POSITIVE), rng.random());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let inside = (0..CONFIDENCE_DRAWS)
        .filter(|_| {
            let z = nalgebra::Vector6::from_fn(|_, _| normal());
            let e = l * z;
            e.fixed_rows::<3>(0).norm() <= tolerance && e.fixed_rows::<3>(3).norm() <= rotation
        })
        .count();
    inside as f64 / CONFIDENCE_DRAWS as f64
}

/// The `n` keypoints of strongest response, in keypoint order; `None` when there are no more than `n`.
fn strongest(features: &Features, n: usize) -> Option<Vec<usize>> {
    if features.len() <= n {
        return None;
    }
    let k = &features.keypoints;
    let mut chosen: Vec<usize> = (0..k.len()).collect();
    chosen.sort_by(|&a, &b| k[b].response.total_cmp(&k[a].response).then(a.cmp(&b)));
    chosen.truncate(n);
    chosen.sort_unstable();
    Some(chosen)
}

/// Wall time of PnP and of stages 2 and 3's own matching, seconds, summed over a query's attempts.
#[derive(Default)]
struct StageTimes {
    pnp_s: f64,
    stages_s: f64,
}

/// What [`after_search`] answers: the matches the pose was estimated from, the pose, and stage 1's matches.
type Searched = (Vec<Ranked>, Option<AbsolutePose>, Vec<LandmarkMatch>);

/// From stage 1's matches (one per landmark) to the matches and pose: PnP, then stages 2 and 3 as `params` say.
fn after_search(
    data: &MapData,
    query: &Query,
    stage1: Vec<Ranked>,
    params: &LocalizeSettings,
    times: &mut StageTimes,
) -> Result<Searched, MapError> {
    let Query { features, embeddings, camera, prior } = *query;
    let estimate = |matches: &[Ranked], pnp_s: &mut f64| -> Result<Option<AbsolutePose>, MapError> {
        let t = std::time::Instant::now();
        let p3: Vec<[f64; 3]> = matches.iter().map(|r| data.landmarks[&r.m.landmark].point).collect();
        let p2: Vec<(f32, f32)> =
            matches.iter().map(|r| (features.keypoints[r.m.keypoint].x, features.keypoints[r.m.keypoint].y)).collect();
        let pose = if camera.focal_unknown() {
            absolute_pose_unknown_focal(&p3, &p2, camera, &params.ransac, params.min_inliers)?
        } else {
            absolute_pose(&p3, &p2, camera, &params.ransac, params.min_inliers)?
        };
        *pnp_s += t.elapsed().as_secs_f64();
        Ok(pose)
    };
    let inliers = |p: &Option<AbsolutePose>| p.as_ref().map_or(0, |p| p.inliers.len());
    let mut matches = join(stage1);
    if !(params.candidate_matching || params.guided_search) {
        // Stage 1 alone keeps the order it always had: the nearest embeddings first, ties in keypoint order.
        matches.sort_by(|a, b| a.m.distance.total_cmp(&b.m.distance).then(a.m.keypoint.cmp(&b.m.keypoint)));
    }
    let stage1: Vec<LandmarkMatch> = matches.iter().map(|r| r.m).collect();
    let mut pose = estimate(&matches, &mut times.pnp_s)?;
    if params.candidate_matching && inliers(&pose) < params.candidate_skip_inliers {
        let t = std::time::Instant::now();
        let candidates =
            data.covisible_keyframes(matches.iter().map(|r| r.m.landmark), |_| true, params.candidate_keyframes);
        let every: Vec<usize> = (0..features.len()).collect();
        let stage2 = candidate_matches(data, &candidates, features, &every, embeddings, prior, params)?;
        times.stages_s += t.elapsed().as_secs_f64();
        let joined = join(matches.iter().copied().chain(stage2));
        if joined.len() > matches.len() {
            let again = estimate(&joined, &mut times.pnp_s)?;
            if inliers(&again) >= inliers(&pose) {
                (matches, pose) = (joined, again);
            }
        }
    }
    if let Some(p) = pose.as_ref().filter(|_| params.guided_search) {
        let t = std::time::Instant::now();
        let guided = guided_matches(data, p, query, &matches, params);
        times.stages_s += t.elapsed().as_secs_f64();
        if !guided.is_empty() {
            let joined = join(matches.iter().copied().chain(guided));
            let again = estimate(&joined, &mut times.pnp_s)?;
            if inliers(&again) >= inliers(&pose) {
                (matches, pose) = (joined, again);
            }
        }
    }
    Ok((matches, pose, stage1))
}

/// Localises a query (features with their embeddings, intrinsics) against a map.
pub fn localize(
    data: &MapData,
    index: &EmbeddingIndex,
    features: &Features,
    embeddings: &[f32],
    camera: &Camera,
    prior: Option<&Prior>,
    params: &LocalizeSettings,
) -> Result<Localization, MapError> {
    if embeddings.len() != features.len() * data.meta.dim {
        return Err(MapError::InvalidInput {
            field: "embeddings".into(),
            reason: format!(
                "{} values for {} keypoints of dimension {}",
                embeddings.len(),
                features.len(),
                data.meta.dim
            ),
        });
    }
    if let Some(p) = prior {
        let bound = crate::camera::MAX_COORDINATE;
        if !(p.position.iter().all(|v| v.is_finite() && v.abs() <= bound) && p.radius.is_finite() && p.radius > 0.0) {
            return Err(MapError::InvalidInput {
                field: "prior".into(),
                reason: format!("needs a finite position within {bound} map units and a positive radius"),
            });
        }
    }
    let t = std::time::Instant::now();
    // Stage 1 searches only the strongest keypoints when capped; stages 2 and 3 read every keypoint (their
    // searches are the candidates' landmarks and windows around projected landmarks, not the whole map).
    let rows: Vec<usize> = strongest(features, params.max_query_keypoints.max(params.min_inliers))
        .unwrap_or_else(|| (0..features.len()).collect());
    let mut found = index_hits(data, index, embeddings, &rows, prior, params);
    let mut search_s = t.elapsed().as_secs_f64();
    let mut timing = StageTimes::default();
    let query = Query { features, embeddings, camera, prior };
    // The capped hits are kept for the fallback only when there can be one.
    let may_fall_back = rows.len() < features.len() && params.full_search_below_inliers > 0;
    let first = if may_fall_back { found.clone() } else { std::mem::take(&mut found) };
    let (mut matches, mut pose, mut stage1) = after_search(data, &query, one_per_landmark(first), params, &mut timing)?;
    if may_fall_back && pose.as_ref().map_or(0, |p| p.inliers.len()) < params.full_search_below_inliers {
        // The fallback: the other keypoints searched too, and the query answered as without the cap (per
        // keypoint, a search and its acceptance do not depend on the others, so the hits are the same).
        let t = std::time::Instant::now();
        let mut searched = vec![false; features.len()];
        rows.iter().for_each(|&i| searched[i] = true);
        let rest: Vec<usize> = (0..features.len()).filter(|&i| !searched[i]).collect();
        found.extend(index_hits(data, index, embeddings, &rest, prior, params));
        found.sort_by_key(|r| r.m.keypoint);
        search_s += t.elapsed().as_secs_f64();
        (matches, pose, stage1) = after_search(data, &query, one_per_landmark(found), params, &mut timing)?;
    }
    let StageTimes { pnp_s, stages_s } = timing;
    if let Some(c) = pose.as_mut().and_then(|p| p.covariance_w2c.as_mut()) {
        *c *= params.covariance_scale;
    }
    let p3: Vec<[f64; 3]> = matches.iter().map(|r| data.landmarks[&r.m.landmark].point).collect();
    let confidence = pose.as_ref().map_or(0.0, |p| confidence(p, &p3));
    let matches = matches.into_iter().map(|r| r.m).collect();
    Ok(Localization { pose, matches, confidence, points: p3, stage1, search_s, pnp_s, stages_s })
}
