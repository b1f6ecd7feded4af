//! The track estimator on synthetic scenes: exact frames, a scale between track and map, a frame with a wrong
//! relative pose, a frame of another scene, and a track whose joint estimate loses to one frame.

use nalgebra::{Isometry3, Point3, Similarity3, Translation3, UnitQuaternion};
use rand::{Rng, SeedableRng};

use crate::camera::Camera;
use crate::pose::{absolute_pose, rotation_error_deg, RansacSettings, TrackFrame, TrackScale, TrackerError};

use crate::pose::track::track_pose;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

/// Map points in a slab 4-8 m in front of the track's origin.
fn map_points(rng: &mut rand::rngs::StdRng, n: usize, map_from_track: &Similarity3<f64>) -> Vec<[f64; 3]> {
    (0..n)
        .map(|_| {
            let p = Point3::new(rng.random_range(-4.0..4.0), rng.random_range(-3.0..3.0), rng.random_range(4.0..8.0));
            let m = map_from_track.transform_point(&p);
            [m.x, m.y, m.z]
        })
        .collect()
}

/// Frame `i` of a track moving along x: camera-to-track pose, a few degrees of yaw each.
fn track_pose_of(i: usize) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(0.3 * i as f64, 0.05 * i as f64, 0.0),
        UnitQuaternion::from_euler_angles(0.0, (3.0 * i as f64).to_radians(), 0.0),
    )
}

/// A frame seeing `points` (map) through `map_from_track` at `camera_to_track`, with 0.5 px noise and a share
/// `outliers` of its matches replaced by random pixels; its own pose by single-frame PnP.
fn frame(
    rng: &mut rand::rngs::StdRng,
    points: &[[f64; 3]],
    map_from_track: &Similarity3<f64>,
    camera_to_track: Isometry3<f64>,
    outliers: f64,
) -> TrackFrame {
    let cam = camera();
    let (mut p3, mut p2) = (Vec::new(), Vec::new());
    for x in points {
        let t = map_from_track.inverse_transform_point(&Point3::new(x[0], x[1], x[2]));
        let c = camera_to_track.inverse_transform_point(&t);
        if c.z <= 0.1 {
            continue;
        }
        let (u, v) = (cam.fx * c.x / c.z + cam.cx, cam.fy * c.y / c.z + cam.cy);
        if !(0.0..640.0).contains(&u) || !(0.0..480.0).contains(&v) {
            continue;
        }
        let (u, v) = if rng.random_bool(outliers) {
            (rng.random_range(0.0..640.0), rng.random_range(0.0..480.0))
        } else {
            (u + rng.random_range(-0.5..0.5), v + rng.random_range(-0.5..0.5))
        };
        p3.push(*x);
        p2.push((u as f32, v as f32));
    }
    let own = absolute_pose(&p3, &p2, &cam, &RansacSettings::opencv(4.0), 12).unwrap();
    TrackFrame { camera_to_track, camera: cam, points3d: p3, points2d: p2, own }
}

fn truth() -> Similarity3<f64> {
    Similarity3::from_parts(Translation3::new(10.0, -2.0, 3.0), UnitQuaternion::from_euler_angles(0.1, -0.4, 0.2), 1.0)
}

fn error(est: &Similarity3<f64>, truth: &Similarity3<f64>) -> (f64, f64) {
    let t = (est.isometry.translation.vector - truth.isometry.translation.vector).norm();
    let r =
        rotation_error_deg(&est.isometry.rotation.to_rotation_matrix(), &truth.isometry.rotation.to_rotation_matrix());
    (t, r)
}

#[test]
fn three_exact_frames_give_the_transform() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(1);
    let s = truth();
    let points = map_points(&mut rng, 300, &s);
    let frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.3)).collect();
    let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    let (dt, dr) = error(&t.map_from_track, &s);
    assert!(dt < 0.02 && dr < 0.1, "{dt} m, {dr} deg");
    assert!(t.single_frame.is_none());
    assert!(t.frames.iter().all(|f| !f.dropped && f.inliers.len() > 100), "{:?}", t.frames.len());
    assert!(t.covariance_w2c.is_some());
    // Frame 2's camera in the map is the truth's.
    let c = t.camera_to_map(&frames[2].camera_to_track);
    let want = s.isometry * frames[2].camera_to_track;
    assert!((c.translation.vector - want.translation.vector).norm() < 0.02);
}

