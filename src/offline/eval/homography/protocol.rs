//! The settings of a homography evaluation: the methods compared and the thresholds the module docs' figures
//! are measured with.

use serde::{Deserialize, Serialize};

use crate::describe::constellation::{self, NeighbourRule};
use crate::describe::features::ExtractorSettings;
use crate::matching::SconeMatcher;
use crate::offline::eval::methods::Method;

/// Settings of a homography evaluation.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyConfig {
    pub methods: Vec<Method>,
    pub ratio: f32,
    pub same_corner_px: f32,
    pub scone_matcher: SconeMatcher,
    /// The embedding's own ratio in the fused matchers (`union`, `both`); `None`: `ratio`.
    #[serde(default)]
    pub scone_ratio: Option<f32>,
    /// MAGSAC++ inlier threshold of the fitted homography, pixels.
    pub ransac_px: f64,
    /// A match (and a constellation member) is correct within this many pixels of the true H's image.
    pub correct_px: f64,
    /// Constellation size of the neighbour share.
    pub k: usize,
    /// Neighbour rules whose share is also measured (the pairs' `neighbour_share` is always the shipped
    /// rule's, [`NeighbourRule::Nearest`]).
    #[serde(default)]
    pub neighbour_rules: Vec<NeighbourRule>,
    pub extractor: ExtractorSettings,
}

impl Default for HomographyConfig {
    fn default() -> Self {
        Self {
            methods: vec![Method::Scone, Method::SconePlain, Method::Freak, Method::Orb, Method::Sift],
            ratio: crate::matching::DEFAULT_RATIO,
            same_corner_px: crate::matching::SAME_CORNER_PX,
            scone_matcher: SconeMatcher::default(),
            scone_ratio: None,
            ransac_px: 3.0,
            correct_px: 3.0,
            k: constellation::DEFAULT_K,
            neighbour_rules: Vec::new(),
            extractor: ExtractorSettings::default(),
        }
    }
}
