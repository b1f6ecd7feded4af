//! `scone eval pairs`: relative pose between image pairs of a real scene, per method, the paper's protocol.
//!
//! In each window of `window` frames the first frame is the reference and every later frame is matched to it.
//! Per pair and method: putative matches (ratio test), then for each RANSAC seed (the correspondences are
//! shuffled with the seed, which changes RANSAC's samples) findEssentialMat + recoverPose; the error is
//! max(rotation error, translation-direction error), 180 degrees when estimation fails. Per method: AUC and
//! accuracy at 5/10/20 degrees averaged over seeds, median errors, match precision, the RANSAC iterations the
//! inlier ratio requires, and timings.
//!
//! Match precision: a putative match is correct when it agrees with the ground truth: with depth at the
//! reference keypoint, its back-projection lands within `depth_px` of the matched keypoint; without depth
//! (or without a reading there), both points lie within `epipolar_px` of each other's ground-truth epipolar
//! line. Matches only checkable by the weaker epipolar test are counted as such (reported per scene).

use std::collections::HashMap;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, Vector3};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::describe::decode::{decode_depth_png, decode_grey, ImageLimitSettings};
use crate::describe::embedding::Embedder;
use crate::describe::features::ExtractorSettings;
use crate::matching::{RatioTest, SconeMatcher};
use crate::offline::eval::methods::{describe, putative_matches, Described, Method};
use crate::offline::eval::stats::{accuracy, auc, markdown_table, median};
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;
use crate::pose::{
    ransac_iterations_needed, relative_motion, relative_pose, rotation_error_deg, translation_angle_deg, RansacSettings,
};

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Settings of a pair evaluation.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PairsConfig {
    pub methods: Vec<Method>,
    pub window: usize,
    pub seeds: u64,
    pub ratio: f32,
    pub mutual: bool,
    /// The ratio test's same-corner radius in pixels (`matching::RatioTest`); 0 = OpenCV's plain test, which
    /// reports written before the option existed used.
    #[serde(default)]
    pub same_corner_px: f32,
    /// How the `scone` method picks its matches (`matching::SconeMatcher`); reports written before the option
    /// existed used the plain embedding.
    #[serde(default)]
    pub scone_matcher: SconeMatcher,
    /// The embedding's own ratio in the fused matchers (`union`, `both`); `None`: `ratio`, as reports written
    /// before the option existed used.
    #[serde(default)]
    pub scone_ratio: Option<f32>,
    pub ransac: RansacSettings,
    pub depth_px: f64,
    pub epipolar_px: f64,
    /// Pairs whose ground-truth baseline is shorter than this (scene units) are also reported apart: their
    /// translation direction is noise (TUM's 30 Hz burst: millimetres), so they are scored by the rotation
    /// error alone there, and the other pairs by the usual max(rotation, translation). 0 = off.
    #[serde(default)]
    pub short_baseline: f64,
    pub extractor: ExtractorSettings,
}

impl Default for PairsConfig {
    fn default() -> Self {
        Self {
            methods: vec![Method::Scone, Method::Freak, Method::FreakGms, Method::Orb, Method::Sift],
            window: 100,
            seeds: 5,
            ratio: crate::matching::DEFAULT_RATIO,
            mutual: false,
            same_corner_px: crate::matching::SAME_CORNER_PX,
            scone_matcher: SconeMatcher::default(),
            scone_ratio: None,
            ransac: RansacSettings::default(),
            depth_px: 4.0,
            epipolar_px: 2.0,
            short_baseline: 0.0,
            extractor: ExtractorSettings::default(),
        }
    }
}

/// One pair, one method.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PairRecord {
    pub method: Method,
    pub reference: String,
    pub frame: String,
    /// Rotation angle between the two cameras (ground truth), degrees.
    pub angular_distance_deg: f64,
    /// Distance between the two camera centres (ground truth), scene units.
    #[serde(default)]
    pub baseline: f64,
    pub matches: usize,
    /// Matches checkable against the ground truth, and how many of those are correct.
    pub checked: usize,
    pub correct: usize,
    /// Per seed: max(rotation, translation) error in degrees (180 = failure).
    pub errors_deg: Vec<f64>,
    pub rotation_errors_deg: Vec<f64>,
    pub translation_errors_deg: Vec<f64>,
    /// Per seed: KITTI-style translation error, |s t_est - t_gt| in scene units, with the estimated unit
    /// direction scaled to the ground-truth baseline (s = |t_gt|: two-view geometry has no scale); NaN = failure.
    #[serde(default)]
    pub translation_errors: Vec<f64>,
    pub inliers: Vec<usize>,
    /// Per seed: iterations RANSAC needs at the found inlier ratio (confidence 0.999, 5-point samples).
    pub iterations_needed: Vec<f64>,
    pub match_seconds: f64,
}

