//! Unit tests of the stages beyond the plain search: localisation against candidate keyframes (stage 2, with
//! FREAK's bits), guided search (stage 3), and map building that uses the known poses.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};

use crate::camera::{Camera, Pose};
use crate::describe::features::{Features, Keypoint, DESCRIPTOR_BYTES};
use crate::map::builder::{plan_keyframe, BuildSettings, KeyframeInput};
use crate::map::index::{EmbeddingIndex, IndexSettings};
use crate::map::localize::{localize, Localization, LocalizeSettings, Prior};
use crate::map::model::{Keyframe, MapData, NewObservation, Record};
use crate::map::tests::{meta, vectors};

const DIM: usize = 48;
const N: usize = 200;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

/// Landmark `i` of the test scene: seen at a scattered pixel by a camera at the origin looking along +z.
fn pixel(i: usize) -> (f32, f32) {
    (((i * 37) % 600 + 20) as f32, ((i * 91) % 440 + 20) as f32)
}

fn point(i: usize) -> [f64; 3] {
    let (x, y) = pixel(i);
    let c = camera();
    let z = 4.0 + (i % 7) as f64;
    [(f64::from(x) - c.cx) / c.fx * z, (f64::from(y) - c.cy) / c.fy * z, z]
}

/// FREAK bits of landmark `i` (distinct per landmark).
fn bits(i: usize, seed: u64) -> [u8; DESCRIPTOR_BYTES] {
    let mut s = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ seed;
    std::array::from_fn(|_| {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s as u8
    })
}

fn keypoints(pixels: impl Iterator<Item = (f32, f32)>) -> Vec<Keypoint> {
    pixels.map(|(x, y)| Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }).collect()
}

/// A keyframe at `translation` (identity rotation) observing landmarks `first..first + N` at the test pixels,
/// with embeddings `embeddings` and FREAK bits of seed `seed`, its points moved by `translation`.
fn add_keyframe(data: &mut MapData, id: u64, translation: [f64; 3], first: u64, embeddings: Vec<f32>, seed: u64) {
    let descriptors = (0..N).flat_map(|i| bits(i, seed)).collect();
    let keyframe = Keyframe {
        id,
        pose: Pose { translation, rotation: [0.0, 0.0, 0.0, 1.0] },
        camera: camera(),
        keypoints: keypoints((0..N).map(pixel)),
        descriptors,
        embeddings,
    };
    let moved = |p: [f64; 3]| [p[0] + translation[0], p[1] + translation[1], p[2] + translation[2]];
    let record = Record::AddKeyframe {
        keyframe,
        new_landmarks: (0..N).map(|i| (first + i as u64, moved(point(i)))).collect(),
        observations: (0..N)
            .map(|i| NewObservation { landmark: first + i as u64, keyframe: id, keypoint: i as u32 })
            .collect(),
    };
    data.check(&record).unwrap();
    data.apply(&record).unwrap();
}

/// The scene's map, and beside it (1 km away) a keyframe of look-alikes: landmarks whose embeddings equal the
/// scene's for every `i` below `alike`, so that stage 1's ratio test (against the whole map) refuses them.
fn map_with_look_alikes(alike: usize) -> MapData {
    let mut data = MapData::new(meta(DIM));
    let e = vectors(N, DIM, 5);
    add_keyframe(&mut data, 0, [0.0; 3], 0, e.clone(), 1);
    let other = vectors(N, DIM, 99);
    let look_alike: Vec<f32> = (0..N)
        .flat_map(|i| if i < alike { &e[i * DIM..(i + 1) * DIM] } else { &other[i * DIM..(i + 1) * DIM] })
        .copied()
        .collect();
    add_keyframe(&mut data, 1, [1000.0, 0.0, 0.0], N as u64, look_alike, 2);
    data
}

/// The query: the scene's keypoints seen again from the origin, embeddings slightly perturbed, FREAK bits
/// the map keyframe's.
fn query(garbage: std::ops::Range<usize>) -> (Features, Vec<f32>) {
    let e = vectors(N, DIM, 5);
    let noise = vectors(N, DIM, 7);
    let random = vectors(N, DIM, 11);
    let embeddings = (0..N)
        .flat_map(|i| {
            let row = i * DIM..(i + 1) * DIM;
            let g = garbage.contains(&i);
            row.map(move |j| (j, g))
        })
        .map(|(j, g)| if g { random[j] } else { e[j] + 0.02 * noise[j] })
        .collect();
    let features = Features {
        width: 640,
        height: 480,
        keypoints: keypoints((0..N).map(pixel)),
        descriptors: (0..N).map(|i| bits(i, 1)).collect(),
        context: Vec::new(),
    };
    (features, embeddings)
}

