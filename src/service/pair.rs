//! MatchPair: two frames described, matched (`matching::SconeMatcher`) and their relative pose estimated.

use super::core::Service;
use super::error::ServiceError;
use super::frame::FrameInput;
use crate::describe::pipeline::StageTimes;
use crate::matching::{match_scone, Match, RatioTest, SconeFrame, SconeMatcher, DEFAULT_RATIO, SAME_CORNER_PX};
use crate::pose::{relative_pose, RelativePose};

/// Pair matching settings a client may choose. The ratio test's same-corner radius is the project's
/// default ([`crate::matching::SAME_CORNER_PX`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairOptions {
    pub ratio: f32,
    pub mutual: bool,
    /// How the matches are picked (`matching::SconeMatcher`); `None`: the model's declared matcher
    /// ([`Service::default_matcher`]).
    pub matcher: Option<SconeMatcher>,
}

impl Default for PairOptions {
    fn default() -> Self {
        Self { ratio: DEFAULT_RATIO, mutual: false, matcher: None }
    }
}

/// Matches between two frames and their relative pose.
#[derive(Debug, Clone)]
pub struct PairOutcome {
    /// The matcher that picked the matches (the request's, or the model's default).
    pub matcher: SconeMatcher,
    pub matches: Vec<Match>,
    /// Keypoint positions of each frame (the matches index into them), for pictures.
    pub points1: Vec<(f32, f32)>,
    pub points2: Vec<(f32, f32)>,
    /// Camera 1 into camera 2, when enough matches support one.
    pub pose: Option<RelativePose>,
    pub times: StageTimes,
}

impl PairOutcome {
    /// Whether each match (in the order of [`PairOutcome::matches`]) is an inlier of the pose; all false
    /// without a pose.
    pub fn inlier_flags(&self) -> Vec<bool> {
        let inliers = self.pose.as_ref().map_or(&[][..], |p| &p.inliers[..]);
        (0..self.matches.len()).map(|i| inliers.get(i).copied().unwrap_or(false)).collect()
    }

    /// Matches that are inliers of the pose (0 without one).
    pub fn inlier_count(&self) -> usize {
        self.pose.as_ref().map_or(0, |p| p.inlier_count)
    }
}

impl Service {
    /// SConE matches between two frames (ratio test, optional mutual check) and their relative pose.
    pub fn match_pair(&self, a: FrameInput, b: FrameInput, options: PairOptions) -> Result<PairOutcome, ServiceError> {
        if !crate::matching::is_ratio(options.ratio) {
            return Err(ServiceError::invalid("ratio", format!("{} is outside (0, 1]", options.ratio)));
        }
        self.check_source(&a.source)?;
        self.check_source(&b.source)?;
        let cam1 = Self::camera(&a, "frame1.intrinsics")?;
        let cam2 = Self::camera(&b, "frame2.intrinsics")?;
        let d1 = self.describe_source(a.source, Some((&cam1, &a.distortion)))?;
        Self::check_frame_size(&d1, &cam1, "frame1.intrinsics")?;
        let d2 = self.describe_source(b.source, Some((&cam2, &b.distortion)))?;
        Self::check_frame_size(&d2, &cam2, "frame2.intrinsics")?;
        let mut times = d1.times.clone();
        times.add(&d2.times);
        let matcher = options.matcher.unwrap_or(self.default_matcher);
        let test = RatioTest { ratio: options.ratio, mutual: options.mutual, same_corner_px: SAME_CORNER_PX };
        let (points1, points2) = (d1.features.points(), d2.features.points());
        let matches = times.time("match", || {
            let (freak1, freak2) = (d1.features.descriptor_mat()?, d2.features.descriptor_mat()?);
            let sizes1: Vec<f32> = d1.features.keypoints.iter().map(|k| k.size).collect();
            let sizes2: Vec<f32> = d2.features.keypoints.iter().map(|k| k.size).collect();
            let f1 = SconeFrame {
                embeddings: &d1.embeddings,
                dim: d1.dim,
                freak: &freak1,
                points: &points1,
                sizes: &sizes1,
            };
            let f2 = SconeFrame {
                embeddings: &d2.embeddings,
                dim: d2.dim,
                freak: &freak2,
                points: &points2,
                sizes: &sizes2,
            };
            match_scone(matcher, &f1, &f2, &test)
        })?;
        let p1: Vec<(f32, f32)> = matches.iter().map(|m| d1.features.keypoints[m.query]).map(|k| (k.x, k.y)).collect();
        let p2: Vec<(f32, f32)> = matches.iter().map(|m| d2.features.keypoints[m.train]).map(|k| (k.x, k.y)).collect();
        let pose = times.time("pose", || relative_pose(&p1, &p2, &cam1, &cam2, &self.ransac))?;
        Ok(PairOutcome { matcher, matches, pose, times, points1, points2 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pair_outcome_flags_each_match_once_and_none_without_a_pose() {
        let m = |i| Match { query: i, train: i, distance: 0.1 };
        let mut o = PairOutcome {
            matcher: SconeMatcher::Union,
            matches: vec![m(0), m(1), m(2)],
            pose: None,
            times: StageTimes::default(),
            points1: vec![],
            points2: vec![],
        };
        assert_eq!((o.inlier_flags(), o.inlier_count()), (vec![false; 3], 0));
        o.pose = Some(RelativePose {
            rotation: nalgebra::Rotation3::identity(),
            translation: nalgebra::Vector3::x(),
            inliers: vec![true, false, true],
            inlier_count: 2,
        });
        assert_eq!((o.inlier_flags(), o.inlier_count()), (vec![true, false, true], 2));
    }
}
