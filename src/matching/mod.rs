//! Descriptor matching: nearest neighbour with Lowe's ratio test and an optional mutual check.
//!
//! The ratio test compares the nearest descriptor with the nearest *competitor*. With OpenCV's plain test
//! (`same_corner_px = 0`) the competitor is the second-nearest descriptor. On a pyramid detector that is often
//! the same corner found again on another level, a pixel or two away: on castle-P30 the project's extractor
//! gives 1,140 keypoint pairs within 2 px per frame of 1,500 keypoints. Such a pair is not an ambiguity, and a
//! match to either is correct, so with `same_corner_px > 0` candidates whose keypoint lies within that radius of
//! the nearest one's are skipped and the ratio is taken against the nearest candidate beyond it. SConE is
//! trained on the same rule: keypoints within 2 px of the positive are not negatives (`exclude_px`).
//!
//! The neighbours themselves come from [`nearest`]: brute force in both directions from one distance matrix
//! (the mutual check), OpenCV's answer to the bit.

use opencv::core::{DMatch, Mat, Vector, NORM_HAMMING, NORM_L2};
use opencv::features2d::BFMatcher;
use opencv::prelude::*;

use crate::describe::features::{Features, DESCRIPTOR_BYTES};
use crate::error::FeatureError;
use crate::matching::nearest::nearest_both_ways;

pub mod nearest;

/// A putative correspondence: keypoint `query` of the first image, keypoint `train` of the second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub query: usize,
    pub train: usize,
    pub distance: f32,
}

/// The project's default radius for [`RatioTest::same_corner_px`]: the training loss's `exclude_px`.
pub const SAME_CORNER_PX: f32 = 2.0;

/// Lowe's ratio threshold the project uses wherever a caller does not choose one (pairs, map building,
/// relocalisation, the evaluation).
pub const DEFAULT_RATIO: f32 = 0.8;

/// Whether `ratio` is a usable ratio-test threshold: in (0, 1] (NaN is not).
pub fn is_ratio(ratio: f32) -> bool {
    ratio > 0.0 && ratio <= 1.0
}

/// Candidates examined for a competitor beyond the same-corner radius. FAST's non-maximum suppression leaves
/// a corner about one keypoint per pyramid level, so 10 covers the default eight levels with room to spare; when
/// all of them are the same corner the last one's distance stands in, which can only make the test stricter.
const SAME_CORNER_CANDIDATES: i32 = 10;

/// Lowe's ratio test and the checks around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RatioTest {
    /// A match is kept when `nearest < ratio * competitor`.
    pub ratio: f32,
    /// The nearest neighbour of the match's keypoint in `b`, searched back in `a`, must be the query.
    pub mutual: bool,
    /// Candidates whose keypoint lies within this many pixels of the nearest neighbour's are the same corner
    /// and not competitors (see the module docs); 0 = OpenCV's plain ratio test.
    pub same_corner_px: f32,
}

impl RatioTest {
    /// OpenCV's plain ratio test (the second-nearest descriptor is the competitor), no mutual check.
    pub fn plain(ratio: f32) -> Self {
        Self { ratio, mutual: false, same_corner_px: 0.0 }
    }

    /// The project's default: ratio `ratio`, no mutual check, same-corner radius [`SAME_CORNER_PX`].
    pub fn new(ratio: f32) -> Self {
        Self { ratio, mutual: false, same_corner_px: SAME_CORNER_PX }
    }
}

/// The ratio test's competitor among `cands` (distance, keypoint of `b`), nearest first, at least two: the
/// second candidate, or with `same_corner_px > 0` the nearest whose keypoint lies beyond that radius of the
/// nearest one's; when all are the same corner, the last one's distance stands in.
fn competitor(cands: &[(f32, usize)], b_points: &[(f32, f32)], same_corner_px: f32) -> f32 {
    if same_corner_px <= 0.0 {
        return cands[1].0;
    }
    let r2 = same_corner_px * same_corner_px;
    let p0 = b_points[cands[0].1];
    cands
        .iter()
        .skip(1)
        .find(|(_, t)| {
            let p = b_points[*t];
            (p.0 - p0.0).powi(2) + (p.1 - p0.1).powi(2) > r2
        })
        .map_or(cands[cands.len() - 1].0, |c| c.0)
}

