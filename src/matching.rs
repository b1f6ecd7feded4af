//! Descriptor matching: nearest neighbour with Lowe's ratio test and an optional mutual check.
//!
//! The ratio test compares the nearest descriptor with the nearest *competitor*. With OpenCV's plain test
//! (`same_corner_px = 0`) the competitor is the second-nearest descriptor. On a pyramid detector that is often
//! the same corner found again on another level, a pixel or two away: on castle-P30 the project's extractor
//! gives 1,140 keypoint pairs within 2 px per frame of 1,500 keypoints. Such a pair is not an ambiguity, and a
//! match to either is correct, so with `same_corner_px > 0` candidates whose keypoint lies within that radius of
//! the nearest one's are skipped and the ratio is taken against the nearest candidate beyond it. SConE is
//! trained on the same rule: keypoints within 2 px of the positive are not negatives (`exclude_px`).

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

/// The project's default radius for [`RatioTest::same_corner_px`]: the training loss's `exclude_px`.
pub const SAME_CORNER_PX: f32 = 2.0;

/// Candidates examined for a competitor beyond the same-corner radius. FAST's non-maximum suppression leaves
/// a corner about one keypoint per pyramid level, so 10 covers the default six levels with room to spare; when
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

/// Nearest neighbours of `a`'s rows in `b` with OpenCV's brute-force matcher, ratio test and optional mutual
/// check. `b_points` are the pixel positions of `b`'s rows; they are read only when `test.same_corner_px > 0`.
pub fn match_descriptors(
    a: &Mat,
    b: &Mat,
    norm: i32,
    test: &RatioTest,
    b_points: &[(f32, f32)],
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
    let matcher = BFMatcher::new(norm, false)?;
    let mut knn = Vector::<Vector<DMatch>>::new();
    let k = if same_corner { SAME_CORNER_CANDIDATES } else { 2 };
    matcher.knn_train_match(a, b, &mut knn, k, &Mat::default(), false)?;
    let r2 = test.same_corner_px * test.same_corner_px;
    let reverse: Option<Vec<i32>> = if test.mutual {
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
        let m0 = pair.get(0)?;
        let competitor = if same_corner {
            let p0 = b_points[m0.train_idx as usize];
            let beyond = pair.iter().skip(1).find(|m| {
                let p = b_points[m.train_idx as usize];
                (p.0 - p0.0).powi(2) + (p.1 - p0.1).powi(2) > r2
            });
            match beyond {
                Some(m) => m.distance,
                None => pair.get(pair.len() - 1)?.distance,
            }
        } else {
            pair.get(1)?.distance
        };
        if m0.distance >= test.ratio * competitor {
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
mod tests {
    use super::*;

    /// One query; in `b` the true match (distance 1), its duplicate 1 px away (distance 1.1) and a distinct
    /// corner 50 px away (distance `far`).
    fn case(far: f32) -> (Vec<f32>, Vec<f32>, Vec<(f32, f32)>) {
        let a = vec![0.0, 0.0];
        let b = vec![1.0, 0.0, 0.0, 1.1, far, 0.0];
        (a, b, vec![(10.0, 10.0), (11.0, 10.0), (60.0, 10.0)])
    }

    #[test]
    fn plain_test_counts_a_duplicate_as_the_competitor() {
        let (a, b, pts) = case(3.0);
        assert!(match_l2(&a, &b, 2, &RatioTest::plain(0.8), &pts).unwrap().is_empty());
    }

    #[test]
    fn same_corner_test_looks_past_the_duplicate() {
        let (a, b, pts) = case(3.0);
        let m = match_l2(&a, &b, 2, &RatioTest::new(0.8), &pts).unwrap();
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].query, m[0].train), (0, 0));
        // A distinct corner nearly as close is still an ambiguity.
        let (a, b, pts) = case(1.2);
        assert!(match_l2(&a, &b, 2, &RatioTest::new(0.8), &pts).unwrap().is_empty());
        // The radius is a parameter: at 0.5 px the duplicate 1 px away competes again.
        let (a, b, pts) = case(3.0);
        let narrow = RatioTest { same_corner_px: 0.5, ..RatioTest::new(0.8) };
        assert!(match_l2(&a, &b, 2, &narrow, &pts).unwrap().is_empty());
    }

    #[test]
    fn all_candidates_one_corner_uses_the_last_distance() {
        // Only the match and its duplicate: the duplicate's distance stands in, as the plain test would use.
        let a = vec![0.0, 0.0];
        let b = vec![1.0, 0.0, 0.0, 1.1];
        let pts = vec![(10.0, 10.0), (11.0, 10.0)];
        assert!(match_l2(&a, &b, 2, &RatioTest::new(0.8), &pts).unwrap().is_empty());
        let b = vec![1.0, 0.0, 0.0, 2.0];
        assert_eq!(match_l2(&a, &b, 2, &RatioTest::new(0.8), &pts).unwrap().len(), 1);
    }

    #[test]
    fn positions_must_cover_every_row() {
        let (a, b, pts) = case(3.0);
        assert!(match_l2(&a, &b, 2, &RatioTest::new(0.8), &pts[..2]).is_err());
        assert!(match_l2(&a, &b, 2, &RatioTest::plain(0.8), &[]).is_ok());
    }
}
