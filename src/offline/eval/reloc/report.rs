//! What a relocalisation evaluation reports: one record per query and method, each method's summary (success
//! at three thresholds, errors, match precision, the covariance's and the confidence's calibration, false
//! poses on foreign scenes), and the queries binned by their viewing angle to the map.

use serde::{Deserialize, Serialize};

use crate::offline::eval::methods::Method;
use crate::offline::eval::reloc::diagnose::Diagnosis;
use crate::offline::eval::reloc::protocol::{PnpVariant, RelocConfig};
use crate::offline::eval::stats::median;
use crate::pose::CHI2_6_95;

/// Viewing-angle bins (degrees, lower bounds) of the queries' distance to the map.
pub const ANGLE_BINS: [f64; 4] = [0.0, 10.0, 20.0, 40.0];

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct QueryRecord {
    pub frame: String,
    pub localised: bool,
    pub translation_error: f64,
    pub rotation_error_deg: f64,
    pub matches: usize,
    pub correct_matches: usize,
    pub inliers: usize,
    pub confidence: f64,
    pub seconds: f64,
    /// Baseline to the nearest map camera centre (scene units).
    #[serde(default)]
    pub baseline_to_map: f64,
    /// Viewing angle to the most similarly oriented map keyframe (degrees).
    #[serde(default)]
    pub angle_to_map_deg: f64,
    /// The focal length the pose was estimated with (the scene's, or the estimate with `unknown_focal`).
    #[serde(default)]
    pub focal: Option<f64>,
    /// Squared Mahalanobis distance of the true pose under the pose's covariance (6 degrees of freedom).
    #[serde(default)]
    pub mahalanobis2: Option<f64>,
    /// Whether the pose is within the tolerances its confidence is the probability of (`localize::confidence`:
    /// 2° and 5 % of the inliers' median depth).
    #[serde(default)]
    pub within_confidence_tolerance: Option<bool>,
    /// Stage 1's cap of an `also_caps` run on the same map (absent: the configuration's own settings).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage1_cap: Option<usize>,
    /// The estimator of an `also_pnp` run on the same map (absent: the configuration's own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pnp: Option<PnpVariant>,
    /// Where the query was lost (single frames with a known focal length; `diagnose`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diagnosis: Option<Diagnosis>,
}

/// Success of the queries whose viewing angle to the map falls in one bin.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct BinSummary {
    /// `[lo, hi)` degrees (`hi` infinite for the last).
    pub angle_deg: (f64, f64),
    pub queries: usize,
    pub median_baseline: f64,
    pub within_5cm_5deg: f64,
    pub within_025m_2deg: f64,
    pub within_05m_5deg: f64,
    pub match_precision: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RelocSummary {
    pub method: Method,
    pub map_keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    pub queries: usize,
    pub within_025m_2deg: f64,
    pub within_05m_5deg: f64,
    pub within_5m_10deg: f64,
    pub not_localised: f64,
    pub median_translation_error: f64,
    pub median_rotation_error_deg: f64,
    pub match_precision: f64,
    pub mean_matches: f64,
    pub build_seconds: f64,
    pub mean_query_ms: f64,
    /// Observations of distractor scenes in the map.
    #[serde(default)]
    pub distractor_observations: usize,
    /// Landmarks of the evaluated scene (`landmarks` counts the distractors' too).
    #[serde(default)]
    pub scene_landmarks: usize,
    #[serde(default)]
    pub within_5cm_5deg: f64,
    /// The queries by viewing angle to the map.
    #[serde(default)]
    pub bins: Vec<BinSummary>,
    /// Share of the localised queries whose true pose lies in the covariance's 95 % ellipsoid.
    #[serde(default)]
    pub covariance_coverage: f64,
    /// Median relative error of the focal length over the localised queries (0 when it was given).
    #[serde(default)]
    pub median_focal_error: f64,
    /// Over the localised queries: the mean confidence, and the share within the confidence's tolerances
    /// (they agree when the confidence is calibrated).
    #[serde(default)]
    pub mean_confidence: f64,
    #[serde(default)]
    pub within_confidence_tolerance: f64,
    /// Frames of other scenes localised against the map, and how many got a pose (false poses).
    #[serde(default)]
    pub foreign_queries: usize,
    #[serde(default)]
    pub foreign_localised: usize,
    /// Stage 1's cap of an `also_caps` run on the same map (absent: the configuration's own settings).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage1_cap: Option<usize>,
    /// The estimator of an `also_pnp` run on the same map (absent: the configuration's own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pnp: Option<PnpVariant>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RelocReport {
    pub scene: String,
    /// Extent of the ground-truth camera path (largest distance between two camera centres), scene units.
    pub path_extent: f64,
    pub config: RelocConfig,
    pub summaries: Vec<RelocSummary>,
    pub queries: Vec<(Method, QueryRecord)>,
}

