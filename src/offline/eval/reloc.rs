//! `scone eval reloc`: relocalisation against a map built from part of a scene.
//!
//! The map is built from every `stride`-th frame with its ground-truth pose (and depth where the scene has
//! it) by the service's map-building code; every other frame is localised against it. Per method: the share
//! of queries within (0.25 m, 2 deg), (0.5 m, 5 deg) and (5 m, 10 deg), median errors of the localised
//! queries, the share not localised, and 2D-3D match precision (a match is correct when the landmark projects
//! with the query's ground-truth pose within `precision_px` of the keypoint).
//!
//! Methods share the map code: SConE embeddings (L2), FREAK bits as ±1 vectors (L2 on them ranks exactly as
//! Hamming, so the search is an exact popcount search; the ratio test is applied to Hamming distances by
//! using sqrt(ratio) on L2), and SIFT (L2). All searches here are exact, so the comparison is about the
//! descriptors, not the index.

use std::time::Instant;

use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use super::median;
use super::methods::{describe, Described, Method};
use crate::decode::{decode_depth_png, decode_grey, ImageLimits};
use crate::embedding::Embedder;
use crate::features::{ExtractorConfig, Features};
use crate::map::builder::{plan_keyframe, BuildParams, Depth, KeyframeInput};
use crate::map::index::{EmbeddingIndex, IndexParams};
use crate::map::localize::{localize, LocalizeParams};
use crate::map::model::{MapData, MapMeta};
use crate::offline::scene::Scene;
use crate::pose::rotation_error_deg;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RelocConfig {
    pub methods: Vec<Method>,
    pub stride: usize,
    pub extractor: ExtractorConfig,
    pub build: BuildParams,
    pub localize: LocalizeParams,
    pub precision_px: f64,
}

impl Default for RelocConfig {
    fn default() -> Self {
        Self {
            methods: vec![Method::Scone, Method::Freak, Method::Sift],
            stride: 3,
            extractor: ExtractorConfig::default(),
            build: BuildParams::default(),
            localize: LocalizeParams::default(),
            precision_px: 5.0,
        }
    }
}

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

/// Vectors a method's descriptors are compared as, row-major, with their dimension.
fn vectors(method: Method, d: &Described) -> Result<(Vec<f32>, usize), BoxError> {
    let rows = d.descriptors.rows() as usize;
    if rows == 0 {
        return Ok((Vec::new(), if method == Method::Freak { 512 } else { d.descriptors.cols().max(1) as usize }));
    }
    match method {
        Method::Freak => {
            let mut out = Vec::with_capacity(rows * 512);
            for r in 0..rows as i32 {
                for byte in d.descriptors.at_row::<u8>(r)? {
                    for bit in 0..8 {
                        out.push(if byte >> bit & 1 == 1 { 1.0 } else { -1.0 });
                    }
                }
            }
            Ok((out, 512))
        }
        _ => {
            let cols = d.descriptors.cols() as usize;
            let mut out = Vec::with_capacity(rows * cols);
            for r in 0..rows as i32 {
                out.extend_from_slice(d.descriptors.at_row::<f32>(r)?);
            }
            Ok((out, cols))
        }
    }
}

