//! Steps 2 and 3 of map building (module docs), and the tracks: which landmarks a new keyframe observes through
//! its matches, which it creates from depth or by triangulation, and which candidate keypoints join them.

use std::collections::{HashMap, HashSet};

use nalgebra::Point3;
use opencv::prelude::*;

use crate::error::MapError;
use crate::map::builder::geometry::{reproj_err, triangulate};
use crate::map::builder::input::{Depth, KeyframeInput};
use crate::map::builder::settings::BuildSettings;
use crate::map::model::{Keyframe, MapData, NewObservation};
use crate::matching::Match;

/// A match of the new keyframe's keypoint (first) with a candidate's keypoint (second).
pub(super) type CandidateMatch<'d> = (&'d Keyframe, usize, usize);

/// The landmarks a new keyframe observes and creates, as the steps decide them: a keypoint of the new keyframe
/// takes at most one landmark, and a candidate's keypoint joins at most one new observation.
pub(super) struct NewLandmarks<'a> {
    data: &'a MapData,
    input: &'a KeyframeInput<'a>,
    params: &'a BuildSettings,
    /// (candidate, keypoint) -> landmark, for the candidates' live observations.
    observed: HashMap<(u64, u32), u64>,
    /// Keypoint of the new keyframe -> the landmark it observes.
    assigned: HashMap<u32, u64>,
    assigned_landmarks: HashSet<u64>,
    /// Candidate keypoints that joined a landmark here.
    used_old: HashSet<(u64, u32)>,
    new_landmarks: Vec<(u64, [f64; 3])>,
    observations: Vec<NewObservation>,
    next: u64,
}

impl<'a> NewLandmarks<'a> {
    pub fn new(
        data: &'a MapData,
        input: &'a KeyframeInput<'a>,
        params: &'a BuildSettings,
        candidates: &[&Keyframe],
    ) -> Self {
        let candidate_ids: Vec<u64> = candidates.iter().map(|k| k.id).collect();
        let observed =
            data.observations_of_keyframes(&candidate_ids).map(|o| ((o.keyframe, o.keypoint), o.landmark)).collect();
        Self {
            data,
            input,
            params,
            observed,
            assigned: HashMap::new(),
            assigned_landmarks: HashSet::new(),
            used_old: HashSet::new(),
            new_landmarks: Vec::new(),
            observations: Vec::new(),
            next: data.next_landmark,
        }
    }

    /// The new landmarks (id, point) and every new observation, in the order they were decided.
    pub fn into_parts(self) -> (Vec<(u64, [f64; 3])>, Vec<NewObservation>) {
        (self.new_landmarks, self.observations)
    }

    fn keypoint(&self, i: usize) -> (f32, f32) {
        (self.input.features.keypoints[i].x, self.input.features.keypoints[i].y)
    }

    /// A new landmark at `point`, observed by the new keyframe's keypoint `a`.
    fn create(&mut self, a: usize, point: [f64; 3]) -> u64 {
        let id = self.next;
        self.next += 1;
        self.new_landmarks.push((id, point));
        self.assigned.insert(a as u32, id);
        self.observations.push(NewObservation { landmark: id, keyframe: self.input.id, keypoint: a as u32 });
        id
    }