/// A query's nearest candidate when it passes the ratio test against its competitor (`row`: the query's
/// candidates nearest first, as (train row, distance); `cands` is scratch space).
fn ratio_winner(
    query: usize,
    row: impl IntoIterator<Item = (usize, f32)>,
    cands: &mut Vec<(f32, usize)>,
    b_points: &[(f32, f32)],
    test: &RatioTest,
) -> Option<Match> {
    cands.clear();
    cands.extend(row.into_iter().map(|(t, d)| (d, t)));
    if cands.len() < 2 {
        return None;
    }
    let (distance, train) = cands[0];
    (distance < test.ratio * competitor(cands, b_points, test.same_corner_px)).then_some(Match {
        query,
        train,
        distance,
    })
}

/// An OpenCV match as (train row, distance), the form [`ratio_winner`] reads.
pub(crate) fn train_and_distance(m: DMatch) -> (usize, f32) {
    (m.train_idx as usize, m.distance)
}

/// Nearest neighbours of `a`'s rows in `b` with OpenCV's brute-force matcher, ratio test and optional mutual
/// check. `b_points` are the pixel positions of `b`'s rows; they are read only when `test.same_corner_px > 0`.
pub fn match_descriptors(
    a: &Mat,
    b: &Mat,
    norm: i32,
    test: &RatioTest,
    b_points: &[(f32, f32)],
) -> Result<Vec<Match>, FeatureError> {
    match_descriptors_masked(a, b, norm, test, b_points, &Mat::default())
}

/// [`match_descriptors`] where only the pairs `mask` admits compete (`a.rows() x b.rows()`, `CV_8U`, nonzero =
/// admitted; empty admits all): a ratio test among the admitted candidates, and a mutual check among them too.
pub fn match_descriptors_masked(
    a: &Mat,
    b: &Mat,
    norm: i32,
    test: &RatioTest,
    b_points: &[(f32, f32)],
    mask: &Mat,
) -> Result<Vec<Match>, FeatureError> {
    if a.rows() < 1 || b.rows() < 2 {
        return Ok(Vec::new());
    }
    let same_corner = test.same_corner_px > 0.0;
    if same_corner && b_points.len() != b.rows() as usize {
        return Err(FeatureError::OpenCv(opencv::Error::new(
            opencv::core::StsBadArg,
            format!("{} keypoint positions for {} descriptors", b_points.len(), b.rows()),
        )));
    }
    let k = if same_corner { SAME_CORNER_CANDIDATES } else { 2 };
    let mut cands: Vec<(f32, usize)> = Vec::with_capacity(k as usize);
    if test.mutual {
        // Both directions from one distance matrix.
        let both = nearest_both_ways(a, b, norm, k as usize, mask)?;
        let winners = both
            .forward
            .iter()
            .enumerate()
            .filter_map(|(q, row)| ratio_winner(q, row.iter().copied(), &mut cands, b_points, test));
        return Ok(winners.filter(|m| both.back[m.train] == Some(m.query)).collect());
    }
    let mut knn = Vector::<Vector<DMatch>>::new();
    BFMatcher::new(norm, false)?.knn_train_match(a, b, &mut knn, k, mask, false)?;
    let winners = knn
        .iter()
        .enumerate()
        .filter_map(|(q, row)| ratio_winner(q, row.iter().map(train_and_distance), &mut cands, b_points, test));
    Ok(winners.collect())
}

