//! Unit tests of map building's decisions on small synthetic scenes: which keyframes are candidates, which
//! matches the epipolar window lets compete, what depth back-projects, which triangulated points are kept,
//! when a matched landmark is observed, what external observations become, and what each setting moves.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use opencv::core::{Mat, Scalar, CV_16U};
use opencv::prelude::*;

use super::candidates::{candidates, epipolar_mask};
use super::*;
use crate::camera::Camera;
use crate::describe::features::{Features, Keypoint, DESCRIPTOR_BYTES};
use crate::map::model::{MapData, NewObservation};
use crate::map::tests::{meta, vectors};

const DIM: usize = 16;
/// Points of the test scene.
const N: usize = 40;
/// Metres per raw depth unit (TUM's).
const DEPTH_SCALE: f64 = 1.0 / 5000.0;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

fn keypoint(x: f32, y: f32) -> Keypoint {
    Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }
}

/// A camera-to-world pose at `x` on the x axis, looking along +z.
fn at(x: f64) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::identity())
}

/// Point `k` of the test scene: 4-8 m in front of a camera at the origin looking along +z, at a grid pixel
/// (8 columns 70 px apart, 5 rows 80 px apart).
fn point(k: usize) -> Point3<f64> {
    let (u, v) = (80.0 + (k % 8) as f64 * 70.0, 40.0 + (k / 8) as f64 * 80.0);
    let z = 4.0 + (k * 3 % 5) as f64;
    let c = camera();
    Point3::new((u - c.cx) / c.fx * z, (v - c.cy) / c.fy * z, z)
}

/// What a keyframe at `pose` sees of the scene: keypoint `k` is point `k`, with embedding `k` of one set of
/// vectors (the same in every view, so views match keypoint for keypoint).
struct View {
    pose: Isometry3<f64>,
    features: Features,
    embeddings: Vec<f32>,
}

impl View {
    fn of(pose: Isometry3<f64>) -> Self {
        let keypoints = (0..N)
            .map(|k| {
                let (u, v) = camera().project(&pose.inverse_transform_point(&point(k))).expect("in front");
                assert!((0.0..640.0).contains(&u) && (0.0..480.0).contains(&v), "point {k} leaves the image");
                keypoint(u as f32, v as f32)
            })
            .collect();
        let features = Features {
            width: 640,
            height: 480,
            keypoints,
            descriptors: vec![[0u8; DESCRIPTOR_BYTES]; N],
            context: Vec::new(),
        };
        Self { pose, features, embeddings: vectors(N, DIM, 7) }
    }

    /// The view with the embeddings of keypoints `a` and `b` swapped: each matches the other's keypoint.
    fn swapped(mut self, a: usize, b: usize) -> Self {
        for j in 0..DIM {
            self.embeddings.swap(a * DIM + j, b * DIM + j);
        }
        self
    }

    /// A depth image with every keypoint's true depth at its (rounded) pixel.
    fn depth(&self) -> Mat {
        let mut image = Mat::new_rows_cols_with_default(480, 640, CV_16U, Scalar::all(0.0)).unwrap();
        for (k, p) in self.features.keypoints.iter().enumerate() {
            let z = self.pose.inverse_transform_point(&point(k)).z;
            *image.at_2d_mut::<u16>(p.y.round() as i32, p.x.round() as i32).unwrap() = (z / DEPTH_SCALE).round() as u16;
        }
        image
    }

    fn input<'a>(&'a self, id: u64, depth: Option<&'a Mat>) -> KeyframeInput<'a> {
        KeyframeInput {
            id,
            pose: self.pose,
            camera: camera(),
            features: &self.features,
            embeddings: &self.embeddings,
            depth: depth.map(|image| Depth { image, scale: DEPTH_SCALE }),
            external: None,
        }
    }
}

/// The new landmarks and observations of a planned keyframe without external landmarks.
fn parts(record: &Record) -> (&[(u64, [f64; 3])], &[NewObservation]) {
    match record {
        Record::AddKeyframe { new_landmarks, observations, .. } => (new_landmarks, observations),
        other => panic!("expected a keyframe record, got {other:?}"),
    }
}

