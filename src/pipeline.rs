//! The path every image and every client keypoint set takes: decode -> FAST + FREAK -> constellations ->
//! SConE embeddings. Transports and commands call this; nothing else strings the stages together.

use std::sync::Arc;

use crate::constellation;
use crate::decode::{decode_grey, ImageLimits};
use crate::embedding::Embedder;
use crate::error::{EmbeddingError, FeatureError};
use crate::features::{self, ExtractorConfig, Features};

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
    pub extractor: ExtractorConfig,
    pub limits: ImageLimits,
    pub embedder: Arc<Embedder>,
}

impl Describer {
    /// Encoded image -> features and embeddings.
    pub fn describe_image(&self, bytes: &[u8]) -> Result<Described, DescribeError> {
        let image = decode_grey(bytes, &self.limits)?;
        let features = features::extract(&image, &self.extractor)?;
        self.describe_features(features)
    }

    /// Embeddings of a stored keyframe (its keypoints and FREAK descriptors) with this model.
    pub fn embed_keyframe(&self, keyframe: &crate::map::model::Keyframe) -> Result<Vec<f32>, DescribeError> {
        let features = features::from_precomputed(
            keyframe.camera.width,
            keyframe.camera.height,
            keyframe.keypoints.clone(),
            &keyframe.descriptors,
            &features::KeypointLimits { max_keypoints: usize::MAX, ..Default::default() },
        )?;
        Ok(self.describe_features(features)?.embeddings)
    }

    /// Features (extracted here or validated client keypoints) -> embeddings.
    pub fn describe_features(&self, features: Features) -> Result<Described, DescribeError> {
        let c = constellation::build(&features.keypoints, self.embedder.k());
        let embeddings = self.embedder.embed(&features, &c)?;
        Ok(Described { features, embeddings })
    }
}