/// How SConE picks its matches between two frames. Every variant runs on the same keypoints, and the two that
/// combine SConE with FREAK read the FREAK descriptors those keypoints already carry (no second extraction).
/// The default, used by MatchPair and `scone eval pairs` alike, was chosen on the selection split under a rule
/// fixed before scoring (docs/model-experiments.md): rerank on real pairs (+0.015 mean AUC@10 over plain,
/// union -0.004), then scale-aware for zoom (rerank, with union where the images differ by a zoom of 1.6 or
/// more: the same AUC on the real selection pairs, 0.575 against 0.250 of the zoomed warps within 5 px).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum SconeMatcher {
    /// The SConE embedding alone: L2 nearest neighbour with the ratio test.
    Plain,
    /// SConE's ratio-test matches, plus FREAK's (Hamming, the same test) for the keypoints SConE left
    /// unmatched. SConE keeps its precision where it answers; FREAK adds the spread-out survivors it has more of.
    Union,
    /// Every SConE ratio-test match and every FREAK ratio-test match (the same test), each pair of keypoints
    /// once. A keypoint the two answer differently keeps both candidates and the pose's robust estimate
    /// decides, so no match FREAK finds is lost because SConE answered otherwise
    /// (docs/model-experiments.md, "every match of both"). Inliers count matches: with both answers on the
    /// epipolar line, or one corner found on two pyramid levels, a keypoint counts twice.
    Both,
    /// FREAK's [`RERANK_CANDIDATES`] nearest descriptors of each keypoint, re-ordered by SConE distance; the
    /// ratio test runs on the SConE distances of those candidates.
    Rerank,
    /// [`SconeMatcher::Rerank`], unless the two images differ in scale by [`SCALE_AWARE_ZOOM`] or more (the
    /// median size ratio of FREAK's ratio-test matches, at least [`SCALE_AWARE_MIN_MATCHES`] of them); then
    /// [`SconeMatcher::Union`]. Under such a zoom the constellations share fewer than half their members
    /// (`scone eval homography`'s neighbour share), so FREAK answers where SConE cannot. The default, chosen
    /// on the selection split (docs/model-experiments.md, "the matcher under zoom").
    #[default]
    ScaleAware,
    /// One descriptor of both: each keypoint's unit embedding followed by its FREAK bits as ±1/√512. The
    /// squared distance is |Δe|² + 4·Hamming/512, each part over [0, 4], so every match is judged on both
    /// descriptors with equal weight. The ratio applies to that squared distance, as FREAK's does to Hamming
    /// (itself a squared distance of the bits): 0.8 there is 0.894 on the L2 distance
    /// (docs/model-experiments.md, "the joint descriptor's test in FREAK's unit"). A frame without FREAK bits
    /// for every keypoint is matched by the embedding alone, with the ratio as given.
    Joint,
    /// FREAK descriptors alone (Hamming nearest neighbour, the same ratio test): the baseline SConE is
    /// compared with, so that a client or the console can put the two side by side on the same keypoints.
    Freak,
}

impl SconeMatcher {
    /// The matcher a model declares (`scone.matcher` in its metadata, `crate::describe::embedding`); a model that
    /// declares none ships with `scale-aware`, the default of the models made before they declared one.
    pub fn declared(name: Option<&str>) -> Result<Self, String> {
        match name {
            None => Ok(Self::default()),
            Some(n) => <Self as clap::ValueEnum>::from_str(n, false).map_err(|_| {
                format!("metadata 'scone.matcher' names no matcher: '{n}' (plain, union, both, rerank, scale-aware, joint, freak)")
            }),
        }
    }

    pub fn name(&self) -> &'static str {
        match self {
            SconeMatcher::Plain => "plain",
            SconeMatcher::Union => "union",
            SconeMatcher::Both => "both",
            SconeMatcher::Rerank => "rerank",
            SconeMatcher::ScaleAware => "scale-aware",
            SconeMatcher::Joint => "joint",
            SconeMatcher::Freak => "freak",
        }
    }
}

