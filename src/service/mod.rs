//! The operations the service offers, in domain types: one function per RPC. A gRPC method and its HTTP twin
//! both validate their wire format, build these inputs, call the same function here and map the one
//! [`ServiceError`] through [`ServiceError::kind`]. Nothing here knows about tonic, axum or HTTP.
//!
//! Every function is synchronous and CPU-bound (OpenCV, ONNX Runtime, index search, fsync): transports call
//! them on the bounded [`crate::cpu_pool::CpuPool`], never on async worker threads.
//!
//! Maps load after the listeners are up (health says NOT_SERVING meanwhile), so the store is attached once it
//! is ready; map operations before that answer [`ServiceError::NotReady`].

mod error;

use std::sync::{Arc, OnceLock};

use opencv::prelude::MatTraitConst;
use serde::Serialize;

use crate::camera::validate_camera;
use crate::camera::Camera;
use crate::camera::Pose;
pub use crate::camera::{Distortion, DistortionModel, PoseConvention, Similarity};
use crate::decode::{check_limits, decode_depth_png, ImageLimitSettings};
use crate::error::{MapError, PoseError};
use crate::features::{self, Features, Keypoint, KeypointLimitSettings};
use crate::map::builder::{Depth, KeyframeInput};
use crate::map::localize::LandmarkMatch;
use crate::map::store::{KeyframeAdded, MapContents, MapStore, ModelInfo, StoreSettings};
// What the transports need of the map layer, so that they import only this module.
pub use crate::map::builder::ExternalObservation;
pub use crate::map::localize::Prior;
pub use crate::map::store::{Map, MapSummary};
use crate::matching::{match_scone, Match, RatioTest, SconeFrame, SconeMatcher, DEFAULT_RATIO, SAME_CORNER_PX};
use crate::pipeline::{Describer, StageTimes};
use crate::pose::{relative_pose, AbsolutePose, RansacSettings, RelativePose};
pub use error::{ErrorKind, ServiceError};

/// Keypoints with FREAK descriptors computed by a client (see the client contract in the proto).
#[derive(Debug, Clone, Default)]
pub struct KeypointsInput {
    pub width: u32,
    pub height: u32,
    pub keypoints: Vec<Keypoint>,
    /// 64 bytes per keypoint.
    pub descriptors: Vec<u8>,
    /// The model the client targets, if it says.
    pub model_id: Option<String>,
}

/// Where a frame's features come from.
#[derive(Debug, Clone)]
pub enum FrameSource {
    /// PNG or JPEG bytes.
    Image(Vec<u8>),
    Keypoints(KeypointsInput),
}

/// A frame with its intrinsics (required to estimate a pose, except by Localize, which estimates an unknown
/// focal length) and its lens distortion.
#[derive(Debug, Clone)]
pub struct FrameInput {
    pub source: FrameSource,
    /// As the client gave it: 0 for what it left out ([`Camera::with_defaults`] fills the defaults).
    pub camera: Option<Camera>,
    /// The keypoints are undistorted with it before constellations, triangulation and PnP.
    pub distortion: Distortion,
}

/// Landmarks a contents request may ask for at most.
pub const MAX_CONTENTS_LANDMARKS: usize = 200_000;
/// Landmarks a contents request gets when it does not say.
pub const DEFAULT_CONTENTS_LANDMARKS: usize = 20_000;

/// Keypoints and embeddings of one frame.
#[derive(Debug, Clone)]
pub struct Description {
    pub features: Features,
    /// `[N, dim]`, row-major, unit norm.
    pub embeddings: Vec<f32>,
    pub dim: usize,
    pub model_id: String,
    pub times: StageTimes,
}

/// Pair matching settings a client may choose. The ratio test's same-corner radius is the project's
/// default ([`crate::matching::SAME_CORNER_PX`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairOptions {
    pub ratio: f32,
    pub mutual: bool,
    /// How the matches are picked (`matching::SconeMatcher`).
    pub matcher: SconeMatcher,
}

impl Default for PairOptions {
    fn default() -> Self {
        Self { ratio: DEFAULT_RATIO, mutual: false, matcher: SconeMatcher::default() }
    }
}

