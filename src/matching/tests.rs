//! Matching by each descriptor and each SConE matcher on small hand-built frames: the ratio test's competitor,
//! the same-corner rule, and what union, both, joint, rerank and scale-aware keep.

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

/// Two frames of three keypoints far apart: SConE embeddings and FREAK bytes chosen per case.
fn frames(ea: Vec<f32>, eb: Vec<f32>, fa: [[u8; 64]; 3], fb: [[u8; 64]; 3]) -> (Vec<f32>, Vec<f32>, Mat, Mat) {
    let to_mat = |rows: [[u8; 64]; 3]| {
        let flat: Vec<u8> = rows.iter().flatten().copied().collect();
        Mat::new_rows_cols_with_data(3, 64, &flat).unwrap().try_clone().unwrap()
    };
    (ea, eb, to_mat(fa), to_mat(fb))
}

const PTS: [(f32, f32); 3] = [(10.0, 10.0), (100.0, 10.0), (10.0, 100.0)];

/// A FREAK descriptor whose first `bytes` bytes have every bit set (8 x `bytes` ones), the rest none.
fn ones(bytes: usize) -> [u8; 64] {
    let mut d = [0u8; 64];
    d[..bytes].fill(0xff);
    d
}

/// The (query, train) pairs, sorted, that `matcher` finds between three keypoints with SConE embeddings `ea` and
/// the fixed frame `b` below. FREAK: query 0 matches 1, query 1 clearly matches 1, query 2 is 128 bits from
/// both b1 and b2.
fn fused(ea: Vec<f32>, matcher: SconeMatcher) -> Vec<(usize, usize)> {
    fused_with(ea, matcher, 0.8)
}

/// [`fused`] with the embedding held to its own ratio `embedding_ratio` (FREAK's stays 0.8).
fn fused_with(ea: Vec<f32>, matcher: SconeMatcher, embedding_ratio: f32) -> Vec<(usize, usize)> {
    let eb = vec![0.0, 0.0, 5.0, 4.0, 5.0, 6.0];
    let (z, o, half, three_quarters) = (ones(0), ones(64), ones(32), ones(48));
    let (ea, eb, fa, fb) = frames(ea, eb, [o, o, three_quarters], [z, o, half]);
    let (a, b) = (
        SconeFrame { embeddings: &ea, dim: 2, freak: &fa, points: &PTS, sizes: &[] },
        SconeFrame { embeddings: &eb, dim: 2, freak: &fb, points: &PTS, sizes: &[] },
    );
    let (test, embedding) = (RatioTest::new(0.8), RatioTest::new(embedding_ratio));
    let mut got: Vec<_> =
        match_scone_with(matcher, &a, &b, &test, &embedding).unwrap().iter().map(|m| (m.query, m.train)).collect();
    got.sort_unstable();
    got
}

#[test]
fn the_embeddings_own_ratio_decides_its_matches_in_union_and_both_and_leaves_freaks_alone() {
    // Query 2's embedding is 0.92 from b1 and 1.08 from b2 (ratio 0.85): no SConE match at 0.8, one at 0.9.
    // FREAK finds query 2 nothing (128 bits from both) whatever the embedding's ratio.
    let ea = vec![0.0, 0.0, 5.0, 5.0, 5.0, 4.92];
    assert_eq!(fused(ea.clone(), SconeMatcher::Union), vec![(0, 0), (1, 1)]);
    assert_eq!(fused_with(ea.clone(), SconeMatcher::Union, 0.9), vec![(0, 0), (1, 1), (2, 1)]);
    assert_eq!(fused_with(ea.clone(), SconeMatcher::Both, 0.9), vec![(0, 0), (0, 1), (1, 1), (2, 1)]);
    assert_eq!(fused_with(ea.clone(), SconeMatcher::Freak, 0.9), vec![(0, 1), (1, 1)]);
    // The embedding alone (`plain`) keeps the request's test.
    assert_eq!(fused_with(ea, SconeMatcher::Plain, 0.9), vec![(0, 0)]);
}