/// FREAK candidates per keypoint that [`SconeMatcher::Rerank`] re-orders.
pub const RERANK_CANDIDATES: i32 = 10;

/// The zoom between two images from which [`SconeMatcher::ScaleAware`] falls back on FREAK.
pub const SCALE_AWARE_ZOOM: f32 = 1.6;
/// FREAK matches [`SconeMatcher::ScaleAware`] needs to estimate the zoom; with fewer it re-ranks.
pub const SCALE_AWARE_MIN_MATCHES: usize = 10;

/// One frame as the SConE matchers see it: `[N, dim]` embeddings, FREAK descriptors (`[N, 64]` u8),
/// keypoint positions and sizes, all of the same N keypoints.
pub struct SconeFrame<'a> {
    pub embeddings: &'a [f32],
    pub dim: usize,
    pub freak: &'a Mat,
    pub points: &'a [(f32, f32)],
    /// Keypoint sizes (diameters, pixels); [`SconeMatcher::ScaleAware`] reads them.
    pub sizes: &'a [f32],
}

/// The zoom between `a` and `b` (>= 1, either way) from the median size ratio of `matches`; None with fewer
/// than [`SCALE_AWARE_MIN_MATCHES`].
pub fn pair_zoom(a_sizes: &[f32], b_sizes: &[f32], matches: &[Match]) -> Option<f32> {
    let mut logs: Vec<f32> = matches
        .iter()
        .filter_map(|m| {
            let (sa, sb) = (*a_sizes.get(m.query)?, *b_sizes.get(m.train)?);
            (sa > 0.0 && sb > 0.0).then(|| (sb / sa).ln())
        })
        .collect();
    if logs.len() < SCALE_AWARE_MIN_MATCHES {
        return None;
    }
    let mid = logs.len() / 2;
    let (_, median, _) = logs.select_nth_unstable_by(mid, f32::total_cmp);
    Some(median.abs().exp())
}

/// SConE matches of `a`'s keypoints in `b` by `matcher`.
pub fn match_scone(
    matcher: SconeMatcher,
    a: &SconeFrame,
    b: &SconeFrame,
    test: &RatioTest,
) -> Result<Vec<Match>, FeatureError> {
    match_scone_with(matcher, a, b, test, test)
}

/// [`match_scone`] with the embedding held to its own ratio test, `embedding`, in the fused matchers
/// ([`SconeMatcher::Union`], [`SconeMatcher::Both`]); FREAK's matches there, and every other matcher, keep
/// `test`.
pub fn match_scone_with(
    matcher: SconeMatcher,
    a: &SconeFrame,
    b: &SconeFrame,
    test: &RatioTest,
    embedding: &RatioTest,
) -> Result<Vec<Match>, FeatureError> {
    match matcher {
        SconeMatcher::Plain => match_l2(a.embeddings, b.embeddings, a.dim, test, b.points),
        SconeMatcher::Union => {
            let freak = match_descriptors(a.freak, b.freak, NORM_HAMMING, test, b.points)?;
            union(a, b, embedding, freak)
        }
        SconeMatcher::Both => {
            let freak = match_descriptors(a.freak, b.freak, NORM_HAMMING, test, b.points)?;
            both(a, b, embedding, freak)
        }
        SconeMatcher::Rerank => rerank(a, b, test),
        SconeMatcher::ScaleAware => {
            // One FREAK search serves both the zoom estimate and the re-ranking.
            let knn = freak_knn(a, b)?;
            let freak = freak_ratio_matches(&knn, a, b, test)?;
            match pair_zoom(a.sizes, b.sizes, &freak) {
                Some(zoom) if zoom >= SCALE_AWARE_ZOOM => union(a, b, test, freak),
                _ => rerank_knn(&knn, a, b, test),
            }
        }
        SconeMatcher::Joint => match (joint_rows(a)?, joint_rows(b)?) {
            (Some(ja), Some(jb)) => {
                let squared = RatioTest { ratio: test.ratio.sqrt(), ..*test };
                match_descriptors(&ja, &jb, NORM_L2, &squared, b.points)
            }
            _ => match_l2(a.embeddings, b.embeddings, a.dim, test, b.points),
        },
        SconeMatcher::Freak => match_descriptors(a.freak, b.freak, NORM_HAMMING, test, b.points),
    }
}

