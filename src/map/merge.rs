//! Merging one map into another (`MergeMaps`): two mapping runs of one place become one map.
//!
//! 1. **Where the source lies in the target.** Every source keyframe is localised in the target from its
//!    stored keypoints and embeddings (the same 2D-3D matching and PnP as Localize). Unless the client gives
//!    the transform, the similarity (rotation, translation, scale) that takes source coordinates to target
//!    coordinates comes from those localised keyframes: RANSAC over pairs of them (the rotation of one, the
//!    scale from the distance between the two centres), inliers by camera centre within
//!    [`CENTRE_TOLERANCE`] of the target centres' spread and rotation within [`ROTATION_TOLERANCE_DEG`],
//!    then Umeyama's fit over the inliers' centres (OpenCV `estimateAffine3D`, scale on, reflections off)
//!    when they span more than a line. Fewer than [`MIN_LOCALISED`] localised keyframes, or fewer inliers,
//!    is an error that says how many localised.
//! 2. **Re-expressed and fused.** Source keyframes (ids moved past the target's when any collides) and
//!    landmarks are carried into the target's frame. A source landmark is fused with the target landmark
//!    that its observations matched most often as PnP inliers of keyframes that agree with the transform,
//!    counting a match only when the transform puts the source point within [`FUSION_DEPTH_FRACTION`] of the
//!    target's (each target landmark takes at most one source landmark, the one with most such matches): its
//!    observations then observe the target's landmark, whose point stays. Links to an external SfM's point ids are not carried (two runs' ids are not one space).
//! 3. **One record.** The result is one [`Record::Merge`], appended and fsynced like any write: after kill -9
//!    the target is either as it was or merged, and the source is never written.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use nalgebra::{Matrix3, Point3, Rotation3, Similarity3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Point3d, Vector};
use opencv::prelude::*;

use crate::camera::Pose;
use crate::describe::features::Features;
use crate::error::MapError;
use crate::map::index::EmbeddingIndex;
use crate::map::localize::{localize, LocalizeSettings};
use crate::map::model::{Keyframe, MapData, NewObservation, Record};

/// Localised source keyframes needed to estimate the transform.
pub const MIN_LOCALISED: usize = 3;
/// A localised keyframe agrees with a transform when its centre lands within this fraction of the spread of
/// the localised keyframes' target centres (their RMS distance to their mean) ...
pub const CENTRE_TOLERANCE: f64 = 0.1;
/// ... and its rotation within this many degrees.
pub const ROTATION_TOLERANCE_DEG: f64 = 5.0;
/// A source landmark is fused with a target landmark only when the transform puts it within this fraction of
/// the target landmark's distance to the voting camera (5 cm at 1 m).
pub const FUSION_DEPTH_FRACTION: f64 = 0.05;

/// What a merge did, for the answer.
#[derive(Debug, Clone, PartialEq)]
pub struct MergePlan {
    pub record: Record,
    /// Source coordinates to target coordinates.
    pub transform: Similarity3<f64>,
    /// Whether `transform` was estimated (not given).
    pub estimated: bool,
    pub source_keyframes: usize,
    /// Source keyframes localised in the target, and those that agree with the transform.
    pub localised: usize,
    pub inliers: usize,
    /// Added to every source keyframe id (0 when no id collides).
    pub keyframe_id_offset: u64,
    pub landmarks_fused: usize,
    pub landmarks_added: usize,
}

/// A source keyframe localised in the target.
struct Located {
    keyframe: u64,
    /// Its camera-to-world pose in the target.
    pose: nalgebra::Isometry3<f64>,
    /// (keypoint, target landmark) of the PnP inliers.
    matches: Vec<(u32, u64)>,
}

fn located(target: &MapData, index: &EmbeddingIndex, kf: &Keyframe, params: &LocalizeSettings) -> Option<Located> {
    let features = Features {
        width: kf.camera.width,
        height: kf.camera.height,
        keypoints: kf.keypoints.clone(),
        descriptors: Vec::new(),
        context: Vec::new(),
    };
    let out = localize(target, index, &features, &kf.embeddings, &kf.camera, None, params).ok()?;
    let pose = out.pose?;
    let matches = pose.inliers.iter().map(|&i| &out.matches[i]).map(|m| (m.keypoint as u32, m.landmark)).collect();
    Some(Located { keyframe: kf.id, pose: pose.camera_to_world, matches })
}