/// Matches between two frames and their relative pose.
#[derive(Debug, Clone)]
pub struct PairOutcome {
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
    /// Metres per depth unit.
    pub depth_scale: f64,
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

/// Loaded maps, and the ids of maps held back with the reason.
pub type MapListing = (Vec<MapSummary>, Vec<(String, String)>);

/// Counts of what the service holds, for metrics.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Holdings {
    pub maps: usize,
    pub held_back: usize,
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    /// Estimated memory of the loaded maps.
    pub loaded_bytes: u64,
    /// The map cache's counts since start, by event (hit, miss, load, eviction, check, change, check_error,
    /// log_cut).
    pub cache_events: Vec<(&'static str, u64)>,
    pub cache_load_seconds: f64,
    /// Calls to the storage service (object storage) since start.
    pub storage: Vec<crate::map::storage::backend::OperationStats>,
}

/// The service's core: the description path, the map store and the limits on client input.
pub struct Service {
    describer: Describer,
    keypoint_limits: KeypointLimitSettings,
    ransac: RansacSettings,
    store: OnceLock<Arc<MapStore>>,
}

impl Service {
    /// `ransac`: MatchPair's essential-matrix search (`Settings::relative_pose`).
    pub fn new(describer: Describer, keypoint_limits: KeypointLimitSettings, ransac: RansacSettings) -> Self {
        Self { describer, keypoint_limits, ransac, store: OnceLock::new() }
    }

    /// Makes maps available (once, after they loaded).
    pub fn attach_store(&self, store: Arc<MapStore>) {
        let _ = self.store.set(store);
    }

    /// Opens the maps `config` describes, for the model this service embeds with, and makes them available.
    /// Blocks: in eager mode every map is loaded here.
    pub fn open_store(&self, config: StoreSettings) -> Result<(), MapError> {
        let e = &self.describer.embedder;
        let info = ModelInfo { model_id: e.model_id().to_string(), k: e.k(), dim: e.dim() };
        self.attach_store(Arc::new(MapStore::open(config, info)?));
        Ok(())
    }

    /// With maps loaded on demand: whether `map` must be loaded before its request runs (`Some(true)`) or is
    /// in memory (`Some(false)`); `None` when every map is loaded at start (or the maps are not open yet).
    pub fn map_to_prepare(&self, map: &str) -> Option<bool> {
        let store = self.store.get()?;
        store.is_lazy().then(|| !store.is_loaded(map))
    }

    /// Loads `map` if it is not in memory and checks that it is fresh; holding the result keeps the map from
    /// being evicted until the request is done. Blocks (a load, a manifest round trip).
    pub fn prepare(&self, map: &str) -> Result<Arc<Map>, ServiceError> {
        Ok(self.store()?.prepare(map)?)
    }

    pub fn store(&self) -> Result<&Arc<MapStore>, ServiceError> {
        self.store.get().ok_or(ServiceError::NotReady)
    }

    pub fn is_ready(&self) -> bool {
        self.store.get().is_some()
    }

    pub fn model_id(&self) -> &str {
        self.describer.embedder.model_id()
    }

    pub fn dim(&self) -> usize {
        self.describer.embedder.dim()
    }

    pub fn image_limits(&self) -> &ImageLimitSettings {
        &self.describer.limits
    }

    fn features(&self, source: FrameSource, times: &mut StageTimes) -> Result<Features, ServiceError> {
        self.check_source(&source)?;
        match source {
            FrameSource::Image(bytes) => Ok(self.describer.extract(&bytes, times)?),
            FrameSource::Keypoints(k) => {
                if let Some(m) = k.model_id.as_deref().filter(|m| !m.is_empty()) {
                    if m != self.model_id() {
                        return Err(ServiceError::ModelMismatch {
                            client: m.to_string(),
                            server: self.model_id().to_string(),
                        });
                    }
                }
                Ok(times.time("validate", || {
                    features::from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &self.keypoint_limits)
                })?)
            }
        }
    }

    /// Features and embeddings of a frame; with a lens (`camera`, `distortion`), the keypoints are undistorted
    /// first, so that constellations, triangulation and PnP see a pinhole camera's.
    fn describe_source(
        &self,
        source: FrameSource,
        lens: Option<(&Camera, &Distortion)>,
    ) -> Result<Description, ServiceError> {
        let mut times = StageTimes::default();
        let mut features = self.features(source, &mut times)?;
        if let Some((cam, distortion)) = lens.filter(|(_, d)| !d.is_none()) {
            times.time("undistort", || -> Result<(), ServiceError> {
                let moved = distortion.undistort(cam, &features.points())?;
                // A keypoint whose undistorted position leaves the image (the far corners of a wide lens, or
                // a point the model does not invert) is dropped: stored keyframes keep the keypoint contract
                // (inside the image), so re-embedding and client keypoint checks hold for them.
                let inside = |x: f32, y: f32| {
                    x.is_finite()
                        && y.is_finite()
                        && (0.0..=(cam.width - 1) as f32).contains(&x)
                        && (0.0..=(cam.height - 1) as f32).contains(&y)
                };
                let old = std::mem::take(&mut features.keypoints);
                let descriptors = std::mem::take(&mut features.descriptors);
                for ((mut k, d), (x, y)) in old.into_iter().zip(descriptors).zip(moved) {
                    if inside(x, y) {
                        (k.x, k.y) = (x, y);
                        features.keypoints.push(k);
                        features.descriptors.push(d);
                    }
                }
                Ok(())
            })?;
        }
        let d = self.describer.embed(features, &mut times)?;
        Ok(Description {
            features: d.features,
            embeddings: d.embeddings,
            dim: self.dim(),
            model_id: self.model_id().to_string(),
            times,
        })
    }

