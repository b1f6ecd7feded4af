//! Relocalisation: a query's keypoints and embeddings against a map -> camera-to-world pose.
//!
//! Each query keypoint takes its `knn` nearest observations in the map's index (optionally only those whose
//! landmark lies within a prior's radius). The nearest landmark is accepted when its distance is below
//! `ratio` times the distance to the nearest *other* landmark (several observations of one landmark do not
//! make it ambiguous); when all `knn` hits belong to one landmark it is accepted. One query keypoint per
//! landmark is kept (the closest). The 2D-3D matches go to solvePnPRansac + refinement; fewer than
//! `min_inliers` inliers means "not localised": no pose rather than a wrong one. A camera without a focal
//! length ([`Camera::focal_unknown`]) has it estimated with the pose (`pose::absolute_pose_unknown_focal`).
//! The pose comes with the covariance of its refinement, scaled by `covariance_scale`.
//!
//! Confidence in [0, 1] is the probability, under the pose's scaled covariance, that the pose lies within
//! [`CONFIDENCE_ROTATION_DEG`] and within [`CONFIDENCE_DEPTH_FRACTION`] of the inliers' median depth of the
//! truth ([`confidence`]): it is as calibrated as the covariance is (BENCHMARKS.md has both on real scenes),
//! and, like the covariance, it does not see a wrong pose that many inliers support.

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::MapError;
use crate::features::Features;
use crate::map::index::EmbeddingIndex;
use crate::map::model::MapData;
use crate::pose::{absolute_pose, absolute_pose_unknown_focal, AbsolutePose, RansacSettings};

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocalizeSettings {
    pub ratio: f32,
    pub knn: usize,
    pub ransac: RansacSettings,
    pub min_inliers: usize,
    /// Only this many of the query's keypoints, the strongest by detector response, are searched in the
    /// index (all of them are still embedded: a constellation is made of all keypoints). The search is the
    /// largest stage on a large map and grows with the number of queries: on the 479k-observation benchmark
    /// map, 400 takes a relocalisation from 92 to 48 ms (search 67 -> 25 ms) with 97 of 100 near queries within
    /// (0.25 m, 2°) against 98. Off by default (every keypoint is searched): on the validation scenes' far
    /// queries it costs successes (KITTI: SConE 4 -> 1 of 25 within (0.25 m, 2°)), see BENCHMARKS.md.
    /// Keypoints of equal response keep their order, so client keypoints without responses are searched in
    /// the order sent.
    pub max_query_keypoints: usize,
    /// Multiplies the pose covariance of the refinement (`σ² (JᵀJ)⁻¹`), which counts only the query's pixel
    /// noise: the map's landmarks have errors of their own, so the raw ellipsoid is too small. 26: the 95th
    /// percentile of the raw squared Mahalanobis distance over 17 localised far-map queries of the training
    /// scenes with pixel-accurate ground truth, over χ²₆(0.95) (BENCHMARKS.md, "Clients without calibration,
    /// and how sure a pose is").
    pub covariance_scale: f64,
}

impl Default for LocalizeSettings {
    fn default() -> Self {
        Self {
            ratio: crate::matching::DEFAULT_RATIO,
            knn: 4,
            ransac: RansacSettings { threshold_px: 4.0, confidence: 0.999, max_iters: 2000, ..Default::default() },
            min_inliers: 15,
            max_query_keypoints: usize::MAX,
            covariance_scale: 26.0,
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
        Ok(())
    }
}

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
    /// Wall time of the index search (with the ratio test) and of PnP, seconds.
    pub search_s: f64,
    pub pnp_s: f64,
}

/// 2D-3D matches of a query against the map.
pub fn match_landmarks(
    data: &MapData,
    index: &EmbeddingIndex,
    embeddings: &[f32],
    prior: Option<&Prior>,
    params: &LocalizeSettings,
) -> Vec<LandmarkMatch> {
    let dim = data.meta.dim;
    let near = |obs: usize| -> bool {
        let Some(p) = prior else { return true };
        let l = &data.landmarks[&data.observations[obs].landmark].point;
        let d =
            ((l[0] - p.position[0]).powi(2) + (l[1] - p.position[1]).powi(2) + (l[2] - p.position[2]).powi(2)).sqrt();
        d <= p.radius
    };
    let accept: crate::map::index::Accept = if prior.is_some() { Some(&near) } else { None };
    let all_hits = index.search_many(data, &embeddings[..embeddings.len() / dim * dim], params.knn.max(2), accept);
    let mut best: std::collections::HashMap<u64, LandmarkMatch> = std::collections::HashMap::new();
    for (i, hits) in all_hits.iter().enumerate() {
        let Some(first) = hits.first() else { continue };
        let lm = data.observations[first.observation].landmark;
        let other = hits.iter().find(|h| data.observations[h.observation].landmark != lm);
        if let Some(o) = other {
            if first.distance >= params.ratio * o.distance {
                continue;
            }
        }
        let m = LandmarkMatch { keypoint: i, landmark: lm, distance: first.distance };
        best.entry(lm)
            .and_modify(|b| {
                if m.distance < b.distance {
                    *b = m
                }
            })
            .or_insert(m);
    }
    let mut out: Vec<LandmarkMatch> = best.into_values().collect();
    out.sort_by_key(|m| m.keypoint);
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
    let mut matches = match strongest(features, params.max_query_keypoints.max(params.min_inliers)) {
        None => match_landmarks(data, index, embeddings, prior, params),
        Some(chosen) => {
            let dim = data.meta.dim;
            let subset: Vec<f32> =
                chosen.iter().flat_map(|&i| embeddings[i * dim..(i + 1) * dim].iter().copied()).collect();
            let mut m = match_landmarks(data, index, &subset, prior, params);
            for x in &mut m {
                x.keypoint = chosen[x.keypoint];
            }
            m
        }
    };
    // Best first: PnP's PROSAC sampler draws from the front.
    matches.sort_by(|a, b| a.distance.total_cmp(&b.distance));
    let search_s = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let p3: Vec<[f64; 3]> = matches.iter().map(|m| data.landmarks[&m.landmark].point).collect();
    let p2: Vec<(f32, f32)> =
        matches.iter().map(|m| (features.keypoints[m.keypoint].x, features.keypoints[m.keypoint].y)).collect();
    let mut pose = if camera.focal_unknown() {
        absolute_pose_unknown_focal(&p3, &p2, camera, &params.ransac, params.min_inliers)?
    } else {
        absolute_pose(&p3, &p2, camera, &params.ransac, params.min_inliers)?
    };
    if let Some(c) = pose.as_mut().and_then(|p| p.covariance_w2c.as_mut()) {
        *c *= params.covariance_scale;
    }
    let confidence = pose.as_ref().map_or(0.0, |p| confidence(p, &p3));
    Ok(Localization { pose, matches, confidence, points: p3, search_s, pnp_s: t.elapsed().as_secs_f64() })
}
