//! The protocol's split of the frames and the report's angle bins, on made-up frames and records.

use super::protocol::{split_frames, RelocConfig};
use super::report::{bin_summaries, QueryRecord};

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
        stage1_cap: None,
        pnp: None,
        diagnosis: None,
    };
    let recs = [rec(5.0, 0.01), rec(15.0, 0.3), rec(50.0, 0.1)];
    let bins = bin_summaries(&recs, 1.0);
    assert_eq!(bins.iter().map(|b| b.queries).collect::<Vec<_>>(), vec![1, 1, 0, 1]);
    assert_eq!((bins[0].within_5cm_5deg, bins[1].within_025m_2deg, bins[1].within_05m_5deg), (1.0, 0.0, 1.0));
    // Thresholds in scene units: x10 lets the 0.3 error pass (0.25 m x 10).
    assert_eq!(bin_summaries(&recs, 10.0)[1].within_025m_2deg, 1.0);
}

#[test]
fn stages_without_stage_two_search_every_keypoint_and_with_it_keep_the_cap() {
    use super::protocol::{with_stages, Stage};
    use crate::map::builder::BuildSettings;
    use crate::map::localize::LocalizeSettings;
    let capped = LocalizeSettings { max_query_keypoints: 100, full_search_below_inliers: 100, ..Default::default() };
    for stages in [&[][..], &[Stage::Guided], &[Stage::Build]] {
        let (_, l) = with_stages(BuildSettings::default(), capped, stages);
        assert!(!l.candidate_matching, "{stages:?}");
        assert_eq!((l.max_query_keypoints, l.full_search_below_inliers), (usize::MAX, 0), "{stages:?}");
    }
    for stages in [&[Stage::Candidates][..], &[Stage::Freak, Stage::Guided]] {
        let (_, l) = with_stages(BuildSettings::default(), capped, stages);
        assert!(l.candidate_matching, "{stages:?}");
        assert_eq!((l.max_query_keypoints, l.full_search_below_inliers), (100, 100), "{stages:?}");
    }
}