#[test]
fn union_adds_freak_matches_only_for_keypoints_scone_left_unmatched_and_both_adds_every_one() {
    // SConE: query 0 clearly matches 0; queries 1 and 2 are ambiguous (equidistant from b1 and b2).
    let ea = vec![0.0, 0.0, 5.0, 5.0, 5.0, 5.0];
    assert_eq!(fused(ea.clone(), SconeMatcher::Plain), vec![(0, 0)]);
    // SConE's answer for query 0 stands; FREAK adds query 1; query 2 has no answer from either.
    assert_eq!(fused(ea.clone(), SconeMatcher::Union), vec![(0, 0), (1, 1)]);
    // `both` also keeps FREAK's disagreeing answer for query 0.
    assert_eq!(fused(ea, SconeMatcher::Both), vec![(0, 0), (0, 1), (1, 1)]);
}

#[test]
fn both_keeps_a_pair_that_both_descriptors_found_once() {
    // As above, but SConE now finds query 1's match (1, 1) too, the same pair FREAK finds.
    let ea = vec![0.0, 0.0, 5.0, 4.0, 5.0, 5.0];
    assert_eq!(fused(ea.clone(), SconeMatcher::Plain), vec![(0, 0), (1, 1)]);
    assert_eq!(fused(ea.clone(), SconeMatcher::Freak), vec![(0, 1), (1, 1)]);
    assert_eq!(fused(ea, SconeMatcher::Both), vec![(0, 0), (0, 1), (1, 1)]);
}

#[test]
fn joint_weighs_both_descriptors_in_every_match() {
    // Query 0: the embedding is equidistant from b0 and b1, FREAK's bits decide for b1. Query 1: FREAK is
    // equidistant from b1 and b2 (128 bits each), the embedding decides for b2. Query 2: both descriptors
    // together are equidistant from b0 and b2 (squared 2 + 1 each), so no match.
    let s = std::f32::consts::FRAC_1_SQRT_2;
    let ea = vec![s, s, -1.0, 0.0, 0.0, -1.0];
    let eb = vec![1.0, 0.0, 0.0, 1.0, -1.0, 0.0];
    let (z, o, quarter, half, three_quarters) = (ones(0), ones(64), ones(16), ones(32), ones(48));
    let (ea, eb, fa, fb) = frames(ea, eb, [o, three_quarters, quarter], [z, o, half]);
    let (a, b) = (
        SconeFrame { embeddings: &ea, dim: 2, freak: &fa, points: &PTS, sizes: &[] },
        SconeFrame { embeddings: &eb, dim: 2, freak: &fb, points: &PTS, sizes: &[] },
    );
    let test = RatioTest::new(0.8);
    let pairs = |m: &[Match]| m.iter().map(|m| (m.query, m.train)).collect::<Vec<_>>();
    let joint = match_scone(SconeMatcher::Joint, &a, &b, &test).unwrap();
    assert_eq!(pairs(&joint), vec![(0, 1), (1, 2)]);
    // Each alone misses one of them.
    assert_eq!(pairs(&match_scone(SconeMatcher::Plain, &a, &b, &test).unwrap()), vec![(1, 2)]);
    assert_eq!(pairs(&match_scone(SconeMatcher::Freak, &a, &b, &test).unwrap()), vec![(0, 1)]);
    // The distance is the joint descriptor's L2: query 0 to b1 differs in the embedding only.
    let d01 = (s * s + (s - 1.0) * (s - 1.0)).sqrt();
    assert!((joint[0].distance - d01).abs() < 1e-5, "{} against {d01}", joint[0].distance);
    // Query 1 to b2: the same embedding, 128 bits apart, so 4 * 128 / 512 = 1.
    assert!((joint[1].distance - 1.0).abs() < 1e-5, "{}", joint[1].distance);
    // The ratio applies to the squared distance: 0.3 there is 0.548 on the L2 distance, which query 0
    // passes (0.766 against 2.14, 0.36) and query 1 does not (1 against 1.73, 0.58).
    let strict = RatioTest::new(0.3);
    assert_eq!(pairs(&match_scone(SconeMatcher::Joint, &a, &b, &strict).unwrap()), vec![(0, 1)]);
    // Without bits for every keypoint, the embedding alone answers.
    let none = Mat::default();
    let bare = SconeFrame { embeddings: &ea, dim: 2, freak: &none, points: &PTS, sizes: &[] };
    assert_eq!(
        pairs(&match_scone(SconeMatcher::Joint, &bare, &b, &test).unwrap()),
        pairs(&match_scone(SconeMatcher::Plain, &bare, &b, &test).unwrap())
    );
}

