//! `scone eval homography`: matching under exact homographies (zoom, rotation, viewpoint, light, blur, JPEG),
//! per method, on sequences in the HPatches layout.
//!
//! A sequence is a folder holding `1.<ext> .. N.<ext>` (png, ppm, jpg) and `H_1_k` for k = 2..N, each a 3x3
//! matrix in text that sends pixels of image 1 to pixels of image k. Every pair (1, k) is scored per method:
//!
//! - **putative matches**: the method's keypoints and descriptors, the ratio test with the same-corner rule
//!   (SConE by the evaluation's matcher, as `scone eval pairs`);
//! - **correct matches**: those whose keypoint in image 1, sent through the true H, lands within `correct_px`
//!   of the matched keypoint; the **mean matching accuracy** (MMA) is their share of the putative matches;
//! - **homography accuracy**: H is fitted to the putative matches with MAGSAC++ (`ransac_px`); its error is the
//!   mean distance between where the fitted and the true H send image 1's four corners (infinite when no H is
//!   found), and the report gives the share of pairs within 3 / 5 / 10 px.
//!
//! Pairs are binned by the zoom and the in-plane rotation of the true H at image 1's centre: the zoom is
//! `max(s, 1/s)` with `s` the square root of the Jacobian's determinant, the rotation the angle of the
//! Jacobian's nearest similarity.
//!
//! **Neighbour share**: for the project's keypoints (SConE's and FREAK's), the number of a keypoint's
//! constellation members whose image under the true H lies within `correct_px` of a member of the
//! constellation of its corresponding keypoint (the keypoint of image k nearest to its own image, when within
//! `correct_px`), per slot of the constellation (k). It measures how much of a constellation survives the
//! change, before any network sees it; with `neighbour_rules` it is measured for each candidate rule of
//! `constellation::NeighbourRule` as well.

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use opencv::core::{Mat, Point2f, Vector};
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use crate::constellation::{self, Constellations, NeighbourRule};
use crate::decode::{decode_grey, GreyImage, ImageLimitSettings};
use crate::embedding::Embedder;
use crate::features::{ExtractorSettings, Keypoint};
use crate::matching::{RatioTest, SconeMatcher};
use crate::offline::eval::methods::{describe, putative_matches, Described, Method};
use crate::offline::eval::stats::{markdown_table, median};
use crate::progress::Progress;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Upper edges of the zoom bins (the last bin is open).
pub const ZOOM_EDGES: [f64; 5] = [1.25, 1.6, 2.0, 2.5, 3.0];
/// Upper edges of the rotation bins, degrees.
pub const ROTATION_EDGES: [f64; 5] = [15.0, 45.0, 90.0, 135.0, 180.0];
/// Corner-error thresholds the report gives the share of pairs within.
pub const CORNER_PX: [f64; 3] = [3.0, 5.0, 10.0];

/// Settings of a homography evaluation.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyConfig {
    pub methods: Vec<Method>,
    pub ratio: f32,
    pub same_corner_px: f32,
    pub scone_matcher: SconeMatcher,
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
            ransac_px: 3.0,
            correct_px: 3.0,
            k: constellation::DEFAULT_K,
            neighbour_rules: Vec::new(),
            extractor: ExtractorSettings::default(),
        }
    }
}

/// A sequence in the HPatches layout.
#[derive(Debug, Clone)]
pub struct Sequence {
    pub name: String,
    /// Image files 1..=N.
    pub images: Vec<PathBuf>,
    /// `H_1_k` for k = 2..=N (index k - 2).
    pub homographies: Vec<Matrix3<f64>>,
}