fn rotation_of(p: &Pose) -> UnitQuaternion<f64> {
    p.isometry().rotation
}

fn centre(p: &Pose) -> Vector3<f64> {
    Vector3::from(p.translation)
}

/// The similarity through a pair: the rotation of `a`, the scale from the two centres' distances.
fn hypothesis(a: (&Pose, &Located), b: (&Pose, &Located)) -> Option<Similarity3<f64>> {
    let rotation = a.1.pose.rotation * rotation_of(a.0).inverse();
    let (sa, sb) = (centre(a.0), centre(b.0));
    let (ta, tb) = (a.1.pose.translation.vector, b.1.pose.translation.vector);
    let d = (sb - sa).norm();
    if d < 1e-9 {
        return None;
    }
    let scale = (tb - ta).norm() / d;
    (scale > 0.0 && scale.is_finite())
        .then(|| Similarity3::from_parts(Translation3::from(ta - scale * (rotation * sa)), rotation, scale))
}

/// Which localised keyframes agree with `s`.
fn agreeing(s: &Similarity3<f64>, pairs: &[(&Pose, &Located)], tolerance: f64) -> Vec<usize> {
    (0..pairs.len())
        .filter(|&i| {
            let (source, at) = pairs[i];
            let c = s * Point3::from(centre(source));
            let r = s.isometry.rotation * rotation_of(source);
            (c.coords - at.pose.translation.vector).norm() <= tolerance
                && r.angle_to(&at.pose.rotation).to_degrees() <= ROTATION_TOLERANCE_DEG
        })
        .collect()
}

/// Umeyama's similarity from source to target centres (OpenCV), when they span more than a line.
fn umeyama(source: &[Vector3<f64>], target: &[Vector3<f64>]) -> Result<Option<Similarity3<f64>>, MapError> {
    let spread = |v: &[Vector3<f64>]| {
        let mean = v.iter().sum::<Vector3<f64>>() / v.len() as f64;
        let m = v.iter().fold(Matrix3::zeros(), |acc, p| acc + (p - mean) * (p - mean).transpose());
        let e = m.symmetric_eigenvalues();
        let (lo, hi) = (e.min(), e.max());
        (e.sum() - lo - hi, hi)
    };
    let (middle, largest) = spread(source);
    if source.len() < 3 || middle <= 1e-4 * largest {
        return Ok(None);
    }
    let cv = |v: &[Vector3<f64>]| -> Vector<Point3d> { v.iter().map(|p| Point3d::new(p.x, p.y, p.z)).collect() };
    let mut scale = 1.0;
    let m: Mat = opencv::calib3d::estimate_affine_3d_1(&cv(source), &cv(target), Some(&mut scale), true)
        .map_err(|e| MapError::InvalidInput { field: "merge".into(), reason: format!("Umeyama's fit failed: {e}") })?;
    let at = |r: i32, c: i32| m.at_2d::<f64>(r, c).copied().unwrap_or(f64::NAN);
    let r = Matrix3::from_fn(|i, j| at(i as i32, j as i32));
    let t = Vector3::new(at(0, 3), at(1, 3), at(2, 3));
    if !(scale.is_finite() && scale > 0.0 && r.iter().chain(t.iter()).all(|v| v.is_finite())) {
        return Ok(None);
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&r));
    Ok(Some(Similarity3::from_parts(Translation3::from(t), rotation, scale)))
}

