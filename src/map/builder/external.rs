//! External landmarks (module docs, steps 1-4): the observations an external SfM made of a keyframe checked,
//! each given the nearest free keypoint, and linked to the landmark of its SfM id or made one.

use std::collections::HashMap;

use nalgebra::Point3;
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::builder::geometry::project;
use crate::map::builder::input::{ExternalObservation, KeyframeInput};
use crate::map::builder::settings::BuildSettings;
use crate::map::model::{MapData, NewObservation};

/// Most external observations one keyframe may carry (COLMAP images hold a few thousand).
pub const MAX_EXTERNAL_OBSERVATIONS: usize = 100_000;

/// What became of a keyframe's external observations.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExternalCounts {
    /// Given in the request.
    pub given: usize,
    /// Stored as observations (of new or linked landmarks).
    pub associated: usize,
    /// Behind the camera, reprojecting too far from their pixel, or a second view of one id.
    pub rejected: usize,
    /// Valid, but no keypoint within the radius was free.
    pub unassociated: usize,
}

pub(super) fn invalid(field: &str, reason: String) -> MapError {
    MapError::InvalidInput { field: field.to_string(), reason }
}

/// A 3D point as clients write it, `(x, y, z)`.
fn point_text(p: &[f64; 3]) -> String {
    format!("({}, {}, {})", p[0], p[1], p[2])
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt()
}

/// The landmarks, observations and links of a keyframe with external landmarks.
pub(super) struct ExternalPlan {
    pub new_landmarks: Vec<(u64, [f64; 3])>,
    pub observations: Vec<NewObservation>,
    pub external_ids: Vec<(u64, u64)>,
    pub counts: ExternalCounts,
}

/// Steps 1-4 of the module docs for `external`, the observations of keyframe `input`.
pub(super) fn plan_external(
    data: &MapData,
    input: &KeyframeInput,
    external: &[ExternalObservation],
    params: &BuildSettings,
) -> Result<ExternalPlan, MapError> {
    if external.len() > MAX_EXTERNAL_OBSERVATIONS {
        return Err(invalid(
            "external_landmarks",
            format!("{} observations, the limit is {MAX_EXTERNAL_OBSERVATIONS}", external.len()),
        ));
    }
    refuse_malformed(data, external, params.external_point_tolerance)?;
    let mut counts = ExternalCounts { given: external.len(), ..Default::default() };
    let valid = accepted_views(input, external, params, &mut counts);
    let pairs = nearest_keypoints(input, external, &valid, params, &mut counts);
    // 4. Linked ids observe their landmark; new ids create one.
    let mut plan =
        ExternalPlan { new_landmarks: Vec::new(), observations: Vec::new(), external_ids: Vec::new(), counts };
    let mut next = data.next_landmark;
    for (i, k) in pairs {
        let o = &external[i];
        let landmark = match data.external_ids.get(&o.landmark_id) {
            Some(&lm) => lm,
            None => {
                let id = next;
                next += 1;
                plan.new_landmarks.push((id, o.point));
                plan.external_ids.push((o.landmark_id, id));
                id
            }
        };
        plan.observations.push(NewObservation { landmark, keyframe: input.id, keypoint: k as u32 });
    }
    plan.counts.associated = plan.observations.len();
    Ok(plan)
}