/// Reads a 3x3 homography written as 9 whitespace-separated numbers.
pub fn read_homography(path: &Path) -> Result<Matrix3<f64>, BoxError> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let v: Vec<f64> = text
        .split_whitespace()
        .map(|s| s.parse::<f64>().map_err(|e| format!("{}: {s:?}: {e}", path.display())))
        .collect::<Result<_, _>>()?;
    if v.len() != 9 || v.iter().any(|x| !x.is_finite()) {
        return Err(format!("{}: expected 9 finite numbers, found {}", path.display(), v.len()).into());
    }
    let h = Matrix3::from_row_slice(&v);
    if h.determinant().abs() < 1e-12 {
        return Err(format!("{}: the homography is singular", path.display()).into());
    }
    Ok(h)
}

fn image_file(dir: &Path, i: usize) -> Option<PathBuf> {
    ["png", "ppm", "jpg", "jpeg"].iter().map(|ext| dir.join(format!("{i}.{ext}"))).find(|p| p.is_file())
}

impl Sequence {
    /// Loads a sequence folder: images 1, 2, ... for as long as both the image and `H_1_k` exist.
    pub fn load(dir: &Path) -> Result<Sequence, BoxError> {
        let first = image_file(dir, 1).ok_or_else(|| format!("{}: no image 1.png / 1.ppm / 1.jpg", dir.display()))?;
        let mut images = vec![first];
        let mut homographies = Vec::new();
        for k in 2.. {
            let h = dir.join(format!("H_1_{k}"));
            match (image_file(dir, k), h.is_file()) {
                (Some(img), true) => {
                    homographies.push(read_homography(&h)?);
                    images.push(img);
                }
                (None, false) => break,
                (Some(_), false) => return Err(format!("{}: image {k} has no H_1_{k}", dir.display()).into()),
                (None, true) => return Err(format!("{}: H_1_{k} has no image {k}", dir.display()).into()),
            }
        }
        if homographies.is_empty() {
            return Err(format!("{}: no pair (image 2 and H_1_2)", dir.display()).into());
        }
        let name =
            dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string());
        Ok(Sequence { name, images, homographies })
    }
}

/// The sequences under `roots`: a root holding `H_1_2` is a sequence, otherwise each of its sub-folders that
/// holds one is (sorted by name).
pub fn find_sequences(roots: &[PathBuf]) -> Result<Vec<PathBuf>, BoxError> {
    let mut out = Vec::new();
    for root in roots {
        if root.join("H_1_2").is_file() {
            out.push(root.clone());
            continue;
        }
        let mut subs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| format!("{}: {e}", root.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join("H_1_2").is_file())
            .collect();
        if subs.is_empty() {
            return Err(format!("{}: neither a sequence (H_1_2) nor a folder of sequences", root.display()).into());
        }
        subs.sort();
        out.extend(subs);
    }
    Ok(out)
}

/// Where `h` sends `(x, y)`; None behind the camera (w <= 0).
pub fn apply(h: &Matrix3<f64>, x: f64, y: f64) -> Option<(f64, f64)> {
    let p = h * Vector3::new(x, y, 1.0);
    (p.z > 1e-12).then(|| (p.x / p.z, p.y / p.z))
}

/// Zoom (`max(s, 1/s)`) and in-plane rotation (degrees, 0..=180) of `h` at `(x, y)`.
pub fn local_zoom_rotation(h: &Matrix3<f64>, x: f64, y: f64) -> (f64, f64) {
    let d = 0.5;
    let (Some(c), Some(px), Some(py)) = (apply(h, x, y), apply(h, x + d, y), apply(h, x, y + d)) else {
        return (f64::INFINITY, 0.0);
    };
    let (a, cc) = ((px.0 - c.0) / d, (px.1 - c.1) / d);
    let (b, dd) = ((py.0 - c.0) / d, (py.1 - c.1) / d);
    let s = (a * dd - b * cc).abs().sqrt();
    let zoom = if s > 0.0 { s.max(1.0 / s) } else { f64::INFINITY };
    let rotation = (cc - b).atan2(a + dd).to_degrees().abs();
    (zoom, rotation)
}