/// Per-method summary.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MethodSummary {
    pub method: Method,
    pub pairs: usize,
    pub auc5: f64,
    pub auc10: f64,
    pub auc20: f64,
    pub acc5: f64,
    pub acc10: f64,
    pub acc20: f64,
    pub median_rotation_deg: f64,
    pub median_translation_deg: f64,
    pub failures: f64,
    pub mean_matches: f64,
    pub match_precision: f64,
    pub checked_share: f64,
    pub median_iterations_needed: f64,
    pub describe_ms: f64,
    pub match_ms: f64,
    /// Median KITTI-style translation error of the successful estimates (scene units; see `PairRecord`).
    #[serde(default)]
    pub median_translation_error: f64,
    /// With `short_baseline` set: AUC@10 of the pairs at or above it (max(rotation, translation)), of the
    /// shorter pairs by rotation alone, and how many pairs are short.
    #[serde(default)]
    pub auc10_long_pairs: Option<f64>,
    #[serde(default)]
    pub auc10_short_pairs_rotation: Option<f64>,
    #[serde(default)]
    pub short_pairs: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PairsReport {
    pub scene: String,
    pub has_depth: bool,
    pub config: PairsConfig,
    pub summaries: Vec<MethodSummary>,
    pub pairs: Vec<PairRecord>,
}

/// Ground-truth checks of a putative match between a reference frame and another frame.
struct Truth<'a> {
    cam: &'a Camera,
    motion: Isometry3<f64>,
    fundamental: Matrix3<f64>,
    depth: Option<&'a opencv::core::Mat>,
}

impl Truth<'_> {
    fn new<'a>(
        cam: &'a Camera,
        t_w1: &Isometry3<f64>,
        t_w2: &Isometry3<f64>,
        depth: Option<&'a opencv::core::Mat>,
    ) -> Truth<'a> {
        let motion = relative_motion(t_w1, t_w2);
        let t = motion.translation.vector;
        let tx = Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0);
        let e = tx * motion.rotation.to_rotation_matrix().matrix();
        let k = Matrix3::new(cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0);
        let kinv = k.try_inverse().expect("validated intrinsics");
        Truth { cam, motion, fundamental: kinv.transpose() * e * kinv, depth }
    }

    /// Some(correct) when checkable, None otherwise.
    fn check(&self, a: (f32, f32), b: (f32, f32), depth_px: f64, epipolar_px: f64) -> Option<bool> {
        use opencv::prelude::MatTraitConst;
        if let Some(depth) = self.depth {
            let (x, y) = (a.0.round() as i32, a.1.round() as i32);
            if x >= 0 && y >= 0 && x < depth.cols() && y < depth.rows() {
                let raw = *depth.at_2d::<u16>(y, x).ok()?;
                if raw > 0 {
                    let z = raw as f64 / crate::describe::decode::TUM_DEPTH_PER_METRE;
                    let p1 = Vector3::new(
                        (a.0 as f64 - self.cam.cx) / self.cam.fx * z,
                        (a.1 as f64 - self.cam.cy) / self.cam.fy * z,
                        z,
                    );
                    let p2 = self.motion * nalgebra::Point3::from(p1);
                    let close =
                        self.cam.project(&p2).is_some_and(|(u, v)| (u - b.0 as f64).hypot(v - b.1 as f64) <= depth_px);
                    return Some(close);
                }
            }
        }
        if self.motion.translation.vector.norm() < 1e-9 {
            return None;
        }
        let pa = Vector3::new(a.0 as f64, a.1 as f64, 1.0);
        let pb = Vector3::new(b.0 as f64, b.1 as f64, 1.0);
        let l2 = self.fundamental * pa;
        let l1 = self.fundamental.transpose() * pb;
        let d2 = pb.dot(&l2).abs() / l2.x.hypot(l2.y);
        let d1 = pa.dot(&l1).abs() / l1.x.hypot(l1.y);
        Some(d1.max(d2) <= epipolar_px)
    }
}

