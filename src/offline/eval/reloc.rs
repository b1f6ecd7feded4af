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
//!
//! **Far maps and distractors** (the harder protocol; flags of `scone eval reloc`):
//! * `map_block = (a, b)`: the map is the posed frames from fraction `a` to `b` of the sequence (a contiguous
//!   block), and the queries are all the others, so most queries are far from every map keyframe. Each query
//!   records its distance to the map: the baseline to the nearest map camera centre and the viewing angle to
//!   the most similarly oriented map keyframe; the summary bins the queries by that angle (`ANGLE_BINS`).
//! * `distractors`: keyframes of other real scenes are added to the same map, far away from it in space (so
//!   their landmarks can only be wrong matches), until the map holds `distractor_observations` of their
//!   observations; the nearest neighbours must then be found among many look-alikes. With distractors the
//!   index is the service's (HNSW above `IndexSettings::exact_below` observations), as a deployment's is.
//! * `unit_scale`: the success thresholds are multiplied by it (scenes whose units are not metres).
//!
//! **What a client without calibration gets, and how sure a pose is** (issue 28):
//! * `unknown_focal`: every query is localised without its focal length, as Localize does for a client that
//!   leaves `fx`, `fy` out (with `centre_principal_point`, the principal point is the image centre as well);
//!   each record keeps the focal length used, and the summary the median relative error against the scene's.
//! * Every localised query records `mahalanobis2`, the squared Mahalanobis distance of the true pose under the
//!   pose's covariance (`localize.covariance_scale` applied): the summary's `covariance_coverage` is the share
//!   of localised queries within the 95 % ellipsoid (`pose::CHI2_6_95`), which should be close to 0.95.

use std::time::Instant;

use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::{Camera, PoseConvention};
use crate::decode::{decode_depth_png, decode_grey, ImageLimitSettings};
use crate::embedding::Embedder;
use crate::features::{ExtractorSettings, Features};
use crate::map::builder::{plan_keyframe, BuildSettings, Depth, KeyframeInput};
use crate::map::index::{EmbeddingIndex, IndexPoints, IndexSettings};
use crate::map::localize::{localize, within_confidence_tolerance, LocalizeSettings};
use crate::map::model::{MapData, MapMeta};
use crate::offline::eval::methods::{describe, Described, Method};
use crate::offline::eval::stats::{markdown_table, median};
use crate::offline::scene::Scene;
use crate::pose::{pose_covariance, pose_difference, rotation_error_deg, CHI2_6_95};
use crate::progress::Progress;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RelocConfig {
    pub methods: Vec<Method>,
    pub stride: usize,
    pub extractor: ExtractorSettings,
    pub build: BuildSettings,
    pub localize: LocalizeSettings,
    pub precision_px: f64,
    /// Map from a contiguous block `[a, b)` of the posed frames (fractions) instead of every `stride`-th.
    #[serde(default)]
    pub map_block: Option<(f64, f64)>,
    /// Other scenes whose keyframes are added to the map as distractors.
    #[serde(default)]
    pub distractors: Vec<std::path::PathBuf>,
    /// Distractor observations to add (0: none). Distractor scenes are walked frame by frame (every
    /// `distractor_stride`-th) until the count is reached.
    #[serde(default)]
    pub distractor_observations: usize,
    #[serde(default = "one")]
    pub distractor_stride: usize,
    /// Multiplies the success thresholds (1 for scenes in metres).
    #[serde(default = "one_f")]
    pub unit_scale: f64,
    /// Localise the queries without their focal length (estimated with the pose).
    #[serde(default)]
    pub unknown_focal: bool,
    /// With `unknown_focal`: the principal point is the image centre too (a client that knows nothing of its
    /// camera), not the scene's.
    #[serde(default)]
    pub centre_principal_point: bool,
    /// Frames of other scenes localised against the map: every one localised is a false pose.
    #[serde(default)]
    pub foreign: Vec<std::path::PathBuf>,
    /// Every N-th frame of the foreign scenes.
    #[serde(default = "five")]
    pub foreign_stride: usize,
    /// What the index's graph holds once distractors make the map large: the service's default (reports
    /// written before the setting read as one point per observation, which they ran with).
    #[serde(default)]
    pub index_points: IndexPoints,
}

/// The parts of issue 27 an evaluation can turn on one by one (`--stages`); the rest stay as today's pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Stage 2: matching against the covisibility vote's candidate keyframes.
    Candidates,
    /// Stage 2 with FREAK's matches joined to the embedding's.
    Freak,
    /// Stage 3: guided search by projection and the pose estimated again.
    Guided,
    /// Map building with the known poses (epipolar window, covisible candidates, tracks, FREAK matches).
    Build,
}