    /// Keypoints, FREAK descriptors and SConE embeddings of a frame.
    pub fn describe(&self, source: FrameSource) -> Result<Description, ServiceError> {
        self.describe_source(source, None)
    }

    /// The frame's intrinsics with their defaults, checked. Called after [`Service::check_source`], so a
    /// frame whose image cannot be read is reported as such, not as intrinsics without a size.
    fn camera(frame: &FrameInput, field: &str) -> Result<Camera, ServiceError> {
        let cam = frame.camera.ok_or_else(|| ServiceError::invalid(field, "intrinsics are required"))?.with_defaults();
        if cam.focal_unknown() {
            return Err(ServiceError::invalid(
                field,
                "fx and fy are required here (only Localize estimates an unknown focal length)",
            ));
        }
        Self::checked(cam, field)
    }

    fn checked(cam: Camera, field: &str) -> Result<Camera, ServiceError> {
        validate_camera(&cam).map_err(|e| Self::intrinsics_error(e, field))?;
        Ok(cam)
    }

    fn intrinsics_error(e: PoseError, field: &str) -> ServiceError {
        match e {
            PoseError::Intrinsics { reason } => ServiceError::invalid(field, reason),
            other => ServiceError::Pose(other),
        }
    }

    /// A Localize query's intrinsics: as [`Service::camera`], except that the focal length may be unknown
    /// (`fx`, `fy` absent, or no intrinsics at all: then the size is the frame's and the principal point its
    /// centre). An unknown focal length with a distortion model is refused: undistorting needs the focal length.
    fn query_camera(frame: &FrameInput, size: (u32, u32), field: &str) -> Result<Camera, ServiceError> {
        let given =
            frame.camera.unwrap_or(Camera { fx: 0.0, fy: 0.0, cx: 0.0, cy: 0.0, width: size.0, height: size.1 });
        let cam = given.with_defaults();
        if !cam.focal_unknown() {
            return Self::checked(cam, field);
        }
        if !frame.distortion.is_none() {
            return Err(ServiceError::invalid(field, "a distortion model needs fx and fy (the focal length)"));
        }
        Self::checked(cam.with_focal(1.0), field).map(|_| cam)
    }

    /// Cheap checks of a frame's source before anything else looks at the frame: an image's size and header
    /// (format, dimensions; no decoding), a keypoint set's image size against the same image limits.
    fn check_source(&self, source: &FrameSource) -> Result<(), ServiceError> {
        let limits = &self.describer.limits;
        match source {
            FrameSource::Image(bytes) => {
                check_limits(bytes, limits)?;
            }
            FrameSource::Keypoints(k) => {
                limits.check_dimensions(
                    k.width,
                    k.height,
                    ["keypoint set width", "keypoint set height", "keypoint set pixels"],
                )?;
            }
        }
        Ok(())
    }

    fn check_frame_size(d: &Description, cam: &Camera, field: &str) -> Result<(), ServiceError> {
        if d.features.width != cam.width || d.features.height != cam.height {
            return Err(ServiceError::invalid(
                field,
                format!(
                    "intrinsics are for {}x{} but the frame is {}x{}",
                    cam.width, cam.height, d.features.width, d.features.height
                ),
            ));
        }
        Ok(())
    }

