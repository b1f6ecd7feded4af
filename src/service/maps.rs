//! The map operations: create, list, delete, import (on no map yet), and those on a map the caller looked up
//! once for the request ([`super::Service::map`]): its summary and contents, keyframe writes and removals,
//! merges into it, export.

use opencv::prelude::MatTraitConst;

use super::core::Service;
use super::error::ServiceError;
use super::frame::FrameInput;
use crate::camera::{Pose, PoseConvention, Similarity};
use crate::describe::decode::{decode_depth_png, TUM_DEPTH_SCALE};
use crate::describe::pipeline::StageTimes;
use crate::error::MapError;
use crate::map::builder::{Depth, ExternalObservation, KeyframeInput};
use crate::map::store::{KeyframeAdded, MapContents};
use crate::map::store::{Map, MapSummary};

/// Landmarks a contents request may ask for at most.
pub const MAX_CONTENTS_LANDMARKS: usize = 200_000;
/// Landmarks a contents request gets when it does not say.
pub const DEFAULT_CONTENTS_LANDMARKS: usize = 20_000;

/// A posed keyframe to add to a map.
#[derive(Debug, Clone)]
pub struct KeyframeRequest {
    pub id: u64,
    pub frame: FrameInput,
    /// The keyframe's pose, as the client gave it (`convention`).
    pub pose: Pose,
    pub convention: PoseConvention,
    /// 16-bit PNG aligned with the image.
    pub depth_png: Option<Vec<u8>>,
    /// Metres per depth unit; `None` for TUM's (1 / 5000, [`TUM_DEPTH_SCALE`]).
    pub depth_scale: Option<f64>,
    /// Landmarks given by an external SfM (empty: none; then depth or triangulation).
    pub external_landmarks: Vec<ExternalObservation>,
}

/// What a merge did.
#[derive(Debug, Clone)]
pub struct MergeOutcome {
    /// The target after the merge.
    pub target: MapSummary,
    /// Source coordinates to target coordinates (given, or estimated).
    pub transform: Similarity,
    pub estimated: bool,
    pub source_keyframes: usize,
    /// Source keyframes localised in the target, and (when estimated) those the transform agrees with.
    pub localised: usize,
    pub inliers: usize,
    /// Added to every source keyframe id (0 when none collided with the target's).
    pub keyframe_id_offset: u64,
    /// Source landmarks fused with a target landmark, and those added as new.
    pub landmarks_fused: usize,
    pub landmarks_added: usize,
}

/// What ListMaps answers.
#[derive(Debug, Clone, Default)]
pub struct MapListing {
    /// The maps: the loaded ones, or with maps loaded on demand every stored one.
    pub maps: Vec<MapSummary>,
    /// Maps that could not be loaded: (id, why).
    pub held_back: Vec<(String, String)>,
}

impl Service {
    /// Adds a posed keyframe to `map`; returns once the write is durable.
    pub fn add_keyframe(
        &self,
        map: &Map,
        request: KeyframeRequest,
    ) -> Result<(KeyframeAdded, StageTimes), ServiceError> {
        let store = self.store()?;
        request.pose.validate().map_err(|problem| ServiceError::invalid("pose", format!("pose {problem}")))?;
        let depth_scale = request.depth_scale.unwrap_or(TUM_DEPTH_SCALE);
        if !(depth_scale.is_finite() && depth_scale > 0.0) {
            return Err(ServiceError::invalid("depth_scale", format!("{depth_scale} must be positive")));
        }
        self.check_source(&request.frame.source)?;
        let cam = Self::camera(&request.frame, "frame.intrinsics")?;
        let depth = match &request.depth_png {
            Some(bytes) => Some(
                decode_depth_png(bytes, &self.describer.limits)
                    .map_err(|e| ServiceError::invalid("depth", e.to_string()))?,
            ),
            None => None,
        };
        let distortion = &request.frame.distortion;
        if depth.is_some() && !distortion.is_none() {
            return Err(ServiceError::invalid(
                "depth",
                "depth with a distortion model is not supported (the depth image is aligned with the distorted \
                 image): undistort the image and depth on the client, or send no depth",
            ));
        }
        let mut external = request.external_landmarks;
        if !distortion.is_none() && !external.is_empty() {
            let pixels: Vec<(f32, f32)> = external.iter().map(|o| (o.x as f32, o.y as f32)).collect();
            let moved =
                distortion.undistort(&cam, &pixels).map_err(|e| Self::intrinsics_error(e, "frame.intrinsics"))?;
            for (o, (x, y)) in external.iter_mut().zip(moved) {
                (o.x, o.y) = (x.into(), y.into());
            }
        }
        let d = self.describe_source(request.frame.source, Some((&cam, distortion)))?;
        Self::check_frame_size(&d, &cam, "frame.intrinsics")?;
        if let Some(m) = &depth {
            if m.cols() as u32 != cam.width || m.rows() as u32 != cam.height {
                return Err(ServiceError::invalid(
                    "depth",
                    format!("depth is {}x{}, the frame is {}x{}", m.cols(), m.rows(), cam.width, cam.height),
                ));
            }
        }
        let mut times = d.times;
        let input = KeyframeInput {
            id: request.id,
            // Checked as given (a non-unit quaternion is refused, not renormalised), then converted.
            pose: request.convention.to_opencv_camera_to_world(&request.pose.isometry()),
            camera: cam,
            features: &d.features,
            embeddings: &d.embeddings,
            depth: depth.as_ref().map(|image| Depth { image, scale: depth_scale }),
            external: (!external.is_empty()).then_some(&external[..]),
        };
        let added = times.time("write", || store.add_keyframe(map, &input))?;
        Ok((added, times))
    }