/// Mean distance between where `est` and `truth` send the corners of a `w` x `h` image.
pub fn corner_error(est: &Matrix3<f64>, truth: &Matrix3<f64>, w: u32, h: u32) -> f64 {
    let (w, h) = (w as f64 - 1.0, h as f64 - 1.0);
    let corners = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)];
    let mut sum = 0.0;
    for (x, y) in corners {
        match (apply(est, x, y), apply(truth, x, y)) {
            (Some(e), Some(t)) => sum += (e.0 - t.0).hypot(e.1 - t.1),
            _ => return f64::INFINITY,
        }
    }
    sum / 4.0
}

/// MAGSAC++ homography of the correspondences, None when there are fewer than 4 or none is found.
pub fn fit_homography(
    src: &[(f32, f32)],
    dst: &[(f32, f32)],
    ransac_px: f64,
) -> Result<Option<Matrix3<f64>>, BoxError> {
    if src.len() < 4 {
        return Ok(None);
    }
    let s: Vector<Point2f> = src.iter().map(|p| Point2f::new(p.0, p.1)).collect();
    let d: Vector<Point2f> = dst.iter().map(|p| Point2f::new(p.0, p.1)).collect();
    let mut mask = Mat::default();
    let h = opencv::calib3d::find_homography_ext(
        &s,
        &d,
        opencv::calib3d::USAC_MAGSAC,
        ransac_px,
        &mut mask,
        10_000,
        0.9999,
    )?;
    if h.empty() || h.rows() != 3 || h.cols() != 3 {
        return Ok(None);
    }
    let mut m = Matrix3::zeros();
    for r in 0..3 {
        for c in 0..3 {
            m[(r, c)] = *h.at_2d::<f64>(r as i32, c as i32)?;
        }
    }
    Ok((m.iter().all(|x| x.is_finite()) && m.determinant().abs() > 1e-12).then_some(m))
}

/// For each keypoint of `a`, the keypoint of `b` nearest to its image under `h`, when within `px`.
fn correspondences(a: &[Keypoint], b: &[Keypoint], h: &Matrix3<f64>, px: f64) -> Vec<Option<usize>> {
    let cell = px.max(1.0) as f32;
    let mut grid: std::collections::HashMap<(i32, i32), Vec<usize>> = std::collections::HashMap::new();
    for (j, k) in b.iter().enumerate() {
        grid.entry(((k.x / cell).floor() as i32, (k.y / cell).floor() as i32)).or_default().push(j);
    }
    a.iter()
        .map(|k| {
            let (x, y) = apply(h, k.x as f64, k.y as f64)?;
            let (cx, cy) = ((x as f32 / cell).floor() as i32, (y as f32 / cell).floor() as i32);
            let mut best: Option<(f64, usize)> = None;
            for gx in cx - 1..=cx + 1 {
                for gy in cy - 1..=cy + 1 {
                    for &j in grid.get(&(gx, gy)).map(Vec::as_slice).unwrap_or(&[]) {
                        let d = (b[j].x as f64 - x).hypot(b[j].y as f64 - y);
                        if d <= px && best.is_none_or(|(bd, _)| d < bd) {
                            best = Some((d, j));
                        }
                    }
                }
            }
            best.map(|(_, j)| j)
        })
        .collect()
}

