//! The geometry of homographies, the bins, the fit, the neighbour share and the sequence layout, on synthetic
//! warps and files.

use nalgebra::Matrix3;

use super::geometry::{apply, corner_error, fit_homography, local_geometry};
use super::neighbours::{neighbour_share, ring_share};
use super::report::{rotation_bin, tilt_bin, zoom_bin};
use super::sequence::Sequence;
use crate::describe::constellation;
use crate::describe::features::Keypoint;

fn similarity(zoom: f64, deg: f64, tx: f64, ty: f64) -> Matrix3<f64> {
    let (s, c) = deg.to_radians().sin_cos();
    Matrix3::new(zoom * c, -zoom * s, tx, zoom * s, zoom * c, ty, 0.0, 0.0, 1.0)
}

#[test]
fn zoom_and_rotation_of_a_similarity_and_no_tilt() {
    for (z, r) in [(1.0, 0.0), (2.0, 30.0), (0.5, -120.0), (2.7, 179.0)] {
        let g = local_geometry(&similarity(z, r, 10.0, -5.0), 100.0, 50.0);
        assert!((g.zoom - z.max(1.0 / z)).abs() < 1e-6, "{z}: {}", g.zoom);
        assert!((g.rotation_deg - r.abs()).abs() < 1e-6, "{r}: {}", g.rotation_deg);
        assert!(g.tilt_deg < 1e-4, "{}", g.tilt_deg);
    }
}

/// A plane turned by t about the y axis, seen head-on before: x shrinks by cos t, y stays. That is a tilt of t
/// and no zoom; a zoom of 2 on top is a zoom of 2.
#[test]
fn a_tilt_is_a_tilt_and_not_a_zoom() {
    for t in [20.0f64, 45.0, 60.0] {
        let c = t.to_radians().cos();
        let g = local_geometry(&Matrix3::new(c, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 100.0, 50.0);
        assert!((g.tilt_deg - t).abs() < 1e-6 && (g.zoom - 1.0).abs() < 1e-9, "{t}: {g:?}");
        let g = local_geometry(&Matrix3::new(2.0 * c, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0), 100.0, 50.0);
        assert!((g.tilt_deg - t).abs() < 1e-6 && (g.zoom - 2.0).abs() < 1e-9, "{t}: {g:?}");
    }
    assert_eq!(tilt_bin(10.0), "0-15deg");
    assert_eq!(tilt_bin(50.0), "45-60deg");
}

#[test]
fn corner_error_is_zero_for_the_truth_and_grows_with_a_shift() {
    let h = similarity(1.5, 20.0, 3.0, 4.0);
    assert!(corner_error(&h, &h, 640, 480) < 1e-9);
    let shifted = Matrix3::new(1.0, 0.0, 2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0) * h;
    assert!((corner_error(&shifted, &h, 640, 480) - 2.0).abs() < 1e-9);
}

#[test]
fn bins_cover_the_range() {
    assert_eq!(zoom_bin(1.0), "1-1.25x");
    assert_eq!(zoom_bin(1.3), "1.25-1.6x");
    assert_eq!(zoom_bin(2.49), "2-2.5x");
    assert_eq!(zoom_bin(3.2), ">= 3x");
    assert_eq!(rotation_bin(0.0), "0-15deg");
    assert_eq!(rotation_bin(100.0), "90-135deg");
    assert_eq!(rotation_bin(180.0), "135-180deg");
}

#[test]
fn a_fitted_homography_recovers_an_exact_warp() {
    let h = similarity(1.8, 60.0, 300.0, -40.0);
    let src: Vec<(f32, f32)> = (0..60).map(|i| ((i * 37 % 600) as f32 + 10.0, (i * 53 % 440) as f32 + 10.0)).collect();
    let dst: Vec<(f32, f32)> = src
        .iter()
        .map(|p| {
            let (x, y) = apply(&h, p.0 as f64, p.1 as f64).unwrap();
            (x as f32, y as f32)
        })
        .collect();
    let est = fit_homography(&src, &dst, 3.0).unwrap().expect("a homography");
    assert!(corner_error(&est, &h, 640, 480) < 0.5);
    assert!(fit_homography(&src[..3], &dst[..3], 3.0).unwrap().is_none());
}

fn kp(x: f32, y: f32) -> Keypoint {
    Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }
}

