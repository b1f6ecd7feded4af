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

/// A map of one keyframe at the origin looking along +z, its `n` landmarks seen at scattered pixels, and a query
/// taken from the same pose with the same keypoints.
fn one_keyframe_map(n: usize) -> (crate::map::model::MapData, Vec<crate::describe::features::Keypoint>) {
    use crate::camera::Pose;
    use crate::describe::features::Keypoint;
    use crate::map::model::{Keyframe, MapData, NewObservation, Record};
    let camera = camera();
    let pixels: Vec<(f32, f32)> =
        (0..n).map(|i| (((i * 37) % 600 + 20) as f32, ((i * 91) % 440 + 20) as f32)).collect();
    let keypoints: Vec<Keypoint> =
        pixels.iter().map(|&(x, y)| Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }).collect();
    let point = |(x, y): (f32, f32), i: usize| {
        let z = 4.0 + (i % 7) as f64;
        [(f64::from(x) - camera.cx) / camera.fx * z, (f64::from(y) - camera.cy) / camera.fy * z, z]
    };
    let meta =
        crate::map::model::MapMeta { id: "m".into(), model_id: "test".into(), k: 20, dim: 8, created_unix_ms: 1 };
    let mut data = MapData::new(meta);
    let record = Record::AddKeyframe {
        keyframe: Keyframe {
            id: 0,
            pose: Pose { translation: [0.0; 3], rotation: [0.0, 0.0, 0.0, 1.0] },
            camera,
            keypoints: keypoints.clone(),
            descriptors: vec![0; n * crate::describe::features::DESCRIPTOR_BYTES],
            embeddings: (0..n * 8).map(|j| if j % 8 == (j / 8) % 8 { 1.0 } else { 0.0 }).collect(),
        },
        new_landmarks: (0..n).map(|i| (i as u64, point(pixels[i], i))).collect(),
        observations: (0..n).map(|i| NewObservation { landmark: i as u64, keyframe: 0, keypoint: i as u32 }).collect(),
    };
    data.check(&record).unwrap();
    data.apply(&record).unwrap();
    (data, keypoints)
}

fn camera() -> crate::camera::Camera {
    crate::camera::Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

/// A localisation whose matches pair keypoint `i` with landmark `landmark(i)` for every `i` below `n`.
fn answer(
    data: &crate::map::model::MapData,
    n: usize,
    landmark: impl Fn(usize) -> usize,
    pose: Option<crate::pose::AbsolutePose>,
) -> crate::map::localize::Localization {
    use crate::map::localize::{LandmarkMatch, Localization};
    let matches: Vec<LandmarkMatch> =
        (0..n).map(|i| LandmarkMatch { keypoint: i, landmark: landmark(i) as u64, distance: 0.1 }).collect();
    let points = matches.iter().map(|m| data.landmarks[&m.landmark].point).collect();
    Localization {
        pose,
        stage1: matches.clone(),
        matches,
        confidence: 0.0,
        points,
        search_s: 0.0,
        pnp_s: 0.0,
        stages_s: 0.0,
    }
}

#[test]
fn a_query_is_charged_to_the_first_stage_that_left_it_too_little() {
    use super::diagnose::{diagnose, LostAt, QueryTruth};
    use crate::map::localize::LocalizeSettings;
    use nalgebra::{Isometry3, Vector3};
    let n = 120;
    let (data, keypoints) = one_keyframe_map(n);
    let (camera, params) = (camera(), LocalizeSettings::default());
    let at =
        |truth| QueryTruth { truth, camera: &camera, keypoints: &keypoints, precision_px: 5.0, within: (0.25, 2.0) };
    let here = Isometry3::identity();
    let q = at(&here);
    // Every match right and no pose: the estimator is to blame, and finds the pose without the floor.
    let all_right = answer(&data, n, |i| i, None);
    let d = diagnose(&data, &q, &all_right, n, &params).unwrap();
    assert_eq!((d.reachable_map, d.reachable_candidates, d.true_inliers), (n, n, n));
    assert!(d.unfloored_within && d.unfloored_inliers == n, "{d:?}");
    assert_eq!(d.lost_at, LostAt::Estimator);
    // The same matches with their pose: localised.
    let pose = crate::pose::absolute_pose(&all_right.points, &pixels(&keypoints), &camera, &params.ransac, 15)
        .unwrap()
        .unwrap();
    let d = diagnose(&data, &q, &answer(&data, n, |i| i, Some(pose)), n, &params).unwrap();
    assert_eq!(d.lost_at, LostAt::Localised);
    // Every match wrong while the map holds the view: matching lost it.
    let d = diagnose(&data, &q, &answer(&data, n, |i| (i + 1) % n, None), 0, &params).unwrap();
    assert_eq!((d.reachable_map, d.stage1_correct, d.true_inliers, d.lost_at), (n, 0, 0, LostAt::Matching));
    // A query looking away from every landmark: the map holds nothing of its view.
    let away = Isometry3::new(Vector3::zeros(), Vector3::new(0.0, std::f64::consts::PI, 0.0));
    let d = diagnose(&data, &at(&away), &answer(&data, n, |i| i, None), 0, &params).unwrap();
    assert_eq!((d.reachable_map, d.lost_at), (0, LostAt::Map));
}

fn pixels(keypoints: &[crate::describe::features::Keypoint]) -> Vec<(f32, f32)> {
    keypoints.iter().map(|k| (k.x, k.y)).collect()
}