/// Settings with exactly `stages` of issue 27 on, over today's pipeline.
pub fn with_stages(
    build: BuildSettings,
    localize: LocalizeSettings,
    stages: &[Stage],
) -> (BuildSettings, LocalizeSettings) {
    let on = |s: Stage| stages.contains(&s);
    let build = if on(Stage::Build) { build.with_known_poses() } else { build.unguided() };
    let localize = LocalizeSettings {
        candidate_matching: on(Stage::Candidates) || on(Stage::Freak),
        candidate_freak: on(Stage::Freak),
        guided_search: on(Stage::Guided),
        ..localize
    };
    (build, localize)
}

fn one() -> usize {
    1
}

fn five() -> usize {
    5
}

fn one_f() -> f64 {
    1.0
}

/// Viewing-angle bins (degrees, lower bounds) of the queries' distance to the map.
pub const ANGLE_BINS: [f64; 4] = [0.0, 10.0, 20.0, 40.0];

/// Where distractor keyframes are put: this far from the evaluated scene (scene units), one offset per
/// distractor scene, so their landmarks never fall where the scene's are.
const DISTRACTOR_OFFSET: f64 = 1.0e4;

impl Default for RelocConfig {
    fn default() -> Self {
        Self {
            methods: vec![Method::Scone, Method::Freak, Method::Sift],
            stride: 3,
            extractor: ExtractorSettings::default(),
            build: BuildSettings::default(),
            localize: LocalizeSettings::default(),
            precision_px: 5.0,
            map_block: None,
            distractors: Vec::new(),
            distractor_observations: 0,
            distractor_stride: 1,
            unit_scale: 1.0,
            unknown_focal: false,
            centre_principal_point: false,
            foreign: Vec::new(),
            foreign_stride: 5,
            index_points: IndexSettings::default().points,
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

/// The features the service would hold for `d`: its keypoints and, for SConE, their FREAK bits (a keyframe's
/// payload keeps them, and the stages that join FREAK's matches read them).
fn features_of(d: &Described) -> Result<Features, BoxError> {
    let mut descriptors = Vec::new();
    if let Some(bits) = &d.freak {
        for r in 0..bits.rows() {
            let row = bits.at_row::<u8>(r)?;
            descriptors.push(row.try_into().map_err(|_| format!("FREAK row of {} bytes", row.len()))?);
        }
    }
    Ok(Features { width: d.width, height: d.height, keypoints: d.keypoints.clone(), descriptors, context: Vec::new() })
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
    let limits = ImageLimitSettings::default();
    let posed: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
    let (map_frames, query_frames) = split_frames(&posed, cfg)?;
    let centres: Vec<_> = posed.iter().map(|&i| scene.frames[i].pose.unwrap().translation.vector).collect();
    let path_extent = centres.iter().flat_map(|a| centres.iter().map(move |b| (a - b).norm())).fold(0.0f64, f64::max);
    let mut images = Vec::new();
    for f in &scene.frames {
        let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
        images.push(decode_grey(&bytes, &limits)?);
    }
    let mut summaries = Vec::new();
    let mut queries = Vec::new();
    let per_method = images.len() + map_frames.len() + query_frames.len();
    let mut progress = Progress::new("eval reloc", cfg.methods.len() * per_method);
    for &method in &cfg.methods {
        let ratio_scale = |r: f32| if method == Method::Freak { r.sqrt() } else { r };
        let build = BuildSettings { ratio: ratio_scale(cfg.build.ratio), ..cfg.build };
        // Every ratio test on distances: FREAK's ±1 vectors take the square root (a ratio on Hamming distances).
        let loc = LocalizeSettings {
            ratio: ratio_scale(cfg.localize.ratio),
            candidate_ratio: ratio_scale(cfg.localize.candidate_ratio),
            guided_ratio: ratio_scale(cfg.localize.guided_ratio),
            ..cfg.localize
        };
        let described: Vec<Described> = images
            .iter()
            .map(|im| describe(method, im, &cfg.extractor, embedder))
            .inspect(|_| progress.step())
            .collect::<Result<_, _>>()?;
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
            progress.step();
            let d = &described[i];
            let features = features_of(d)?;
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
        let scene_observations = data.observations.len();
        for (si, dir) in cfg.distractors.iter().enumerate() {
            if data.observations.len() - scene_observations >= cfg.distractor_observations {
                break;
            }
            add_distractors(&mut data, dir, si, scene_observations, method, cfg, &build, embedder)?;
        }
        let distractor_observations = data.observations.len() - scene_observations;
        // Exact search on the scene alone (the descriptors compared, not the index); the service's index
        // (HNSW above `exact_below`) once distractors make the map large, as a deployment's is.
        let params = if distractor_observations > 0 {
            IndexSettings { points: cfg.index_points, ..IndexSettings::default() }
        } else {
            IndexSettings { exact_below: usize::MAX, ..IndexSettings::default() }
        };
        let mut index = EmbeddingIndex::new(params);
        index.sync(&data);
        let build_seconds = t0.elapsed().as_secs_f64();
        let mut recs = Vec::new();
        let query_camera = match (cfg.unknown_focal, cfg.centre_principal_point) {
            (false, _) => scene.camera,
            (true, false) => Camera { fx: 0.0, fy: 0.0, ..scene.camera },
            (true, true) => Camera { fx: 0.0, fy: 0.0, cx: 0.0, cy: 0.0, ..scene.camera }.with_defaults(),
        };
        for &i in &query_frames {
            progress.step();
            let d = &described[i];
            let features = features_of(d)?;
            let t = Instant::now();
            let out = localize(&data, &index, &features, &vecs[i].0, &query_camera, None, &loc)?;
            let seconds = t.elapsed().as_secs_f64() + d.seconds;
            let gt = scene.frames[i].pose.unwrap();
            let gt_cw = gt.inverse();
            let (baseline_to_map, angle_to_map_deg) = distance_to_map(scene, &map_frames, &gt);
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
            let within_confidence_tolerance =
                out.pose.as_ref().map(|p| within_confidence_tolerance(p, &out.points, &gt));
            let mahalanobis2 = out.pose.as_ref().and_then(|p| {
                let sigma = pose_covariance(PoseConvention::default(), &p.camera_to_world, p.covariance_w2c.as_ref()?);
                let e = pose_difference(&gt, &p.camera_to_world);
                sigma.try_inverse().map(|inv| (e.transpose() * inv * e)[0])
            });
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
                baseline_to_map,
                angle_to_map_deg,
                focal: out.pose.as_ref().map(|p| p.focal),
                mahalanobis2,
                within_confidence_tolerance,
            });
        }
        let (foreign_queries, foreign_localised) = foreign_poses(&data, &index, method, cfg, &loc, embedder)?;
        let q = recs.len().max(1) as f64;
        let u = cfg.unit_scale;
        let within = |t: f64, r: f64| {
            recs.iter().filter(|x| x.translation_error <= t * u && x.rotation_error_deg <= r).count() as f64 / q
        };
        let bins = bin_summaries(&recs, u);
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
            distractor_observations,
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
            foreign_queries,
            foreign_localised,
            median_focal_error: {
                let truth = (scene.camera.fx + scene.camera.fy) / 2.0;
                median(&recs.iter().filter_map(|r| r.focal).map(|f| (f - truth).abs() / truth).collect::<Vec<_>>())
            },
        });
        queries.extend(recs.into_iter().map(|r| (method, r)));
    }
    Ok(RelocReport { scene: scene.name.clone(), path_extent, config: cfg.clone(), summaries, queries })
}