/// What a method's map held and what building it cost, as its summary reports them.
pub(super) struct MapFigures {
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    pub distractor_observations: usize,
    pub scene_landmarks: usize,
    pub build_seconds: f64,
}

/// `method`'s summary over its query records: `map` as built, `foreign` the (frames, localised) of the foreign
/// scenes, `scene_focal` the scene's true focal length, `unit_scale` the success thresholds' factor.
pub(super) fn summarise(
    method: Method,
    recs: &[QueryRecord],
    map: MapFigures,
    foreign: (usize, usize),
    scene_focal: f64,
    unit_scale: f64,
) -> RelocSummary {
    let q = recs.len().max(1) as f64;
    let u = unit_scale;
    let within = |t: f64, r: f64| {
        recs.iter().filter(|x| x.translation_error <= t * u && x.rotation_error_deg <= r).count() as f64 / q
    };
    let bins = bin_summaries(recs, u);
    let loc_t: Vec<f64> = recs.iter().filter(|r| r.localised).map(|r| r.translation_error).collect();
    let loc_r: Vec<f64> = recs.iter().filter(|r| r.localised).map(|r| r.rotation_error_deg).collect();
    let matches: usize = recs.iter().map(|r| r.matches).sum();
    let correct: usize = recs.iter().map(|r| r.correct_matches).sum();
    RelocSummary {
        method,
        map_keyframes: map.keyframes,
        landmarks: map.landmarks,
        observations: map.observations,
        queries: recs.len(),
        within_025m_2deg: within(0.25, 2.0),
        within_05m_5deg: within(0.5, 5.0),
        within_5m_10deg: within(5.0, 10.0),
        not_localised: recs.iter().filter(|r| !r.localised).count() as f64 / q,
        median_translation_error: median(&loc_t),
        median_rotation_error_deg: median(&loc_r),
        match_precision: correct as f64 / matches.max(1) as f64,
        mean_matches: matches as f64 / q,
        build_seconds: map.build_seconds,
        mean_query_ms: 1e3 * recs.iter().map(|r| r.seconds).sum::<f64>() / q,
        distractor_observations: map.distractor_observations,
        scene_landmarks: map.scene_landmarks,
        within_5cm_5deg: within(0.05, 5.0),
        bins,
        covariance_coverage: {
            let d2: Vec<f64> = recs.iter().filter_map(|r| r.mahalanobis2).collect();
            d2.iter().filter(|&&d| d <= CHI2_6_95).count() as f64 / d2.len().max(1) as f64
        },
        mean_confidence: {
            let c: Vec<f64> = recs.iter().filter(|r| r.localised).map(|r| r.confidence).collect();
            c.iter().sum::<f64>() / c.len().max(1) as f64
        },
        within_confidence_tolerance: {
            let w: Vec<bool> = recs.iter().filter_map(|r| r.within_confidence_tolerance).collect();
            w.iter().filter(|&&b| b).count() as f64 / w.len().max(1) as f64
        },
        foreign_queries: foreign.0,
        foreign_localised: foreign.1,
        stage1_cap: None,
        pnp: None,
        median_focal_error: {
            let truth = scene_focal;
            median(&recs.iter().filter_map(|r| r.focal).map(|f| (f - truth).abs() / truth).collect::<Vec<_>>())
        },
    }
}

pub(super) fn bin_summaries(recs: &[QueryRecord], unit_scale: f64) -> Vec<BinSummary> {
    let mut out = Vec::new();
    for (b, &lo) in ANGLE_BINS.iter().enumerate() {
        let hi = ANGLE_BINS.get(b + 1).copied().unwrap_or(f64::INFINITY);
        let inside: Vec<&QueryRecord> =
            recs.iter().filter(|r| r.angle_to_map_deg >= lo && r.angle_to_map_deg < hi).collect();
        let n = inside.len().max(1) as f64;
        let within = |t: f64, r: f64| {
            inside.iter().filter(|x| x.translation_error <= t * unit_scale && x.rotation_error_deg <= r).count() as f64
                / n
        };
        let matches: usize = inside.iter().map(|r| r.matches).sum();
        let correct: usize = inside.iter().map(|r| r.correct_matches).sum();
        out.push(BinSummary {
            angle_deg: (lo, hi),
            queries: inside.len(),
            median_baseline: median(&inside.iter().map(|r| r.baseline_to_map).collect::<Vec<_>>()),
            within_5cm_5deg: within(0.05, 5.0),
            within_025m_2deg: within(0.25, 2.0),
            within_05m_5deg: within(0.5, 5.0),
            match_precision: correct as f64 / matches.max(1) as f64,
        });
    }
    out
}