/// [`SconeMatcher::Joint`]'s descriptors of a frame: per keypoint its embedding, then its FREAK bits as
/// ±1/√512 (least significant bit of each byte first); `None` when the frame lacks bits for some keypoint.
fn joint_rows(f: &SconeFrame) -> Result<Option<Mat>, FeatureError> {
    let n = f.points.len();
    let bytes = DESCRIPTOR_BYTES;
    if n == 0 || f.freak.rows() as usize != n || f.freak.cols() as usize != bytes || f.embeddings.len() != n * f.dim {
        return Ok(None);
    }
    let bits = f.freak.data_bytes()?;
    let w = ((bytes * 8) as f32).sqrt().recip();
    let width = f.dim + bytes * 8;
    let mut rows = Vec::with_capacity(n * width);
    for (e, d) in f.embeddings.chunks_exact(f.dim).zip(bits.chunks_exact(bytes)) {
        rows.extend_from_slice(e);
        rows.extend(d.iter().flat_map(|&byte| (0..8).map(move |k| if byte >> k & 1 == 1 { w } else { -w })));
    }
    Ok(Some(embedding_mat(&rows, width)?))
}

/// SConE's ratio-test matches, plus `freak`'s for the keypoints SConE left unmatched.
fn union(a: &SconeFrame, b: &SconeFrame, test: &RatioTest, freak: Vec<Match>) -> Result<Vec<Match>, FeatureError> {
    let mut out = match_l2(a.embeddings, b.embeddings, a.dim, test, b.points)?;
    let mut answered = vec![false; a.points.len()];
    for m in &out {
        answered[m.query] = true;
    }
    out.extend(freak.into_iter().filter(|m| !answered[m.query]));
    Ok(out)
}

/// SConE's ratio-test matches, plus every one of `freak`'s that SConE did not also find.
fn both(a: &SconeFrame, b: &SconeFrame, test: &RatioTest, freak: Vec<Match>) -> Result<Vec<Match>, FeatureError> {
    let mut out = match_l2(a.embeddings, b.embeddings, a.dim, test, b.points)?;
    let found: std::collections::HashSet<(usize, usize)> = out.iter().map(|m| (m.query, m.train)).collect();
    out.extend(freak.into_iter().filter(|m| !found.contains(&(m.query, m.train))));
    Ok(out)
}

fn l2(x: &[f32], y: &[f32]) -> f32 {
    x.iter().zip(y).map(|(p, q)| (p - q) * (p - q)).sum::<f32>().sqrt()
}

/// FREAK's [`RERANK_CANDIDATES`] nearest descriptors in `b` of each of `a`'s keypoints (empty when either frame
/// has too few keypoints to rank).
fn freak_knn(a: &SconeFrame, b: &SconeFrame) -> Result<Vector<Vector<DMatch>>, FeatureError> {
    let mut knn = Vector::<Vector<DMatch>>::new();
    if a.freak.rows() >= 1 && b.freak.rows() >= 2 {
        BFMatcher::new(NORM_HAMMING, false)?.knn_train_match(
            a.freak,
            b.freak,
            &mut knn,
            RERANK_CANDIDATES,
            &Mat::default(),
            false,
        )?;
    }
    Ok(knn)
}