/// Checks a map block `a:b` (fractions of the posed frames): `0 <= a < b <= 1`.
pub fn check_block(a: f64, b: f64) -> Result<(), String> {
    if (0.0..1.0).contains(&a) && a < b && b <= 1.0 {
        Ok(())
    } else {
        Err(format!("map block {a}:{b}: needs 0 <= a < b <= 1"))
    }
}

/// The map's frames and the queries: every `stride`-th posed frame and the rest, or a contiguous block and the
/// rest.
fn split_frames(posed: &[usize], cfg: &RelocConfig) -> Result<(Vec<usize>, Vec<usize>), BoxError> {
    let (map, queries): (Vec<usize>, Vec<usize>) = match cfg.map_block {
        Some((a, b)) => {
            check_block(a, b)?;
            let n = posed.len() as f64;
            let (lo, hi) = ((a * n).floor() as usize, ((b * n).ceil() as usize).min(posed.len()));
            let map = posed[lo..hi].to_vec();
            (map.clone(), posed.iter().copied().filter(|i| !map.contains(i)).collect())
        }
        None => {
            let stride = cfg.stride.max(2);
            posed.iter().copied().partition(|i| i % stride == 0)
        }
    };
    if map.is_empty() || queries.is_empty() {
        return Err(format!("{} map frames and {} queries: both must be non-empty", map.len(), queries.len()).into());
    }
    Ok((map, queries))
}

