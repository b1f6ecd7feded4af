//! Issue 28, section 5: merging two maps of one place. A scene's keyframes are split into two maps, each moved
//! into its own random world frame (rotation, translation, scale); after the merge the source's keyframes sit
//! where the target's frame puts them, and the merged map localises at least as often as the better of the
//! two. A merge killed with SIGKILL at any moment leaves the target as it was or merged, and the source intact.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Point3, Similarity3, Translation3, UnitQuaternion, Vector3};
use scone::map::builder::KeyframeInput;
use scone::offline::scene::Scene;
use scone::server::proto;
use tonic::Code;

use crate::common::{fixture, shared_data, temp_dir};
use crate::durability::open;
use crate::service::{add_keyframes, clients, image_frame, keyframe_requests, serve, settings};

/// A world frame of its own: rotation, translation and scale drawn from `seed`.
fn frame_of(seed: u64) -> Similarity3<f64> {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let mut u = move || {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        (x >> 11) as f64 / (1u64 << 53) as f64
    };
    let axis = Vector3::new(u() - 0.5, u() - 0.5, u() - 0.5);
    let rotation = UnitQuaternion::from_scaled_axis(axis.normalize() * (0.5 + 2.5 * u()));
    let t = Vector3::new(20.0 * u() - 10.0, 20.0 * u() - 10.0, 20.0 * u() - 10.0);
    Similarity3::from_parts(Translation3::from(t), rotation, 0.3 + 3.0 * u())
}

/// A camera-to-world pose carried into the frame `s` (the camera's own axes unchanged).
fn moved(s: &Similarity3<f64>, p: &Isometry3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from((s * Point3::from(p.translation.vector)).coords),
        s.isometry.rotation * p.rotation,
    )
}

fn pose_msg(p: &Isometry3<f64>) -> proto::Pose {
    let (q, t) = (p.rotation.quaternion(), p.translation.vector);
    proto::Pose { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

fn pose_of(p: &proto::Pose) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(p.tx, p.ty, p.tz),
        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(p.qw, p.qx, p.qy, p.qz)),
    )
}

/// Keyframes of `frames` in the world frame `s`, without depth (depth is metric; the moved world is not).
fn moved_keyframes(map: &str, scene: &Scene, frames: &[usize], s: &Similarity3<f64>) -> Vec<proto::AddKeyframeRequest> {
    let mut reqs = keyframe_requests(map, scene, frames);
    for (r, &i) in reqs.iter_mut().zip(frames) {
        r.pose = Some(pose_msg(&moved(s, &scene.frames[i].pose.unwrap())));
        r.depth_png = Vec::new();
    }
    reqs
}