/// Plans `input`, checks the record against `data` and applies it.
fn add(data: &mut MapData, input: &KeyframeInput, params: &BuildSettings) -> Record {
    let record = plan_keyframe(data, input, params).unwrap();
    data.check(&record).unwrap();
    data.apply(&record).unwrap();
    record
}

/// Keypoints of keyframe `keyframe` the record's observations use.
fn observed_keypoints(observations: &[NewObservation], keyframe: u64) -> Vec<u32> {
    let mut out: Vec<u32> = observations.iter().filter(|o| o.keyframe == keyframe).map(|o| o.keypoint).collect();
    out.sort_unstable();
    out
}

fn close(a: &[f64; 3], b: &Point3<f64>, tolerance: f64) -> bool {
    (Vector3::from(*a) - b.coords).norm() <= tolerance
}

#[test]
fn triangulation_makes_one_landmark_per_match_at_the_true_point_seen_by_both_keyframes() {
    let params = BuildSettings::default();
    let mut data = MapData::new(meta(DIM));
    let first = View::of(at(0.0));
    let record = add(&mut data, &first.input(0, None), &params);
    let (new, observations) = parts(&record);
    assert!(new.is_empty() && observations.is_empty(), "a first keyframe without depth has nothing to match");

    let second = View::of(at(0.4));
    let record = add(&mut data, &second.input(1, None), &params);
    let (new, observations) = parts(&record);
    assert_eq!(new.len(), N);
    assert_eq!(observations.len(), 2 * N);
    for &(id, p) in new {
        let seen: Vec<(u64, u32)> =
            observations.iter().filter(|o| o.landmark == id).map(|o| (o.keyframe, o.keypoint)).collect();
        assert_eq!(seen.len(), 2, "landmark {id}: {seen:?}");
        let k = seen[0].1;
        assert!(seen.contains(&(0, k)) && seen.contains(&(1, k)), "landmark {id}: {seen:?}");
        assert!(close(&p, &point(k as usize), 1e-3), "landmark {id} at {p:?}, point {k} at {:?}", point(k as usize));
    }
}

#[test]
fn triangulation_needs_the_parallax_the_settings_ask_for() {
    // 1 cm apart: the rays meet at 0.06-0.14 degrees, the nearer and more central points at the larger angles.
    let (first, second) = (View::of(at(0.0)), View::of(at(0.01)));
    let parallax = |k: usize| {
        let p = point(k).coords;
        let (a, b) = (p.normalize(), (p - Vector3::new(0.01, 0.0, 0.0)).normalize());
        a.dot(&b).clamp(-1.0, 1.0).acos().to_degrees()
    };
    let kept = |min_parallax_deg: f64| {
        let params = BuildSettings { min_parallax_deg, ..BuildSettings::default() };
        let mut data = MapData::new(meta(DIM));
        add(&mut data, &first.input(0, None), &params);
        let record = plan_keyframe(&data, &second.input(1, None), &params).unwrap();
        observed_keypoints(parts(&record).1, 1)
    };
    assert_eq!(kept(BuildSettings::default().min_parallax_deg), Vec::<u32>::new());
    let wide: Vec<u32> = (0..N).filter(|&k| parallax(k) >= 0.098).map(|k| k as u32).collect();
    assert_eq!(wide.len(), 14);
    assert_eq!(kept(0.098), wide);
    assert_eq!(kept(0.05).len(), N);
}

#[test]
fn a_wrong_match_does_not_reproject_and_makes_no_landmark() {
    let params = BuildSettings::default();
    let mut data = MapData::new(meta(DIM));
    add(&mut data, &View::of(at(0.0)).input(0, None), &params);
    // Keypoints 0 and 9 (rows 80 px apart) match each other's counterpart: their rays do not meet.
    let second = View::of(at(0.4)).swapped(0, 9);
    let record = plan_keyframe(&data, &second.input(1, None), &params).unwrap();
    let (new, observations) = parts(&record);
    assert_eq!(new.len(), N - 2);
    let used = observed_keypoints(observations, 1);
    assert!(!used.contains(&0) && !used.contains(&9), "{used:?}");
    // With a reprojection tolerance past the 80 px the landmark is made from the wrong pair.
    let loose = BuildSettings { reproj_px: 200.0, ..params };
    assert!(parts(&plan_keyframe(&data, &second.input(1, None), &loose).unwrap()).0.len() > N - 2);
}