/// Localises the query against `data` (exact search: the maps here are small) with the test camera.
fn locate(data: &MapData, features: &Features, embeddings: &[f32], params: &LocalizeSettings) -> Localization {
    let index = EmbeddingIndex::new(IndexSettings::default());
    localize(data, &index, features, embeddings, &camera(), None, params).unwrap()
}

fn correct(l: &Localization) -> usize {
    l.matches.iter().filter(|m| m.landmark == m.keypoint as u64).count()
}

#[test]
fn stage_two_finds_a_query_that_look_alikes_hide_from_the_index_search() {
    // 190 of 200 landmarks have a look-alike elsewhere in the map: stage 1 keeps only the 10 unique ones, too
    // few for a pose, but they vote for keyframe 0, and against its landmarks alone all 200 are unambiguous.
    let data = map_with_look_alikes(190);
    let (features, embeddings) = query(0..0);
    let old = LocalizeSettings::default().stage_one_only();
    let l = locate(&data, &features, &embeddings, &old);
    assert!(l.pose.is_none(), "stage 1 alone: {} matches", l.matches.len());
    assert_eq!(l.matches.len(), 10);
    let staged = LocalizeSettings { candidate_matching: true, ..LocalizeSettings::default().stage_one_only() };
    let l = locate(&data, &features, &embeddings, &staged);
    let pose = l.pose.as_ref().expect("stage 2 localises");
    assert!(pose.camera_to_world.translation.vector.norm() < 1e-3);
    assert_eq!(correct(&l), l.matches.len(), "every match is the true landmark");
    assert!(l.matches.len() >= 190, "{} matches", l.matches.len());
    assert!(l.stages_s > 0.0);
}

#[test]
fn stage_two_joins_freak_matches_where_the_embedding_fails() {
    // Keypoints 100-189 carry embeddings of nothing in the map; their FREAK bits are the keyframe's.
    let data = map_with_look_alikes(190);
    let (features, embeddings) = query(100..190);
    let without = LocalizeSettings { candidate_matching: true, ..LocalizeSettings::default().stage_one_only() };
    // Correct matches of the keypoints whose embeddings describe nothing (chance ones may be wrong matches).
    let rescued = |l: &Localization| {
        l.matches.iter().filter(|m| (100..190).contains(&m.keypoint) && m.landmark == m.keypoint as u64).count()
    };
    let l = locate(&data, &features, &embeddings, &without);
    assert_eq!(rescued(&l), 0);
    let with = LocalizeSettings { candidate_freak: true, ..without };
    let l = locate(&data, &features, &embeddings, &with);
    assert!(rescued(&l) >= 80, "FREAK joined {} of 90", rescued(&l));
    let pose = l.pose.as_ref().expect("localised");
    assert!(pose.inliers.iter().all(|&i| l.matches[i].landmark == l.matches[i].keypoint as u64));
    // Without FREAK bits on the query the join is skipped, not an error.
    let bare = Features { descriptors: Vec::new(), ..features };
    let l = locate(&data, &bare, &embeddings, &with);
    assert_eq!(rescued(&l), 0);
}

#[test]
fn stage_three_adds_the_projected_landmarks_and_never_creates_a_pose() {
    let guided_only = LocalizeSettings { guided_search: true, ..LocalizeSettings::default().stage_one_only() };
    // 60 unique landmarks give stage 1 a pose; guided search adds the 140 hidden by their look-alikes.
    let data = map_with_look_alikes(140);
    let (features, embeddings) = query(0..0);
    let old = locate(&data, &features, &embeddings, &LocalizeSettings::default().stage_one_only());
    let before = old.pose.expect("stage 1 localises").inliers.len();
    let l = locate(&data, &features, &embeddings, &guided_only);
    let after = l.pose.as_ref().expect("still localised").inliers.len();
    assert!(before <= 60 && after >= 180, "inliers {before} -> {after}");
    assert_eq!(correct(&l), l.matches.len());
    // 10 unique landmarks give no pose, and stage 3 alone does not make one.
    let data = map_with_look_alikes(190);
    let l = locate(&data, &features, &embeddings, &guided_only);
    assert!(l.pose.is_none());
    assert_eq!(l.matches.len(), 10);
}