pub fn evaluate(scene: &Scene, cfg: &RelocConfig, embedder: Option<&Embedder>) -> Result<RelocReport, BoxError> {
    let limits = ImageLimits::default();
    let posed: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
    let stride = cfg.stride.max(2);
    let map_frames: Vec<usize> = posed.iter().copied().filter(|i| i % stride == 0).collect();
    let query_frames: Vec<usize> = posed.iter().copied().filter(|i| i % stride != 0).collect();
    let centres: Vec<_> = posed.iter().map(|&i| scene.frames[i].pose.unwrap().translation.vector).collect();
    let path_extent = centres.iter().flat_map(|a| centres.iter().map(move |b| (a - b).norm())).fold(0.0f64, f64::max);
    let mut images = Vec::new();
    for f in &scene.frames {
        let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
        images.push(decode_grey(&bytes, &limits)?);
    }
    let mut summaries = Vec::new();
    let mut queries = Vec::new();
    for &method in &cfg.methods {
        let ratio_scale = |r: f32| if method == Method::Freak { r.sqrt() } else { r };
        let build = BuildParams { ratio: ratio_scale(cfg.build.ratio), ..cfg.build };
        let loc = LocalizeParams { ratio: ratio_scale(cfg.localize.ratio), ..cfg.localize };
        let described: Vec<Described> =
            images.iter().map(|im| describe(method, im, &cfg.extractor, embedder)).collect::<Result<_, _>>()?;
        let vecs: Vec<(Vec<f32>, usize)> = described.iter().map(|d| vectors(method, d)).collect::<Result<_, _>>()?;
        let dim = vecs.iter().map(|v| v.1).max().unwrap_or(1);
        let mut data = MapData::new(MapMeta {
            id: format!("eval-{}", method.name()),
            model_id: embedder.map(|e| e.model_id().to_string()).unwrap_or_default(),
            k: 20,
            dim,
            created_unix_ms: 0,
        });
        let t0 = Instant::now();
        for &i in &map_frames {
            let d = &described[i];
            let features =
                Features { width: d.width, height: d.height, keypoints: d.keypoints.clone(), descriptors: vec![] };
            let depth_mat = match &scene.frames[i].depth {
                Some(p) => Some(decode_depth_png(&std::fs::read(p)?, &limits)?),
                None => None,
            };
            let input = KeyframeInput {
                id: i as u64,
                pose: scene.frames[i].pose.unwrap(),
                camera: scene.camera,
                features: &features,
                embeddings: &vecs[i].0,
                depth: depth_mat.as_ref().map(|m| Depth { image: m, scale: crate::decode::TUM_DEPTH_SCALE }),
                external: None,
            };
            let record = plan_keyframe(&data, &input, &build)?;
            data.check(&record).map_err(|e| format!("frame {i}: {e}"))?;
            data.apply(&record);
        }
        let mut index = EmbeddingIndex::new(IndexParams { exact_below: usize::MAX, ..IndexParams::default() });
        index.sync(&data);
        let build_seconds = t0.elapsed().as_secs_f64();
        let mut recs = Vec::new();
        for &i in &query_frames {
            let d = &described[i];
            let features =
                Features { width: d.width, height: d.height, keypoints: d.keypoints.clone(), descriptors: vec![] };
            let t = Instant::now();
            let out = localize(&data, &index, &features, &vecs[i].0, &scene.camera, None, &loc)?;
            let seconds = t.elapsed().as_secs_f64() + d.seconds;
            let gt = scene.frames[i].pose.unwrap();
            let gt_cw = gt.inverse();
            let correct = out
                .matches
                .iter()
                .filter(|m| {
                    let p = nalgebra::Point3::from(data.landmarks[&m.landmark].point);
                    let k = &features.keypoints[m.keypoint];
                    scene
                        .camera
                        .project(&(gt_cw * p))
                        .is_some_and(|(u, v)| (u - k.x as f64).hypot(v - k.y as f64) <= cfg.precision_px)
                })
                .count();
            let (localised, te, re, inliers) = match &out.pose {
                Some(p) => (
                    true,
                    (p.camera_to_world.translation.vector - gt.translation.vector).norm(),
                    rotation_error_deg(
                        &p.camera_to_world.rotation.to_rotation_matrix(),
                        &gt.rotation.to_rotation_matrix(),
                    ),
                    p.inliers.len(),
                ),
                None => (false, f64::INFINITY, 180.0, 0),
            };
            recs.push(QueryRecord {
                frame: scene.frames[i].stamp.clone(),
                localised,
                translation_error: te,
                rotation_error_deg: re,
                matches: out.matches.len(),
                correct_matches: correct,
                inliers,
                confidence: out.confidence,
                seconds,
            });
        }
        let q = recs.len().max(1) as f64;
        let within = |t: f64, r: f64| {
            recs.iter().filter(|x| x.translation_error <= t && x.rotation_error_deg <= r).count() as f64 / q
        };
        let loc_t: Vec<f64> = recs.iter().filter(|r| r.localised).map(|r| r.translation_error).collect();
        let loc_r: Vec<f64> = recs.iter().filter(|r| r.localised).map(|r| r.rotation_error_deg).collect();
        let matches: usize = recs.iter().map(|r| r.matches).sum();
        let correct: usize = recs.iter().map(|r| r.correct_matches).sum();
        summaries.push(RelocSummary {
            method,
            map_keyframes: data.keyframes.len(),
            landmarks: data.landmarks.len(),
            observations: data.observations.len(),
            queries: recs.len(),
            within_025m_2deg: within(0.25, 2.0),
            within_05m_5deg: within(0.5, 5.0),
            within_5m_10deg: within(5.0, 10.0),
            not_localised: recs.iter().filter(|r| !r.localised).count() as f64 / q,
            median_translation_error: median(&loc_t),
            median_rotation_error_deg: median(&loc_r),
            match_precision: correct as f64 / matches.max(1) as f64,
            mean_matches: matches as f64 / q,
            build_seconds,
            mean_query_ms: 1e3 * recs.iter().map(|r| r.seconds).sum::<f64>() / q,
        });
        queries.extend(recs.into_iter().map(|r| (method, r)));
    }
    Ok(RelocReport { scene: scene.name.clone(), path_extent, config: cfg.clone(), summaries, queries })
}

pub fn markdown(r: &RelocReport) -> String {
    let mut s = format!(
        "{} (map: every {}th frame; camera path extent {:.2} scene units; 2D-3D precision at {} px)\n\n",
        r.scene, r.config.stride, r.path_extent, r.config.precision_px
    );
    s.push_str("| method | keyframes | landmarks | queries | (0.25 m, 2°) | (0.5 m, 5°) | (5 m, 10°) | not localised | med. t | med. R (deg) | 2D-3D precision | matches | query ms |\n");
    s.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for m in &r.summaries {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {:.2} | {:.3} | {:.0} | {:.0} |\n",
            m.method.name(),
            m.map_keyframes,
            m.landmarks,
            m.queries,
            m.within_025m_2deg,
            m.within_05m_5deg,
            m.within_5m_10deg,
            m.not_localised,
            m.median_translation_error,
            m.median_rotation_error_deg,
            m.match_precision,
            m.mean_matches,
            m.mean_query_ms
        ));
    }
    s
}