#[test]
fn depth_back_projects_every_free_keypoint_with_a_reading_in_range() {
    let pose = Isometry3::new(Vector3::new(1.0, 2.0, 3.0), Vector3::new(0.0, 0.2, 0.05));
    let pixels = [(100.2, 50.7), (300.0, 200.0), (400.0, 300.0), (500.0, 400.0), (-3.0, 10.0), (639.4, 479.4)];
    // 4 m; no reading; 5 cm (under min_depth); 9 m; outside the image; 2 m at the last pixel.
    let raw = [20_000u16, 0, 250, 45_000, 20_000, 10_000];
    let mut image = Mat::new_rows_cols_with_default(480, 640, CV_16U, Scalar::all(0.0)).unwrap();
    for (&(x, y), &r) in pixels.iter().zip(&raw) {
        if x >= 0.0 {
            *image.at_2d_mut::<u16>((y as f64).round() as i32, (x as f64).round() as i32).unwrap() = r;
        }
    }
    let features = Features {
        width: 640,
        height: 480,
        keypoints: pixels.iter().map(|&(x, y)| keypoint(x, y)).collect(),
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; pixels.len()],
        context: Vec::new(),
    };
    let embeddings = vectors(pixels.len(), DIM, 3);
    let input = KeyframeInput {
        id: 0,
        pose,
        camera: camera(),
        features: &features,
        embeddings: &embeddings,
        depth: Some(Depth { image: &image, scale: DEPTH_SCALE }),
        external: None,
    };
    let plan_with = |params: &BuildSettings| plan_keyframe(&MapData::new(meta(DIM)), &input, params).unwrap();
    let record = plan_with(&BuildSettings::default());
    let (new, observations) = parts(&record);
    assert_eq!(observed_keypoints(observations, 0), vec![0, 3, 5]);
    let c = camera();
    for o in observations {
        let (x, y) = (f64::from(pixels[o.keypoint as usize].0), f64::from(pixels[o.keypoint as usize].1));
        let z = f64::from(raw[o.keypoint as usize]) * DEPTH_SCALE;
        let expected = pose * Point3::new((x - c.cx) / c.fx * z, (y - c.cy) / c.fy * z, z);
        let (_, p) = new.iter().find(|l| l.0 == o.landmark).unwrap();
        assert!(close(p, &expected, 1e-9), "keypoint {}: {p:?}, expected {expected:?}", o.keypoint);
    }
    let near = plan_with(&BuildSettings { max_depth: 8.0, ..BuildSettings::default() });
    assert_eq!(observed_keypoints(parts(&near).1, 0), vec![0, 5], "9 m is beyond max_depth");
    let far = plan_with(&BuildSettings { min_depth: 3.0, ..BuildSettings::default() });
    assert_eq!(observed_keypoints(parts(&far).1, 0), vec![0, 3], "2 m is under min_depth");
}

#[test]
fn a_matched_landmark_is_observed_where_it_reprojects_and_depth_fills_the_rest() {
    let params = BuildSettings::default();
    let mut data = MapData::new(meta(DIM));
    let first = View::of(at(0.0));
    let depth0 = first.depth();
    let record = add(&mut data, &first.input(0, Some(&depth0)), &params);
    assert_eq!(parts(&record).0.len(), N, "depth makes every landmark of the first keyframe");
    let landmarks = data.keypoint_landmarks(0);

    // At its true pose, every keypoint observes the landmark its match observes, and depth makes none.
    let second = View::of(at(0.4));
    let depth1 = second.depth();
    let record = plan_keyframe(&data, &second.input(1, Some(&depth1)), &params).unwrap();
    let (new, observations) = parts(&record);
    assert!(new.is_empty(), "{} new landmarks", new.len());
    assert_eq!(observations.len(), N);
    assert!(observations.iter().all(|o| o.keyframe == 1 && o.landmark == landmarks[&o.keypoint]));

    // Given half a metre off, the landmarks reproject 31-62 px from the keypoints: depth makes new ones.
    let off = View { pose: at(0.9), ..View::of(at(0.4)) };
    let record = plan_keyframe(&data, &off.input(1, Some(&depth1)), &params).unwrap();
    let (new, observations) = parts(&record);
    assert_eq!(new.len(), N);
    assert!(observations.iter().all(|o| new.iter().any(|l| l.0 == o.landmark)));
    // A tolerance past that observes them again.
    let loose = BuildSettings { reproj_px: 100.0, ..params };
    let record = plan_keyframe(&data, &off.input(1, Some(&depth1)), &loose).unwrap();
    assert!(parts(&record).0.is_empty());
}