#[test]
fn a_scale_between_track_and_map_is_estimated() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(2);
    let mut s = truth();
    s.set_scaling(2.5);
    let points = map_points(&mut rng, 300, &s);
    let frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.3)).collect();
    let t = track_pose(&frames, TrackScale::Free, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    assert!((t.map_from_track.scaling() - 2.5).abs() < 0.05, "{}", t.map_from_track.scaling());
    let (dt, dr) = error(&t.map_from_track, &s);
    assert!(dt < 0.1 && dr < 0.2, "{dt} m, {dr} deg");
    // A rigid estimate of the same track cannot fit every frame.
    let rigid = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    assert!(rigid.inlier_count() < t.inlier_count(), "{} vs {}", rigid.inlier_count(), t.inlier_count());
}

/// A frame whose relative pose is 20 degrees off (a tracker that slipped) is dropped, and the others still
/// give the transform.
#[test]
fn a_frame_with_a_wrong_relative_pose_is_dropped() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let s = truth();
    let points = map_points(&mut rng, 300, &s);
    let mut frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.3)).collect();
    let off = UnitQuaternion::from_euler_angles(0.0, 20f64.to_radians(), 0.0);
    frames[1].camera_to_track =
        Isometry3::from_parts(frames[1].camera_to_track.translation, off * frames[1].camera_to_track.rotation);
    let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    assert!(t.frames[1].dropped && t.frames[1].inliers.is_empty(), "{:?}", t.frames[1]);
    assert!(!t.frames[0].dropped && !t.frames[2].dropped);
    let (dt, dr) = error(&t.map_from_track, &s);
    assert!(dt < 0.02 && dr < 0.1, "{dt} m, {dr} deg");
}

/// A frame of another scene (its matches point at nothing it sees) adds no inliers and changes nothing.
#[test]
fn a_frame_of_another_scene_changes_nothing() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    let s = truth();
    let points = map_points(&mut rng, 300, &s);
    let mut frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.3)).collect();
    frames[2] = frame(&mut rng, &points, &s, track_pose_of(2), 1.0);
    let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    assert!(t.frames[2].inliers.len() < 10, "{}", t.frames[2].inliers.len());
    let (dt, dr) = error(&t.map_from_track, &s);
    assert!(dt < 0.02 && dr < 0.1, "{dt} m, {dr} deg");
}

/// Frames that each see too little to be located alone are located together.
#[test]
fn weak_frames_together_are_located() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let s = truth();
    let points = map_points(&mut rng, 36, &s);
    let frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.6)).collect();
    let alone = |f: &TrackFrame| f.own.as_ref().map_or(0, |p| p.inliers.len());
    let min = 24;
    assert!(frames.iter().all(|f| alone(f) < min), "{:?}", frames.iter().map(alone).collect::<Vec<_>>());
    let counts: Vec<(usize, usize)> = frames.iter().map(|f| (f.points3d.len(), alone(f))).collect();
    let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), min, 7, &TrackerError::default())
        .unwrap()
        .unwrap_or_else(|| panic!("not located: (matches, alone) {counts:?}"));
    assert!(t.inlier_count() >= min);
    let (dt, dr) = error(&t.map_from_track, &s);
    assert!(dt < 0.1 && dr < 0.5, "{dt} m, {dr} deg");
}