/// Mean share of constellation members that survive `h` (module docs), and the corresponding keypoints it is
/// averaged over; None when no keypoint corresponds.
pub fn neighbour_share(
    a: &[Keypoint],
    ca: &Constellations,
    b: &[Keypoint],
    cb: &Constellations,
    h: &Matrix3<f64>,
    px: f64,
) -> Option<(f64, usize)> {
    let corr = correspondences(a, b, h, px);
    let (mut sum, mut n) = (0.0, 0usize);
    for (i, j) in corr.iter().enumerate() {
        let Some(j) = *j else { continue };
        let members_b: Vec<&Keypoint> = cb
            .neighbours_of(j)
            .iter()
            .zip(cb.mask_of(j))
            .filter(|(_, &m)| m > 0)
            .map(|(&m, _)| &b[m as usize])
            .collect();
        let members_a: Vec<usize> =
            ca.neighbours_of(i).iter().zip(ca.mask_of(i)).filter(|(_, &m)| m > 0).map(|(&m, _)| m as usize).collect();
        if members_a.is_empty() || ca.k == 0 {
            continue;
        }
        let kept = members_a
            .iter()
            .filter(|&&m| {
                apply(h, a[m].x as f64, a[m].y as f64)
                    .is_some_and(|(x, y)| members_b.iter().any(|q| (q.x as f64 - x).hypot(q.y as f64 - y) <= px))
            })
            .count();
        sum += kept as f64 / ca.k as f64;
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64, n))
}

/// One pair, one method.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct HomographyPair {
    pub method: Method,
    pub sequence: String,
    /// k of the pair (1, k).
    pub image: usize,
    pub zoom: f64,
    pub rotation_deg: f64,
    pub matches: usize,
    pub correct: usize,
    /// Mean corner error of the fitted homography, pixels (infinite when none was found; JSON null).
    #[serde(with = "finite_or_null")]
    pub corner_error_px: f64,
    /// Neighbour share of the project's keypoints for this pair (the same for every method that uses them),
    /// None for other methods or when no keypoint corresponds.
    pub neighbour_share: Option<f64>,
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

fn summarise(method: Method, pairs: &[&HomographyPair], describe_ms: f64) -> HomographySummary {
    let recs: Vec<&&HomographyPair> = pairs.iter().filter(|p| p.method == method).collect();
    let n = recs.len();
    let nf = n.max(1) as f64;
    let mut within = [0.0; 3];
    for (w, t) in within.iter_mut().zip(CORNER_PX) {
        *w = recs.iter().filter(|p| p.corner_error_px <= t).count() as f64 / nf;
    }
    let errors: Vec<f64> = recs.iter().map(|p| p.corner_error_px).collect();
    let shares: Vec<f64> = recs.iter().filter_map(|p| p.neighbour_share).collect();
    HomographySummary {
        method,
        pairs: n,
        within,
        mma: recs.iter().map(|p| p.correct as f64 / p.matches.max(1) as f64).sum::<f64>() / nf,
        mean_correct: recs.iter().map(|p| p.correct as f64).sum::<f64>() / nf,
        mean_matches: recs.iter().map(|p| p.matches as f64).sum::<f64>() / nf,
        median_corner_error_px: (n > 0).then(|| median(&errors)).filter(|e| e.is_finite()),
        mean_neighbour_share: (!shares.is_empty()).then(|| shares.iter().sum::<f64>() / shares.len() as f64),
        describe_ms,
    }
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

fn load_image(path: &Path) -> Result<GreyImage, BoxError> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(decode_grey(&bytes, &ImageLimitSettings::default()).map_err(|e| format!("{}: {e}", path.display()))?)
}