/// Under an exact similarity every constellation survives (share 1); shifting half of image 2's other
/// keypoints away brings it down.
#[test]
fn neighbour_share_follows_what_moves() {
    // A jittered grid: no two distances tie, so the nearest-first order is the same in both images.
    let jitter = |i: usize, m: usize| ((i * m * 7919) % 1000) as f32 / 1000.0 * 9.0;
    let a: Vec<Keypoint> = (0..100)
        .map(|i| kp(20.0 + (i % 10) as f32 * 23.0 + jitter(i, 3), 20.0 + (i / 10) as f32 * 19.0 + jitter(i, 5)))
        .collect();
    let h = similarity(1.3, 40.0, 200.0, 10.0);
    let b: Vec<Keypoint> = a
        .iter()
        .map(|k| {
            let (x, y) = apply(&h, k.x as f64, k.y as f64).unwrap();
            kp(x as f32, y as f32)
        })
        .collect();
    let (ca, cb) = (constellation::build(&a, 8), constellation::build(&b, 8));
    let s = neighbour_share(&a, &ca, &b, &cb, &h, 3.0).unwrap();
    assert_eq!(s.keypoints, 100);
    assert!((s.share - 1.0).abs() < 1e-9, "{s:?}");
    // Turned 90 degrees, a member lands on another member only by chance on this grid.
    assert!(s.chance < 0.5, "{s:?}");
    let mut moved = b.clone();
    for (i, k) in moved.iter_mut().enumerate() {
        if i % 2 == 1 {
            k.x += 1000.0;
        }
    }
    let cm = constellation::build(&moved, 8);
    let s = neighbour_share(&a, &ca, &moved, &cm, &h, 3.0).unwrap();
    assert!(s.share < 0.8, "{s:?}");
}

/// Rings follow their keypoints' size and angle: under a similarity with sizes and angles that follow it, every
/// sample lands on its counterpart, turned 90 degrees almost none does; sizes that do not follow the zoom lose
/// the outer rings.
#[test]
fn ring_share_follows_size_and_angle() {
    let a: Vec<Keypoint> =
        (0..20).map(|i| Keypoint { angle: (i * 37 % 360) as f32, ..kp(100.0 + i as f32 * 30.0, 200.0) }).collect();
    let h = similarity(1.5, 30.0, 50.0, -20.0);
    let follow = |k: &Keypoint, zoom: f32| {
        let (x, y) = apply(&h, k.x as f64, k.y as f64).unwrap();
        Keypoint { x: x as f32, y: y as f32, size: k.size * zoom, angle: (k.angle + 30.0) % 360.0, ..*k }
    };
    let b: Vec<Keypoint> = a.iter().map(|k| follow(k, 1.5)).collect();
    let s = ring_share(&a, &b, &h, 3.0).unwrap();
    assert_eq!(s.keypoints, 20);
    assert!(s.share > 0.95 && s.chance < 0.1, "{s:?}");
    let same_size: Vec<Keypoint> = a.iter().map(|k| follow(k, 1.0)).collect();
    let t = ring_share(&a, &same_size, &h, 3.0).unwrap();
    assert!(t.share < 0.5, "{t:?}");
}

#[test]
fn a_sequence_loads_and_bad_files_are_named() {
    let dir = crate::test_dir::temp_dir("homography-seq");
    let img = opencv::core::Mat::new_rows_cols_with_default(48, 64, opencv::core::CV_8UC1, 128.into()).unwrap();
    let mut png = opencv::core::Vector::<u8>::new();
    opencv::imgcodecs::imencode(".png", &img, &mut png, &opencv::core::Vector::new()).unwrap();
    std::fs::write(dir.join("1.png"), png.as_slice()).unwrap();
    std::fs::write(dir.join("2.png"), png.as_slice()).unwrap();
    std::fs::write(dir.join("H_1_2"), "1 0 0\n0 1 0\n0 0 1\n").unwrap();
    let s = Sequence::load(&dir).unwrap();
    assert_eq!((s.images.len(), s.homographies.len()), (2, 1));
    std::fs::write(dir.join("H_1_2"), "1 0 0 0 1 0 0 0\n").unwrap();
    let e = Sequence::load(&dir).unwrap_err().to_string();
    assert!(e.contains("H_1_2") && e.contains("9 finite numbers"), "{e}");
    std::fs::write(dir.join("H_1_2"), "0 0 0 0 0 0 0 0 0\n").unwrap();
    assert!(Sequence::load(&dir).unwrap_err().to_string().contains("singular"));
}