/// Baseline to the nearest map camera centre, and viewing angle to the most similarly oriented map keyframe.
fn distance_to_map(scene: &Scene, map_frames: &[usize], pose: &nalgebra::Isometry3<f64>) -> (f64, f64) {
    let mut baseline = f64::INFINITY;
    let mut angle = f64::INFINITY;
    for &k in map_frames {
        let kp = scene.frames[k].pose.expect("map frames are posed");
        baseline = baseline.min((kp.translation.vector - pose.translation.vector).norm());
        angle = angle.min(kp.rotation.angle_to(&pose.rotation).to_degrees());
    }
    (baseline, angle)
}

fn bin_summaries(recs: &[QueryRecord], unit_scale: f64) -> Vec<BinSummary> {
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

/// Every `foreign_stride`-th frame of the foreign scenes localised against the map: (frames, localised).
fn foreign_poses(
    data: &MapData,
    index: &EmbeddingIndex,
    method: Method,
    cfg: &RelocConfig,
    loc: &LocalizeSettings,
    embedder: Option<&Embedder>,
) -> Result<(usize, usize), BoxError> {
    let limits = ImageLimitSettings::default();
    let (mut frames, mut localised) = (0, 0);
    for dir in &cfg.foreign {
        let other = Scene::load(dir)?;
        for f in other.frames.iter().step_by(cfg.foreign_stride.max(1)) {
            let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
            let d = describe(method, &decode_grey(&bytes, &limits)?, &cfg.extractor, embedder)?;
            let (v, _) = vectors(method, &d)?;
            let out = localize(data, index, &features_of(&d)?, &v, &other.camera, None, loc)?;
            frames += 1;
            localised += usize::from(out.pose.is_some());
        }
    }
    Ok((frames, localised))
}

/// Adds keyframes of the scene in `dir` to `data`, moved [`DISTRACTOR_OFFSET`] away per scene, until the map
/// holds `cfg.distractor_observations` observations beyond the evaluated scene's `base`.
#[allow(clippy::too_many_arguments)]
fn add_distractors(
    data: &mut MapData,
    dir: &std::path::Path,
    scene_index: usize,
    base: usize,
    method: Method,
    cfg: &RelocConfig,
    build: &BuildSettings,
    embedder: Option<&Embedder>,
) -> Result<(), BoxError> {
    let limits = ImageLimitSettings::default();
    let other = Scene::load(dir)?;
    let offset = nalgebra::Vector3::new(DISTRACTOR_OFFSET * (scene_index + 1) as f64, 0.0, 0.0);
    for (fi, f) in other.frames.iter().enumerate().step_by(cfg.distractor_stride.max(1)) {
        if data.observations.len() - base >= cfg.distractor_observations {
            break;
        }
        let Some(pose) = f.pose else { continue };
        let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
        let d = describe(method, &decode_grey(&bytes, &limits)?, &cfg.extractor, embedder)?;
        let (v, dim) = vectors(method, &d)?;
        if dim != data.meta.dim && !v.is_empty() {
            return Err(format!("distractor {}: dimension {dim}, the map's is {}", other.name, data.meta.dim).into());
        }
        let features = features_of(&d)?;
        let depth = match &f.depth {
            Some(p) => Some(decode_depth_png(&std::fs::read(p)?, &limits)?),
            None => None,
        };
        let moved = nalgebra::Isometry3::from_parts((pose.translation.vector + offset).into(), pose.rotation);
        let input = KeyframeInput {
            id: 1_000_000 * (scene_index as u64 + 1) + fi as u64,
            pose: moved,
            camera: other.camera,
            features: &features,
            embeddings: &v,
            depth: depth.as_ref().map(|m| Depth { image: m, scale: crate::decode::TUM_DEPTH_SCALE }),
            external: None,
        };
        let record = plan_keyframe(data, &input, build)?;
        data.check(&record).map_err(|e| format!("distractor frame {fi}: {e}"))?;
        data.apply(&record);
    }
    Ok(())
}

pub fn markdown(r: &RelocReport) -> String {
    let map = match r.config.map_block {
        Some((a, b)) => format!("the block {a:.2}-{b:.2} of the posed frames"),
        None => format!("every {}th frame", r.config.stride),
    };
    let mut s = format!(
        "{} (map: {map}; camera path extent {:.2} scene units; thresholds x {}; 2D-3D precision at {} px)\n\n",
        r.scene, r.path_extent, r.config.unit_scale, r.config.precision_px
    );
    let headers = [
        "method",
        "keyframes",
        "landmarks",
        "queries",
        "(0.25 m, 2°)",
        "(0.5 m, 5°)",
        "(5 m, 10°)",
        "not localised",
        "med. t",
        "med. R (deg)",
        "2D-3D precision",
        "matches",
        "query ms",
        "cov. 95 %",
        "confidence / within",
        "focal err.",
        "observations",
        "foreign localised",
    ];
    s.push_str(&markdown_table(
        &headers,
        r.summaries.iter().map(|m| {
            vec![
                m.method.name().to_string(),
                m.map_keyframes.to_string(),
                m.landmarks.to_string(),
                m.queries.to_string(),
                format!("{:.2}", m.within_025m_2deg),
                format!("{:.2}", m.within_05m_5deg),
                format!("{:.2}", m.within_5m_10deg),
                format!("{:.2}", m.not_localised),
                format!("{:.3}", m.median_translation_error),
                format!("{:.2}", m.median_rotation_error_deg),
                format!("{:.3}", m.match_precision),
                format!("{:.0}", m.mean_matches),
                format!("{:.0}", m.mean_query_ms),
                format!("{:.2}", m.covariance_coverage),
                format!("{:.2} / {:.2}", m.mean_confidence, m.within_confidence_tolerance),
                format!("{:.3}", m.median_focal_error),
                m.observations.to_string(),
                format!("{} / {}", m.foreign_localised, m.foreign_queries),
            ]
        }),
    ));
    s.push_str("\nBy viewing angle to the most similarly oriented map keyframe (success within (5 cm, 5°) / (0.25 m, 2°) / (0.5 m, 5°); 2D-3D precision):\n\n");
    let headers = [
        "method",
        "distractor obs.",
        "angle (deg)",
        "queries",
        "median baseline",
        "(5 cm, 5°)",
        "(0.25 m, 2°)",
        "(0.5 m, 5°)",
        "precision",
    ];
    s.push_str(&markdown_table(
        &headers,
        r.summaries.iter().flat_map(|m| {
            m.bins.iter().filter(|b| b.queries > 0).map(move |b| {
                let hi = if b.angle_deg.1.is_finite() { format!("{:.0}", b.angle_deg.1) } else { "inf".into() };
                vec![
                    m.method.name().to_string(),
                    m.distractor_observations.to_string(),
                    format!("{:.0}-{hi}", b.angle_deg.0),
                    b.queries.to_string(),
                    format!("{:.3}", b.median_baseline),
                    format!("{:.2}", b.within_5cm_5deg),
                    format!("{:.2}", b.within_025m_2deg),
                    format!("{:.2}", b.within_05m_5deg),
                    format!("{:.3}", b.match_precision),
                ]
            })
        }),
    ));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_block_map_takes_a_contiguous_part_and_leaves_the_rest_as_queries() {
        let posed: Vec<usize> = (0..10).collect();
        let cfg = RelocConfig { map_block: Some((0.0, 0.3)), ..Default::default() };
        assert_eq!(split_frames(&posed, &cfg).unwrap(), (vec![0, 1, 2], (3..10).collect()));
        let cfg = RelocConfig { map_block: Some((0.5, 1.0)), ..Default::default() };
        assert_eq!(split_frames(&posed, &cfg).unwrap().0, vec![5, 6, 7, 8, 9]);
        let cfg = RelocConfig { stride: 3, ..Default::default() };
        assert_eq!(split_frames(&posed, &cfg).unwrap().0, vec![0, 3, 6, 9]);
        let all = RelocConfig { map_block: Some((0.0, 1.0)), ..Default::default() };
        assert!(split_frames(&posed, &all).is_err(), "no queries left");
    }

    #[test]
    fn queries_fall_into_their_angle_bins_with_scaled_thresholds() {
        let rec = |angle: f64, t: f64| QueryRecord {
            frame: String::new(),
            localised: true,
            translation_error: t,
            rotation_error_deg: 1.0,
            matches: 10,
            correct_matches: 5,
            inliers: 8,
            confidence: 1.0,
            seconds: 0.0,
            baseline_to_map: 1.0,
            angle_to_map_deg: angle,
            focal: None,
            mahalanobis2: None,
            within_confidence_tolerance: None,
        };
        let recs = [rec(5.0, 0.01), rec(15.0, 0.3), rec(50.0, 0.1)];
        let bins = bin_summaries(&recs, 1.0);
        assert_eq!(bins.iter().map(|b| b.queries).collect::<Vec<_>>(), vec![1, 1, 0, 1]);
        assert_eq!((bins[0].within_5cm_5deg, bins[1].within_025m_2deg, bins[1].within_05m_5deg), (1.0, 0.0, 1.0));
        // Thresholds in scene units: x10 lets the 0.3 error pass (0.25 m x 10).
        assert_eq!(bin_summaries(&recs, 10.0)[1].within_025m_2deg, 1.0);
    }
}
