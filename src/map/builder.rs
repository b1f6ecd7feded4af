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
//! **With the known poses** ([`BuildSettings::with_known_poses`], issue 27; off by default, because the rule
//! fixed before scoring did not keep it on the selection scenes, BENCHMARKS.md): step 1 adds the
//! `covisible_candidates` keyframes sharing the most landmarks with the nearest ones; step 2 lets a keypoint
//! compete only with the candidate keypoints within `epipolar_px` of its epipolar line (the fundamental matrix
//! of the two poses), joins FREAK's matches for keypoints the embedding left unmatched (`freak_matches`), and
//! with `extend_tracks` a landmark the new keyframe observes also takes every candidate keypoint the new
//! keypoint matched where it reprojects within `reproj_px`, so tracks grow across keyframes instead of stopping
//! at pairs. (Two landmarks that turn out to be one are not fused: that would need a record of its own.)
//!
//! **External landmarks** (a map made by an external SfM such as COLMAP, see [`crate::offline::colmap`]): a keyframe may
//! carry [`ExternalObservation`]s, each a pixel of this keyframe, the SfM's id of the 3D point seen there and
//! that point. Such a keyframe takes its landmarks from them *instead of* steps 2-3: no matching against
//! earlier keyframes, no depth, no triangulation. The SfM already decided which pixels see which point and
//! refined the points with all its views; mixing in our own matches would attach SfM points to keypoints the
//! SfM did not associate, and back-projected or triangulated points would duplicate SfM points with worse
//! ones. (Depth together with external landmarks is refused rather than silently ignored.) Later keyframes
//! without external landmarks still match against these and may add observations to them. In order:
//!
//! 1. Malformed input refuses the whole request ([`MapError::InvalidInput`] naming
//!    `external_landmarks[i]...`): a non-finite value, one id given with two points that differ by more than
//!    `external_point_tolerance`, an id the map already links to a point that far away, more than
//!    [`MAX_EXTERNAL_OBSERVATIONS`].
//! 2. Each observation is checked against the keyframe's pose and intrinsics: the point must be in front of
//!    the camera and reproject within `external_reproj_px` of the given pixel. Failures are *rejected*
//!    (counted in [`ExternalCounts`], not stored). Of two observations of one id in this keyframe the one
//!    with the larger error is rejected too.
//! 3. Each remaining observation takes the nearest keypoint of this keyframe within `external_radius_px`;
//!    a keypoint takes at most one observation, the nearest (the others stay *unassociated*, not moved to a
//!    farther keypoint, which would likely be a different corner).
//! 4. An id the map links already adds an observation to that landmark; a new id creates one landmark
//!    (at the given point) and the link, so the views of one SfM point across keyframes are one landmark.
//!
//! The result is a [`Record`]: applying it (and logging it) is the store's job. Nothing here depends on what
//! the embeddings are, so the evaluation runs the same code for FREAK (bits as ±1, where L2 ranks exactly as
//! Hamming) and SIFT.

use std::collections::{HashMap, HashSet};

use nalgebra::{Isometry3, Point3, Vector3};
use opencv::core::{Mat, Point2d, Vector};
use opencv::prelude::*;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::camera::Pose;
use crate::error::MapError;
use crate::features::Features;
use crate::features::{bits_mat, DESCRIPTOR_BYTES};
use crate::map::model::{Keyframe, MapData, NewObservation, Record};
use crate::matching::{embedding_mat, match_descriptors_masked, RatioTest};
use opencv::core::{NORM_HAMMING, NORM_L2};

/// Settings of map building.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BuildSettings {
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
    /// External landmarks: an observation takes the nearest keypoint within this many pixels. 2 px: the
    /// SfM's feature (COLMAP: SIFT, sub-pixel) and our FAST corner of the same image structure lie within
    /// about 1-2 px (FAST positions on pyramid level l are quantised to 1.2^l px, 1.7 px on level 3), while a
    /// wrong keypoint that close is rare (1,500 keypoints in 640 x 480 leave one keypoint per ~200 px^2 on
    /// average, so about 6 % of a 2 px disc holds one by chance) and would still be a pixel of the same spot.
    pub external_radius_px: f64,
    /// External landmarks: largest reprojection error, with the given pose and intrinsics, of an accepted
    /// observation. 4 px is COLMAP's own `filter_max_reproj_error`, so every observation COLMAP keeps passes
    /// unless the pose, intrinsics or pixel convention do not fit it (then nearly all fail, as they should).
    pub external_reproj_px: f64,
    /// External landmarks: two points given for one id are the same point when they differ by at most this
    /// much (map units). An SfM has one point per id; copies differ only by rounding (f32 on the way, 1e-6
    /// relative at 100 m), never by 0.1 mm.
    pub external_point_tolerance: f64,
    /// Matching guided by the known poses: a keypoint of the new keyframe competes (ratio test, mutual check)
    /// only with the candidate's keypoints within this many pixels of its epipolar line (0: every keypoint).
    pub epipolar_px: f64,
    /// Besides the `candidates` nearest keyframes, this many keyframes that share the most landmarks with them
    /// (covisibility) are matched too.
    pub covisible_candidates: usize,
    /// A landmark the new keyframe observes (matched or just triangulated) also takes the candidates'
    /// keypoints the new keyframe's keypoint matched, where it reprojects within `reproj_px`: tracks grow
    /// across keyframes instead of stopping at pairs.
    pub extend_tracks: bool,
    /// FREAK's matches (Hamming, the same ratio, where both keyframes carry FREAK bits) join the embedding's
    /// for keypoints the embedding left unmatched.
    pub freak_matches: bool,
}