/// Runs the evaluation on the sequences in `dirs`.
pub fn evaluate(
    dirs: &[PathBuf],
    cfg: &HomographyConfig,
    embedder: Option<&Embedder>,
) -> Result<HomographyReport, BoxError> {
    if cfg.scone_matcher == SconeMatcher::Freak {
        return Err("scone_matcher freak is FREAK, not SConE: compare with the freak method instead".into());
    }
    let sequences: Vec<Sequence> = dirs.iter().map(|d| Sequence::load(d)).collect::<Result<_, _>>()?;
    let total: usize = sequences.iter().map(|s| s.images.len() * cfg.methods.len()).sum();
    let mut progress = Progress::new("eval homography", total);
    let mut records = Vec::new();
    let mut rule_shares = Vec::new();
    let mut describe_seconds: std::collections::HashMap<Method, Vec<f64>> = Default::default();
    let test = RatioTest { ratio: cfg.ratio, mutual: false, same_corner_px: cfg.same_corner_px };
    for seq in &sequences {
        let images: Vec<GreyImage> = seq.images.iter().map(|p| load_image(p)).collect::<Result<_, _>>()?;
        let geometry: Vec<(f64, f64)> = seq
            .homographies
            .iter()
            .map(|h| local_zoom_rotation(h, images[0].width() as f64 / 2.0, images[0].height() as f64 / 2.0))
            .collect();
        // The project's keypoints (SConE and FREAK share them): the neighbour share of every pair.
        let uses_project_keypoints =
            |m: Method| matches!(m, Method::Scone | Method::SconePlain | Method::Freak | Method::FreakGms);
        let mut shares: Vec<Option<f64>> = vec![None; seq.homographies.len()];
        if cfg.methods.iter().any(|&m| uses_project_keypoints(m)) || !cfg.neighbour_rules.is_empty() {
            let kps: Vec<Vec<Keypoint>> = images
                .iter()
                .map(|im| crate::features::extract(im, &cfg.extractor).map(|f| f.keypoints))
                .collect::<Result<_, _>>()?;
            // Each pair's share under `rule`.
            let shares_of = |rule: NeighbourRule| -> Vec<Option<f64>> {
                let cons: Vec<Constellations> = kps.iter().map(|k| constellation::build_with(k, cfg.k, rule)).collect();
                let share = |(i, h): (usize, &Matrix3<f64>)| {
                    neighbour_share(&kps[0], &cons[0], &kps[i + 1], &cons[i + 1], h, cfg.correct_px).map(|s| s.0)
                };
                seq.homographies.iter().enumerate().map(share).collect()
            };
            shares = shares_of(NeighbourRule::Nearest);
            for &rule in &cfg.neighbour_rules {
                for (i, share) in shares_of(rule).into_iter().enumerate() {
                    rule_shares.push(RuleShare {
                        rule,
                        sequence: seq.name.clone(),
                        image: i + 2,
                        zoom: geometry[i].0,
                        rotation_deg: geometry[i].1,
                        share,
                    });
                }
            }
        }
        for &method in &cfg.methods {
            let mut described: Vec<Described> = Vec::with_capacity(images.len());
            for im in &images {
                described.push(describe(method, im, &cfg.extractor, embedder)?);
                progress.step();
            }
            describe_seconds.entry(method).or_default().extend(described.iter().map(|d| d.seconds));
            let a = &described[0];
            for (i, h) in seq.homographies.iter().enumerate() {
                let b = &described[i + 1];
                let t0 = std::time::Instant::now();
                let matches = putative_matches(method, a, b, &test, cfg.scone_matcher)?;
                let match_seconds = t0.elapsed().as_secs_f64();
                let src: Vec<(f32, f32)> =
                    matches.iter().map(|m| (a.keypoints[m.query].x, a.keypoints[m.query].y)).collect();
                let dst: Vec<(f32, f32)> =
                    matches.iter().map(|m| (b.keypoints[m.train].x, b.keypoints[m.train].y)).collect();
                let correct = src
                    .iter()
                    .zip(&dst)
                    .filter(|(p, q)| {
                        apply(h, p.0 as f64, p.1 as f64)
                            .is_some_and(|(x, y)| (x - q.0 as f64).hypot(y - q.1 as f64) <= cfg.correct_px)
                    })
                    .count();
                let corner_error_px = match fit_homography(&src, &dst, cfg.ransac_px)? {
                    Some(est) => corner_error(&est, h, a.width, a.height),
                    None => f64::INFINITY,
                };
                records.push(HomographyPair {
                    method,
                    sequence: seq.name.clone(),
                    image: i + 2,
                    zoom: geometry[i].0,
                    rotation_deg: geometry[i].1,
                    matches: matches.len(),
                    correct,
                    corner_error_px,
                    neighbour_share: if uses_project_keypoints(method) { shares[i] } else { None },
                    match_seconds,
                });
            }
        }
    }
    let ms = |m: Method| {
        let s = describe_seconds.get(&m).map(Vec::as_slice).unwrap_or(&[]);
        1e3 * s.iter().sum::<f64>() / s.len().max(1) as f64
    };
    let all: Vec<&HomographyPair> = records.iter().collect();
    let summaries = cfg.methods.iter().map(|&m| summarise(m, &all, ms(m))).collect();
    let mut bins = Vec::new();
    for (axis, key, lower, edges) in
        [("zoom", zoom_bin as fn(f64) -> String, 1.0, &ZOOM_EDGES), ("rotation", rotation_bin, 0.0, &ROTATION_EDGES)]
    {
        let value = |p: &HomographyPair| if axis == "zoom" { p.zoom } else { p.rotation_deg };
        let labels = bin_labels(records.iter().map(value), key, lower, edges);
        for label in labels {
            let inside: Vec<&HomographyPair> = records.iter().filter(|p| key(value(p)) == label).collect();
            bins.push(HomographyBin {
                axis: axis.to_string(),
                label,
                summaries: cfg.methods.iter().map(|&m| summarise(m, &inside, ms(m))).collect(),
            });
        }
    }
    Ok(HomographyReport {
        config: cfg.clone(),
        sequences: sequences.iter().map(|s| s.name.clone()).collect(),
        summaries,
        bins,
        pairs: records,
        rule_shares,
    })
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| format!("{x:.digits$}")).unwrap_or_else(|| "-".into())
}

