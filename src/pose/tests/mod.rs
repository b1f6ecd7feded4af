//! Pose estimation on synthetic cameras and points: known motions recovered, duplicates, too few points, bad
//! intrinsics, the stopping rule, and covariances that cover the truth; the track estimator's scenes are in
//! `track_tests.rs` beside this one.

use nalgebra::{Isometry3, Vector3};

use super::relative::representatives;
use super::*;
use crate::camera::{Camera, PoseConvention};
use crate::error::PoseError;

mod track_tests;

fn cam() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

fn project(cam: &Camera, t_cw: &Isometry3<f64>, p: &Vector3<f64>) -> Option<(f32, f32)> {
    let c = t_cw * nalgebra::Point3::from(*p);
    (c.z > 0.1).then(|| ((cam.fx * c.x / c.z + cam.cx) as f32, (cam.fy * c.y / c.z + cam.cy) as f32))
}

/// Camera 2's pose (camera-to-world) in the relative-pose tests; camera 1 is at the origin.
fn second_camera() -> Isometry3<f64> {
    Isometry3::new(Vector3::new(0.5, 0.05, 0.1), Vector3::new(0.02, -0.15, 0.03))
}

/// A point's index and its pixel positions in cameras 1 and 2.
type Seen = (usize, (f32, f32), (f32, f32));

/// Point `i` of `n` spread 4-9 m in front of camera 1, projected into both cameras, for the points both
/// cameras see.
fn two_views(n: usize) -> Vec<Seen> {
    let (c, t_w2) = (cam(), second_camera());
    (0..n)
        .filter_map(|i| {
            let x = Vector3::new(
                ((i * 37) % 100) as f64 / 25.0 - 2.0,
                ((i * 53) % 100) as f64 / 33.0 - 1.5,
                4.0 + ((i * 71) % 100) as f64 / 20.0,
            );
            Some((i, project(&c, &Isometry3::identity(), &x)?, project(&c, &t_w2.inverse(), &x)?))
        })
        .collect()
}

/// Points spread in front of both cameras, a known motion, 30 % outliers: the pose comes back.
#[test]
fn relative_pose_recovers_a_known_motion() {
    let c = cam();
    let (mut p1, mut p2) = (Vec::new(), Vec::new());
    for (i, a, b) in two_views(200) {
        p1.push(a);
        p2.push(if i % 10 < 3 { (b.0 + 40.0 + (i % 7) as f32 * 9.0, b.1 - 25.0) } else { b });
    }
    let pose = relative_pose(&p1, &p2, &c, &c, &RansacSettings::default()).unwrap().unwrap();
    let gt = relative_motion(&Isometry3::identity(), &second_camera());
    assert!(rotation_error_deg(&pose.rotation, &gt.rotation.to_rotation_matrix()) < 0.5);
    assert!(translation_angle_deg(&pose.translation, &gt.translation.vector) < 2.0);
    assert!(pose.inlier_count >= p1.len() * 6 / 10);
}

#[test]
fn duplicates_are_left_out_of_the_estimate_and_share_their_representative_flag() {
    let p1 = [(10.0, 10.0), (11.0, 10.5), (10.5, 10.0), (50.0, 50.0), (11.0, 10.0)];
    let p2 = [(20.0, 20.0), (21.0, 20.0), (40.0, 20.0), (60.0, 60.0), (20.5, 21.0)];
    // 1 and 4 copy 0 in both images; 2 is near 0 in image 1 only, so it stays.
    let (kept, rep) = representatives(&p1, &p2, 2.0);
    assert_eq!(kept, vec![0, 2, 3]);
    assert_eq!(rep, vec![0, 0, 1, 2, 0]);
    assert_eq!(representatives(&p1, &p2, 0.0).0.len(), 5);
    // The same motion as above with every correspondence given three times, 1 px apart: the pose is the
    // same, and each input gets a flag, copies included.
    let c = cam();
    let (mut p1, mut p2) = (Vec::new(), Vec::new());
    for (_, a, b) in two_views(120) {
        for d in [0.0, 0.7, -0.7] {
            p1.push((a.0 + d, a.1));
            p2.push((b.0, b.1 + d));
        }
    }
    let params = RansacSettings { duplicate_px: 2.0, threshold_px: 2.0, ..Default::default() };
    let pose = relative_pose(&p1, &p2, &c, &c, &params).unwrap().unwrap();
    let gt = relative_motion(&Isometry3::identity(), &second_camera());
    assert!(rotation_error_deg(&pose.rotation, &gt.rotation.to_rotation_matrix()) < 0.5);
    assert_eq!(pose.inliers.len(), p1.len());
    assert!(pose.inlier_count >= p1.len() * 9 / 10, "{} of {}", pose.inlier_count, p1.len());
    assert!(RansacSettings { duplicate_px: f64::NAN, ..Default::default() }.validate().is_err());
}