#[test]
fn a_query_keypoint_cap_bounds_stage_one_and_stages_two_and_three_read_every_keypoint() {
    let data = map_with_look_alikes(0);
    let (features, embeddings) = query(0..0);
    let capped = LocalizeSettings { max_query_keypoints: 50, ..LocalizeSettings::default().stage_one_only() };
    let l = locate(&data, &features, &embeddings, &capped);
    assert_eq!(l.matches.len(), 50);
    assert!(l.matches.iter().all(|m| m.keypoint < 50), "stage 1 searched only the first 50 (equal responses)");
    // Stage 2 matches the whole query against the keyframe the 50 voted for (skipped above 100 inliers: 50
    // give fewer).
    let staged = LocalizeSettings { candidate_matching: true, ..capped };
    let l = locate(&data, &features, &embeddings, &staged);
    assert!(l.matches.len() >= 190, "stage 2 reached {} keypoints", l.matches.len());
    assert!(l.matches.iter().any(|m| m.keypoint >= 50));
    assert_eq!(correct(&l), l.matches.len());
    let guided = LocalizeSettings { guided_search: true, ..capped };
    let l = locate(&data, &features, &embeddings, &guided);
    assert!(l.matches.len() >= 190, "guided search reached {} keypoints", l.matches.len());
    assert_eq!(correct(&l), l.matches.len());
}

/// A scene of `points` 3D points in front of cameras at the origin looking along +z, with one embedding and
/// one set of FREAK bits per point.
struct Scene3 {
    points: Vec<Point3<f64>>,
    embeddings: Vec<f32>,
}

impl Scene3 {
    fn new(n: usize) -> Self {
        let r = vectors(n, 3, 21);
        let points = (0..n)
            .map(|i| {
                let v = &r[i * 3..i * 3 + 3];
                Point3::new(f64::from(v[0]) * 3.0, f64::from(v[1]) * 2.0, 7.0 + f64::from(v[2]) * 3.0)
            })
            .collect();
        Self { points, embeddings: vectors(n, DIM, 23) }
    }

    /// What a keyframe at `x` on the x axis sees: keypoint k is point `seen[k]`.
    fn view(&self, x: f64) -> (Isometry3<f64>, Features, Vec<f32>, Vec<usize>) {
        let pose = Isometry3::from_parts(Translation3::new(x, 0.0, 0.0), UnitQuaternion::identity());
        let cam = camera();
        let mut seen = Vec::new();
        let mut pixels = Vec::new();
        for (i, p) in self.points.iter().enumerate() {
            if let Some((u, v)) = cam.project(&pose.inverse_transform_point(p)) {
                if u >= 0.0 && v >= 0.0 && u < 640.0 && v < 480.0 {
                    seen.push(i);
                    pixels.push((u as f32, v as f32));
                }
            }
        }
        let embeddings = seen.iter().flat_map(|&i| self.embeddings[i * DIM..(i + 1) * DIM].iter().copied()).collect();
        let features = Features {
            width: 640,
            height: 480,
            keypoints: keypoints(pixels.into_iter()),
            descriptors: seen.iter().map(|&i| bits(i, 3)).collect(),
            context: Vec::new(),
        };
        (pose, features, embeddings, seen)
    }
}

/// A keyframe with a known pose, without depth or external landmarks.
fn posed<'a>(id: u64, pose: Isometry3<f64>, features: &'a Features, embeddings: &'a [f32]) -> KeyframeInput<'a> {
    KeyframeInput { id, pose, camera: camera(), features, embeddings, depth: None, external: None }
}

fn build(scene: &Scene3, xs: &[f64], params: &BuildSettings) -> MapData {
    let mut data = MapData::new(meta(DIM));
    for (id, &x) in xs.iter().enumerate() {
        let (pose, features, embeddings, _) = scene.view(x);
        let input = posed(id as u64, pose, &features, &embeddings);
        let record = plan_keyframe(&data, &input, params).unwrap();
        data.check(&record).unwrap();
        data.apply(&record).unwrap();
    }
    data
}