/// A keyframe at `x` on the x axis (looking along +z, or along -z when `backwards`) with three keypoints, each
/// observing landmark `landmarks[i]` (made by this record when it is new to `data`).
fn add_observer(data: &mut MapData, id: u64, x: f64, backwards: bool, landmarks: &[u64]) {
    let rotation = if backwards {
        UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0)
    } else {
        UnitQuaternion::identity()
    };
    let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), rotation);
    let n = landmarks.len();
    let keyframe = crate::map::model::Keyframe {
        id,
        pose: crate::camera::Pose::from_isometry(&pose),
        camera: camera(),
        keypoints: (0..n).map(|i| keypoint(100.0 + 50.0 * i as f32, 100.0)).collect(),
        descriptors: vec![0; n * DESCRIPTOR_BYTES],
        embeddings: vectors(n, DIM, id),
    };
    let new_landmarks =
        landmarks.iter().filter(|l| !data.landmarks.contains_key(l)).map(|&l| (l, [x, 0.0, 5.0])).collect();
    let observations = landmarks
        .iter()
        .enumerate()
        .map(|(i, &l)| NewObservation { landmark: l, keyframe: id, keypoint: i as u32 })
        .collect();
    let record = Record::AddKeyframe { keyframe, new_landmarks, observations };
    data.check(&record).unwrap();
    data.apply(&record).unwrap();
}

#[test]
fn candidates_are_the_nearest_keyframes_looking_the_same_way_then_the_covisible_ones() {
    let mut data = MapData::new(meta(DIM));
    add_observer(&mut data, 1, 3.0, false, &[0, 1, 2]);
    add_observer(&mut data, 2, 1.0, false, &[3]);
    add_observer(&mut data, 3, 0.5, true, &[0, 1, 2]); // nearest, but looking the other way
    add_observer(&mut data, 4, 20.0, false, &[0, 1]);
    add_observer(&mut data, 5, 25.0, false, &[2]);
    add_observer(&mut data, 6, 2.0, false, &[4]);
    let view = View::of(at(0.0));
    let input = view.input(9, None);
    let ids = |params: BuildSettings| candidates(&data, &input, &params).iter().map(|k| k.id).collect::<Vec<_>>();
    let nearest = |n: usize| BuildSettings { candidates: n, ..BuildSettings::default() };
    assert_eq!(ids(nearest(2)), vec![2, 6]);
    assert_eq!(ids(nearest(10)), vec![2, 6, 1, 4, 5]);
    assert_eq!(ids(nearest(0)), Vec::<u64>::new());
    // Keyframe 1 shares landmarks 0 and 1 with keyframe 4, landmark 2 with keyframe 5 (keyframe 3, which
    // shares all three, looks the other way).
    let covisible = |n: usize| BuildSettings { covisible_candidates: n, ..nearest(3) };
    assert_eq!(ids(covisible(1)), vec![2, 6, 1, 4]);
    assert_eq!(ids(covisible(5)), vec![2, 6, 1, 4, 5]);
    // No candidate, no match: a keyframe without depth then makes nothing.
    let record = plan_keyframe(&data, &input, &nearest(0)).unwrap();
    assert!(parts(&record).0.is_empty() && parts(&record).1.is_empty());
}

