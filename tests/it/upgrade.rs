//! A map written by the format-3 writer (`tests/fixtures/map-format3`: a bincode snapshot and two log records
//! after it) opens in this build, localises exactly as the format-3 build answered, and is rewritten in format
//! 4; the real binary killed with SIGKILL at any moment of its start (the rewrite included) leaves a map that
//! opens with every keyframe and answers the same.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use scone::map::storage::format::FORMAT_VERSION;
use scone::map::storage::local::LocalJournal;
use scone::offline::scene::Scene;
use scone::settings::Settings;

use crate::common::{fixture, temp_dir};
use crate::service::{serve, settings};

/// A data directory holding a copy of the fixture's map (`format3`).
fn data_with_the_fixture(name: &str) -> crate::test_dir::TestDir {
    let data = temp_dir(name);
    let map = data.join("maps/format3");
    std::fs::create_dir_all(&map).unwrap();
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(fixture("map-format3/maps/format3").join(f), map.join(f)).unwrap();
    }
    data
}

/// The format versions of a map directory's snapshot and log.
fn versions(map: &Path) -> (u32, u32) {
    let version = |f: &str| {
        let b = std::fs::read(map.join(f)).unwrap();
        u32::from_le_bytes(b[8..12].try_into().unwrap())
    };
    (version("snapshot.bin"), version("log.bin"))
}

/// The fixture's settings: at most 240 keypoints per image, as the map was made.
fn fixture_settings(data: &Path) -> Settings {
    let mut s = settings(data);
    s.extractor.max_keypoints = Some(240);
    s
}

/// Localize of frame 3 against the map `format3` served from `data`, as the HTTP answer's JSON.
async fn localize_frame_3(data: &Path) -> serde_json::Value {
    let server = serve(fixture_settings(data)).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let c = scene.camera;
    let r = reqwest::Client::new()
        .post(format!(
            "http://{}/v1/maps/format3/localize?fx={}&fy={}&cx={}&cy={}",
            server.http_addr, c.fx, c.fy, c.cx, c.cy
        ))
        .header("content-type", "image/png")
        .body(std::fs::read(&scene.frames[3].rgb).unwrap())
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let answer = r.json().await.unwrap();
    server.shutdown().await.unwrap();
    answer
}

/// The answer the format-3 build gave.
fn recorded_answer() -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(fixture("map-format3/localize-frame3.json")).unwrap()).unwrap()
}

/// The same answer: the same counts, the same pose and covariance up to rounding.
fn assert_same_answer(got: &serde_json::Value, want: &serde_json::Value) {
    for k in ["localized", "matches", "inliers", "focal_estimated"] {
        assert_eq!(got[k], want[k], "{k}: {got} against {want}");
    }
    let close = |a: &serde_json::Value, b: &serde_json::Value| {
        let (a, b) = (a.as_f64().unwrap(), b.as_f64().unwrap());
        (a - b).abs() <= 1e-9 + 1e-6 * b.abs()
    };
    for k in ["tx", "ty", "tz", "qx", "qy", "qz", "qw"] {
        assert!(close(&got["pose"][k], &want["pose"][k]), "pose {k}: {got} against {want}");
    }
    for k in ["reprojection_error", "confidence", "focal_length"] {
        assert!(close(&got[k], &want[k]), "{k}: {got} against {want}");
    }
    let (a, b) = (got["covariance"].as_array().unwrap(), want["covariance"].as_array().unwrap());
    assert!(a.len() == b.len() && a.iter().zip(b).all(|(a, b)| close(a, b)), "covariance: {got} against {want}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_format_3_map_localises_as_the_format_3_build_answered_and_is_rewritten_in_format_4() {
    let data = data_with_the_fixture("upgrade-localise");
    let map = data.join("maps/format3");
    assert_eq!(versions(&map), (3, 3));
    let answer = localize_frame_3(&data).await;
    assert_same_answer(&answer, &recorded_answer());
    assert_eq!(versions(&map), (FORMAT_VERSION, FORMAT_VERSION), "the start rewrote the map");
    // Rewritten, it opens and answers the same again.
    let (stored, _, report) = LocalJournal::open(&map, 0).unwrap();
    assert_eq!((report.replayed, stored.keyframes.len()), (0, 4));
    assert_same_answer(&localize_frame_3(&data).await, &recorded_answer());
}

/// `scone serve` on `data`, killed with SIGKILL `after` its start.
fn start_and_kill_9(data: &Path, after: Duration) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_scone"))
        .args(["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0"])
        .arg("--data-dir")
        .arg(data)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(after);
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_at_any_moment_of_the_rewrite_loses_no_keyframe_and_the_map_answers_the_same() {
    // The map as the rewrite leaves it, read back.
    let reference = data_with_the_fixture("upgrade-kill9-reference");
    let (expected, _, _) = LocalJournal::open(&reference.join("maps/format3"), 0).unwrap();
    assert_eq!(expected.keyframes.len(), 4);

    // Kills at growing delays, from before the map is read until after it is rewritten, then a millisecond
    // apart between the last kill that found it old and the first that found it rewritten: each leaves it old,
    // half rewritten (a new snapshot, the old log) or rewritten, and each of them opens whole.
    let mut seen = Vec::new();
    let mut halfway: Option<(crate::test_dir::TestDir, (u32, u32))> = None;
    let mut kill_at = |delay_ms: u64| {
        let data = data_with_the_fixture("upgrade-kill9");
        let map = data.join("maps/format3");
        start_and_kill_9(&data, Duration::from_millis(delay_ms));
        let state = versions(&map);
        seen.push((delay_ms, state));
        let copy: PathBuf = temp_dir("upgrade-kill9-open").join("format3");
        std::fs::create_dir_all(&copy).unwrap();
        for entry in std::fs::read_dir(&map).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), copy.join(entry.file_name())).unwrap();
        }
        let (data_after, _, _) = LocalJournal::open(&copy, 0).unwrap();
        assert!(data_after == expected, "killed {delay_ms} ms after the start ({state:?}): the map differs");
        if state != (3, 3) && state != (FORMAT_VERSION, FORMAT_VERSION) || halfway.is_none() {
            halfway = Some((data, state));
        }
        state
    };
    let t = Instant::now();
    let (mut old, mut delay_ms) = (0u64, 0u64);
    loop {
        assert!(t.elapsed() < Duration::from_secs(300), "the map was never rewritten");
        if kill_at(delay_ms) == (FORMAT_VERSION, FORMAT_VERSION) {
            break;
        }
        old = delay_ms;
        delay_ms = (delay_ms * 5 / 4).max(delay_ms + 20);
    }
    for d in old + 1..delay_ms {
        kill_at(d);
    }
    eprintln!("kill -9 after (ms, versions of snapshot and log): {seen:?}");
    assert!(seen[0].1 == (3, 3), "the first kill came before the rewrite: {seen:?}");

    // One of the killed maps, started again: the rewrite finishes and the answer is the format-3 build's.
    let (data, state) = halfway.unwrap();
    eprintln!("restarting a map killed at versions {state:?}");
    assert_same_answer(&localize_frame_3(&data).await, &recorded_answer());
    assert_eq!(versions(&data.join("maps/format3")), (FORMAT_VERSION, FORMAT_VERSION));
}
