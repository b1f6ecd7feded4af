//! What a homography evaluation reports: one record per pair and method, each method's figures over all pairs
//! and per bin of zoom, of rotation and of tilt, and the neighbour share per rule.

use serde::{Deserialize, Serialize};

use crate::describe::constellation::NeighbourRule;
use crate::offline::eval::homography::protocol::HomographyConfig;
use crate::offline::eval::methods::Method;
use crate::offline::eval::stats::median;

/// Upper edges of the zoom bins (the last bin is open).
pub const ZOOM_EDGES: [f64; 5] = [1.25, 1.6, 2.0, 2.5, 3.0];
/// Upper edges of the rotation bins, degrees.
pub const ROTATION_EDGES: [f64; 5] = [15.0, 45.0, 90.0, 135.0, 180.0];
/// Upper edges of the tilt (out-of-plane angle) bins, degrees.
pub const TILT_EDGES: [f64; 5] = [15.0, 30.0, 45.0, 60.0, 90.0];
/// Corner-error thresholds the report gives the share of pairs within.
pub const CORNER_PX: [f64; 3] = [3.0, 5.0, 10.0];

/// One pair, one method.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyPair {
    pub method: Method,
    pub sequence: String,
    /// k of the pair (1, k).
    pub image: usize,
    pub zoom: f64,
    pub rotation_deg: f64,
    /// Out-of-plane angle of the true H at image 1's centre, degrees (0 in reports written without it).
    #[serde(default)]
    pub tilt_deg: f64,
    pub matches: usize,
    pub correct: usize,
    /// Mean corner error of the fitted homography, pixels (infinite when none was found; JSON null).
    #[serde(with = "finite_or_null")]
    pub corner_error_px: f64,
    /// Neighbour share of the project's keypoints for this pair (the same for every method that uses them),
    /// None for other methods or when no keypoint corresponds.
    pub neighbour_share: Option<f64>,
    /// The same share with the warped members turned 90 degrees about their keypoint: what chance alone keeps.
    #[serde(default)]
    pub neighbour_chance: Option<f64>,
    /// Ring share: of each corresponding keypoint's ring samples (centre left out), those whose image under
    /// the true H lands within `correct_px` of the same sample of its correspondent; and the same with the
    /// correspondent's ring turned 90 degrees (chance).
    #[serde(default)]
    pub ring_share: Option<f64>,
    #[serde(default)]
    pub ring_chance: Option<f64>,
    pub match_seconds: f64,
}

/// One pair's neighbour share under one rule.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RuleShare {
    pub rule: NeighbourRule,
    pub sequence: String,
    pub image: usize,
    pub zoom: f64,
    pub rotation_deg: f64,
    #[serde(default)]
    pub tilt_deg: f64,
    pub share: Option<f64>,
}

mod finite_or_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

/// Figures of a set of pairs of one method.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographySummary {
    pub method: Method,
    pub pairs: usize,
    /// Share of pairs whose corner error is within 3, 5 and 10 px.
    pub within: [f64; 3],
    /// Mean over pairs of the share of correct putative matches (pairs without matches count 0).
    pub mma: f64,
    pub mean_correct: f64,
    pub mean_matches: f64,
    /// Median corner error (failures count as infinite), pixels.
    pub median_corner_error_px: Option<f64>,
    pub mean_neighbour_share: Option<f64>,
    /// Means over pairs of the neighbour share and the ring share above chance (share minus chance).
    #[serde(default)]
    pub mean_neighbour_above_chance: Option<f64>,
    #[serde(default)]
    pub mean_ring_above_chance: Option<f64>,
    pub describe_ms: f64,
}

/// One bin of one axis: its label and each method's figures there.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyBin {
    pub axis: String,
    pub label: String,
    pub summaries: Vec<HomographySummary>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyReport {
    pub config: HomographyConfig,
    pub sequences: Vec<String>,
    pub summaries: Vec<HomographySummary>,
    pub bins: Vec<HomographyBin>,
    pub pairs: Vec<HomographyPair>,
    #[serde(default)]
    pub rule_shares: Vec<RuleShare>,
}