impl Default for BuildSettings {
    fn default() -> Self {
        Self {
            ratio: crate::matching::DEFAULT_RATIO,
            reproj_px: 3.0,
            min_parallax_deg: 1.0,
            candidates: 5,
            min_depth: 0.1,
            max_depth: 40.0,
            external_radius_px: 2.0,
            external_reproj_px: 4.0,
            external_point_tolerance: 1e-4,
            epipolar_px: 0.0,
            covisible_candidates: 0,
            extend_tracks: false,
            freak_matches: false,
        }
    }
}

impl BuildSettings {
    /// Map building before issue 27, and the default (issue 27's rule did not keep the alternative): the
    /// nearest keyframes, every keypoint competing, pairs only, the embedding alone.
    pub fn unguided(self) -> Self {
        Self { epipolar_px: 0.0, covisible_candidates: 0, extend_tracks: false, freak_matches: false, ..self }
    }

    /// Map building that uses the known poses (issue 27, section 2): an 8 px epipolar window, 3 covisible
    /// candidates, tracks extended across keyframes, FREAK's matches joined.
    pub fn with_known_poses(self) -> Self {
        Self { epipolar_px: 8.0, covisible_candidates: 3, extend_tracks: true, freak_matches: true, ..self }
    }

    /// Checks the settings of external landmarks (the others have always been taken as given).
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("external_radius_px", self.external_radius_px),
            ("external_reproj_px", self.external_reproj_px),
            ("external_point_tolerance", self.external_point_tolerance),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be positive, got {v}"));
            }
        }
        if !(self.epipolar_px.is_finite() && self.epipolar_px >= 0.0) {
            return Err(format!("epipolar_px must be 0 (off) or positive, got {}", self.epipolar_px));
        }
        if self.external_radius_px > 64.0 {
            return Err(format!("external_radius_px {} is over 64 px", self.external_radius_px));
        }
        Ok(())
    }
}

/// Most external observations one keyframe may carry (COLMAP images hold a few thousand).
pub const MAX_EXTERNAL_OBSERVATIONS: usize = 100_000;

/// An observation of a landmark given by an external SfM: where this keyframe sees it and where it is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ExternalObservation {
    /// Pixel in this keyframe (x right, y down, (0, 0) the centre of the top-left pixel).
    pub x: f64,
    pub y: f64,
    /// The SfM's id of the 3D point (COLMAP's POINT3D_ID); one id across keyframes is one landmark.
    pub landmark_id: u64,
    /// The point in world coordinates.
    pub point: [f64; 3],
}

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

/// A planned keyframe record, with what became of its external observations.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    pub record: Record,
    pub external: ExternalCounts,
}

/// Depth for a keyframe: 16-bit image and the factor that turns raw values into metres.
pub struct Depth<'a> {
    pub image: &'a Mat,
    /// Metres per raw unit (TUM: [`crate::decode::TUM_DEPTH_SCALE`]).
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
    /// Landmarks given by an external SfM; `Some` (even empty) means this keyframe takes its landmarks from
    /// them only (see the module docs).
    pub external: Option<&'a [ExternalObservation]>,
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
pub fn plan_keyframe(data: &MapData, input: &KeyframeInput, params: &BuildSettings) -> Result<Record, MapError> {
    Ok(plan(data, input, params)?.record)
}