/// Frame pairs of the protocol: (reference index, frame index).
pub fn window_pairs(frames: usize, window: usize) -> Vec<(usize, usize)> {
    let w = window.max(2);
    let mut out = Vec::new();
    let mut start = 0;
    while start < frames {
        for j in start + 1..(start + w).min(frames) {
            out.push((start, j));
        }
        start += w;
    }
    out
}

/// Runs the evaluation on a scene.
pub fn evaluate(scene: &Scene, cfg: &PairsConfig, embedder: Option<&Embedder>) -> Result<PairsReport, BoxError> {
    if cfg.scone_matcher == SconeMatcher::Freak {
        return Err("scone_matcher freak is FREAK, not SConE: compare with the freak method instead".into());
    }
    let limits = ImageLimitSettings::default();
    let pairs: Vec<(usize, usize)> = window_pairs(scene.frames.len(), cfg.window)
        .into_iter()
        .filter(|&(i, j)| scene.frames[i].pose.is_some() && scene.frames[j].pose.is_some())
        .collect();
    let mut needed: Vec<usize> = pairs.iter().flat_map(|&(i, j)| [i, j]).collect();
    needed.sort_unstable();
    needed.dedup();
    let mut images = HashMap::new();
    for &i in &needed {
        let bytes =
            std::fs::read(&scene.frames[i].rgb).map_err(|e| format!("{}: {e}", scene.frames[i].rgb.display()))?;
        images.insert(i, decode_grey(&bytes, &limits)?);
    }
    let mut depths = HashMap::new();
    for &(i, _) in &pairs {
        if let (Some(path), std::collections::hash_map::Entry::Vacant(slot)) = (&scene.frames[i].depth, depths.entry(i))
        {
            let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
            slot.insert(decode_depth_png(&bytes, &ImageLimitSettings::default())?);
        }
    }
    let mut records = Vec::new();
    let mut describe_seconds: HashMap<Method, Vec<f64>> = HashMap::new();
    let mut progress = Progress::new("eval pairs", cfg.methods.len() * (needed.len() + pairs.len()));
    for &method in &cfg.methods {
        let mut described: HashMap<usize, Described> = HashMap::new();
        for &i in &needed {
            progress.step();
            let d = describe(method, &images[&i], &cfg.extractor, embedder)?;
            describe_seconds.entry(method).or_default().push(d.seconds);
            described.insert(i, d);
        }
        for &(i, j) in &pairs {
            progress.step();
            let (a, b) = (&described[&i], &described[&j]);
            let t0 = Instant::now();
            let test = RatioTest { ratio: cfg.ratio, mutual: cfg.mutual, same_corner_px: cfg.same_corner_px };
            let matches = putative_matches(method, a, b, &test, cfg.scone_matcher, cfg.scone_ratio)?;
            let match_seconds = t0.elapsed().as_secs_f64();
            let t_w1 = scene.frames[i].pose.expect("filtered");
            let t_w2 = scene.frames[j].pose.expect("filtered");
            let truth = Truth::new(&scene.camera, &t_w1, &t_w2, depths.get(&i));
            let (mut checked, mut correct) = (0, 0);
            for m in &matches {
                let (ka, kb) = (a.keypoints[m.query], b.keypoints[m.train]);
                if let Some(ok) = truth.check((ka.x, ka.y), (kb.x, kb.y), cfg.depth_px, cfg.epipolar_px) {
                    checked += 1;
                    correct += ok as usize;
                }
            }
            let gt = &truth.motion;
            let gt_rot = gt.rotation.to_rotation_matrix();
            let mut rec = PairRecord {
                method,
                reference: scene.frames[i].stamp.clone(),
                frame: scene.frames[j].stamp.clone(),
                angular_distance_deg: gt.rotation.angle().to_degrees(),
                baseline: gt.translation.vector.norm(),
                matches: matches.len(),
                checked,
                correct,
                errors_deg: Vec::new(),
                rotation_errors_deg: Vec::new(),
                translation_errors_deg: Vec::new(),
                translation_errors: Vec::new(),
                inliers: Vec::new(),
                iterations_needed: Vec::new(),
                match_seconds,
            };
            for seed in 0..cfg.seeds {
                let mut order: Vec<usize> = (0..matches.len()).collect();
                order.shuffle(&mut rand::rngs::StdRng::seed_from_u64(seed));
                let p1: Vec<(f32, f32)> =
                    order.iter().map(|&k| (a.keypoints[matches[k].query].x, a.keypoints[matches[k].query].y)).collect();
                let p2: Vec<(f32, f32)> =
                    order.iter().map(|&k| (b.keypoints[matches[k].train].x, b.keypoints[matches[k].train].y)).collect();
                match relative_pose(&p1, &p2, &scene.camera, &scene.camera, &cfg.ransac)? {
                    Some(pose) => {
                        let r = rotation_error_deg(&pose.rotation, &gt_rot);
                        let t = translation_angle_deg(&pose.translation, &gt.translation.vector);
                        rec.rotation_errors_deg.push(r);
                        rec.translation_errors_deg.push(t);
                        let g = gt.translation.vector;
                        let est = pose.translation.normalize() * g.norm();
                        rec.translation_errors.push((est - g).norm());
                        rec.errors_deg.push(r.max(t));
                        rec.inliers.push(pose.inlier_count);
                        rec.iterations_needed.push(ransac_iterations_needed(
                            pose.inlier_count as f64 / matches.len() as f64,
                            5,
                            cfg.ransac.confidence,
                        ));
                    }
                    None => {
                        rec.rotation_errors_deg.push(180.0);
                        rec.translation_errors_deg.push(180.0);
                        rec.translation_errors.push(f64::NAN);
                        rec.errors_deg.push(180.0);
                        rec.inliers.push(0);
                        rec.iterations_needed.push(f64::INFINITY);
                    }
                }
            }
            records.push(rec);
        }
    }
    let summaries = cfg
        .methods
        .iter()
        .map(|&m| {
            summarise(
                m,
                &records,
                cfg.seeds as usize,
                describe_seconds.get(&m).map(Vec::as_slice).unwrap_or(&[]),
                cfg.short_baseline,
            )
        })
        .collect();
    Ok(PairsReport {
        scene: scene.name.clone(),
        has_depth: !depths.is_empty(),
        config: cfg.clone(),
        summaries,
        pairs: records,
    })
}