#[test]
fn pair_zoom_is_the_median_size_ratio_either_way() {
    let a = vec![7.0f32; 20];
    let mut b: Vec<f32> = vec![14.0; 20];
    b[0] = 7.0; // an outlier does not move the median
    let all: Vec<Match> = (0..20).map(|i| Match { query: i, train: i, distance: 0.0 }).collect();
    assert!((pair_zoom(&a, &b, &all).unwrap() - 2.0).abs() < 1e-5);
    assert!((pair_zoom(&b, &a, &all).unwrap() - 2.0).abs() < 1e-5);
    assert!(pair_zoom(&a, &b, &all[..SCALE_AWARE_MIN_MATCHES - 1]).is_none());
    // Sizes missing (a client that sent none) give no estimate, and scale-aware re-ranks.
    assert!(pair_zoom(&[], &[], &all).is_none());
}

/// Scale-aware answers as rerank between images of one scale, and as union under a zoom of 1.6 or more.
#[test]
fn scale_aware_falls_back_on_union_under_zoom() {
    // 12 keypoints per frame, FREAK bits distinct per keypoint and equal across the frames (every FREAK
    // match is k -> k); SConE embeddings agree with FREAK except that keypoint 0 is ambiguous for SConE.
    let n = 12;
    let bits: Vec<[u8; 64]> = (0..n).map(|k| ones((k + 1) * 5)).collect();
    let mut ea: Vec<f32> = (0..n).flat_map(|k| [10.0 * k as f32, 0.0]).collect();
    ea[0] = 5.0; // halfway between b0 and b1
    let eb: Vec<f32> = (0..n).flat_map(|k| [10.0 * k as f32, 0.0]).collect();
    let fa = Mat::new_rows_cols_with_data(n as i32, 64, bits.as_flattened()).unwrap().try_clone().unwrap();
    let fb = fa.try_clone().unwrap();
    let pts: Vec<(f32, f32)> = (0..n).map(|k| (50.0 * k as f32, 0.0)).collect();
    let one_scale = vec![7.0f32; n];
    let zoomed = vec![7.0f32 * 1.8; n];
    let test = RatioTest::new(0.8);
    let run = |matcher, sizes_b: &[f32]| {
        let a = SconeFrame { embeddings: &ea, dim: 2, freak: &fa, points: &pts, sizes: &one_scale };
        let b = SconeFrame { embeddings: &eb, dim: 2, freak: &fb, points: &pts, sizes: sizes_b };
        let mut m: Vec<(usize, usize)> =
            match_scone(matcher, &a, &b, &test).unwrap().iter().map(|m| (m.query, m.train)).collect();
        m.sort_unstable();
        m
    };
    assert_eq!(run(SconeMatcher::ScaleAware, &one_scale), run(SconeMatcher::Rerank, &one_scale));
    assert_eq!(run(SconeMatcher::ScaleAware, &zoomed), run(SconeMatcher::Union, &zoomed));
    assert_ne!(run(SconeMatcher::Rerank, &zoomed), run(SconeMatcher::Union, &zoomed));
}