#[test]
fn the_epipolar_window_keeps_the_candidate_keypoints_near_the_line() {
    // The candidate 40 cm along x: epipolar lines are image rows.
    let features = Features {
        width: 640,
        height: 480,
        keypoints: vec![keypoint(300.0, 200.0), keypoint(100.0, 50.0)],
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; 2],
        context: Vec::new(),
    };
    let embeddings = vectors(2, DIM, 1);
    let input = KeyframeInput {
        id: 1,
        pose: at(0.0),
        camera: camera(),
        features: &features,
        embeddings: &embeddings,
        depth: None,
        external: None,
    };
    let cand = crate::map::model::Keyframe {
        id: 0,
        pose: crate::camera::Pose::from_isometry(&at(0.4)),
        camera: camera(),
        keypoints: vec![keypoint(250.0, 200.0), keypoint(250.0, 205.0), keypoint(250.0, 212.0), keypoint(50.0, 50.5)],
        descriptors: vec![0; 4 * DESCRIPTOR_BYTES],
        embeddings: vectors(4, DIM, 2),
    };
    let rows = |px: f64| {
        let mask = epipolar_mask(&input, &cand, px).unwrap();
        (0..2).map(|r| (0..4).map(|c| *mask.at_2d::<u8>(r, c).unwrap()).collect::<Vec<_>>()).collect::<Vec<_>>()
    };
    assert_eq!(rows(8.0), vec![vec![1, 1, 0, 0], vec![0, 0, 0, 1]]);
    assert_eq!(rows(2.0), vec![vec![1, 0, 0, 0], vec![0, 0, 0, 1]]);
    // The same centre: no epipolar geometry, an empty mask lets every pair compete.
    let same = crate::map::model::Keyframe { pose: crate::camera::Pose::from_isometry(&at(0.0)), ..cand };
    assert!(epipolar_mask(&input, &same, 8.0).unwrap().empty());
}

#[test]
fn external_observations_follow_the_radius_and_the_reprojection_tolerance() {
    let features = Features {
        width: 640,
        height: 480,
        keypoints: vec![keypoint(100.0, 100.0), keypoint(300.0, 100.0)],
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; 2],
        context: Vec::new(),
    };
    let embeddings = vectors(2, DIM, 5);
    let c = camera();
    let seen_at = |x: f64, y: f64, id: u64| ExternalObservation {
        x,
        y,
        landmark_id: id,
        point: [(x - c.cx) / c.fx * 5.0, (y - c.cy) / c.fy * 5.0, 5.0],
    };
    // 1.5 px from keypoint 0; 3 px from keypoint 1, and from where its point reprojects.
    let mut off = seen_at(300.0, 100.0, 2);
    off.x += 3.0;
    let external = [seen_at(101.5, 100.0, 1), off];
    let input = KeyframeInput {
        id: 0,
        pose: Isometry3::identity(),
        camera: c,
        features: &features,
        embeddings: &embeddings,
        depth: None,
        external: Some(&external),
    };
    let counts = |params: BuildSettings| {
        let p = plan(&MapData::new(meta(DIM)), &input, &params).unwrap();
        assert_eq!(p.record, plan_keyframe(&MapData::new(meta(DIM)), &input, &params).unwrap());
        (p.external.associated, p.external.rejected, p.external.unassociated)
    };
    let defaults = BuildSettings::default();
    assert_eq!(counts(defaults), (1, 0, 1), "within 4 px; the second is 3 px from keypoint 1, past 2 px");
    assert_eq!(counts(BuildSettings { external_radius_px: 4.0, ..defaults }), (2, 0, 0));
    assert_eq!(counts(BuildSettings { external_radius_px: 1.0, ..defaults }), (0, 0, 2));
    assert_eq!(counts(BuildSettings { external_reproj_px: 2.0, ..defaults }), (1, 1, 0));
}

#[test]
fn input_that_does_not_fit_the_map_is_refused() {
    let params = BuildSettings::default();
    let mut data = MapData::new(meta(DIM));
    let view = View::of(at(0.0));
    add(&mut data, &view.input(0, None), &params);
    let again = plan_keyframe(&data, &view.input(0, None), &params).unwrap_err();
    assert!(matches!(again, MapError::KeyframeExists { keyframe: 0, .. }), "{again}");
    let short = KeyframeInput { embeddings: &view.embeddings[..DIM], ..view.input(1, None) };
    let err = plan_keyframe(&data, &short, &params).unwrap_err();
    assert!(matches!(&err, MapError::InvalidInput { field, .. } if field == "embeddings"), "{err}");
    let nowhere = KeyframeInput { pose: at(f64::NAN), ..view.input(1, None) };
    let err = plan_keyframe(&data, &nowhere, &params).unwrap_err();
    assert!(matches!(&err, MapError::InvalidInput { field, .. } if field == "pose"), "{err}");
}