    /// Step 2: a match to a candidate keypoint that observes a landmark adds an observation of it when the
    /// landmark reprojects within `reproj_px` of the new keypoint, in front of the camera (a landmark once).
    /// Returns the matches to unobserved candidate keypoints, to triangulate (none with depth).
    pub fn observe_matched<'d>(
        &mut self,
        candidates: &[&'d Keyframe],
        matches: &[Vec<Match>],
    ) -> Vec<CandidateMatch<'d>> {
        let mut to_triangulate = Vec::new();
        for (cand, matches) in candidates.iter().zip(matches) {
            for m in matches {
                let (a, b) = (m.query, m.train as u32);
                if self.assigned.contains_key(&(a as u32)) {
                    continue;
                }
                if let Some(&lm) = self.observed.get(&(cand.id, b)) {
                    let point = Point3::from(self.data.landmarks[&lm].point);
                    let (input, params) = (self.input, self.params);
                    if reproj_err(&input.pose, &input.camera, &point, self.keypoint(a))
                        .is_some_and(|e| e <= params.reproj_px)
                        && !self.assigned_landmarks.contains(&lm)
                    {
                        self.assigned.insert(a as u32, lm);
                        self.assigned_landmarks.insert(lm);
                        self.observations.push(NewObservation { landmark: lm, keyframe: input.id, keypoint: a as u32 });
                    }
                } else if self.input.depth.is_none() {
                    to_triangulate.push((*cand, a, b as usize));
                }
            }
        }
        to_triangulate
    }

    /// Step 3 with depth: every keypoint still without a landmark and with a reading in
    /// `[min_depth, max_depth]` is back-projected into a new landmark.
    pub fn back_project(&mut self, depth: &Depth) -> Result<(), MapError> {
        let (input, params) = (self.input, self.params);
        for a in 0..input.features.len() {
            if self.assigned.contains_key(&(a as u32)) {
                continue;
            }
            let (x, y) = self.keypoint(a);
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
            let pw = input.pose * pc;
            self.create(a, [pw.x, pw.y, pw.z]);
        }
        Ok(())
    }

    /// Step 3 without depth: the matches `to_triangulate` are triangulated with the known poses, candidate by
    /// candidate in `candidates`' order. A point is kept when it lies in front of both cameras, reprojects within
    /// `reproj_px` in both and the rays meet at `min_parallax_deg` or more; it becomes a landmark both keyframes
    /// observe.
    pub fn triangulate_matches(
        &mut self,
        candidates: &[&Keyframe],
        to_triangulate: &[CandidateMatch],
    ) -> Result<(), MapError> {
        let (input, params) = (self.input, self.params);
        let mut by_cand: HashMap<u64, Vec<(usize, usize)>> = HashMap::new();
        for (cand, a, b) in to_triangulate {
            by_cand.entry(cand.id).or_default().push((*a, *b));
        }
        for cand in candidates {
            let Some(pairs) = by_cand.get(&cand.id) else { continue };
            let cpose = cand.pose.isometry();
            let pix: Vec<_> =
                pairs.iter().map(|&(a, b)| (self.keypoint(a), (cand.keypoints[b].x, cand.keypoints[b].y))).collect();
            let points = triangulate((&input.pose, &input.camera), (&cpose, &cand.camera), &pix)?;
            for ((a, b), point) in pairs.iter().zip(points) {
                let Some(point) = point else { continue };
                if self.assigned.contains_key(&(*a as u32)) || self.used_old.contains(&(cand.id, *b as u32)) {
                    continue;
                }
                let ea = reproj_err(&input.pose, &input.camera, &point, self.keypoint(*a));
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
                let id = self.create(*a, [point.x, point.y, point.z]);
                self.used_old.insert((cand.id, *b as u32));
                self.observations.push(NewObservation { landmark: id, keyframe: cand.id, keypoint: *b as u32 });
            }
        }
        Ok(())
    }

    /// Tracks (`extend_tracks`): a landmark the new keyframe observes also takes every candidate keypoint the
    /// new keypoint matched, where it reprojects within `reproj_px` and the candidate does not observe it yet.
    pub fn extend_tracks(&mut self, candidates: &[&Keyframe], matches: &[Vec<Match>]) {
        let (data, params) = (self.data, self.params);
        // Which keyframe observes which landmark, for the landmarks the new keyframe observes.
        let mut seen_by: HashSet<(u64, u64)> = HashSet::new();
        for lm in self.assigned.values() {
            for &o in data.landmarks.get(lm).map(|l| l.observations.as_slice()).unwrap_or_default() {
                seen_by.insert((data.observations[o as usize].keyframe, *lm));
            }
        }
        seen_by.extend(self.observations.iter().map(|o| (o.keyframe, o.landmark)));
        let point_of: HashMap<u64, [f64; 3]> = self.new_landmarks.iter().copied().collect();
        for (cand, matches) in candidates.iter().zip(matches) {
            for m in matches {
                let (a, b) = (m.query, m.train as u32);
                let Some(&lm) = self.assigned.get(&(a as u32)) else { continue };
                if self.observed.contains_key(&(cand.id, b))
                    || self.used_old.contains(&(cand.id, b))
                    || seen_by.contains(&(cand.id, lm))
                {
                    continue;
                }
                let point = Point3::from(point_of.get(&lm).copied().unwrap_or_else(|| data.landmarks[&lm].point));
                let kb = (cand.keypoints[b as usize].x, cand.keypoints[b as usize].y);
                if reproj_err(&cand.pose.isometry(), &cand.camera, &point, kb).is_some_and(|e| e <= params.reproj_px) {
                    self.used_old.insert((cand.id, b));
                    seen_by.insert((cand.id, lm));
                    self.observations.push(NewObservation { landmark: lm, keyframe: cand.id, keypoint: b });
                }
            }
        }
    }
}
