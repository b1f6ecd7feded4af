//! LocalizeTrack: several frames with known poses relative to each other (a phone's tracker, a rig's
//! extrinsics) located together against the map they were given. Each frame is described and goes through
//! Localize's stages on its own; the frames' matches and poses then go to the track estimator
//! ([`crate::pose::track_pose`]).

use nalgebra::{Isometry3, Matrix6, Similarity3};
use rayon::prelude::*;

use super::core::Service;
use super::error::ServiceError;
use super::frame::FrameInput;
use crate::camera::{Pose, PoseConvention};
use crate::describe::pipeline::StageTimes;
use crate::map::localize::{confidence, Prior};
use crate::map::store::Map;
use crate::pose::{track_pose, AbsolutePose, TrackFrame, TrackScale, TrackerError};

/// Frames a track may hold.
pub const TRACK_FRAMES: std::ops::RangeInclusive<usize> = 2..=10;
/// Seed of the track estimator's minimal sets: the same request gets the same answer.
const TRACK_SEED: u64 = 43;

/// One frame of a track: the frame, and its pose in the track's frame as the client gave it.
#[derive(Debug, Clone)]
pub struct TrackFrameInput {
    pub frame: FrameInput,
    pub pose: Pose,
}

/// A track query.
#[derive(Debug, Clone)]
pub struct TrackRequest {
    pub frames: Vec<TrackFrameInput>,
    /// The convention of the frames' poses and of the answer's.
    pub convention: PoseConvention,
    pub scale: TrackScale,
    pub prior: Option<Prior>,
    /// How far the frames' poses in the track may be off: it widens the answer's covariance.
    pub tracker: TrackerError,
}

/// What became of one frame.
#[derive(Debug, Clone)]
pub struct TrackFrameOutcome {
    /// Camera-to-map (OpenCV axes), when the track is localised.
    pub camera_to_map: Option<Isometry3<f64>>,
    pub matches: usize,
    pub inliers: usize,
    pub dropped: bool,
    pub localized_alone: bool,
}

/// The outcome of a track query.
#[derive(Debug, Clone)]
pub struct TrackOutcome {
    /// Track to map (world frames: the same in every pose convention).
    pub map_from_track: Option<Similarity3<f64>>,
    pub frames: Vec<TrackFrameOutcome>,
    pub inliers: usize,
    pub reprojection_error: f64,
    pub confidence: f64,
    /// Frame 0's world-to-camera covariance, as a single frame's ([`AbsolutePose::covariance_w2c`]).
    pub covariance_w2c: Option<Matrix6<f64>>,
    pub single_frame: Option<usize>,
    pub times: StageTimes,
}

impl TrackOutcome {
    /// Frame 0's pose covariance in `convention`, row-major 6x6, as Localize answers it; empty without one.
    pub fn covariance(&self, convention: PoseConvention) -> Vec<f64> {
        let (Some(c), Some(pose)) = (&self.covariance_w2c, self.frames.first().and_then(|f| f.camera_to_map)) else {
            return Vec::new();
        };
        let m = crate::pose::pose_covariance(convention, &pose, c);
        (0..6).flat_map(|r| (0..6).map(move |col| m[(r, col)])).collect()
    }
}

