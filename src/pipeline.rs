//! The path every image and every client keypoint set takes: decode -> FAST + FREAK -> context (the ring
//! context sampled from the image, or constellations built from the keypoints) -> SConE embeddings. The service, the commands and the evaluation call this; nothing else strings the stages
//! together. Callers that report stage times pass a [`StageTimes`] for the describer to fill.

use std::sync::Arc;
use std::time::Instant;

use crate::decode::{decode_grey, GreyImage, ImageLimitSettings};
use crate::embedding::Embedder;
use crate::error::{EmbeddingError, FeatureError};
use crate::features::{self, ExtractorSettings, Features};

/// Wall time of each stage of a request, seconds, in order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StageTimes(pub Vec<(&'static str, f64)>);

impl StageTimes {
    /// Runs `f` and records its wall time as `stage`.
    pub fn time<R>(&mut self, stage: &'static str, f: impl FnOnce() -> R) -> R {
        let t = Instant::now();
        let r = f();
        self.0.push((stage, t.elapsed().as_secs_f64()));
        r
    }

    /// Adds `other`'s times, summing stages both have (the two frames of a pair).
    pub fn add(&mut self, other: &StageTimes) {
        for (s, t) in &other.0 {
            match self.0.iter_mut().find(|(n, _)| n == s) {
                Some(e) => e.1 += t,
                None => self.0.push((s, *t)),
            }
        }
    }
}

/// SConE embeddings of a feature set (`[N, embedder.dim()]`, row-major): its context (constellations built
/// here, or the ring contexts it carries), then the model.
pub fn embed(embedder: &Embedder, features: &Features) -> Result<Vec<f32>, EmbeddingError> {
    embedder.embed(features)
}

/// FAST + FREAK features of a decoded image, with their ring contexts when `embedder` reads them: what every
/// caller that embeds an image's features extracts ([`Describer::extract`] times the two steps).
pub fn extract_for(
    image: &GreyImage,
    extractor: &ExtractorSettings,
    embedder: &Embedder,
) -> Result<Features, FeatureError> {
    let mut features = features::extract(image, extractor)?;
    if embedder.needs_context() {
        features.sample_context(image)?;
    }
    Ok(features)
}

/// Errors of the whole path.
#[derive(Debug, thiserror::Error)]
pub enum DescribeError {
    #[error(transparent)]
    Feature(#[from] FeatureError),
    #[error(transparent)]
    Embedding(#[from] EmbeddingError),
}

/// Features of an image with their SConE embeddings (`[N, dim]`, row-major).
#[derive(Debug, Clone)]
pub struct Described {
    pub features: Features,
    pub embeddings: Vec<f32>,
}

/// Extraction settings, limits and the model, shared by all callers.
#[derive(Debug, Clone)]
pub struct Describer {
    pub extractor: ExtractorSettings,
    pub limits: ImageLimitSettings,
    pub embedder: Arc<Embedder>,
}

impl Describer {
    /// Encoded image -> features and embeddings.
    pub fn describe_image(&self, bytes: &[u8]) -> Result<Described, DescribeError> {
        let mut times = StageTimes::default();
        let features = self.extract(bytes, &mut times)?;
        Ok(self.embed(features, &mut times)?)
    }

    /// Encoded image -> FAST + FREAK features, with their ring contexts when the model reads them; timing
    /// `decode`, `extract` and `context`.
    pub fn extract(&self, bytes: &[u8], times: &mut StageTimes) -> Result<Features, FeatureError> {
        let image = times.time("decode", || decode_grey(bytes, &self.limits))?;
        let mut features = times.time("extract", || features::extract(&image, &self.extractor))?;
        if self.embedder.needs_context() {
            times.time("context", || features.sample_context(&image))?;
        }
        Ok(features)
    }

    /// Features (extracted here or validated client keypoints) -> embeddings, timing `embed`.
    pub fn embed(&self, features: Features, times: &mut StageTimes) -> Result<Described, EmbeddingError> {
        let embeddings = times.time("embed", || embed(&self.embedder, &features))?;
        Ok(Described { features, embeddings })
    }
}
