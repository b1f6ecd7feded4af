//! A frame's way in: its source (an image or a client's keypoints) checked and described, its intrinsics
//! checked. Describe is this alone; MatchPair, Localize and AddKeyframe start here.

use super::core::Service;
use super::error::ServiceError;
use crate::camera::{validate_camera, Camera, Distortion};
use crate::describe::decode::check_limits;
use crate::describe::features::{self, Features, Keypoint};
use crate::describe::pipeline::{Described, StageTimes};
use crate::error::{FeatureError, PoseError};

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
    /// The ring context, `ring_context::SAMPLES` bytes per keypoint (empty: not sent).
    pub context: Vec<u8>,
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

impl Service {
    /// The frame's features, with their embeddings when they were made with them: a ring model's embedding
    /// does not depend on where a keypoint lies, so an image is described in one go (its stages overlapped,
    /// `pipeline::describe_decoded`) and undistortion only drops keypoints and their rows.
    fn features(
        &self,
        source: FrameSource,
        times: &mut StageTimes,
    ) -> Result<(Features, Option<Vec<f32>>), ServiceError> {
        self.check_source(&source)?;
        match source {
            FrameSource::Image(bytes) if self.describer.embedder.needs_context() => {
                let d = self.describer.describe_timed(&bytes, times)?;
                Ok((d.features, Some(d.embeddings)))
            }
            FrameSource::Image(bytes) => Ok((self.describer.extract(&bytes, times)?, None)),
            FrameSource::Keypoints(k) => {
                if let Some(m) = k.model_id.as_deref().filter(|m| !m.is_empty()) {
                    if m != self.model_id() {
                        return Err(ServiceError::ModelMismatch {
                            client: m.to_string(),
                            server: self.model_id().to_string(),
                        });
                    }
                }
                let needs_context = self.describer.embedder.needs_context();
                Ok((
                    times.time("validate", || -> Result<Features, FeatureError> {
                        let f = features::from_precomputed(
                            k.width,
                            k.height,
                            k.keypoints,
                            &k.descriptors,
                            &self.keypoint_limits,
                        )?;
                        if needs_context && k.context.is_empty() {
                            return Err(FeatureError::InvalidContext {
                                reason: format!(
                                    "model {} reads each keypoint's ring context (client contract revision 3, step \
                                 9): send the keypoint set's context",
                                    self.model_id()
                                ),
                            });
                        }
                        if needs_context {
                            features::with_context(f, &k.context)
                        } else {
                            Ok(f)
                        }
                    })?,
                    None,
                ))
            }
        }
    }

    /// Features and embeddings of a frame; with a lens (`camera`, `distortion`), the keypoints are undistorted
    /// first, so that constellations, triangulation and PnP see a pinhole camera's.
    pub(super) fn describe_source(
        &self,
        source: FrameSource,
        lens: Option<(&Camera, &Distortion)>,
    ) -> Result<Description, ServiceError> {
        let mut times = StageTimes::default();
        let (mut features, mut embeddings) = self.features(source, &mut times)?;
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
                // Ring contexts stay as sampled: they describe the image around the keypoint where it is.
                let context = std::mem::take(&mut features.context);
                let mut context = context.into_iter();
                let dim = self.dim();
                let rows = embeddings.take();
                let mut kept_rows = rows.as_ref().map(|_| Vec::new());
                for (i, ((mut k, d), (x, y))) in old.into_iter().zip(descriptors).zip(moved).enumerate() {
                    let c = context.next();
                    if inside(x, y) {
                        (k.x, k.y) = (x, y);
                        features.keypoints.push(k);
                        features.descriptors.push(d);
                        features.context.extend(c);
                        if let (Some(rows), Some(kept)) = (&rows, &mut kept_rows) {
                            kept.extend_from_slice(&rows[i * dim..(i + 1) * dim]);
                        }
                    }
                }
                embeddings = kept_rows;
                Ok(())
            })?;
        }
        let d = match embeddings {
            Some(embeddings) => Described { features, embeddings },
            None => self.describer.embed(features, &mut times)?,
        };
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
    pub(super) fn camera(frame: &FrameInput, field: &str) -> Result<Camera, ServiceError> {
        let cam = frame.camera.ok_or_else(|| ServiceError::invalid(field, "intrinsics are required"))?.with_defaults();
        if cam.focal_unknown() {
            return Err(ServiceError::invalid(
                field,
                "fx and fy are required here (only Localize estimates an unknown focal length)",
            ));
        }
        Self::checked(cam, field)
    }

    pub(super) fn checked(cam: Camera, field: &str) -> Result<Camera, ServiceError> {
        validate_camera(&cam).map_err(|e| Self::intrinsics_error(e, field))?;
        Ok(cam)
    }

    pub(super) fn intrinsics_error(e: PoseError, field: &str) -> ServiceError {
        match e {
            PoseError::Intrinsics { reason } => ServiceError::invalid(field, reason),
            other => ServiceError::Pose(other),
        }
    }

    /// A Localize query's intrinsics: as [`Service::camera`], except that the focal length may be unknown
    /// (`fx`, `fy` absent, or no intrinsics at all: then the size is the frame's and the principal point its
    /// centre). An unknown focal length with a distortion model is refused: undistorting needs the focal length.
    pub(super) fn query_camera(frame: &FrameInput, size: (u32, u32), field: &str) -> Result<Camera, ServiceError> {
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
    pub(super) fn check_source(&self, source: &FrameSource) -> Result<(), ServiceError> {
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

    pub(super) fn check_frame_size(d: &Description, cam: &Camera, field: &str) -> Result<(), ServiceError> {
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
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::describe::embedding::{Embedder, EmbedderSettings};
    use crate::describe::pipeline::Describer;

    /// A ring model's image described through a lens: the keypoints whose undistorted position leaves the image
    /// are dropped with their embedding rows, and every other keypoint keeps, in order, the embedding the
    /// lens-free description gave it (its descriptor, context and response unchanged).
    #[test]
    fn a_lens_drops_keypoints_with_their_embedding_rows() {
        let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
        assert!(embedder.needs_context());
        let describer =
            Describer { extractor: embedder.extraction(), limits: Default::default(), embedder: embedder.clone() };
        let service = Service::new(describer, Default::default(), Default::default()).unwrap();
        let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg")).unwrap();
        let plain = service.describe(FrameSource::Image(bytes.clone())).unwrap();
        let cam = Camera { fx: 400.0, fy: 400.0, cx: 320.0, cy: 240.0, width: 640, height: 480 };
        let barrel = Distortion::RadialTangential(vec![-0.3, 0.0, 0.0, 0.0]);
        let lensed = service.describe_source(FrameSource::Image(bytes), Some((&cam, &barrel))).unwrap();
        let (a, b, dim) = (&lensed.features, &plain.features, embedder.dim());
        assert!(a.len() + 50 < b.len() && a.len() > 500, "{} of {} keypoints kept", a.len(), b.len());
        assert_eq!((lensed.embeddings.len(), a.context.len()), (a.len() * dim, a.len()));
        let mut j = 0;
        for i in 0..a.len() {
            let same = |j: usize| {
                b.descriptors[j] == a.descriptors[i]
                    && b.context[j] == a.context[i]
                    && b.keypoints[j].response == a.keypoints[i].response
            };
            while !same(j) {
                j += 1;
            }
            assert_eq!(lensed.embeddings[i * dim..(i + 1) * dim], plain.embeddings[j * dim..(j + 1) * dim], "row {i}");
            j += 1;
        }
    }
}
