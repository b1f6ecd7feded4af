//! Durability with a real child process: `scone map write-scene` writes keyframes through the map store and
//! prints "ack <id>" only once each write is durable; it is killed with SIGKILL mid-stream, the store is
//! reopened, and every acknowledged keyframe must be there and the map must localise a held-out frame.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::Arc;

use scone::describe::decode::ImageLimitSettings;
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::pipeline::Describer;
use scone::map::store::{MapStore, ModelInfo, StoreSettings};
use scone::offline::scene::Scene;
use scone::pose::rotation_error_deg;

use crate::common::{fixture, temp_dir};

/// The map store of `dir` with the committed model, and a describer with the service's defaults.
pub(crate) fn open(dir: &std::path::Path) -> (MapStore, Describer) {
    open_with(dir, EmbedderSettings::default().model)
}

/// The map store of `dir` for `model`, and a describer at the extraction the model declares.
fn open_with(dir: &std::path::Path, model: std::path::PathBuf) -> (MapStore, Describer) {
    let embedder = Arc::new(Embedder::load(&EmbedderSettings { model, ..EmbedderSettings::default() }).unwrap());
    let info = ModelInfo { model_id: embedder.model_id().into(), k: embedder.k(), dim: embedder.dim() };
    let store =
        MapStore::open(StoreSettings { data_dir: dir.to_path_buf(), ..StoreSettings::default() }, info).unwrap();
    (store, Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder })
}