/// When one frame alone has more inliers than any joint estimate (here: every other frame's relative pose is
/// wrong in its own way), the answer is that frame's pose.
#[test]
fn never_worse_than_the_best_frame() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(6);
    let s = truth();
    let points = map_points(&mut rng, 300, &s);
    let mut frames: Vec<TrackFrame> = (0..3).map(|i| frame(&mut rng, &points, &s, track_pose_of(i), 0.2)).collect();
    for (f, deg) in [(1usize, 25.0f64), (2, -30.0)] {
        let off = UnitQuaternion::from_euler_angles(deg.to_radians(), 0.0, 0.0);
        frames[f].camera_to_track.rotation = off * frames[f].camera_to_track.rotation;
    }
    let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, &TrackerError::default())
        .unwrap()
        .unwrap();
    let alone = frames.iter().map(|f| f.own.as_ref().map_or(0, |p| p.inliers.len())).max().unwrap();
    assert!(t.inlier_count() >= alone, "{} < {alone}", t.inlier_count());
    // Whichever frame it rests on, frame 0's covariance comes with it.
    assert!(t.covariance_w2c.is_some(), "answer from frame {:?}", t.single_frame);
    // The frame the answer rests on is where it truly is, whatever its relative pose said.
    let (anchor, _) = t.frames.iter().enumerate().max_by_key(|(_, f)| f.inliers.len()).unwrap();
    let c = t.camera_to_map(&frames[anchor].camera_to_track);
    let want = s.isometry * track_pose_of(anchor);
    assert!((c.translation.vector - want.translation.vector).norm() < 0.05, "frame {anchor}");
}

/// A standard normal draw (Box-Muller).
fn gaussian(rng: &mut rand::rngs::StdRng) -> f64 {
    let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// The share of `trials` tracks whose frame 0 lies within the answer's 95 % ellipsoid, the relative poses of
/// frames 1 and 2 off by draws of `injected` and the estimator told `told`.
fn coverage(injected: &TrackerError, told: &TrackerError, trials: u64) -> f64 {
    let mut inside = 0;
    for seed in 0..trials {
        let mut rng = rand::rngs::StdRng::seed_from_u64(100 + seed);
        let s = truth();
        let points = map_points(&mut rng, 300, &s);
        let frames: Vec<TrackFrame> = (0..3)
            .map(|i| {
                let mut f = frame(&mut rng, &points, &s, track_pose_of(i), 0.1);
                let distance = (track_pose_of(i).translation.vector - track_pose_of(0).translation.vector).norm();
                let (st, sr) = (
                    // Root mean square sizes as TrackerError means them: a third of the square per axis.
                    injected.translation_share * distance / 3f64.sqrt(),
                    injected.degrees_per_frame.to_radians() * i as f64 / 3f64.sqrt(),
                );
                let mut draw = |sigma: f64| {
                    nalgebra::Vector3::new(gaussian(&mut rng), gaussian(&mut rng), gaussian(&mut rng)) * sigma
                };
                let (dt, dr) = (draw(st), draw(sr));
                f.camera_to_track *= Isometry3::new(dt, dr);
                f
            })
            .collect();
        let t = track_pose(&frames, TrackScale::Rigid, &RansacSettings::opencv(4.0), 12, 7, told).unwrap().unwrap();
        assert_eq!(t.single_frame, None);
        let est = t.camera_to_map(&frames[0].camera_to_track);
        let want = s.isometry * track_pose_of(0);
        let cov = crate::pose::pose_covariance(
            crate::camera::PoseConvention::OpencvCameraToWorld,
            &est,
            t.covariance_w2c.as_ref().unwrap(),
        );
        let d = crate::pose::pose_difference(&est, &want);
        let m = (d.transpose() * cov.try_inverse().unwrap() * d)[(0, 0)];
        inside += usize::from(m <= crate::pose::CHI2_6_95);
    }
    inside as f64 / trials as f64
}

/// The covariance holds the tracker's error it is told of: with relative poses off as a phone's tracker is
/// (1 % of the distance, 0.5 degrees per frame), the 95 % ellipsoid holds frame 0 in most tracks; told the poses
/// are exact, it is overconfident. With exact poses it is the images' covariance alone either way.
#[test]
fn the_covariance_holds_the_trackers_error() {
    let phone = TrackerError::default();
    let rig = TrackerError { translation_share: 0.0, degrees_per_frame: 0.0 };
    let told = coverage(&phone, &phone, 40);
    let untold = coverage(&phone, &rig, 40);
    assert!(told >= 0.85, "told of the tracker's error: {told}");
    assert!(untold < told, "told the poses are exact: {untold} against {told}");
    let exact = coverage(&rig, &rig, 40);
    assert!(exact >= 0.85, "exact poses: {exact}");
}