/// FREAK's ratio-test matches read from `knn` (the same answer as [`match_descriptors`] on Hamming distance,
/// whose same-corner search also looks at [`SAME_CORNER_CANDIDATES`] = [`RERANK_CANDIDATES`] candidates);
/// with the mutual check, the full search runs instead.
fn freak_ratio_matches(
    knn: &Vector<Vector<DMatch>>,
    a: &SconeFrame,
    b: &SconeFrame,
    test: &RatioTest,
) -> Result<Vec<Match>, FeatureError> {
    if test.mutual || (test.same_corner_px > 0.0 && RERANK_CANDIDATES != SAME_CORNER_CANDIDATES) {
        return match_descriptors(a.freak, b.freak, NORM_HAMMING, test, b.points);
    }
    let mut out = Vec::new();
    let mut cands: Vec<(f32, usize)> = Vec::with_capacity(RERANK_CANDIDATES as usize);
    for (q, row) in knn.iter().enumerate() {
        out.extend(ratio_winner(q, row.iter().map(train_and_distance), &mut cands, b.points, test));
    }
    Ok(out)
}

fn rerank(a: &SconeFrame, b: &SconeFrame, test: &RatioTest) -> Result<Vec<Match>, FeatureError> {
    rerank_knn(&freak_knn(a, b)?, a, b, test)
}

/// [`SconeMatcher::Rerank`] on FREAK candidates already found.
fn rerank_knn(
    knn: &Vector<Vector<DMatch>>,
    a: &SconeFrame,
    b: &SconeFrame,
    test: &RatioTest,
) -> Result<Vec<Match>, FeatureError> {
    let dim = a.dim;
    let mut out = Vec::new();
    let mut cand: Vec<(f32, usize)> = Vec::with_capacity(RERANK_CANDIDATES as usize);
    for row in knn.iter() {
        if row.len() < 2 {
            continue;
        }
        let q = row.get(0)?.query_idx as usize;
        let ea = &a.embeddings[q * dim..(q + 1) * dim];
        cand.clear();
        for m in row.iter() {
            let t = m.train_idx as usize;
            cand.push((l2(ea, &b.embeddings[t * dim..(t + 1) * dim]), t));
        }
        cand.sort_by(|x, y| x.0.total_cmp(&y.0));
        let (d0, t0) = cand[0];
        if d0 < test.ratio * competitor(&cand, b.points, test.same_corner_px) {
            out.push(Match { query: q, train: t0, distance: d0 });
        }
    }
    if test.mutual {
        // Mutual check on the re-ranked answers: keep a match only if no other query chose the same keypoint
        // at a smaller distance.
        let mut best: std::collections::HashMap<usize, f32> = std::collections::HashMap::new();
        for m in &out {
            let e = best.entry(m.train).or_insert(f32::INFINITY);
            *e = e.min(m.distance);
        }
        out.retain(|m| best[&m.train] == m.distance);
    }
    Ok(out)
}

/// Embedding rows (`[N, dim]`, row-major) as an OpenCV f32 matrix.
pub fn embedding_mat(rows: &[f32], dim: usize) -> Result<Mat, FeatureError> {
    if rows.is_empty() {
        return Ok(Mat::default());
    }
    let m = Mat::new_rows_cols_with_data((rows.len() / dim) as i32, dim as i32, rows)?;
    Ok(m.try_clone()?)
}

/// SConE matching: L2 nearest neighbour with ratio test (and mutual check) between two embedding sets;
/// `b_points` are the keypoint positions of `b`'s rows.
pub fn match_l2(
    a: &[f32],
    b: &[f32],
    dim: usize,
    test: &RatioTest,
    b_points: &[(f32, f32)],
) -> Result<Vec<Match>, FeatureError> {
    match_descriptors(&embedding_mat(a, dim)?, &embedding_mat(b, dim)?, NORM_L2, test, b_points)
}

/// FREAK matching by exact Hamming distance (OpenCV's brute-force matcher) with `test`.
pub fn match_hamming(a: &Features, b: &Features, test: &RatioTest) -> Result<Vec<Match>, FeatureError> {
    match_descriptors(&a.descriptor_mat()?, &b.descriptor_mat()?, NORM_HAMMING, test, &b.points())
}

#[cfg(test)]
mod tests;