#[test]
fn tracks_extend_to_every_keyframe_that_sees_the_landmark() {
    // Keyframes 0 and 1 are 2 cm apart: too little parallax to triangulate, so their keypoints stay free.
    // Keyframe 2, half a metre away, triangulates with the nearer one and, with tracks extended, the other
    // keyframe's keypoint joins the landmark too.
    let scene = Scene3::new(150);
    let xs = [0.0, 0.02, 0.5];
    let pairs =
        build(&scene, &xs, &BuildSettings { extend_tracks: false, ..BuildSettings::default().with_known_poses() });
    let tracks = build(&scene, &xs, &BuildSettings::default().with_known_poses());
    assert_eq!(pairs.landmarks.len(), tracks.landmarks.len());
    assert!(pairs.landmarks.len() >= 100, "{} landmarks", pairs.landmarks.len());
    assert!(pairs.landmarks.values().all(|l| l.observations.len() == 2));
    let three = tracks.landmarks.values().filter(|l| l.observations.len() == 3).count();
    assert!(three * 10 >= tracks.landmarks.len() * 9, "{three} of {} seen by all three", tracks.landmarks.len());
    // Every observation is of the point its keypoint sees.
    for data in [&pairs, &tracks] {
        for o in &data.observations {
            let (_, _, _, seen) = scene.view(xs[o.keyframe as usize]);
            let truth = scene.points[seen[o.keypoint as usize]];
            let p = data.landmarks[&o.landmark].point;
            assert!((Point3::from(p) - truth).norm() < 1e-3);
        }
    }
}

#[test]
fn the_epipolar_window_matches_what_look_alikes_hide_from_the_plain_ratio_test() {
    // Every point shares its embedding with another point (pairs 2k, 2k + 1): the plain ratio test sees two
    // equal candidates and keeps nothing; within the epipolar window only the true one competes.
    let mut scene = Scene3::new(150);
    for k in (0..150).step_by(2) {
        let (a, b) = (k * DIM, (k + 1) * DIM);
        scene.embeddings.copy_within(a..b, b);
    }
    let xs = [0.0, 0.5];
    let plain = build(&scene, &xs, &BuildSettings::default().unguided());
    let guided =
        build(&scene, &xs, &BuildSettings { freak_matches: false, ..BuildSettings::default().with_known_poses() });
    assert!(plain.landmarks.len() <= 10, "plain: {}", plain.landmarks.len());
    assert!(guided.landmarks.len() >= 100, "guided: {}", guided.landmarks.len());
    for o in &guided.observations {
        let (_, _, _, seen) = scene.view(xs[o.keyframe as usize]);
        let truth = scene.points[seen[o.keypoint as usize]];
        assert!((Point3::from(guided.landmarks[&o.landmark].point) - truth).norm() < 1e-3);
    }
}

#[test]
fn freak_matches_join_the_embeddings_in_map_building() {
    // The second keyframe's embeddings describe nothing; its FREAK bits are the first keyframe's.
    let scene = Scene3::new(150);
    let mut data = MapData::new(meta(DIM));
    for (id, x) in [(0u64, 0.0), (1, 0.5)] {
        let (pose, features, mut embeddings, _) = scene.view(x);
        if id == 1 {
            embeddings = vectors(features.len(), DIM, 77);
        }
        let input = posed(id, pose, &features, &embeddings);
        let without = plan_keyframe(
            &data,
            &input,
            &BuildSettings { freak_matches: false, ..BuildSettings::default().with_known_poses() },
        );
        let record = plan_keyframe(&data, &input, &BuildSettings::default().with_known_poses()).unwrap();
        if id == 1 {
            let Record::AddKeyframe { new_landmarks: none, .. } = without.unwrap() else { unreachable!() };
            let Record::AddKeyframe { new_landmarks: some, .. } = &record else { unreachable!() };
            assert!(none.len() <= 5 && some.len() >= 100, "{} -> {}", none.len(), some.len());
        }
        data.check(&record).unwrap();
        data.apply(&record).unwrap();
    }
}

#[test]
fn stage_settings_are_checked() {
    let ok = LocalizeSettings::default();
    assert!(ok.validate().is_ok());
    for bad in [
        LocalizeSettings { candidate_ratio: 0.0, ..ok },
        LocalizeSettings { guided_ratio: 1.5, ..ok },
        LocalizeSettings { guided_radius_px: f64::NAN, ..ok },
        LocalizeSettings { candidate_keyframes: 0, ..ok },
    ] {
        assert!(bad.validate().is_err(), "{bad:?}");
    }
    assert!(LocalizeSettings { candidate_keyframes: 0, ..ok.stage_one_only() }.validate().is_ok());
    assert!(BuildSettings { epipolar_px: -1.0, ..BuildSettings::default() }.validate().is_err());
}

