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
//! **With the known poses** ([`BuildSettings::with_known_poses`]; off by default, because the rule
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
//!
//! Rooms: `settings.rs` ([`BuildSettings`]), `input.rs` (what a keyframe brings), `candidates.rs` (step 1 and
//! the matching of step 2), `landmarks.rs` (steps 2-3 and the tracks), `external.rs` (external landmarks),
//! `geometry.rs` (projection and triangulation); here, [`plan`], the steps in order.

use crate::camera::Pose;
use crate::error::MapError;
use crate::map::model::{Keyframe, MapData, Record};

mod candidates;
mod external;
mod geometry;
mod input;
mod landmarks;
mod settings;
#[cfg(test)]
mod tests;

pub use external::{ExternalCounts, MAX_EXTERNAL_OBSERVATIONS};
pub use input::{Depth, ExternalObservation, KeyframeInput};
pub use settings::BuildSettings;

use candidates::{candidates, match_candidates};
use external::{invalid, plan_external};
use landmarks::NewLandmarks;

/// A planned keyframe record, with what became of its external observations.
#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    pub record: Record,
    pub external: ExternalCounts,
}

/// Plans the record that adds `input` to `data`.
pub fn plan_keyframe(data: &MapData, input: &KeyframeInput, params: &BuildSettings) -> Result<Record, MapError> {
    Ok(plan(data, input, params)?.record)
}

/// Plans the record that adds `input` to `data`, with the counts of its external observations.
pub fn plan(data: &MapData, input: &KeyframeInput, params: &BuildSettings) -> Result<Plan, MapError> {
    let keyframe = checked_keyframe(data, input)?;
    if let Some(external) = input.external {
        if input.depth.is_some() {
            return Err(invalid("external_landmarks", "give external landmarks or depth, not both".into()));
        }
        let planned = plan_external(data, input, external, params)?;
        let record = Record::AddExternalKeyframe {
            keyframe,
            new_landmarks: planned.new_landmarks,
            observations: planned.observations,
            external_ids: planned.external_ids,
        };
        return Ok(Plan { record, external: planned.counts });
    }
    // The candidates' payloads, read where they are stored.
    let loaded = candidates(data, input, params).into_iter().map(|k| k.load()).collect::<Result<Vec<_>, _>>()?;
    let candidates: Vec<&Keyframe> = loaded.iter().map(|k| &**k).collect();
    let matches = match_candidates(input, &candidates, data.meta.dim, params)?;
    let mut landmarks = NewLandmarks::new(data, input, params, &candidates);
    let to_triangulate = landmarks.observe_matched(&candidates, &matches);
    match &input.depth {
        Some(depth) => landmarks.back_project(depth)?,
        None => landmarks.triangulate_matches(&candidates, &to_triangulate)?,
    }
    if params.extend_tracks {
        landmarks.extend_tracks(&candidates, &matches);
    }
    let (new_landmarks, observations) = landmarks.into_parts();
    let record = Record::AddKeyframe { keyframe, new_landmarks, observations };
    Ok(Plan { record, external: ExternalCounts::default() })
}

/// The keyframe `input` describes, once its embeddings, id, pose and intrinsics are checked against `data`.
fn checked_keyframe(data: &MapData, input: &KeyframeInput) -> Result<Keyframe, MapError> {
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
    Ok(Keyframe {
        id: input.id,
        pose,
        camera: input.camera,
        keypoints: input.features.keypoints.clone(),
        descriptors: input.features.descriptors.as_flattened().to_vec(),
        embeddings: input.embeddings.to_vec(),
    })
}