/// The FREAK matches scale-aware reads from rerank's candidates are those of the full ratio-test search.
#[test]
fn freak_matches_from_the_candidates_equal_the_full_search() {
    let n = 200;
    let mut state = 17u64;
    let mut next = move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 33) as u32
    };
    let bits_a: Vec<u8> = (0..n * 64).map(|_| next() as u8).collect();
    // b: a's descriptors with a few bits flipped, shuffled by a fixed stride, plus noise rows.
    let mut bits_b = bits_a.clone();
    for (i, v) in bits_b.iter_mut().enumerate() {
        if i % 7 == 0 {
            *v ^= 1 << (next() % 8);
        }
    }
    bits_b.extend((0..50 * 64).map(|_| next() as u8));
    let fa = Mat::new_rows_cols_with_data(n as i32, 64, &bits_a).unwrap().try_clone().unwrap();
    let fb = Mat::new_rows_cols_with_data(n as i32 + 50, 64, &bits_b).unwrap().try_clone().unwrap();
    let pa: Vec<(f32, f32)> = (0..n).map(|i| ((i % 20) as f32 * 3.0, (i / 20) as f32 * 3.0)).collect();
    let pb: Vec<(f32, f32)> = (0..n + 50).map(|i| ((i % 20) as f32 * 1.5, (i / 20) as f32 * 1.5)).collect();
    let e = vec![0.0f32; (n + 50) * 2];
    let a = SconeFrame { embeddings: &e[..n * 2], dim: 2, freak: &fa, points: &pa, sizes: &[] };
    let b = SconeFrame { embeddings: &e, dim: 2, freak: &fb, points: &pb, sizes: &[] };
    for test in [RatioTest::new(0.8), RatioTest::plain(0.8), RatioTest::new(0.95)] {
        let knn = freak_knn(&a, &b).unwrap();
        let quick = freak_ratio_matches(&knn, &a, &b, &test).unwrap();
        let full = match_descriptors(&fa, &fb, NORM_HAMMING, &test, &pb).unwrap();
        assert!(!full.is_empty());
        assert_eq!(quick, full, "{test:?}");
    }
}

#[test]
fn rerank_orders_freak_candidates_by_scone_distance() {
    // FREAK prefers b0 for query 0 (identical bits), SConE prefers b2 and is sure of it.
    let (z, o) = ([0u8; 64], [0xffu8; 64]);
    let mut near = [0u8; 64];
    near[0] = 0x0f;
    let ea = vec![0.0, 0.0, 9.0, 9.0, -9.0, 9.0];
    let eb = vec![3.0, 0.0, 9.0, -9.0, 0.1, 0.0];
    let (ea, eb, fa, fb) = frames(ea, eb, [z, o, o], [z, o, near]);
    let (a, b) = (
        SconeFrame { embeddings: &ea, dim: 2, freak: &fa, points: &PTS, sizes: &[] },
        SconeFrame { embeddings: &eb, dim: 2, freak: &fb, points: &PTS, sizes: &[] },
    );
    let m = match_scone(SconeMatcher::Rerank, &a, &b, &RatioTest::new(0.8)).unwrap();
    let q0: Vec<_> = m.iter().filter(|m| m.query == 0).map(|m| m.train).collect();
    assert_eq!(q0, vec![2]);
    // With fewer than two candidates in b there is nothing to rank.
    let one = Mat::new_rows_cols_with_data(1, 64, &z).unwrap().try_clone().unwrap();
    let b1 = SconeFrame { embeddings: &eb[..2], dim: 2, freak: &one, points: &PTS[..1], sizes: &[] };
    assert!(match_scone(SconeMatcher::Rerank, &a, &b1, &RatioTest::new(0.8)).unwrap().is_empty());
}

#[test]
fn a_ratio_threshold_lies_in_zero_to_one() {
    assert!(is_ratio(0.8) && is_ratio(1.0) && is_ratio(f32::MIN_POSITIVE));
    assert!(!is_ratio(0.0) && !is_ratio(-0.5) && !is_ratio(1.01) && !is_ratio(f32::NAN) && !is_ratio(f32::INFINITY));
}