#[test]
fn acknowledged_keyframes_survive_kill_9_and_the_map_localises() {
    let dir = temp_dir("kill9");
    let scene_dir = fixture("rendered");
    let mut child = Command::new(env!("CARGO_BIN_EXE_scone"))
        .args(["map", "write-scene", "--map", "kill", "--stride", "2", "--repeat", "40"])
        .arg("--data-dir")
        .arg(&dir)
        .arg("--scene")
        .arg(&scene_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut acked = Vec::new();
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    while acked.len() < 7 {
        let line = lines.next().expect("child ended early").unwrap();
        let id: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        acked.push(id);
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();

    let (store, describer) = open(&dir);
    let summary = store.summary("kill").unwrap();
    let map = store.get("kill").unwrap();
    map.read(|data, _| {
        for id in &acked {
            assert!(data.keyframes.contains_key(id), "acknowledged keyframe {id} lost after kill -9");
        }
    });
    assert!(summary.keyframes >= acked.len());

    // Writes continue after the restart, and a frame that is not in the map localises.
    let scene = Scene::load(&scene_dir).unwrap();
    let frame = &scene.frames[3];
    let d = describer.describe_image(&std::fs::read(&frame.rgb).unwrap()).unwrap();
    let loc = store.localize(&store.get("kill").unwrap(), &d.features, &d.embeddings, &scene.camera, None).unwrap();
    let pose = loc.pose.expect("held-out frame not localised");
    let gt = frame.pose.unwrap();
    let dt = (pose.camera_to_world.translation.vector - gt.translation.vector).norm();
    let dr = rotation_error_deg(&pose.camera_to_world.rotation.to_rotation_matrix(), &gt.rotation.to_rotation_matrix());
    assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg");
    assert!(loc.confidence > 0.5, "confidence {}", loc.confidence);
}

/// A data directory with a good map and a map whose snapshot is damaged, opened.
fn store_with_a_corrupt_map(name: &str) -> (crate::test_dir::TestDir, MapStore) {
    let dir = temp_dir(name);
    let status = Command::new(env!("CARGO_BIN_EXE_scone"))
        .args(["map", "write-scene", "--map", "good", "--stride", "3"])
        .arg("--data-dir")
        .arg(&dir)
        .arg("--scene")
        .arg(fixture("rendered"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    // A second map whose snapshot is damaged (the command snapshots on exit; log corruption before the end
    // of the log is covered by the storage unit tests).
    let good = dir.join("maps/good");
    let bad = dir.join("maps/bad");
    std::fs::create_dir_all(&bad).unwrap();
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(good.join(f), bad.join(f)).unwrap();
    }
    let mut snapshot = std::fs::read(bad.join("snapshot.bin")).unwrap();
    let mid = snapshot.len() / 2;
    snapshot[mid] ^= 0xff;
    std::fs::write(bad.join("snapshot.bin"), snapshot).unwrap();
    let (store, _) = open(&dir);
    (dir, store)
}

#[test]
fn a_corrupt_map_is_held_back_and_the_others_serve() {
    let (_dir, store) = store_with_a_corrupt_map("heldback");
    let held = store.held_back();
    assert_eq!(held.len(), 1);
    assert_eq!(held[0].0, "bad");
    assert!(held[0].1.contains("snapshot.bin") && held[0].1.contains("checksum"), "{}", held[0].1);
    let err = store.summary("bad").unwrap_err().to_string();
    assert!(err.contains("unavailable"), "{err}");
    assert!(store.summary("good").unwrap().keyframes > 0);
}

/// Issue 16: a held-back map's reason (ListMaps, UNAVAILABLE) carried the server's absolute path of the
/// damaged file. Clients get the file's name and what is wrong; the path goes to the log only.
#[test]
fn regression_held_back_reason_names_no_server_path() {
    let (dir, store) = store_with_a_corrupt_map("heldback-path");
    let dir = dir.to_string_lossy().into_owned();
    let (_, reason) = &store.held_back()[0];
    assert!(!reason.contains(&dir) && !reason.contains('/'), "{reason}");
    assert!(reason.contains("snapshot.bin is corrupt"), "{reason}");
    let err = store.summary("bad").unwrap_err().to_string();
    assert!(!err.contains(&dir), "{err}");
}

/// Queries of one map go on while another map is being written: a writer thread adds keyframes to map "b"
/// while this thread localises against map "a"; several localisations must complete inside the write stream.
#[test]
fn reads_of_one_map_go_on_while_another_is_written() {
    let dir = temp_dir("rw");
    let (store, describer) = open(&dir);
    let store = Arc::new(store);
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let described: Vec<_> =
        scene.frames.iter().map(|f| describer.describe_image(&std::fs::read(&f.rgb).unwrap()).unwrap()).collect();
    let depths: Vec<_> = scene
        .frames
        .iter()
        .map(|f| {
            scone::describe::decode::decode_depth_png(
                &std::fs::read(f.depth.as_ref().unwrap()).unwrap(),
                &ImageLimitSettings::default(),
            )
            .unwrap()
        })
        .collect();
    let write = |map: &str, id: u64, i: usize| {
        let input = scone::map::builder::KeyframeInput {
            id,
            pose: scene.frames[i].pose.unwrap(),
            camera: scene.camera,
            features: &described[i].features,
            embeddings: &described[i].embeddings,
            depth: Some(scone::map::builder::Depth { image: &depths[i], scale: 1.0 / 5000.0 }),
            external: None,
        };
        store.add_keyframe(&store.get(map).unwrap(), &input).unwrap();
    };
    store.create("a").unwrap();
    store.create("b").unwrap();
    for i in (0..scene.frames.len()).step_by(2) {
        write("a", i as u64, i);
    }
    let done = std::sync::atomic::AtomicBool::new(false);
    let during = std::thread::scope(|s| {
        s.spawn(|| {
            for round in 0..2u64 {
                for i in 0..scene.frames.len() {
                    write("b", round * 100 + i as u64, i);
                }
            }
            done.store(true, std::sync::atomic::Ordering::SeqCst);
        });
        let mut during = 0;
        while !done.load(std::sync::atomic::Ordering::SeqCst) {
            let q = &described[1];
            let loc =
                store.localize(&store.get("a").unwrap(), &q.features, &q.embeddings, &scene.camera, None).unwrap();
            assert!(loc.pose.is_some());
            if !done.load(std::sync::atomic::Ordering::SeqCst) {
                during += 1;
            }
        }
        during
    });
    eprintln!("{during} localisations of map a completed while map b was written");
    assert!(during >= 3, "only {during} localisations of map a completed while map b was written");
    assert_eq!(store.summary("b").unwrap().keyframes, 2 * scene.frames.len());
}

/// A map recorded by another model is refused for queries with a clear error, and `scone map reembed`
/// (re-embedding from the stored keypoints and FREAK descriptors) makes it answer again.
#[test]
fn a_map_from_another_model_is_refused_until_re_embedded() {
    // Re-embedding reads the keyframes' keypoints and descriptors, which is all the constellation model reads;
    // the embedded ring model also reads the image around each keypoint, which keyframes do not store.
    let model = scone::describe::embedding::constellation_model_path();
    let open = |dir: &std::path::Path| open_with(dir, model.clone());
    let dir = temp_dir("reembed");
    let (_, describer) = open(&dir);
    let scene = Scene::load(&fixture("rendered")).unwrap();
    {
        // Written by a store that believes it runs an older model.
        let old = ModelInfo { model_id: "sha256:older-model".into(), k: 20, dim: describer.embedder.dim() };
        let store =
            MapStore::open(StoreSettings { data_dir: dir.to_path_buf(), ..StoreSettings::default() }, old).unwrap();
        store.create("m").unwrap();
        for i in (0..scene.frames.len()).step_by(2) {
            let d = describer.describe_image(&std::fs::read(&scene.frames[i].rgb).unwrap()).unwrap();
            let depth = scone::describe::decode::decode_depth_png(
                &std::fs::read(scene.frames[i].depth.as_ref().unwrap()).unwrap(),
                &ImageLimitSettings::default(),
            )
            .unwrap();
            let input = scone::map::builder::KeyframeInput {
                id: i as u64,
                pose: scene.frames[i].pose.unwrap(),
                camera: scene.camera,
                features: &d.features,
                embeddings: &d.embeddings,
                depth: Some(scone::map::builder::Depth { image: &depth, scale: 1.0 / 5000.0 }),
                external: None,
            };
            store.add_keyframe(&store.get("m").unwrap(), &input).unwrap();
        }
    }
    let (store, describer) = open(&dir);
    let q = describer.describe_image(&std::fs::read(&scene.frames[3].rgb).unwrap()).unwrap();
    let err = store
        .localize(&store.get("m").unwrap(), &q.features, &q.embeddings, &scene.camera, None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("sha256:older-model") && err.contains("scone map reembed"), "{err}");
    drop(store);

    let reembed_with = |map: &str, model: &std::path::Path| {
        Command::new(env!("CARGO_BIN_EXE_scone"))
            .args(["map", "reembed", "--map", map])
            .arg("--data-dir")
            .arg(&dir)
            .arg("--model")
            .arg(model)
            .stderr(Stdio::piped())
            .output()
            .unwrap()
    };
    let reembed = |map: &str| reembed_with(map, &model);
    let out = reembed_with("m", &scone::describe::embedding::default_model_path());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && stderr.contains("ring context") && stderr.contains("scone-freak-k20"), "{stderr}");
    let out = reembed("nowhere");
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nowhere"), "{}", String::from_utf8_lossy(&out.stderr));
    let out = reembed("m");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(summary["model_id"], describer.embedder.model_id());
    assert_eq!(summary["keyframes"], scene.frames.len().div_ceil(2));

    let (store, _) = open(&dir);
    let loc = store.localize(&store.get("m").unwrap(), &q.features, &q.embeddings, &scene.camera, None).unwrap();
    let pose = loc.pose.expect("not localised after re-embedding");
    let gt = scene.frames[3].pose.unwrap();
    assert!((pose.camera_to_world.translation.vector - gt.translation.vector).norm() < 0.05);
    // The re-embedding is durable.
    drop(store);
    let (store, _) = open(&dir);
    assert_eq!(store.summary("m").unwrap().model_id, describer.embedder.model_id());
}
