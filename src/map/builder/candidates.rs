//! Steps 1 and 2 of map building (module docs): which earlier keyframes a new keyframe is matched against, and
//! its matches with each of them (the embedding's, within the epipolar window, joined by FREAK's).

use std::collections::HashSet;

use nalgebra::Vector3;
use opencv::core::{Mat, NORM_HAMMING, NORM_L2};
use opencv::prelude::*;
use rayon::prelude::*;

use crate::describe::features::{bits_mat, DESCRIPTOR_BYTES};
use crate::error::MapError;
use crate::map::builder::geometry::viewing_direction;
use crate::map::builder::input::KeyframeInput;
use crate::map::builder::settings::BuildSettings;
use crate::map::model::{Keyframe, MapData, MapKeyframe};
use crate::matching::{embedding_mat, match_descriptors_masked, Match, RatioTest};

/// Step 1: the `candidates` keyframes of `data` nearest to `input` that look the same way (viewing directions
/// less than 90 degrees apart), nearest first, then the `covisible_candidates` that share the most landmarks
/// with them.
pub(super) fn candidates<'d>(data: &'d MapData, input: &KeyframeInput, params: &BuildSettings) -> Vec<&'d MapKeyframe> {
    let centre = input.pose.translation.vector;
    let dir = viewing_direction(&input.pose);
    let mut candidates: Vec<&MapKeyframe> =
        data.keyframes.values().filter(|k| viewing_direction(&k.pose.isometry()).dot(&dir) > 0.0).collect();
    candidates.sort_by(|a, b| {
        let da = (a.pose.isometry().translation.vector - centre).norm();
        let db = (b.pose.isometry().translation.vector - centre).norm();
        da.total_cmp(&db).then(a.id.cmp(&b.id))
    });
    candidates.truncate(params.candidates);
    if params.covisible_candidates > 0 && !candidates.is_empty() {
        let near: HashSet<u64> = candidates.iter().map(|k| k.id).collect();
        let near_ids: Vec<u64> = near.iter().copied().collect();
        let shared = data.observations_of_keyframes(&near_ids).map(|o| o.landmark);
        let seeing =
            |k: u64| !near.contains(&k) && viewing_direction(&data.keyframes[&k].pose.isometry()).dot(&dir) > 0.0;
        let ranked = data.covisible_keyframes(shared, seeing, params.covisible_candidates);
        candidates.extend(ranked.iter().map(|k| &data.keyframes[k]));
    }
    candidates
}

/// Step 2's matching: the new keyframe's matches with each candidate, in the candidates' order. The matching is
/// most of a keyframe's cost and each candidate's is independent: it runs on rayon's threads.
pub(super) fn match_candidates(
    input: &KeyframeInput,
    candidates: &[&Keyframe],
    dim: usize,
    params: &BuildSettings,
) -> Result<Vec<Vec<Match>>, MapError> {
    candidates.par_iter().map(|cand| candidate_matches(input, cand, dim, params)).collect()
}

/// The new keyframe's matches with one candidate: the embedding's (OpenCV's plain ratio test with the mutual
/// check, with which the maps' figures were measured), within the epipolar window when it is on, joined by
/// FREAK's for the keypoints still unmatched when that is on.
fn candidate_matches(
    input: &KeyframeInput,
    cand: &Keyframe,
    dim: usize,
    params: &BuildSettings,
) -> Result<Vec<Match>, MapError> {
    let test = RatioTest { ratio: params.ratio, mutual: true, same_corner_px: 0.0 };
    let mask = if params.epipolar_px > 0.0 { epipolar_mask(input, cand, params.epipolar_px)? } else { Mat::default() };
    let a = embedding_mat(input.embeddings, dim)?;
    let b = embedding_mat(&cand.embeddings, dim)?;
    let mut matches = match_descriptors_masked(&a, &b, NORM_L2, &test, &[], &mask)?;
    let n = input.features.len();
    let bits =
        input.features.descriptors.len() == n && cand.descriptors.len() == cand.keypoints.len() * DESCRIPTOR_BYTES;
    if params.freak_matches && bits {
        let a = input.features.descriptor_mat()?;
        let b = bits_mat(&cand.descriptors)?;
        let (qs, ts): (HashSet<usize>, HashSet<usize>) =
            (matches.iter().map(|m| m.query).collect(), matches.iter().map(|m| m.train).collect());
        let freak = match_descriptors_masked(&a, &b, NORM_HAMMING, &test, &[], &mask)?;
        matches.extend(freak.into_iter().filter(|m| !qs.contains(&m.query) && !ts.contains(&m.train)));
    }
    Ok(matches)
}

/// `[new keypoints, candidate keypoints]` mask of the pairs whose candidate keypoint lies within `px` of the
/// epipolar line of the new keypoint (the fundamental matrix of the two known poses and intrinsics).
pub(super) fn epipolar_mask(input: &KeyframeInput, cand: &Keyframe, px: f64) -> Result<Mat, MapError> {
    let fe = crate::error::FeatureError::from;
    // Relative pose new -> candidate: x_c = R x_n + t.
    let rel = cand.pose.isometry().inverse() * input.pose;
    let (r, t) = (rel.rotation.to_rotation_matrix().into_inner(), rel.translation.vector);
    if t.norm() < 1e-9 {
        return Ok(Mat::default()); // the same centre: no epipolar geometry, every pair competes
    }
    let tx = nalgebra::Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0);
    let kn = nalgebra::Matrix3::from_row_slice(&input.camera.k().concat());
    let kc = nalgebra::Matrix3::from_row_slice(&cand.camera.k().concat());
    let (Some(kn_inv), Some(kc_inv)) = (kn.try_inverse(), kc.try_inverse()) else {
        return Ok(Mat::default());
    };
    let f = kc_inv.transpose() * tx * r * kn_inv;
    let (rows, cols) = (input.features.len(), cand.keypoints.len());
    let mut mask = vec![0u8; rows * cols];
    for (i, p) in input.features.keypoints.iter().enumerate() {
        let l = f * Vector3::new(f64::from(p.x), f64::from(p.y), 1.0);
        let norm = l.x.hypot(l.y);
        let row = &mut mask[i * cols..(i + 1) * cols];
        if norm < 1e-12 {
            row.fill(1); // the epipole: no line, every candidate keypoint competes
            continue;
        }
        for (m, q) in row.iter_mut().zip(&cand.keypoints) {
            let d = (l.x * f64::from(q.x) + l.y * f64::from(q.y) + l.z).abs() / norm;
            *m = u8::from(d <= px);
        }
    }
    Ok(Mat::new_rows_cols_with_data(rows as i32, cols as i32, &mask).map_err(fe)?.try_clone().map_err(fe)?)
}