/// The summaries and the bins as markdown.
pub fn markdown(report: &HomographyReport) -> String {
    let c = &report.config;
    let mut s = format!(
        "{} sequences, {} pairs per method; ratio {}, same-corner radius {} px, SConE matcher {}, MAGSAC++ {} px, correct within {} px\n\n",
        report.sequences.len(),
        report.summaries.first().map(|m| m.pairs).unwrap_or(0),
        c.ratio,
        c.same_corner_px,
        c.scone_matcher.name(),
        c.ransac_px,
        c.correct_px
    );
    let headers = [
        "method",
        "within 3 px",
        "within 5 px",
        "within 10 px",
        "MMA@3",
        "correct",
        "matches",
        "median corner error px",
        "neighbour share",
        "describe ms",
    ];
    s.push_str(&markdown_table(
        &headers,
        report.summaries.iter().map(|m| {
            vec![
                m.method.name().to_string(),
                format!("{:.3}", m.within[0]),
                format!("{:.3}", m.within[1]),
                format!("{:.3}", m.within[2]),
                format!("{:.3}", m.mma),
                format!("{:.1}", m.mean_correct),
                format!("{:.1}", m.mean_matches),
                opt(m.median_corner_error_px, 2),
                opt(m.mean_neighbour_share, 3),
                format!("{:.1}", m.describe_ms),
            ]
        }),
    ));
    for axis in ["zoom", "rotation"] {
        s.push_str(&format!("\nBy {axis} (within 5 px / correct matches / MMA@3; pairs per bin):\n\n"));
        let mut headers: Vec<String> = vec![axis.to_string(), "pairs".into(), "neighbour share".into()];
        headers.extend(report.summaries.iter().map(|m| m.method.name().to_string()));
        let hs: Vec<&str> = headers.iter().map(String::as_str).collect();
        s.push_str(&markdown_table(
            &hs,
            report.bins.iter().filter(|b| b.axis == axis).map(|b| {
                let share = b.summaries.iter().find_map(|m| m.mean_neighbour_share);
                let mut row =
                    vec![b.label.clone(), b.summaries.first().map(|m| m.pairs).unwrap_or(0).to_string(), opt(share, 3)];
                row.extend(
                    b.summaries.iter().map(|m| format!("{:.2} / {:.0} / {:.2}", m.within[1], m.mean_correct, m.mma)),
                );
                row
            }),
        ));
    }
    if !report.rule_shares.is_empty() {
        s.push_str("\nNeighbour share by rule (mean over the pairs of each bin; the last column: all pairs):\n\n");
        let zooms = bin_labels(report.rule_shares.iter().map(|r| r.zoom), zoom_bin, 1.0, &ZOOM_EDGES);
        let rots = bin_labels(report.rule_shares.iter().map(|r| r.rotation_deg), rotation_bin, 0.0, &ROTATION_EDGES);
        let mut headers: Vec<String> = vec!["rule".into()];
        headers.extend(zooms.iter().cloned());
        headers.extend(rots.iter().cloned());
        headers.push("all".into());
        let hs: Vec<&str> = headers.iter().map(String::as_str).collect();
        let mean = |f: &dyn Fn(&RuleShare) -> bool| {
            let v: Vec<f64> = report.rule_shares.iter().filter(|r| f(r)).filter_map(|r| r.share).collect();
            if v.is_empty() {
                "-".to_string()
            } else {
                format!("{:.3}", v.iter().sum::<f64>() / v.len() as f64)
            }
        };
        s.push_str(&markdown_table(
            &hs,
            report.config.neighbour_rules.iter().map(|&rule| {
                let mut row = vec![format!("{rule:?}")];
                row.extend(zooms.iter().map(|l| mean(&|r| r.rule == rule && zoom_bin(r.zoom) == *l)));
                row.extend(rots.iter().map(|l| mean(&|r| r.rule == rule && rotation_bin(r.rotation_deg) == *l)));
                row.push(mean(&|r| r.rule == rule));
                row
            }),
        ));
    }
    s
}