pub(super) fn summarise(method: Method, pairs: &[&HomographyPair], describe_ms: f64) -> HomographySummary {
    let recs: Vec<&&HomographyPair> = pairs.iter().filter(|p| p.method == method).collect();
    let n = recs.len();
    let nf = n.max(1) as f64;
    let mut within = [0.0; 3];
    for (w, t) in within.iter_mut().zip(CORNER_PX) {
        *w = recs.iter().filter(|p| p.corner_error_px <= t).count() as f64 / nf;
    }
    let errors: Vec<f64> = recs.iter().map(|p| p.corner_error_px).collect();
    let shares: Vec<f64> = recs.iter().filter_map(|p| p.neighbour_share).collect();
    let mean = |v: Vec<f64>| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    let above = |share: fn(&HomographyPair) -> (Option<f64>, Option<f64>)| {
        mean(
            recs.iter()
                .filter_map(|p| match share(p) {
                    (Some(s), Some(c)) => Some(s - c),
                    _ => None,
                })
                .collect(),
        )
    };
    HomographySummary {
        method,
        pairs: n,
        within,
        mma: recs.iter().map(|p| p.correct as f64 / p.matches.max(1) as f64).sum::<f64>() / nf,
        mean_correct: recs.iter().map(|p| p.correct as f64).sum::<f64>() / nf,
        mean_matches: recs.iter().map(|p| p.matches as f64).sum::<f64>() / nf,
        median_corner_error_px: (n > 0).then(|| median(&errors)).filter(|e| e.is_finite()),
        mean_neighbour_share: mean(shares),
        mean_neighbour_above_chance: above(|p| (p.neighbour_share, p.neighbour_chance)),
        mean_ring_above_chance: above(|p| (p.ring_share, p.ring_chance)),
        describe_ms,
    }
}

/// Each method's figures per bin of zoom, of rotation and of tilt, for the bins `records` fall in;
/// `describe_ms` is a method's mean describe time.
pub(super) fn binned(
    records: &[HomographyPair],
    methods: &[Method],
    describe_ms: impl Fn(Method) -> f64,
) -> Vec<HomographyBin> {
    let mut bins = Vec::new();
    for (axis, key, lower, edges) in [
        ("zoom", zoom_bin as fn(f64) -> String, 1.0, &ZOOM_EDGES),
        ("rotation", rotation_bin, 0.0, &ROTATION_EDGES),
        ("tilt", tilt_bin, 0.0, &TILT_EDGES),
    ] {
        let value = |p: &HomographyPair| match axis {
            "zoom" => p.zoom,
            "rotation" => p.rotation_deg,
            _ => p.tilt_deg,
        };
        let labels = bin_labels(records.iter().map(value), key, lower, edges);
        for label in labels {
            let inside: Vec<&HomographyPair> = records.iter().filter(|p| key(value(p)) == label).collect();
            bins.push(HomographyBin {
                axis: axis.to_string(),
                label,
                summaries: methods.iter().map(|&m| summarise(m, &inside, describe_ms(m))).collect(),
            });
        }
    }
    bins
}

/// Label of the bin `v` falls in, for upper edges `edges` (the last bin open above).
fn bin_label(v: f64, edges: &[f64], lower: f64, unit: &str) -> String {
    let mut lo = lower;
    for &e in edges {
        if v < e || (e == *edges.last().expect("edges") && v <= e && unit == "deg") {
            return format!("{lo}-{e}{unit}");
        }
        lo = e;
    }
    format!(">= {lo}{unit}")
}

pub fn zoom_bin(z: f64) -> String {
    bin_label(z, &ZOOM_EDGES, 1.0, "x")
}

pub fn rotation_bin(r: f64) -> String {
    bin_label(r, &ROTATION_EDGES, 0.0, "deg")
}

pub fn tilt_bin(t: f64) -> String {
    bin_label(t, &TILT_EDGES, 0.0, "deg")
}

/// The labels of the bins (lower end `lower`, upper edges `edges`) that `values` fall in, in the bins' order.
pub(super) fn bin_labels(
    values: impl Iterator<Item = f64>,
    key: fn(f64) -> String,
    lower: f64,
    edges: &[f64],
) -> Vec<String> {
    let present: std::collections::HashSet<String> = values.map(key).collect();
    let mut all = Vec::new();
    let mut lo = lower;
    for &e in edges {
        all.push(key((lo + e) / 2.0));
        lo = e;
    }
    all.push(key(lo + 1.0));
    all.dedup();
    all.into_iter().filter(|l| present.contains(l)).collect()
}