fn summarise(
    method: Method,
    records: &[PairRecord],
    seeds: usize,
    describe_seconds: &[f64],
    short_baseline: f64,
) -> MethodSummary {
    let recs: Vec<&PairRecord> = records.iter().filter(|r| r.method == method).collect();
    // AUC@10 averaged over seeds of the records `keep` selects, each error read by `err`.
    let auc10_of = |keep: &dyn Fn(&PairRecord) -> bool, err: &dyn Fn(&PairRecord, usize) -> f64| -> Option<f64> {
        let sel: Vec<&&PairRecord> = recs.iter().filter(|r| keep(r)).collect();
        if sel.is_empty() {
            return None;
        }
        let per_seed = (0..seeds).map(|s| auc(&sel.iter().map(|r| err(r, s)).collect::<Vec<_>>(), 10.0));
        Some(per_seed.sum::<f64>() / seeds.max(1) as f64)
    };
    let short = |r: &PairRecord| r.baseline < short_baseline;
    let (auc10_long_pairs, auc10_short_pairs_rotation) = if short_baseline > 0.0 {
        (auc10_of(&|r| !short(r), &|r, s| r.errors_deg[s]), auc10_of(&|r| short(r), &|r, s| r.rotation_errors_deg[s]))
    } else {
        (None, None)
    };
    let t_err: Vec<f64> =
        recs.iter().flat_map(|r| r.translation_errors.iter().copied()).filter(|e| e.is_finite()).collect();
    let per_seed = |f: &dyn Fn(&[f64]) -> f64| {
        (0..seeds).map(|s| f(&recs.iter().map(|r| r.errors_deg[s]).collect::<Vec<_>>())).sum::<f64>()
            / seeds.max(1) as f64
    };
    let all_rot: Vec<f64> = recs.iter().flat_map(|r| r.rotation_errors_deg.iter().copied()).collect();
    let all_trans: Vec<f64> = recs.iter().flat_map(|r| r.translation_errors_deg.iter().copied()).collect();
    let all_err: Vec<f64> = recs.iter().flat_map(|r| r.errors_deg.iter().copied()).collect();
    let iters: Vec<f64> = recs.iter().flat_map(|r| r.iterations_needed.iter().copied()).collect();
    let checked: usize = recs.iter().map(|r| r.checked).sum();
    let correct: usize = recs.iter().map(|r| r.correct).sum();
    let matches: usize = recs.iter().map(|r| r.matches).sum();
    let n = recs.len().max(1) as f64;
    MethodSummary {
        method,
        pairs: recs.len(),
        auc5: per_seed(&|e| auc(e, 5.0)),
        auc10: per_seed(&|e| auc(e, 10.0)),
        auc20: per_seed(&|e| auc(e, 20.0)),
        acc5: per_seed(&|e| accuracy(e, 5.0)),
        acc10: per_seed(&|e| accuracy(e, 10.0)),
        acc20: per_seed(&|e| accuracy(e, 20.0)),
        median_rotation_deg: median(&all_rot),
        median_translation_deg: median(&all_trans),
        failures: all_err.iter().filter(|&&e| e >= 180.0).count() as f64 / all_err.len().max(1) as f64,
        mean_matches: matches as f64 / n,
        match_precision: correct as f64 / checked.max(1) as f64,
        checked_share: checked as f64 / matches.max(1) as f64,
        median_iterations_needed: median(&iters),
        describe_ms: 1e3 * describe_seconds.iter().sum::<f64>() / describe_seconds.len().max(1) as f64,
        match_ms: 1e3 * recs.iter().map(|r| r.match_seconds).sum::<f64>() / n,
        median_translation_error: median(&t_err),
        auc10_long_pairs,
        auc10_short_pairs_rotation,
        short_pairs: if short_baseline > 0.0 { recs.iter().filter(|r| short(r)).count() } else { 0 },
    }
}