#[test]
fn every_stage_keeps_to_the_prior() {
    // Stage 1 finds the unique landmarks inside the radius; stages 2 and 3 must not reach beyond it either.
    let data = map_with_look_alikes(150);
    let (features, embeddings) = query(0..0);
    let prior = Prior { position: [0.0; 3], radius: 7.5 };
    let inside = (0..N).filter(|&i| nalgebra::Vector3::from(point(i)).norm() <= prior.radius).count();
    assert!(inside > 60 && inside < N - 30, "{inside} landmarks inside");
    let all = LocalizeSettings { candidate_freak: true, guided_search: true, ..LocalizeSettings::default() };
    let index = EmbeddingIndex::new(IndexSettings::default());
    let l = localize(&data, &index, &features, &embeddings, &camera(), Some(&prior), &all).unwrap();
    assert!(l.pose.is_some());
    assert!(l.matches.len() >= inside * 9 / 10, "{} of {inside}", l.matches.len());
    for m in &l.matches {
        let p = nalgebra::Vector3::from(data.landmarks[&m.landmark].point);
        assert!(p.norm() <= prior.radius, "landmark {} at {:.2} is outside the prior", m.landmark, p.norm());
    }
}

#[test]
fn keyframes_at_one_centre_match_without_an_epipolar_window() {
    // A keyframe at the centre of an earlier one has no epipolar geometry with it: the window must not shut
    // every pair out, and the new keyframe observes the earlier one's landmarks as without the window.
    let mut data = MapData::new(meta(DIM));
    add_keyframe(&mut data, 0, [0.0; 3], 0, vectors(N, DIM, 5), 1);
    let (features, embeddings) = query(0..0);
    let params = BuildSettings::default().with_known_poses();
    let plan = plan_keyframe(&data, &posed(1, Isometry3::identity(), &features, &embeddings), &params).unwrap();
    let Record::AddKeyframe { observations, .. } = plan else { unreachable!() };
    assert!(observations.len() >= 190, "{} observations", observations.len());
    assert!(observations.iter().all(|o| o.landmark == u64::from(o.keypoint)));
}

#[test]
fn a_capped_query_short_of_the_fallback_inliers_is_answered_as_without_the_cap() {
    let (features, embeddings) = query(0..0);
    let same = |a: &Localization, b: &Localization| {
        assert_eq!(a.matches, b.matches);
        let (pa, pb) = (a.pose.as_ref().expect("localised"), b.pose.as_ref().expect("localised"));
        assert_eq!(pa.inliers, pb.inliers);
        assert_eq!(pa.camera_to_world, pb.camera_to_world);
        assert_eq!(a.confidence, b.confidence);
    };
    // Without look-alikes, and with 150 landmarks whose look-alikes hide them from stage 1.
    for alike in [0, 150] {
        let data = map_with_look_alikes(alike);
        let every_keypoint = LocalizeSettings { max_query_keypoints: usize::MAX, ..LocalizeSettings::default() };
        for base in [LocalizeSettings::default().stage_one_only(), every_keypoint] {
            let every = locate(&data, &features, &embeddings, &base);
            let capped = LocalizeSettings { max_query_keypoints: 50, full_search_below_inliers: 0, ..base };
            let alone = locate(&data, &features, &embeddings, &capped);
            // Short of the inliers: the other 150 keypoints are searched, and the answer is the uncapped one.
            let fallback = LocalizeSettings { full_search_below_inliers: 1000, ..capped };
            same(&locate(&data, &features, &embeddings, &fallback), &every);
            // A capped pose with enough inliers is kept as the capped search gave it.
            let firm = alone.pose.as_ref().map_or(0, |p| p.inliers.len());
            if firm > 0 {
                let kept = LocalizeSettings { full_search_below_inliers: firm, ..capped };
                same(&locate(&data, &features, &embeddings, &kept), &alone);
            }
            if alike == 0 {
                assert!(firm > 0, "50 clean matches localise");
                assert_ne!(alone.matches, every.matches, "the cap changed what stage 1 found");
            }
        }
    }
}
