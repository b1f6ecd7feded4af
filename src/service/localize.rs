//! Localize: a frame described and localised against the map it was given ([`crate::map::localize`]), and
//! what the transports make of the outcome (the covariance in a convention, the picture's points).

use super::core::Service;
use super::error::ServiceError;
use super::frame::{FrameInput, FrameSource};
use crate::camera::{Camera, Distortion, PoseConvention};
use crate::describe::pipeline::StageTimes;
use crate::map::localize::{LandmarkMatch, Prior};
use crate::map::store::Map;
use crate::pose::AbsolutePose;

/// The outcome of a relocalisation.
#[derive(Debug, Clone)]
pub struct LocalizeOutcome {
    pub pose: Option<AbsolutePose>,
    pub matches: Vec<LandmarkMatch>,
    pub confidence: f64,
    pub times: StageTimes,
    /// The query keypoint of each match (pixels) and its landmark's position, in the order of `matches`.
    pub pixels: Vec<(f32, f32)>,
    pub points: Vec<[f64; 3]>,
    /// The query's camera; with an estimated focal length, the estimate (when localised).
    pub camera: Camera,
    /// Whether the query came without a focal length (the pose's `focal` is then the estimate).
    pub focal_estimated: bool,
    /// The query's lens: `pixels` are undistorted, pictures draw them where the image has them.
    pub distortion: Distortion,
}

impl LocalizeOutcome {
    /// The pose's covariance in `convention`, row-major 6x6 ([`crate::pose::pose_covariance`]); empty without
    /// a pose or when the refinement gave none.
    pub fn covariance(&self, convention: PoseConvention) -> Vec<f64> {
        let Some(p) = &self.pose else { return Vec::new() };
        let Some(c) = &p.covariance_w2c else { return Vec::new() };
        let m = crate::pose::pose_covariance(convention, &p.camera_to_world, c);
        // nalgebra is column-major; the covariance is symmetric, but write rows explicitly.
        (0..6).flat_map(|r| (0..6).map(move |col| m[(r, col)])).collect()
    }

    /// Each match as drawn over the query image: its pixel, whether it is an inlier, and its landmark
    /// reprojected at the pose (both through the query's lens, where the image has them).
    pub fn drawn_points(&self) -> Vec<crate::render::LocalizedPoint> {
        let inliers: std::collections::HashSet<usize> =
            self.pose.as_ref().map(|p| p.inliers.iter().copied().collect()).unwrap_or_default();
        let world_to_camera = self.pose.as_ref().map(|p| p.camera_to_world.inverse());
        let through_lens = |p: (f64, f64)| -> (f64, f64) {
            self.distortion.distort(&self.camera, &[p]).ok().and_then(|v| v.first().copied()).unwrap_or(p)
        };
        (0..self.matches.len())
            .map(|i| {
                let [x, y, z] = self.points[i];
                let reprojected = world_to_camera
                    .as_ref()
                    .and_then(|t| self.camera.project(&(t * nalgebra::Point3::new(x, y, z))))
                    .map(through_lens);
                let (u, v) = through_lens((self.pixels[i].0.into(), self.pixels[i].1.into()));
                crate::render::LocalizedPoint { pixel: (u as f32, v as f32), inlier: inliers.contains(&i), reprojected }
            })
            .collect()
    }
}

impl Service {
    /// Camera-to-world pose of a frame against `map` (looked up by the caller, once per request).
    pub fn localize(
        &self,
        map: &Map,
        frame: FrameInput,
        prior: Option<Prior>,
    ) -> Result<LocalizeOutcome, ServiceError> {
        let store = self.store()?;
        self.check_source(&frame.source)?;
        let size = match &frame.source {
            FrameSource::Keypoints(k) => (k.width, k.height),
            FrameSource::Image(bytes) => {
                crate::describe::decode::read_header(bytes).map(|h| (h.width, h.height)).unwrap_or((0, 0))
            }
        };
        let cam = Self::query_camera(&frame, size, "frame.intrinsics")?;
        let d = self.describe_source(frame.source, Some((&cam, &frame.distortion)))?;
        Self::check_frame_size(&d, &cam, "frame.intrinsics")?;
        let mut times = d.times;
        let l = store.localize(map, &d.features, &d.embeddings, &cam, prior.as_ref())?;
        times.0.push(("search", l.search_s));
        times.0.push(("pnp", l.pnp_s));
        times.0.push(("stages", l.stages_s));
        let pixels = l.matches.iter().map(|m| d.features.keypoints[m.keypoint]).map(|k| (k.x, k.y)).collect();
        let focal_estimated = cam.focal_unknown();
        let cam = match &l.pose {
            Some(p) if focal_estimated => cam.with_focal(p.focal),
            _ => cam,
        };
        Ok(LocalizeOutcome {
            focal_estimated,
            distortion: frame.distortion,
            pose: l.pose,
            matches: l.matches,
            confidence: l.confidence,
            times,
            pixels,
            points: l.points,
            camera: cam,
        })
    }
}