/// Step 1: a non-finite value, one id given with two points farther apart than `tol`, or an id the map links
/// to a point that far away refuses the request.
fn refuse_malformed(data: &MapData, external: &[ExternalObservation], tol: f64) -> Result<(), MapError> {
    let mut first_of: HashMap<u64, usize> = HashMap::new();
    for (i, o) in external.iter().enumerate() {
        if !(o.x.is_finite() && o.y.is_finite()) {
            return Err(invalid(
                &format!("external_landmarks[{i}]"),
                format!("pixel ({}, {}) is not finite", o.x, o.y),
            ));
        }
        if !o.point.iter().all(|v| v.is_finite()) {
            return Err(invalid(
                &format!("external_landmarks[{i}].point"),
                format!("{} of landmark {} is not finite", point_text(&o.point), o.landmark_id),
            ));
        }
        match first_of.get(&o.landmark_id) {
            Some(&j) if distance(&external[j].point, &o.point) > tol => {
                return Err(invalid(
                    &format!("external_landmarks[{i}].point"),
                    format!(
                        "landmark {} is also external_landmarks[{j}] with point {}, {:.6} away from {} (tolerance {tol})",
                        o.landmark_id,
                        point_text(&external[j].point),
                        distance(&external[j].point, &o.point),
                        point_text(&o.point)
                    ),
                ));
            }
            Some(_) => {}
            None => {
                first_of.insert(o.landmark_id, i);
            }
        }
        if let Some(held) = data.external_ids.get(&o.landmark_id).and_then(|lm| data.landmarks.get(lm)) {
            let held = held.point;
            let d = distance(&held, &o.point);
            if d > tol {
                return Err(invalid(
                    &format!("external_landmarks[{i}].point"),
                    format!(
                        "landmark {} is at {} in map '{}', {d:.6} away from {} (tolerance {tol})",
                        o.landmark_id,
                        point_text(&held),
                        data.meta.id,
                        point_text(&o.point)
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Step 2: the observations in front of the camera that reproject within `external_reproj_px` of their pixel,
/// one per id (the smaller error), in the order given; the others are counted rejected.
fn accepted_views(
    input: &KeyframeInput,
    external: &[ExternalObservation],
    params: &BuildSettings,
    counts: &mut ExternalCounts,
) -> Vec<usize> {
    let mut best_of: HashMap<u64, (usize, f64)> = HashMap::new();
    for (i, o) in external.iter().enumerate() {
        let Some((u, v, _)) = project(&input.pose, &input.camera, &Point3::from(o.point)) else {
            counts.rejected += 1;
            continue;
        };
        let err = (u - o.x).hypot(v - o.y);
        if err.is_nan() || err > params.external_reproj_px {
            counts.rejected += 1;
            continue;
        }
        match best_of.get_mut(&o.landmark_id) {
            Some(best) => {
                counts.rejected += 1;
                if err < best.1 {
                    *best = (i, err);
                }
            }
            None => {
                best_of.insert(o.landmark_id, (i, err));
            }
        }
    }
    let mut valid: Vec<usize> = best_of.values().map(|b| b.0).collect();
    valid.sort_unstable();
    valid
}

/// Step 3: (observation, keypoint) for each of `valid` that takes the nearest keypoint within
/// `external_radius_px`, a keypoint keeping the nearest of the observations choosing it (the others are counted
/// unassociated); sorted by observation.
fn nearest_keypoints(
    input: &KeyframeInput,
    external: &[ExternalObservation],
    valid: &[usize],
    params: &BuildSettings,
    counts: &mut ExternalCounts,
) -> Vec<(usize, usize)> {
    let radius = params.external_radius_px;
    let cell = radius.max(1.0);
    let key = |x: f64, y: f64| ((x / cell).floor() as i64, (y / cell).floor() as i64);
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (k, p) in input.features.keypoints.iter().enumerate() {
        grid.entry(key(p.x as f64, p.y as f64)).or_default().push(k);
    }
    let reach = (radius / cell).ceil() as i64;
    let mut taken: HashMap<usize, (usize, f64)> = HashMap::new(); // keypoint -> (observation, distance)
    let (w, h) = (input.camera.width as f64, input.camera.height as f64);
    for &i in valid {
        let o = &external[i];
        if o.x < -radius || o.y < -radius || o.x > w - 1.0 + radius || o.y > h - 1.0 + radius {
            counts.unassociated += 1; // no keypoint can be that far outside the image
            continue;
        }
        let (cx, cy) = key(o.x, o.y);
        let mut nearest: Option<(usize, f64)> = None;
        for gx in cx - reach..=cx + reach {
            for gy in cy - reach..=cy + reach {
                for &k in grid.get(&(gx, gy)).into_iter().flatten() {
                    let p = &input.features.keypoints[k];
                    let d = (p.x as f64 - o.x).hypot(p.y as f64 - o.y);
                    if d <= radius && nearest.is_none_or(|n| d < n.1 || (d == n.1 && k < n.0)) {
                        nearest = Some((k, d));
                    }
                }
            }
        }
        let Some((k, d)) = nearest else {
            counts.unassociated += 1;
            continue;
        };
        match taken.get_mut(&k) {
            Some(holder) => {
                counts.unassociated += 1;
                if d < holder.1 {
                    *holder = (i, d);
                }
            }
            None => {
                taken.insert(k, (i, d));
            }
        }
    }
    let mut pairs: Vec<(usize, usize)> = taken.into_iter().map(|(k, (i, _))| (i, k)).collect();
    pairs.sort_unstable();
    pairs
}
