//! Descriptor matching: nearest neighbour with Lowe's ratio test and an optional mutual check.

use opencv::core::{DMatch, Mat, Vector, NORM_HAMMING};
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

/// FREAK matching by exact Hamming distance (OpenCV's brute-force matcher): for each descriptor of `a` its two
/// nearest in `b`; kept when `best < ratio * second`. With `mutual`, `b`'s nearest in `a` must be the query too.
pub fn match_hamming(a: &Features, b: &Features, ratio: f32, mutual: bool) -> Result<Vec<Match>, FeatureError> {
    if a.is_empty() || b.len() < 2 {
        return Ok(Vec::new());
    }
    let da = a.descriptor_mat()?;
    let db = b.descriptor_mat()?;
    let matcher = BFMatcher::new(NORM_HAMMING, false)?;
    let mut knn = Vector::<Vector<DMatch>>::new();
    matcher.knn_train_match(&da, &db, &mut knn, 2, &Mat::default(), false)?;
    let reverse = if mutual {
        let mut best = Vector::<DMatch>::new();
        matcher.train_match(&db, &da, &mut best, &Mat::default())?;
        Some(
            best.iter()
                .map(|m| m.query_idx as usize)
                .zip(best.iter().map(|m| m.train_idx as usize))
                .collect::<std::collections::HashMap<_, _>>(),
        )
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
        let (q, t) = (m0.query_idx as usize, m0.train_idx as usize);
        if let Some(rev) = &reverse {
            if rev.get(&t) != Some(&q) {
                continue;
            }
        }
        out.push(Match { query: q, train: t, distance: m0.distance });
    }
    Ok(out)
}