/// Estimates the transform from the localised keyframes (module docs, step 1).
fn estimate(source: &MapData, located: &[Located]) -> Result<(Similarity3<f64>, Vec<usize>), MapError> {
    let too_few = |inliers: usize| MapError::InvalidInput {
        field: "source".into(),
        reason: format!(
            "{} of the source's {} keyframes localised in the target ({} agree on one transform); at least {} \
             must, or give the transform",
            located.len(),
            source.keyframes.len(),
            inliers,
            MIN_LOCALISED
        ),
    };
    if located.len() < MIN_LOCALISED {
        return Err(too_few(0));
    }
    let pairs = with_source_poses(source, located);
    let tolerance = centre_tolerance(located);
    // Every ordered pair: a few hundred keyframes at most localise in practice, and each try is cheap.
    let mut best: Option<(Similarity3<f64>, Vec<usize>)> = None;
    for i in 0..pairs.len() {
        for j in 0..pairs.len() {
            if i == j {
                continue;
            }
            let Some(h) = hypothesis(pairs[i], pairs[j]) else { continue };
            let agree = agreeing(&h, &pairs, tolerance);
            if best.as_ref().is_none_or(|b| agree.len() > b.1.len()) {
                best = Some((h, agree));
            }
        }
    }
    let Some((mut transform, mut inliers)) = best else { return Err(too_few(0)) };
    if inliers.len() < MIN_LOCALISED {
        return Err(too_few(inliers.len()));
    }
    let src: Vec<Vector3<f64>> = inliers.iter().map(|&i| centre(pairs[i].0)).collect();
    let dst: Vec<Vector3<f64>> = inliers.iter().map(|&i| pairs[i].1.pose.translation.vector).collect();
    if let Some(refit) = umeyama(&src, &dst)? {
        let again = agreeing(&refit, &pairs, tolerance);
        if again.len() >= inliers.len() {
            (transform, inliers) = (refit, again);
        }
    }
    Ok((transform, inliers))
}

/// Each localised keyframe with its pose in the source.
fn with_source_poses<'a>(source: &'a MapData, located: &'a [Located]) -> Vec<(&'a Pose, &'a Located)> {
    located.iter().map(|l| (&source.keyframes[&l.keyframe].pose, l)).collect()
}

/// The tolerance of [`agreeing`] for these localised keyframes: [`CENTRE_TOLERANCE`] of their target
/// centres' spread.
fn centre_tolerance(located: &[Located]) -> f64 {
    let centres: Vec<Vector3<f64>> = located.iter().map(|l| l.pose.translation.vector).collect();
    let mean = centres.iter().sum::<Vector3<f64>>() / centres.len().max(1) as f64;
    let spread = (centres.iter().map(|c| (c - mean).norm_squared()).sum::<f64>() / centres.len().max(1) as f64).sqrt();
    CENTRE_TOLERANCE * spread.max(1e-9)
}

/// A camera-to-world pose carried by `s` into the other world (the camera's own axes unchanged).
pub fn moved_pose(s: &Similarity3<f64>, p: &nalgebra::Isometry3<f64>) -> nalgebra::Isometry3<f64> {
    nalgebra::Isometry3::from_parts(
        Translation3::from((s * Point3::from(p.translation.vector)).coords),
        s.isometry.rotation * p.rotation,
    )
}