/// The `i`-th point of a fixed scatter 3-6.3 units in front of `cam()` at the origin.
fn scattered(i: usize) -> Vector3<f64> {
    Vector3::new(
        ((i * 37) % 100) as f64 / 25.0 - 2.0,
        ((i * 53) % 100) as f64 / 33.0 - 1.5,
        3.0 + ((i * 71) % 100) as f64 / 30.0,
    )
}

#[test]
fn absolute_pose_recovers_a_known_camera() {
    let c = cam();
    let t_wc = Isometry3::new(Vector3::new(0.3, -0.2, -1.0), Vector3::new(0.1, 0.2, -0.05));
    let (mut p3, mut p2) = (Vec::new(), Vec::new());
    for i in 0..150 {
        let x = scattered(i);
        if let Some(uv) = project(&c, &t_wc.inverse(), &x) {
            p3.push([x.x, x.y, x.z]);
            p2.push(if i % 5 == 0 { (uv.0 + 50.0, uv.1 + 30.0) } else { uv });
        }
    }
    let pose =
        absolute_pose(&p3, &p2, &c, &RansacSettings { threshold_px: 2.0, ..Default::default() }, 10).unwrap().unwrap();
    let d = pose.camera_to_world.inverse() * t_wc;
    assert!(d.translation.vector.norm() < 1e-3, "{d:?}");
    assert!(d.rotation.angle() < 1e-3);
    assert!(pose.reprojection_error < 0.01);
}

#[test]
fn minimal_sample_estimators_recover_a_known_camera_among_four_outliers_per_inlier() {
    use crate::pose::PnpMethod;
    use clap::ValueEnum;
    let c = cam();
    let t_wc = Isometry3::new(Vector3::new(0.3, -0.2, -1.0), Vector3::new(0.1, 0.2, -0.05));
    let (mut p3, mut p2) = (Vec::new(), Vec::new());
    // Every fifth of 300 correspondences is an inlier (20 %); the outliers' image points are spread over the
    // frame.
    for i in 0..300usize {
        let x = scattered(i);
        let Some(uv) = project(&c, &t_wc.inverse(), &x) else { continue };
        p3.push([x.x, x.y, x.z]);
        let outlier = (((i * 7919) % 613) as f32, ((i * 104_729) % 479) as f32);
        p2.push(if i % 5 == 0 { uv } else { outlier });
    }
    // EPnP's 5-point samples are clean once in 3,000 draws here, and it is not asked to (the estimators
    // with smaller samples exist for this).
    for &method in PnpMethod::value_variants().iter().filter(|&&m| m != PnpMethod::Epnp) {
        let params = RansacSettings { threshold_px: 2.0, max_iters: 5000, pnp: method, ..Default::default() };
        let pose = absolute_pose(&p3, &p2, &c, &params, 20).unwrap().unwrap_or_else(|| panic!("{method:?}: no pose"));
        let d = pose.camera_to_world.inverse() * t_wc;
        assert!(d.translation.vector.norm() < 1e-2 && d.rotation.angle() < 1e-2, "{method:?}: {d:?}");
        assert!(pose.inliers.len() >= 55, "{method:?}: {} inliers", pose.inliers.len());
    }
}

#[test]
fn too_few_points_give_no_pose() {
    let c = cam();
    let p = vec![(1.0, 2.0); 4];
    assert!(relative_pose(&p, &p, &c, &c, &RansacSettings::default()).unwrap().is_none());
    assert!(absolute_pose(&[[0.0; 3]; 4], &p, &c, &RansacSettings::default(), 10).unwrap().is_none());
}

#[test]
fn nan_intrinsics_are_refused() {
    let bad = Camera { fx: f64::NAN, ..cam() };
    let p = vec![(1.0, 2.0); 8];
    assert!(matches!(
        relative_pose(&p, &p, &bad, &cam(), &RansacSettings::default()),
        Err(PoseError::Intrinsics { .. })
    ));
}