/// Plans the record that adds `input` to `data`, with the counts of its external observations.
pub fn plan(data: &MapData, input: &KeyframeInput, params: &BuildSettings) -> Result<Plan, MapError> {
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
    pose.validate()
        .map_err(|problem| MapError::InvalidInput { field: "pose".into(), reason: format!("pose {problem}") })?;
    crate::camera::validate_camera(&input.camera)?;
    let keyframe = || Keyframe {
        id: input.id,
        pose,
        camera: input.camera,
        keypoints: input.features.keypoints.clone(),
        descriptors: input.features.descriptors.as_flattened().to_vec(),
        embeddings: input.embeddings.to_vec(),
    };
    if let Some(external) = input.external {
        if input.depth.is_some() {
            return Err(invalid("external_landmarks", "give external landmarks or depth, not both".into()));
        }
        let planned = plan_external(data, input, external, params)?;
        let record = Record::AddExternalKeyframe {
            keyframe: keyframe(),
            new_landmarks: planned.new_landmarks,
            observations: planned.observations,
            external_ids: planned.external_ids,
        };
        return Ok(Plan { record, external: planned.counts });
    }
    let kp = |i: usize| (input.features.keypoints[i].x, input.features.keypoints[i].y);

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
    if params.covisible_candidates > 0 && !candidates.is_empty() {
        let near: HashSet<u64> = candidates.iter().map(|k| k.id).collect();
        let near_ids: Vec<u64> = near.iter().copied().collect();
        let shared = data.observations_of_keyframes(&near_ids).map(|o| o.landmark);
        let seeing =
            |k: u64| !near.contains(&k) && viewing_direction(&data.keyframes[&k].pose.isometry()).dot(&dir) > 0.0;
        let ranked = data.covisible_keyframes(shared, seeing, params.covisible_candidates);
        candidates.extend(ranked.iter().map(|k| &data.keyframes[k]));
    }

    // (candidate, keypoint) -> landmark, for the candidates' live observations.
    let candidate_ids: Vec<u64> = candidates.iter().map(|k| k.id).collect();
    let observed: HashMap<(u64, u32), u64> =
        data.observations_of_keyframes(&candidate_ids).map(|o| ((o.keyframe, o.keypoint), o.landmark)).collect();
    let mut assigned: HashMap<u32, u64> = HashMap::new(); // keypoint of the new keyframe -> landmark
    let mut assigned_landmarks: HashSet<u64> = HashSet::new();
    let mut used_old: HashSet<(u64, u32)> = HashSet::new();
    let mut new_landmarks: Vec<(u64, [f64; 3])> = Vec::new();
    let mut observations: Vec<NewObservation> = Vec::new();
    let mut next = data.next_landmark;
    let mut to_triangulate: Vec<(&Keyframe, usize, usize)> = Vec::new();

    let mut matched_pairs: Vec<(&Keyframe, usize, u32)> = Vec::new();
    // The matching is most of a keyframe's cost and each candidate's is independent: on rayon's threads,
    // then taken in the candidates' order, as before.
    let per_candidate: Vec<Vec<crate::matching::Match>> =
        candidates.par_iter().map(|cand| candidate_matches(input, cand, dim, params)).collect::<Result<_, _>>()?;
    for (cand, matches) in candidates.iter().zip(per_candidate) {
        for m in matches {
            let (a, b) = (m.query, m.train as u32);
            matched_pairs.push((cand, a, b));
            if assigned.contains_key(&(a as u32)) {
                continue;
            }
            if let Some(&lm) = observed.get(&(cand.id, b)) {
                let point = Point3::from(data.landmarks[&lm].point);
                if reproj_err(&input.pose, &input.camera, &point, kp(a)).is_some_and(|e| e <= params.reproj_px)
                    && !assigned_landmarks.contains(&lm)
                {
                    assigned.insert(a as u32, lm);
                    assigned_landmarks.insert(lm);
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

    if params.extend_tracks {
        // Which keyframe observes which landmark, for the landmarks the new keyframe observes.
        let mut seen_by: HashSet<(u64, u64)> = HashSet::new();
        for lm in assigned.values() {
            for &o in data.landmarks.get(lm).map(|l| l.observations.as_slice()).unwrap_or_default() {
                seen_by.insert((data.observations[o as usize].keyframe, *lm));
            }
        }
        seen_by.extend(observations.iter().map(|o| (o.keyframe, o.landmark)));
        let point_of: HashMap<u64, [f64; 3]> = new_landmarks.iter().copied().collect();
        for (cand, a, b) in matched_pairs {
            let Some(&lm) = assigned.get(&(a as u32)) else { continue };
            if observed.contains_key(&(cand.id, b))
                || used_old.contains(&(cand.id, b))
                || seen_by.contains(&(cand.id, lm))
            {
                continue;
            }
            let point = Point3::from(point_of.get(&lm).copied().unwrap_or_else(|| data.landmarks[&lm].point));
            let kb = (cand.keypoints[b as usize].x, cand.keypoints[b as usize].y);
            if reproj_err(&cand.pose.isometry(), &cand.camera, &point, kb).is_some_and(|e| e <= params.reproj_px) {
                used_old.insert((cand.id, b));
                seen_by.insert((cand.id, lm));
                observations.push(NewObservation { landmark: lm, keyframe: cand.id, keypoint: b });
            }
        }
    }

    let record = Record::AddKeyframe { keyframe: keyframe(), new_landmarks, observations };
    Ok(Plan { record, external: ExternalCounts::default() })
}

/// The new keyframe's matches with one candidate: the embedding's (OpenCV's plain ratio test with the mutual
/// check, as the maps' figures of issue 5 were measured), within the epipolar window when it is on, joined by
/// FREAK's for the keypoints still unmatched when that is on.
fn candidate_matches(
    input: &KeyframeInput,
    cand: &Keyframe,
    dim: usize,
    params: &BuildSettings,
) -> Result<Vec<crate::matching::Match>, MapError> {
    let test = RatioTest { ratio: params.ratio, mutual: true, same_corner_px: 0.0 };
    let mask = if params.epipolar_px > 0.0 { epipolar_mask(input, cand, params.epipolar_px)? } else { Mat::default() };
    let a = embedding_mat(input.embeddings, dim)?;
    let b = embedding_mat(&cand.embeddings, dim)?;
    let mut matches = match_descriptors_masked(&a, &b, NORM_L2, &test, &[], &mask)?;
    let n = input.features.len();
    let bits =
        input.features.descriptors.len() == n && cand.descriptors.len() == cand.keypoints.len() * DESCRIPTOR_BYTES;
    if params.freak_matches && bits {
        let a = input.features.descriptor_mat()?;
        let b = bits_mat(&cand.descriptors)?;
        let (qs, ts): (HashSet<usize>, HashSet<usize>) =
            (matches.iter().map(|m| m.query).collect(), matches.iter().map(|m| m.train).collect());
        let freak = match_descriptors_masked(&a, &b, NORM_HAMMING, &test, &[], &mask)?;
        matches.extend(freak.into_iter().filter(|m| !qs.contains(&m.query) && !ts.contains(&m.train)));
    }
    Ok(matches)
}

/// `[new keypoints, candidate keypoints]` mask of the pairs whose candidate keypoint lies within `px` of the
/// epipolar line of the new keypoint (the fundamental matrix of the two known poses and intrinsics).
fn epipolar_mask(input: &KeyframeInput, cand: &Keyframe, px: f64) -> Result<Mat, MapError> {
    let fe = crate::error::FeatureError::from;
    // Relative pose new -> candidate: x_c = R x_n + t.
    let rel = cand.pose.isometry().inverse() * input.pose;
    let (r, t) = (rel.rotation.to_rotation_matrix().into_inner(), rel.translation.vector);
    if t.norm() < 1e-9 {
        return Ok(Mat::default()); // the same centre: no epipolar geometry, every pair competes
    }
    let tx = nalgebra::Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0);
    let kn = nalgebra::Matrix3::from_row_slice(&input.camera.k().concat());
    let kc = nalgebra::Matrix3::from_row_slice(&cand.camera.k().concat());
    let (Some(kn_inv), Some(kc_inv)) = (kn.try_inverse(), kc.try_inverse()) else {
        return Ok(Mat::default());
    };
    let f = kc_inv.transpose() * tx * r * kn_inv;
    let (rows, cols) = (input.features.len(), cand.keypoints.len());
    let mut mask = vec![0u8; rows * cols];
    for (i, p) in input.features.keypoints.iter().enumerate() {
        let l = f * Vector3::new(f64::from(p.x), f64::from(p.y), 1.0);
        let norm = l.x.hypot(l.y);
        let row = &mut mask[i * cols..(i + 1) * cols];
        if norm < 1e-12 {
            row.fill(1); // the epipole: no line, every candidate keypoint competes
            continue;
        }
        for (m, q) in row.iter_mut().zip(&cand.keypoints) {
            let d = (l.x * f64::from(q.x) + l.y * f64::from(q.y) + l.z).abs() / norm;
            *m = u8::from(d <= px);
        }
    }
    Ok(Mat::new_rows_cols_with_data(rows as i32, cols as i32, &mask).map_err(fe)?.try_clone().map_err(fe)?)
}

fn invalid(field: &str, reason: String) -> MapError {
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
struct ExternalPlan {
    new_landmarks: Vec<(u64, [f64; 3])>,
    observations: Vec<NewObservation>,
    external_ids: Vec<(u64, u64)>,
    counts: ExternalCounts,
}

/// Steps 1-4 of the module docs for `external`, the observations of keyframe `input`.
fn plan_external(
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
    let tol = params.external_point_tolerance;
    // 1. Malformed input refuses the request.
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
    // 2. Geometry with the given pose and intrinsics; one view per id (the smaller error).
    let mut counts = ExternalCounts { given: external.len(), ..Default::default() };
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
    // 3. The nearest keypoint within the radius; a keypoint keeps the nearest of the observations choosing it.
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
    for &i in &valid {
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
    // 4. Linked ids observe their landmark; new ids create one.
    let mut pairs: Vec<(usize, usize)> = taken.into_iter().map(|(k, (i, _))| (i, k)).collect();
    pairs.sort_unstable();
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