/// The scene's largest distance between two camera centres.
fn extent(scene: &Scene) -> f64 {
    let c: Vec<Vector3<f64>> = scene.frames.iter().filter_map(|f| f.pose).map(|p| p.translation.vector).collect();
    c.iter().flat_map(|a| c.iter().map(move |b| (a - b).norm())).fold(0.0, f64::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_maps_in_their_own_frames_merge_into_one_that_agrees_with_the_truth() {
    let dir = temp_dir("merge");
    let server = serve(settings(&dir)).await;
    let (mut maps, matching) = clients(&server).await;
    let mut scenes = vec![Scene::load(&fixture("rendered")).unwrap()];
    if let Some(data) = shared_data() {
        scenes.push(Scene::load(&data.join("scenes/tum-fr3-long-office")).unwrap());
    }
    for (n, scene) in scenes.iter().enumerate() {
        let frames: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
        let even: Vec<usize> = frames.iter().copied().filter(|i| i % 2 == 0).collect();
        let odd: Vec<usize> = frames.iter().copied().filter(|i| i % 2 == 1).collect();
        let (sa, sb) = (frame_of(11 + n as u64), frame_of(23 + n as u64));
        let (a, b) = (format!("a{n}"), format!("b{n}"));
        for (map, part, s) in [(&a, &even, &sa), (&b, &odd, &sb)] {
            maps.create_map(proto::CreateMapRequest { map_id: map.clone() }).await.unwrap();
            add_keyframes(&mut maps, moved_keyframes(map, scene, part, s), None).await;
        }
        let cam = scene.camera;
        let size = extent(scene);

        // Success of every frame against a map whose frame is `s` (within 5 % of the path and 2°, each widened by
        // `slack_deg` for the merged map: half of its keyframes sit in a frame off by the transform's error, and
        // a pose from landmarks of both halves, each consistent only with itself, can be pulled further. With
        // stage 1 capped at 100 (session 45's default), the query at a source keyframe of a merge whose
        // transform was 0.935° off landed 3.0° off with 658 inliers; with every keypoint searched, 0.99°-off
        // merges kept every frame within 2°).
        let successes = |map: String, s: Similarity3<f64>, slack_deg: f64| {
            let mut matching = matching.clone();
            let scene = scene.clone();
            let frames = frames.clone();
            async move {
                let mut ok = 0;
                for &i in &frames {
                    let r = matching
                        .localize(proto::LocalizeRequest {
                            map_id: map.clone(),
                            frame: Some(image_frame(&scene.frames[i].rgb, &cam)),
                            ..Default::default()
                        })
                        .await
                        .unwrap()
                        .into_inner();
                    let Some(p) = r.pose.as_ref() else { continue };
                    let truth = moved(&s, &scene.frames[i].pose.unwrap());
                    let p = pose_of(p);
                    let dt = (p.translation.vector - truth.translation.vector).norm() / s.scaling();
                    let (t_max, r_max) = ((0.05 + slack_deg.to_radians()) * size, 2.0 + slack_deg);
                    if dt < t_max && p.rotation.angle_to(&truth.rotation).to_degrees() < r_max {
                        ok += 1;
                    }
                }
                ok
            }
        };
        let (before_a, before_b) = (successes(a.clone(), sa, 0.0).await, successes(b.clone(), sb, 0.0).await);

        let r = maps
            .merge_maps(proto::MergeMapsRequest { target_map_id: a.clone(), source_map_id: b.clone(), transform: None })
            .await
            .unwrap()
            .into_inner();
        eprintln!(
            "{}: {} of {} source keyframes localised, {} agree; {} fused, {} added",
            scene.name,
            r.keyframes_localised,
            r.source_keyframes,
            r.transform_inliers,
            r.landmarks_fused,
            r.landmarks_added
        );
        assert!(r.transform_estimated);
        assert_eq!(r.target.as_ref().unwrap().keyframes as usize, frames.len());
        assert!(r.landmarks_fused > 0, "landmarks seen by both maps are fused");
        // The estimated transform is the true one: B's frame into A's.
        let t = r.transform.unwrap();
        let est = Similarity3::from_parts(
            Translation3::new(t.tx, t.ty, t.tz),
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(t.qw, t.qx, t.qy, t.qz)),
            t.scale,
        );
        let truth = sa * sb.inverse();
        assert!((est.scaling() / truth.scaling() - 1.0).abs() < 0.02, "scale {} vs {}", est.scaling(), truth.scaling());
        let degrees = est.isometry.rotation.angle_to(&truth.isometry.rotation).to_degrees();
        eprintln!(
            "{}: transform off by {degrees:.3} deg, scale {:.4} vs {:.4}",
            scene.name,
            est.scaling(),
            truth.scaling()
        );
        // The rotation comes from the localised keyframes' centres (Umeyama): `scone eval merge` measured
        // 0.87-1.05 deg on TUM and 0.05-1.3 deg over the validation scenes (BENCHMARKS.md, "Merging two maps").
        // With the ring model this test's TUM merge lands at 0.3 or 1.0 deg, as map building (parallel index
        // inserts) varies; 1.0 was at the edge of what the protocol measures, 1.5 is above it.
        assert!(degrees < 1.5, "rotation {degrees} deg from the truth");

        // The source's keyframes, in the merged map, where A's frame puts their ground truth.
        let contents: serde_json::Value =
            reqwest::get(format!("http://{}/v1/maps/{a}/contents?max_landmarks=10", server.http_addr))
                .await
                .unwrap()
                .json()
                .await
                .unwrap();
        let kfs = contents["keyframes"].as_array().unwrap();
        assert_eq!(kfs.len(), frames.len());
        for kf in kfs {
            let id = kf["keyframe_id"].as_u64().unwrap() as usize;
            let p = &kf["pose"];
            let f = |k: &str| p[k].as_f64().unwrap();
            let got = Isometry3::from_parts(
                Translation3::new(f("tx"), f("ty"), f("tz")),
                UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(f("qw"), f("qx"), f("qy"), f("qz"))),
            );
            let want = moved(&sa, &scene.frames[id].pose.unwrap());
            let dt = (got.translation.vector - want.translation.vector).norm() / sa.scaling();
            let dr = got.rotation.angle_to(&want.rotation).to_degrees();
            // Moved by the estimated transform, so within its rotation bound above.
            assert!(dt < 0.02 * size && dr < 1.5, "{} keyframe {id}: {dt} / {dr}°", scene.name);
        }

        let after = successes(a.clone(), sa, 2.0 * degrees).await;
        eprintln!("{}: localised {before_a} (A), {before_b} (B), {after} (merged) of {}", scene.name, frames.len());
        assert!(after >= before_a.max(before_b), "merged {after} < max({before_a}, {before_b})");
        // The source is unchanged.
        let info = maps.get_map(proto::GetMapRequest { map_id: b.clone() }).await.unwrap().into_inner();
        assert_eq!(info.keyframes as usize, odd.len());
    }

    // Clear refusals: itself, an unknown map, a bad transform, too little overlap.
    let refused = |target: &str, source: &str, transform: Option<proto::Similarity>| proto::MergeMapsRequest {
        target_map_id: target.into(),
        source_map_id: source.into(),
        transform,
    };
    let e = maps.merge_maps(refused("a0", "a0", None)).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{}", e.message());
    let e = maps.merge_maps(refused("a0", "nowhere", None)).await.unwrap_err();
    assert_eq!(e.code(), Code::NotFound, "{}", e.message());
    let bad = proto::Similarity { qw: 1.0, scale: 0.0, ..Default::default() };
    let e = maps.merge_maps(refused("a0", "b0", Some(bad))).await.unwrap_err();
    assert!(e.code() == Code::InvalidArgument && e.message().contains("scale"), "{}", e.message());
    let scene = Scene::load(&fixture("rendered")).unwrap();
    maps.create_map(proto::CreateMapRequest { map_id: "elsewhere".into() }).await.unwrap();
    let mut far = moved_keyframes("elsewhere", &scene, &[0], &frame_of(5));
    far[0].keyframe_id = 100;
    add_keyframes(&mut maps, far, None).await;
    maps.create_map(proto::CreateMapRequest { map_id: "lonely".into() }).await.unwrap();
    let e = maps.merge_maps(refused("elsewhere", "a0", None)).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{}", e.message());
    assert!(e.message().contains("localised in the target"), "{}", e.message());
    let e = maps.merge_maps(refused("a0", "lonely", None)).await.unwrap_err();
    assert!(e.message().contains("no keyframes"), "{}", e.message());
}

fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), target).unwrap();
        }
    }
}

/// `scone map merge` killed with SIGKILL at moments spread over the merge: every time, the target has its
/// own keyframes or all of both maps' (and all of them once "merged" was printed), and the source is intact.
#[test]
fn a_merge_killed_at_any_moment_leaves_the_target_whole_or_merged_and_the_source_intact() {
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let prepared = temp_dir("merge-kill-base");
    {
        let (store, describer) = open(&prepared);
        for (map, first, s) in [("a", 0, frame_of(3)), ("b", 1, frame_of(4))] {
            store.create(map).unwrap();
            for i in (first..scene.frames.len()).step_by(2) {
                let d = describer.describe_image(&std::fs::read(&scene.frames[i].rgb).unwrap()).unwrap();
                let input = KeyframeInput {
                    id: i as u64,
                    pose: moved(&s, &scene.frames[i].pose.unwrap()),
                    camera: scene.camera,
                    features: &d.features,
                    embeddings: &d.embeddings,
                    depth: None,
                    external: None,
                };
                store.add_keyframe(&store.get(map).unwrap(), &input).unwrap();
            }
        }
        assert!(store.flush().is_empty());
    }
    let run = |dir: &std::path::Path, kill_after: Option<Duration>| -> bool {
        let mut child = Command::new(env!("CARGO_BIN_EXE_scone"))
            .args(["map", "merge", "--target", "a", "--source", "b", "--data-dir"])
            .arg(dir)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let stdout = child.stdout.take().unwrap();
        let reader = std::thread::spawn(move || {
            BufReader::new(stdout).lines().map_while(Result::ok).any(|l| l.starts_with("merged "))
        });
        match kill_after {
            Some(d) => {
                std::thread::sleep(d);
                let _ = child.kill(); // SIGKILL
            }
            None => assert!(child.wait().unwrap().success()),
        }
        child.wait().unwrap();
        reader.join().unwrap()
    };
    // One whole run, timed, to spread the kills over it.
    let whole = temp_dir("merge-kill-whole");
    copy_dir(&prepared, &whole);
    let t = Instant::now();
    assert!(run(&whole, None));
    let duration = t.elapsed();
    let (merged_store, _) = open(&whole);
    let all = merged_store.summary("a").unwrap().keyframes;
    assert_eq!(all, scene.frames.len());
    drop(merged_store);

    let mut outcomes = (0, 0);
    for k in 0..10u32 {
        let dir = temp_dir(&format!("merge-kill-{k}"));
        copy_dir(&prepared, &dir);
        let acknowledged = run(&dir, Some(duration * k / 9));
        let (store, _) = open(&dir);
        let a = store.summary("a").unwrap().keyframes;
        let b = store.summary("b").unwrap();
        assert_eq!(b.keyframes, scene.frames.len() / 2, "kill {k}: the source changed");
        assert!(a == scene.frames.len() / 2 || a == all, "kill {k}: target has {a} keyframes, half a merge");
        if acknowledged {
            assert_eq!(a, all, "kill {k}: an acknowledged merge was lost");
        }
        if a == all {
            outcomes.1 += 1;
        } else {
            outcomes.0 += 1;
        }
    }
    eprintln!("kills: {} left the target as it was, {} merged (whole run {duration:?})", outcomes.0, outcomes.1);
}