    /// SConE matches between two frames (ratio test, optional mutual check) and their relative pose.
    pub fn match_pair(&self, a: FrameInput, b: FrameInput, options: PairOptions) -> Result<PairOutcome, ServiceError> {
        if !(options.ratio > 0.0 && options.ratio <= 1.0) {
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
            match_scone(options.matcher, &f1, &f2, &test)
        })?;
        let p1: Vec<(f32, f32)> = matches.iter().map(|m| d1.features.keypoints[m.query]).map(|k| (k.x, k.y)).collect();
        let p2: Vec<(f32, f32)> = matches.iter().map(|m| d2.features.keypoints[m.train]).map(|k| (k.x, k.y)).collect();
        let pose = times.time("pose", || relative_pose(&p1, &p2, &cam1, &cam2, &self.ransac))?;
        Ok(PairOutcome { matches, pose, times, points1, points2 })
    }

    /// Camera-to-world pose of a frame against a map.
    pub fn localize(
        &self,
        map: &str,
        frame: FrameInput,
        prior: Option<Prior>,
    ) -> Result<LocalizeOutcome, ServiceError> {
        let store = self.store()?;
        // Looked up once: an unknown map is refused before any decoding, and the search runs on this copy.
        let held = store.get(map)?;
        self.check_source(&frame.source)?;
        let size = match &frame.source {
            FrameSource::Keypoints(k) => (k.width, k.height),
            FrameSource::Image(bytes) => {
                crate::decode::read_header(bytes).map(|h| (h.width, h.height)).unwrap_or((0, 0))
            }
        };
        let cam = Self::query_camera(&frame, size, "frame.intrinsics")?;
        let d = self.describe_source(frame.source, Some((&cam, &frame.distortion)))?;
        Self::check_frame_size(&d, &cam, "frame.intrinsics")?;
        let mut times = d.times;
        let l = store.localize_map(&held, &d.features, &d.embeddings, &cam, prior.as_ref())?;
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

    /// Adds a posed keyframe; returns once the write is durable.
    pub fn add_keyframe(
        &self,
        map: &str,
        request: KeyframeRequest,
    ) -> Result<(KeyframeAdded, StageTimes), ServiceError> {
        let store = self.store()?;
        store.get(map)?;
        request.pose.validate().map_err(|reason| ServiceError::invalid("pose", reason))?;
        if !(request.depth_scale.is_finite() && request.depth_scale > 0.0) {
            return Err(ServiceError::invalid("depth_scale", format!("{} must be positive", request.depth_scale)));
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
            depth: depth.as_ref().map(|image| Depth { image, scale: request.depth_scale }),
            external: (!external.is_empty()).then_some(&external[..]),
        };
        let added = times.time("write", || store.add_keyframe(map, &input))?;
        Ok((added, times))
    }

    /// Merges map `source` into map `target` (`map::merge`); `transform` takes source coordinates to the
    /// target's (estimated when absent). Returns once the merge is durable.
    pub fn merge_maps(
        &self,
        target: &str,
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

    /// A map's keyframes and (at most `max_landmarks`) landmarks, for viewers.
    pub fn map_contents(&self, id: &str, max_landmarks: usize) -> Result<MapContents, ServiceError> {
        if max_landmarks == 0 || max_landmarks > MAX_CONTENTS_LANDMARKS {
            return Err(ServiceError::invalid(
                "max_landmarks",
                format!("{max_landmarks} is outside 1..={MAX_CONTENTS_LANDMARKS}"),
            ));
        }
        Ok(self.store()?.contents(id, max_landmarks)?)
    }

    pub fn get_map(&self, id: &str) -> Result<MapSummary, ServiceError> {
        Ok(self.store()?.summary(id)?)
    }

    /// The maps (every stored one in lazy mode), and those held back with the reason.
    pub fn list_maps(&self) -> Result<MapListing, ServiceError> {
        let store = self.store()?;
        Ok((store.list()?, store.held_back()))
    }

    pub fn delete_map(&self, id: &str) -> Result<(), ServiceError> {
        Ok(self.store()?.delete(id)?)
    }

    pub fn remove_keyframe(&self, id: &str, keyframe: u64) -> Result<MapSummary, ServiceError> {
        let store = self.store()?;
        store.remove_keyframe(id, keyframe)?;
        Ok(store.summary(id)?)
    }

    /// The map as one versioned, checksummed file.
    pub fn export_map(&self, id: &str) -> Result<Vec<u8>, ServiceError> {
        Ok(self.store()?.export(id)?)
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

    /// Counts for metrics (cheap: summaries only).
    pub fn holdings(&self) -> Holdings {
        let Some(store) = self.store.get() else { return Holdings::default() };
        let maps = store.loaded();
        let c = store.cache_stats();
        let n = |a: &std::sync::atomic::AtomicU64| a.load(std::sync::atomic::Ordering::Relaxed);
        Holdings {
            maps: maps.len(),
            held_back: store.held_back().len(),
            keyframes: maps.iter().map(|m| m.keyframes).sum(),
            landmarks: maps.iter().map(|m| m.landmarks).sum(),
            observations: maps.iter().map(|m| m.live_observations).sum(),
            loaded_bytes: store.loaded_bytes(),
            cache_events: vec![
                ("hit", n(&c.hits)),
                ("miss", n(&c.misses)),
                ("load", n(&c.loads)),
                ("eviction", n(&c.evictions)),
                ("check", n(&c.checks)),
                ("change", n(&c.changed)),
                ("check_error", n(&c.check_errors)),
                ("log_cut", n(&c.logs_cut)),
            ],
            cache_load_seconds: n(&c.load_nanos) as f64 * 1e-9,
            storage: store.operation_stats(),
        }
    }

    /// Snapshots every map and dumps its index; returns the maps that could not be (their acknowledged writes
    /// are in their logs), with the error.
    pub fn flush(&self) -> Vec<(String, MapError)> {
        self.store.get().map(|s| s.flush()).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pair_outcome_flags_each_match_once_and_none_without_a_pose() {
        let m = |i| Match { query: i, train: i, distance: 0.1 };
        let mut o = PairOutcome {
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