#[test]
fn iterations_needed_follows_the_formula() {
    assert!((ransac_iterations_needed(0.5, 5, 0.999) - 217.6).abs() < 1.0);
    assert!(ransac_iterations_needed(0.0, 5, 0.999).is_infinite());
    assert_eq!(ransac_iterations_needed(1.0, 5, 0.999), 1.0);
}

/// Points 4-9 m in front of a camera, seen with Gaussian pixel noise of 1 px: the refinement's covariance
/// is a covariance of the answer. In each convention, the true pose lies within the 95 % ellipsoid in
/// about 95 % of trials, and the focal length estimated without intrinsics is close to the truth.
#[test]
fn the_covariance_covers_the_truth_in_every_convention_and_the_focal_length_is_estimated() {
    use rand::{Rng, SeedableRng};
    let c = cam();
    let truth = Isometry3::new(Vector3::new(0.3, -0.2, 0.1), Vector3::new(0.05, 0.2, -0.1));
    let mut rng = rand::rngs::StdRng::seed_from_u64(28);
    let mut gauss = move || {
        let (a, b): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
        (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
    };
    let points: Vec<Vector3<f64>> = (0..150)
        .map(|i| {
            truth
                * nalgebra::Point3::new(
                    ((i * 37) % 100) as f64 / 25.0 - 2.0,
                    ((i * 53) % 100) as f64 / 33.0 - 1.5,
                    4.0 + ((i * 71) % 100) as f64 / 20.0,
                )
        })
        .map(|p| p.coords)
        .collect();
    // The points as the camera sees them, with fresh pixel noise on each call.
    let mut noisy_view = || {
        let (mut p3, mut p2) = (Vec::new(), Vec::new());
        for p in &points {
            if let Some((u, v)) = project(&c, &truth.inverse(), p) {
                p3.push([p.x, p.y, p.z]);
                p2.push((u + gauss() as f32, v + gauss() as f32));
            }
        }
        (p3, p2)
    };
    let conventions =
        [PoseConvention::OpencvCameraToWorld, PoseConvention::OpencvWorldToCamera, PoseConvention::OpenglCameraToWorld];
    let trials = 400;
    let mut inside = [0usize; 3];
    let params = RansacSettings { threshold_px: 4.0, confidence: 0.999, max_iters: 2000, ..Default::default() };
    for _ in 0..trials {
        let (p3, p2) = noisy_view();
        let pose = absolute_pose(&p3, &p2, &c, &params, 15).unwrap().unwrap();
        let cov = pose.covariance_w2c.unwrap();
        for (n, conv) in conventions.iter().enumerate() {
            let sigma = pose_covariance(*conv, &pose.camera_to_world, &cov);
            let e = pose_difference(
                &conv.from_opencv_camera_to_world(&truth),
                &conv.from_opencv_camera_to_world(&pose.camera_to_world),
            );
            let d2 = (e.transpose() * sigma.try_inverse().unwrap() * e)[0];
            inside[n] += usize::from(d2 <= CHI2_6_95);
        }
    }
    for (n, k) in inside.iter().enumerate() {
        let share = *k as f64 / trials as f64;
        assert!((0.91..=0.99).contains(&share), "{:?}: {share} of the truths in the 95 % ellipsoid", conventions[n]);
    }

    // Without intrinsics (principal point known): the focal length comes back, and the covariance with it
    // marginalised covers the truth as well (the focal length's uncertainty is in it).
    let unknown = Camera { fx: 0.0, fy: 0.0, ..c };
    let (mut covered, trials) = (0, 120);
    for _ in 0..trials {
        let (p3, p2) = noisy_view();
        let pose = absolute_pose_unknown_focal(&p3, &p2, &unknown, &params, 15).unwrap().unwrap();
        assert!((pose.focal - c.fx).abs() < 0.05 * c.fx, "focal {}", pose.focal);
        let sigma = pose_covariance(PoseConvention::default(), &pose.camera_to_world, &pose.covariance_w2c.unwrap());
        let e = pose_difference(&truth, &pose.camera_to_world);
        covered += usize::from((e.transpose() * sigma.try_inverse().unwrap() * e)[0] <= CHI2_6_95);
    }
    let share = covered as f64 / trials as f64;
    eprintln!("unknown focal length: {share} of the truths in the 95 % ellipsoid");
    assert!((0.88..=0.995).contains(&share), "unknown focal length: {share} of the truths in the 95 % ellipsoid");
}
