//! Descriptor matching: nearest neighbour with Lowe's ratio test and an optional mutual check.

use opencv::core::{DMatch, Mat, Vector, NORM_HAMMING, NORM_L2};
use opencv::features2d::BFMatcher;
use opencv::prelude::*;

use crate::error::FeatureError;
use crate::features::Features;

/// A putative correspondence: keypoint `query` of the first image, keypoint `train` of the second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub query: usize,
    pub train: usize,
    pub distance: f32,
}

/// Nearest neighbours of `a`'s rows in `b` with OpenCV's brute-force matcher, ratio test and optional mutual check.
pub fn match_descriptors(a: &Mat, b: &Mat, norm: i32, ratio: f32, mutual: bool) -> Result<Vec<Match>, FeatureError> {
    if a.rows() < 1 || b.rows() < 2 {
        return Ok(Vec::new());
    }
    let matcher = BFMatcher::new(norm, false)?;
    let mut knn = Vector::<Vector<DMatch>>::new();
    matcher.knn_train_match(a, b, &mut knn, 2, &Mat::default(), false)?;
    let reverse: Option<Vec<i32>> = if mutual {
        let mut best = Vector::<DMatch>::new();
        matcher.train_match(b, a, &mut best, &Mat::default())?;
        let mut rev = vec![-1; b.rows() as usize];
        for m in best.iter() {
            rev[m.query_idx as usize] = m.train_idx;
        }
        Some(rev)
    } else {
        None
    };
    let mut out = Vec::new();
    for pair in knn.iter() {
        if pair.len() < 2 {
            continue;
        }
        let (m0, m1) = (pair.get(0)?, pair.get(1)?);
        if m0.distance >= ratio * m1.distance {
            continue;
        }
        if let Some(rev) = &reverse {
            if rev[m0.train_idx as usize] != m0.query_idx {
                continue;
            }
        }
        out.push(Match { query: m0.query_idx as usize, train: m0.train_idx as usize, distance: m0.distance });
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

/// SConE matching: L2 nearest neighbour with ratio test (and mutual check) between two embedding sets.
pub fn match_l2(a: &[f32], b: &[f32], dim: usize, ratio: f32, mutual: bool) -> Result<Vec<Match>, FeatureError> {
    match_descriptors(&embedding_mat(a, dim)?, &embedding_mat(b, dim)?, NORM_L2, ratio, mutual)
}

/// FREAK matching by exact Hamming distance (OpenCV's brute-force matcher): for each descriptor of `a` its two
/// nearest in `b`; kept when `best < ratio * second`. With `mutual`, `b`'s nearest in `a` must be the query too.
pub fn match_hamming(a: &Features, b: &Features, ratio: f32, mutual: bool) -> Result<Vec<Match>, FeatureError> {
    match_descriptors(&a.descriptor_mat()?, &b.descriptor_mat()?, NORM_HAMMING, ratio, mutual)
}