/// The summaries as a markdown table.
pub fn markdown(report: &PairsReport) -> String {
    let mut s = format!(
        "{} ({} pairs, window {}, {} seeds, ratio {}, same-corner radius {} px, SConE matcher {}, {:?} {} px, at most {} iterations, confidence {})\n\n",
        report.scene,
        report.summaries.first().map(|m| m.pairs).unwrap_or(0),
        report.config.window,
        report.config.seeds,
        report.config.ratio,
        report.config.same_corner_px,
        report.config.scone_matcher.name(),
        report.config.ransac.essential,
        report.config.ransac.threshold_px,
        report.config.ransac.max_iters,
        report.config.ransac.confidence
    );
    let headers = [
        "method",
        "AUC@5",
        "AUC@10",
        "AUC@20",
        "acc@5",
        "acc@10",
        "acc@20",
        "med. rot",
        "med. trans",
        "fail",
        "matches",
        "match precision",
        "RANSAC iters needed (median)",
        "describe ms",
        "match ms",
    ];
    s.push_str(&markdown_table(
        &headers,
        report.summaries.iter().map(|m| {
            vec![
                m.method.name().to_string(),
                format!("{:.3}", m.auc5),
                format!("{:.3}", m.auc10),
                format!("{:.3}", m.auc20),
                format!("{:.2}", m.acc5),
                format!("{:.2}", m.acc10),
                format!("{:.2}", m.acc20),
                format!("{:.2}", m.median_rotation_deg),
                format!("{:.2}", m.median_translation_deg),
                format!("{:.0} %", 100.0 * m.failures),
                format!("{:.0}", m.mean_matches),
                format!("{:.3}", m.match_precision),
                format!("{:.0}", m.median_iterations_needed),
                format!("{:.1}", m.describe_ms),
                format!("{:.1}", m.match_ms),
            ]
        }),
    ));
    if report.config.short_baseline > 0.0 {
        s.push_str(&format!(
            "\nPairs with a baseline under {} (scene units) scored apart, by rotation alone:\n\n",
            report.config.short_baseline
        ));
        let headers = [
            "method",
            "AUC@10, all pairs",
            "AUC@10, longer pairs",
            "short pairs",
            "AUC@10, short pairs (rotation)",
            "med. rot",
            "med. translation error (scaled)",
        ];
        let opt = |v: Option<f64>| v.map(|x| format!("{x:.3}")).unwrap_or_else(|| "-".into());
        s.push_str(&markdown_table(
            &headers,
            report.summaries.iter().map(|m| {
                vec![
                    m.method.name().to_string(),
                    format!("{:.3}", m.auc10),
                    opt(m.auc10_long_pairs),
                    m.short_pairs.to_string(),
                    opt(m.auc10_short_pairs_rotation),
                    format!("{:.2}", m.median_rotation_deg),
                    format!("{:.4}", m.median_translation_error),
                ]
            }),
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_pair_the_first_frame_with_the_rest() {
        assert_eq!(window_pairs(5, 100), vec![(0, 1), (0, 2), (0, 3), (0, 4)]);
        assert_eq!(window_pairs(5, 2), vec![(0, 1), (2, 3)]);
        assert_eq!(window_pairs(21, 10).len(), 18);
    }
}