/// The labels of the bins (lower end `lower`, upper edges `edges`) that `values` fall in, in the bins' order.
fn bin_labels(values: impl Iterator<Item = f64>, key: fn(f64) -> String, lower: f64, edges: &[f64]) -> Vec<String> {
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

#[cfg(test)]
mod tests {
    use super::*;

    fn similarity(zoom: f64, deg: f64, tx: f64, ty: f64) -> Matrix3<f64> {
        let (s, c) = deg.to_radians().sin_cos();
        Matrix3::new(zoom * c, -zoom * s, tx, zoom * s, zoom * c, ty, 0.0, 0.0, 1.0)
    }

    #[test]
    fn zoom_and_rotation_of_a_similarity() {
        for (z, r) in [(1.0, 0.0), (2.0, 30.0), (0.5, -120.0), (2.7, 179.0)] {
            let (zoom, rot) = local_zoom_rotation(&similarity(z, r, 10.0, -5.0), 100.0, 50.0);
            assert!((zoom - z.max(1.0 / z)).abs() < 1e-6, "{z}: {zoom}");
            assert!((rot - r.abs()).abs() < 1e-6, "{r}: {rot}");
        }
    }

    #[test]
    fn corner_error_is_zero_for_the_truth_and_grows_with_a_shift() {
        let h = similarity(1.5, 20.0, 3.0, 4.0);
        assert!(corner_error(&h, &h, 640, 480) < 1e-9);
        let shifted = Matrix3::new(1.0, 0.0, 2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0) * h;
        assert!((corner_error(&shifted, &h, 640, 480) - 2.0).abs() < 1e-9);
    }

    #[test]
    fn bins_cover_the_range() {
        assert_eq!(zoom_bin(1.0), "1-1.25x");
        assert_eq!(zoom_bin(1.3), "1.25-1.6x");
        assert_eq!(zoom_bin(2.49), "2-2.5x");
        assert_eq!(zoom_bin(3.2), ">= 3x");
        assert_eq!(rotation_bin(0.0), "0-15deg");
        assert_eq!(rotation_bin(100.0), "90-135deg");
        assert_eq!(rotation_bin(180.0), "135-180deg");
    }

    #[test]
    fn a_fitted_homography_recovers_an_exact_warp() {
        let h = similarity(1.8, 60.0, 300.0, -40.0);
        let src: Vec<(f32, f32)> =
            (0..60).map(|i| ((i * 37 % 600) as f32 + 10.0, (i * 53 % 440) as f32 + 10.0)).collect();
        let dst: Vec<(f32, f32)> = src
            .iter()
            .map(|p| {
                let (x, y) = apply(&h, p.0 as f64, p.1 as f64).unwrap();
                (x as f32, y as f32)
            })
            .collect();
        let est = fit_homography(&src, &dst, 3.0).unwrap().expect("a homography");
        assert!(corner_error(&est, &h, 640, 480) < 0.5);
        assert!(fit_homography(&src[..3], &dst[..3], 3.0).unwrap().is_none());
    }

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }
    }

    /// Under an exact similarity every constellation survives (share 1); shifting half of image 2's other
    /// keypoints away brings it down.
    #[test]
    fn neighbour_share_follows_what_moves() {
        // A jittered grid: no two distances tie, so the nearest-first order is the same in both images.
        let jitter = |i: usize, m: usize| ((i * m * 7919) % 1000) as f32 / 1000.0 * 9.0;
        let a: Vec<Keypoint> = (0..100)
            .map(|i| kp(20.0 + (i % 10) as f32 * 23.0 + jitter(i, 3), 20.0 + (i / 10) as f32 * 19.0 + jitter(i, 5)))
            .collect();
        let h = similarity(1.3, 40.0, 200.0, 10.0);
        let b: Vec<Keypoint> = a
            .iter()
            .map(|k| {
                let (x, y) = apply(&h, k.x as f64, k.y as f64).unwrap();
                kp(x as f32, y as f32)
            })
            .collect();
        let (ca, cb) = (constellation::build(&a, 8), constellation::build(&b, 8));
        let (share, n) = neighbour_share(&a, &ca, &b, &cb, &h, 3.0).unwrap();
        assert_eq!(n, 100);
        assert!((share - 1.0).abs() < 1e-9, "{share}");
        let mut moved = b.clone();
        for (i, k) in moved.iter_mut().enumerate() {
            if i % 2 == 1 {
                k.x += 1000.0;
            }
        }
        let cm = constellation::build(&moved, 8);
        let (share, _) = neighbour_share(&a, &ca, &moved, &cm, &h, 3.0).unwrap();
        assert!(share < 0.8, "{share}");
    }

    #[test]
    fn a_sequence_loads_and_bad_files_are_named() {
        let dir = crate::test_dir::temp_dir("homography-seq");
        let img = opencv::core::Mat::new_rows_cols_with_default(48, 64, opencv::core::CV_8UC1, 128.into()).unwrap();
        let mut png = opencv::core::Vector::<u8>::new();
        opencv::imgcodecs::imencode(".png", &img, &mut png, &opencv::core::Vector::new()).unwrap();
        std::fs::write(dir.join("1.png"), png.as_slice()).unwrap();
        std::fs::write(dir.join("2.png"), png.as_slice()).unwrap();
        std::fs::write(dir.join("H_1_2"), "1 0 0\n0 1 0\n0 0 1\n").unwrap();
        let s = Sequence::load(&dir).unwrap();
        assert_eq!((s.images.len(), s.homographies.len()), (2, 1));
        std::fs::write(dir.join("H_1_2"), "1 0 0 0 1 0 0 0\n").unwrap();
        let e = Sequence::load(&dir).unwrap_err().to_string();
        assert!(e.contains("H_1_2") && e.contains("9 finite numbers"), "{e}");
        std::fs::write(dir.join("H_1_2"), "0 0 0 0 0 0 0 0 0\n").unwrap();
        assert!(Sequence::load(&dir).unwrap_err().to_string().contains("singular"));
    }
}