/// Plans merging `source` into `target` (module docs). `transform`: source to target coordinates, when the
/// client knows it.
pub fn plan_merge(
    target: &MapData,
    index: &EmbeddingIndex,
    source: &MapData,
    transform: Option<Similarity3<f64>>,
    params: &LocalizeSettings,
) -> Result<MergePlan, MapError> {
    if source.meta.dim != target.meta.dim || source.meta.model_id != target.meta.model_id {
        return Err(MapError::InvalidInput {
            field: "source".into(),
            reason: format!(
                "the source was embedded by model {}, the target by {}: re-embed one of them first",
                source.meta.model_id, target.meta.model_id
            ),
        });
    }
    if source.keyframes.is_empty() {
        return Err(MapError::InvalidInput {
            field: "source".into(),
            reason: "the source map has no keyframes".into(),
        });
    }
    // The source's payloads, read once (where they are stored) for both the localisations and the record.
    let source_keyframes: Vec<Arc<Keyframe>> = source.keyframes.values().map(|k| k.load()).collect::<Result<_, _>>()?;
    let located: Vec<Located> = source_keyframes.iter().filter_map(|kf| located(target, index, kf, params)).collect();
    let (transform, agree, estimated) = match transform {
        Some(t) => {
            // A given transform: the keyframes whose localisation agrees with it vote for fusions.
            let pairs = with_source_poses(source, &located);
            let agree = if located.is_empty() { Vec::new() } else { agreeing(&t, &pairs, centre_tolerance(&located)) };
            (t, agree, false)
        }
        None => {
            let (t, agree) = estimate(source, &located)?;
            (t, agree, true)
        }
    };
    let inliers = if estimated { agree.len() } else { 0 };

    // Fusion votes: source landmark -> target landmark, from the PnP inliers of the keyframes that agree with
    // the transform, when the source point lands near the target's (within FUSION_DEPTH_FRACTION of its
    // distance to the voting camera).
    let source_observed = source.observed_keypoints();
    let mut votes: HashMap<u64, BTreeMap<u64, usize>> = HashMap::new();
    for l in agree.iter().map(|&i| &located[i]) {
        let camera = l.pose.translation.vector;
        for &(keypoint, target_landmark) in &l.matches {
            let Some(&s) = source_observed.get(&(l.keyframe, keypoint)) else { continue };
            let there = Vector3::from(target.landmarks[&target_landmark].point);
            let here = (transform * Point3::from(source.landmarks[&s].point)).coords;
            if (here - there).norm() <= FUSION_DEPTH_FRACTION * (there - camera).norm() {
                *votes.entry(s).or_default().entry(target_landmark).or_default() += 1;
            }
        }
    }
    // Each target landmark takes the source landmark with most votes (ties: the lower id).
    let mut claims: HashMap<u64, (usize, u64)> = HashMap::new();
    for (&s, by_target) in &votes {
        let (&t, &n) = by_target.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0))).expect("a vote");
        let better = claims.get(&t).is_none_or(|&(m, other)| n > m || (n == m && s < other));
        if better {
            claims.insert(t, (n, s));
        }
    }
    let fused: HashMap<u64, u64> = claims.into_iter().map(|(t, (_, s))| (s, t)).collect();

    let id_overflow = || MapError::InvalidInput {
        field: "source".into(),
        reason: "the source's keyframe ids cannot be moved past the target's without overflowing u64".into(),
    };
    let offset = if source.keyframes.keys().any(|id| target.keyframes.contains_key(id)) {
        match target.keyframes.keys().next_back() {
            Some(m) => m.checked_add(1).ok_or_else(id_overflow)?,
            None => 0,
        }
    } else {
        0
    };
    // Each payload read from disk is moved into the record, not copied (a payload in memory is shared with the
    // source map, and copied).
    let keyframes: Vec<Keyframe> = source_keyframes
        .into_iter()
        .map(|kf| {
            let id = kf.id.checked_add(offset).ok_or_else(id_overflow)?;
            let pose = Pose::from_isometry(&moved_pose(&transform, &kf.pose.isometry()));
            Ok(Keyframe { id, pose, ..Arc::unwrap_or_clone(kf) })
        })
        .collect::<Result<_, MapError>>()?;
    let mut new_ids: HashMap<u64, u64> = HashMap::new();
    let mut new_landmarks = Vec::new();
    let mut observations = Vec::new();
    for o in source.observations.iter().filter(|o| o.live) {
        let landmark = match fused.get(&o.landmark) {
            Some(&t) => t,
            None => *new_ids.entry(o.landmark).or_insert_with(|| {
                let id = target.next_landmark + new_landmarks.len() as u64;
                let p = transform * Point3::from(source.landmarks[&o.landmark].point);
                new_landmarks.push((id, [p.x, p.y, p.z]));
                id
            }),
        };
        observations.push(NewObservation { landmark, keyframe: o.keyframe.wrapping_add(offset), keypoint: o.keypoint });
    }
    let plan = MergePlan {
        source_keyframes: source.keyframes.len(),
        localised: located.len(),
        inliers,
        keyframe_id_offset: offset,
        landmarks_fused: fused.len(),
        landmarks_added: new_landmarks.len(),
        transform,
        estimated,
        record: Record::Merge { source: source.meta.id.clone(), keyframes, new_landmarks, observations },
    };
    target.check(&plan.record).map_err(|reason| MapError::InvalidInput { field: "merge".into(), reason })?;
    Ok(plan)
}