    /// Merges map `source` into `target` (`map::merge`); `transform` takes source coordinates to the
    /// target's (estimated when absent). Returns once the merge is durable.
    pub fn merge_maps(
        &self,
        target: &Map,
        source: &str,
        transform: Option<Similarity>,
    ) -> Result<MergeOutcome, ServiceError> {
        let transform =
            transform.map(|t| t.checked().map_err(|reason| ServiceError::invalid("transform", reason))).transpose()?;
        let (plan, target) = self.store()?.merge(target, source, transform)?;
        Ok(MergeOutcome {
            target,
            transform: Similarity::from_nalgebra(&plan.transform),
            estimated: plan.estimated,
            source_keyframes: plan.source_keyframes,
            localised: plan.localised,
            inliers: plan.inliers,
            keyframe_id_offset: plan.keyframe_id_offset,
            landmarks_fused: plan.landmarks_fused,
            landmarks_added: plan.landmarks_added,
        })
    }

    pub fn create_map(&self, id: &str) -> Result<MapSummary, ServiceError> {
        Ok(self.store()?.create(id)?)
    }

    /// `map`'s keyframes and (at most `max_landmarks`) landmarks, for viewers.
    pub fn map_contents(&self, map: &Map, max_landmarks: usize) -> Result<MapContents, ServiceError> {
        if max_landmarks == 0 || max_landmarks > MAX_CONTENTS_LANDMARKS {
            return Err(ServiceError::invalid(
                "max_landmarks",
                format!("{max_landmarks} is outside 1..={MAX_CONTENTS_LANDMARKS}"),
            ));
        }
        Ok(self.store()?.contents(map, max_landmarks))
    }

    /// The maps (every stored one when maps are loaded on demand), and those held back with the reason.
    pub fn list_maps(&self) -> Result<MapListing, ServiceError> {
        let store = self.store()?;
        Ok(MapListing { maps: store.list()?, held_back: store.held_back() })
    }

    pub fn delete_map(&self, id: &str) -> Result<(), ServiceError> {
        Ok(self.store()?.delete(id)?)
    }

    /// Removes a keyframe of `map`; returns the map's summary after the removal.
    pub fn remove_keyframe(&self, map: &Map, keyframe: u64) -> Result<MapSummary, ServiceError> {
        self.store()?.remove_keyframe(map, keyframe)?;
        Ok(map.summary())
    }

    /// `map` as one versioned, checksummed file.
    pub fn export_map(&self, map: &Map) -> Result<Vec<u8>, ServiceError> {
        Ok(self.store()?.export(map)?)
    }

    /// Imports a file made by [`Service::export_map`] under a new id. Importing the same content again into
    /// the map it made succeeds and returns that map (a retry after a lost answer); other content under a
    /// taken id is ALREADY_EXISTS.
    pub fn import_map(&self, id: &str, bytes: &[u8]) -> Result<MapSummary, ServiceError> {
        match self.store()?.import(id, bytes) {
            Err(MapError::Corrupt { reason, .. }) => Err(ServiceError::invalid("map file", reason)),
            r => Ok(r?),
        }
    }
}
