//! The settings of map building: the matching, the tolerances of new landmarks, external landmarks, and the
//! use of the known poses.

use serde::{Deserialize, Serialize};

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
    /// wrong keypoint that close is rare (2,000 keypoints in 640 x 480 leave one keypoint per ~150 px^2 on
    /// average, so about 8 % of a 2 px disc holds one by chance) and would still be a pixel of the same spot.
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
    /// Map building that ignores the known poses, and the default (the rule fixed before scoring on the
    /// selection scenes did not keep the alternative): the nearest keyframes, every keypoint competing, pairs
    /// only, the embedding alone.
    pub fn unguided(self) -> Self {
        Self { epipolar_px: 0.0, covisible_candidates: 0, extend_tracks: false, freak_matches: false, ..self }
    }

    /// Map building that uses the known poses: an 8 px epipolar window, 3 covisible
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