impl Service {
    /// Locates a track in `map` (looked up by the caller, once per request).
    pub fn localize_track(&self, map: &Map, request: TrackRequest) -> Result<TrackOutcome, ServiceError> {
        let store = self.store()?;
        let n = request.frames.len();
        if !TRACK_FRAMES.contains(&n) {
            return Err(ServiceError::invalid(
                "frames",
                format!("{n} given: a track holds {} to {} frames", TRACK_FRAMES.start(), TRACK_FRAMES.end()),
            ));
        }
        if let Some(problem) = request.tracker.problem() {
            return Err(ServiceError::invalid("tracker_error", problem));
        }
        // Every frame is checked before any is described: a bad frame costs no CPU.
        let mut size: Option<(u32, u32)> = None;
        for (i, f) in request.frames.iter().enumerate() {
            f.pose
                .validate()
                .map_err(|problem| ServiceError::invalid(format!("frames[{i}].pose"), format!("pose {problem}")))?;
            self.check_source(&f.frame.source)?;
            let cam = Self::camera(&f.frame, &format!("frames[{i}].frame.intrinsics"))?;
            let this = (cam.width, cam.height);
            if let Some(first) = size.filter(|s| *s != this) {
                return Err(ServiceError::invalid(
                    format!("frames[{i}]"),
                    format!(
                        "is {}x{}, frame 0 is {}x{}: a track's frames share one image size",
                        this.0, this.1, first.0, first.1
                    ),
                ));
            }
            size = Some(this);
        }
        let settings = store.localize_settings();
        // The frames are independent until the joint estimate: described and localised side by side (rayon's
        // pool), so a track costs less than its frames one after the other.
        let (convention, scale, prior, tracker) = (request.convention, request.scale, request.prior, request.tracker);
        let described: Vec<Result<(TrackFrame, StageTimes), ServiceError>> = request
            .frames
            .into_par_iter()
            .enumerate()
            .map(|(i, f)| {
                let field = format!("frames[{i}].frame.intrinsics");
                let cam = Self::camera(&f.frame, &field)?;
                let FrameInput { source, distortion, .. } = f.frame;
                let d = self.describe_source(source, Some((&cam, &distortion)))?;
                Self::check_frame_size(&d, &cam, &field)?;
                let mut times = d.times;
                let l = store.localize(map, &d.features, &d.embeddings, &cam, prior.as_ref())?;
                times.add(&StageTimes(vec![("search", l.search_s), ("pnp", l.pnp_s), ("stages", l.stages_s)]));
                let points2d = l.matches.iter().map(|m| d.features.keypoints[m.keypoint]).map(|k| (k.x, k.y)).collect();
                let frame = TrackFrame {
                    camera_to_track: convention.to_opencv_camera_to_world(&f.pose.isometry()),
                    camera: cam,
                    points3d: l.points,
                    points2d,
                    own: l.pose,
                };
                Ok((frame, times))
            })
            .collect();
        let mut times = StageTimes::default();
        let mut frames = Vec::with_capacity(n);
        for r in described {
            let (frame, t) = r?;
            times.add(&t);
            frames.push(frame);
        }
        let estimate = times.time("track", || {
            track_pose(&frames, scale, &settings.ransac, settings.min_inliers, TRACK_SEED, &tracker)
        })?;
        let Some(t) = estimate else {
            return Ok(TrackOutcome {
                map_from_track: None,
                frames: frames
                    .iter()
                    .map(|f| TrackFrameOutcome {
                        camera_to_map: None,
                        matches: f.points3d.len(),
                        inliers: 0,
                        dropped: false,
                        localized_alone: f.own.is_some(),
                    })
                    .collect(),
                inliers: 0,
                reprojection_error: 0.0,
                confidence: 0.0,
                covariance_w2c: None,
                single_frame: None,
                times,
            });
        };
        let covariance_w2c = t.covariance_w2c.map(|c| c * settings.covariance_scale);
        // Frame 0's confidence, on its inliers (on every frame's when it has none).
        let first = t.camera_to_map(&frames[0].camera_to_track);
        let (inliers, points): (Vec<usize>, Vec<[f64; 3]>) = if t.frames[0].inliers.is_empty() {
            let all: Vec<[f64; 3]> =
                t.frames.iter().zip(&frames).flat_map(|(o, f)| o.inliers.iter().map(|&i| f.points3d[i])).collect();
            ((0..all.len()).collect(), all)
        } else {
            (t.frames[0].inliers.clone(), frames[0].points3d.clone())
        };
        let as_frame = AbsolutePose {
            camera_to_world: first,
            inliers,
            reprojection_error: t.reprojection_error,
            covariance_w2c,
            focal: frames[0].camera.fx,
        };
        Ok(TrackOutcome {
            map_from_track: Some(t.map_from_track),
            frames: t
                .frames
                .iter()
                .zip(&frames)
                .map(|(o, f)| TrackFrameOutcome {
                    camera_to_map: Some(t.camera_to_map(&f.camera_to_track)),
                    matches: f.points3d.len(),
                    inliers: o.inliers.len(),
                    dropped: o.dropped,
                    localized_alone: f.own.is_some(),
                })
                .collect(),
            inliers: t.inlier_count(),
            reprojection_error: t.reprojection_error,
            confidence: confidence(&as_frame, &points),
            covariance_w2c,
            single_frame: t.single_frame,
            times,
        })
    }
}
