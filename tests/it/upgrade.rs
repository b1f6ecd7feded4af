//! A map written by the format-3 writer (`tests/fixtures/map-format3`: a bincode snapshot and two log records
//! after it) opens in this build, localises exactly as the format-3 build answered, and is rewritten in format
//! 4. A large format-3 map (the fixture's keyframes many times over, a snapshot and log records after it), whose
//! rewrite takes long enough to be interrupted, is rewritten by the real binary killed with SIGKILL at moments
//! spread across the rewrite: each kill leaves a map that opens with every keyframe and answers the same, and
//! some kill is shown to have landed in the middle of the rewrite.

use std::collections::HashSet;
use std::io::Read;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use scone::map::model::{Keyframe, MapData, NewObservation, Record};
use scone::map::storage::format::{encode_record_bincode1, FORMAT_VERSION};
use scone::map::storage::local::LocalJournal;
use scone::map::storage::snapshot::encode_snapshot_v3;
use scone::offline::scene::Scene;
use scone::settings::Settings;

use crate::common::{fixture, temp_dir};
use crate::service::{localize_http, serve, settings};

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
    localize_frame_3_with(fixture_settings(data)).await
}

/// Localize of frame 3 against the map `format3`, served with `settings`.
async fn localize_frame_3_with(settings: Settings) -> serde_json::Value {
    let server = serve(settings).await;
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let base = format!("http://{}", server.http_addr);
    let r = localize_http(&reqwest::Client::new(), &base, "format3", &scene, 3).await;
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

/// Keyframes of the fixture, copied this many times into the large map (its last `LARGE_IN_LOG` copies in
/// log records after the snapshot): enough that the rewrite at its start takes a few hundred milliseconds.
const LARGE_COPIES: u64 = 100;
const LARGE_IN_LOG: u64 = 2;

/// Replaces each `dim`-long row of `embeddings` by a pseudo-random one (seeded by `seed`) of the same norm: a
/// copy's keypoints then match no query, so matches go to the fixture's own keyframes alone and are not
/// spread over look-alikes that the ratio test would turn down.
fn scramble(embeddings: &mut [f32], dim: usize, seed: u64) {
    let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    for row in embeddings.chunks_exact_mut(dim) {
        let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
        for v in row.iter_mut() {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            *v = (x >> 40) as f32 / (1u64 << 23) as f32 - 1.0;
        }
        let scale = norm / row.iter().map(|v| v * v).sum::<f32>().sqrt().max(f32::MIN_POSITIVE);
        row.iter_mut().for_each(|v| *v *= scale);
    }
}

/// The records that add the fixture's keyframes again as copy `c`: keyframe ids moved past those of the
/// copies before it, and landmark ids too; each keyframe's record carries its own observations and the
/// landmarks it is the first of its copy to see, and (after copy 0, the fixture's keyframes under their own
/// ids) scrambled embeddings.
fn copy_records(fixture: &MapData, c: u64) -> Vec<Record> {
    let (keyframe_shift, landmark_shift) = (fixture.keyframes.keys().max().unwrap() + 1, fixture.next_landmark);
    let mut created = HashSet::new();
    let mut records = Vec::new();
    for k in fixture.keyframes.values() {
        let mut keyframe = Keyframe::clone(&*k.load().unwrap());
        keyframe.id += c * keyframe_shift;
        if c > 0 {
            scramble(&mut keyframe.embeddings, fixture.meta.dim, c);
        }
        let mut new_landmarks = Vec::new();
        let mut observations = Vec::new();
        for o in fixture.observations.iter().filter(|o| o.keyframe == k.id && o.live) {
            let landmark = o.landmark + c * landmark_shift;
            if created.insert(landmark) {
                new_landmarks.push((landmark, fixture.landmarks[&o.landmark].point));
            }
            observations.push(NewObservation { landmark, keyframe: keyframe.id, keypoint: o.keypoint });
        }
        records.push(Record::AddKeyframe { keyframe, new_landmarks, observations });
    }
    records
}

/// A data directory holding a large map `format3` written in format 3 (bincode 1, by the test encoders of
/// that format): a snapshot of the fixture's keyframes copied `LARGE_COPIES - LARGE_IN_LOG` times, then log
/// records of `LARGE_IN_LOG` more copies. Also the map they make, as the rewrite must keep it.
fn large_format_3_map() -> (crate::test_dir::TestDir, MapData) {
    let source = data_with_the_fixture("upgrade-large-source");
    let (fixture, _, _) = LocalJournal::open(&source.join("maps/format3"), 0).unwrap();
    let mut map = MapData::new(fixture.meta.clone());
    let (mut snapshot, mut log) = (None, b"SCONELOG".to_vec());
    log.extend_from_slice(&3u32.to_le_bytes());
    for c in 0..LARGE_COPIES {
        if c == LARGE_COPIES - LARGE_IN_LOG {
            snapshot = Some(encode_snapshot_v3(&map).unwrap());
        }
        for record in copy_records(&fixture, c) {
            map.check(&record).unwrap();
            map.apply(&record).unwrap();
            if snapshot.is_some() {
                log.extend_from_slice(&encode_record_bincode1(map.version, &record));
            }
        }
    }
    let data = temp_dir("upgrade-large");
    let dir = data.join("maps/format3");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("snapshot.bin"), snapshot.unwrap()).unwrap();
    std::fs::write(dir.join("log.bin"), log).unwrap();
    assert_eq!(header_versions(&dir), (3, 3));
    (data, map)
}

/// The format versions of a map directory's snapshot and log, from their headers only.
fn header_versions(map: &Path) -> (u32, u32) {
    let version = |f: &str| {
        let mut b = [0u8; 12];
        std::fs::File::open(map.join(f)).and_then(|mut file| file.read_exact(&mut b)).unwrap();
        u32::from_le_bytes(b[8..12].try_into().unwrap())
    };
    (version("snapshot.bin"), version("log.bin"))
}

/// Where a rewrite stands, as the files of the map's directory show it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Stage {
    /// The old snapshot and log only (not started, or still reading and encoding).
    Old,
    /// The old files and the new snapshot's temporary file, written in part or whole.
    SnapshotTemp,
    /// The new snapshot over the old log.
    NewSnapshotOldLog,
    /// The new snapshot, the old log and the fresh log's temporary file.
    LogTemp,
    /// The new snapshot and the fresh log.
    Rewritten,
}

impl Stage {
    fn of(map: &Path) -> Stage {
        let temp = |f: &str| map.join(f).exists();
        match (temp("snapshot.tmp"), temp("log.tmp"), header_versions(map)) {
            (_, true, _) => Stage::LogTemp,
            (true, _, _) => Stage::SnapshotTemp,
            (_, _, (3, 3)) => Stage::Old,
            (_, _, (s, l)) if s == FORMAT_VERSION && l == 3 => Stage::NewSnapshotOldLog,
            (_, _, (s, l)) if s == FORMAT_VERSION && l == FORMAT_VERSION => Stage::Rewritten,
            (_, _, other) => panic!("unexpected versions {other:?} in {}", map.display()),
        }
    }

    fn in_between(self) -> bool {
        !matches!(self, Stage::Old | Stage::Rewritten)
    }
}

/// A copy of the map directory `from` (a data directory) in a fresh data directory.
fn copy_data(from: &Path, name: &str) -> crate::test_dir::TestDir {
    let data = temp_dir(name);
    let map = data.join("maps/format3");
    std::fs::create_dir_all(&map).unwrap();
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(from.join("maps/format3").join(f), map.join(f)).unwrap();
    }
    data
}

/// `scone serve` on `data` (the search exact at any size, so no graph is built).
fn start(data: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_scone"))
        .args(["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0"])
        .arg("--data-dir")
        .arg(data)
        .env("SCONE_STORE__INDEX__EXACT_BELOW", usize::MAX.to_string())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// When the stages of an uninterrupted rewrite were first seen after the binary's start.
#[derive(Debug)]
struct Timeline {
    snapshot_temp: Duration,
    rewritten: Duration,
}

/// Starts the binary on a copy of `master` and watches the map's files until they are rewritten.
fn watch_a_rewrite(master: &Path) -> Timeline {
    let data = copy_data(master, "upgrade-large-watch");
    let map = data.join("maps/format3");
    let mut child = start(&data);
    let t = Instant::now();
    let mut first = std::collections::BTreeMap::new();
    loop {
        let stage = Stage::of(&map);
        first.entry(stage).or_insert(t.elapsed());
        if stage == Stage::Rewritten {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "the map was never rewritten");
        std::thread::sleep(Duration::from_micros(200));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    eprintln!("stages first seen after the start: {first:?}");
    Timeline {
        snapshot_temp: first.get(&Stage::SnapshotTemp).copied().unwrap_or(first[&Stage::Rewritten]),
        rewritten: first[&Stage::Rewritten],
    }
}

/// The fixture's settings, the search exact at any size (its answer then does not depend on a graph's build).
fn serve_settings(data: &Path) -> Settings {
    let mut s = fixture_settings(data);
    s.store.index.exact_below = usize::MAX;
    s
}

/// Starts the binary on a copy of `master`, kills it with SIGKILL `delay` after its start, and says where the
/// rewrite stood; then starts the service again on what it left, which must answer `want` and hold `expected`.
async fn kill_and_restart(master: &Path, delay: Duration, expected: &MapData, want: &serde_json::Value) -> Stage {
    let data = copy_data(master, "upgrade-large-kill");
    let map = data.join("maps/format3");
    let mut child = start(&data);
    std::thread::sleep(delay);
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let stage = Stage::of(&map);
    if stage == Stage::SnapshotTemp {
        let part = std::fs::metadata(map.join("snapshot.tmp")).unwrap().len();
        eprintln!("killed {delay:?} after the start: the new snapshot's temporary file held {part} bytes");
    }
    let got = localize_frame_3_with(serve_settings(&data)).await;
    assert_same_answer(&got, want);
    assert_eq!(Stage::of(&map), Stage::Rewritten, "the restart finished the rewrite");
    let (after, _, _) = LocalJournal::open(&map, 0).unwrap();
    assert!(after == *expected, "killed {delay:?} after the start ({stage:?}): the map differs");
    stage
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_in_the_middle_of_a_large_map_s_rewrite_loses_no_keyframe_and_the_map_answers_the_same() {
    let t0 = Instant::now();
    let (master, expected) = large_format_3_map();
    let keyframes = expected.keyframes.len() as u64;
    assert_eq!(keyframes, 4 * LARGE_COPIES);
    let size = std::fs::metadata(master.join("maps/format3/snapshot.bin")).unwrap().len();
    eprintln!("large map: {keyframes} keyframes, a {} MB format-3 snapshot, made in {:?}", size >> 20, t0.elapsed());
    // The reference: the map rewritten without interruption, then served.
    let reference = copy_data(&master, "upgrade-large-reference");
    let want = localize_frame_3_with(serve_settings(&reference)).await;
    assert_eq!(want["localized"], true, "{want}");
    eprintln!("the reference's answer: {want}");
    let (rewritten, _, _) = LocalJournal::open(&reference.join("maps/format3"), 0).unwrap();
    assert!(rewritten == expected, "the uninterrupted rewrite kept the map");
    let size = std::fs::metadata(reference.join("maps/format3/snapshot.bin")).unwrap().len();
    eprintln!("rewritten: a {size}-byte format-4 snapshot");
    let timeline = watch_a_rewrite(&master);
    let window = timeline.rewritten.saturating_sub(timeline.snapshot_temp);
    eprintln!(
        "rewrite: files from {:?} to {:?} after the start ({window:?} on disk)",
        timeline.snapshot_temp, timeline.rewritten
    );

    // Kills at fractions of the time to the end of the rewrite and across its time on disk, then (should
    // scheduling have kept all of them out of it) halving the gap between the last kill that found the map
    // old and the first that found it rewritten. After each, the map starts again, holds every keyframe and
    // answers as the reference.
    let mut seen: Vec<(Duration, Stage)> = Vec::new();
    let mut delays: Vec<Duration> = (1..=10).map(|i| timeline.rewritten * i / 10).collect();
    delays.extend((0..6).map(|i| timeline.snapshot_temp + window * (2 * i + 1) / 12));
    delays.sort();
    for d in delays {
        seen.push((d, kill_and_restart(&master, d, &expected, &want).await));
    }
    for _ in 0..12 {
        if seen.iter().any(|(_, s)| s.in_between()) {
            break;
        }
        let old = seen.iter().filter(|(_, s)| *s == Stage::Old).map(|(d, _)| *d).max().unwrap_or_default();
        let new = seen.iter().filter(|(d, s)| *s == Stage::Rewritten && *d > old).map(|(d, _)| *d).min();
        let new = new.unwrap_or(timeline.rewritten * 2);
        let d = (old + new) / 2;
        seen.push((d, kill_and_restart(&master, d, &expected, &want).await));
    }
    let mut counts = std::collections::BTreeMap::new();
    for (_, s) in &seen {
        *counts.entry(*s).or_insert(0) += 1;
    }
    eprintln!("kill -9 after (delay, stage): {seen:?}");
    eprintln!("kills per stage: {counts:?}; test time {:?}", t0.elapsed());
    assert!(seen.iter().any(|(_, s)| s.in_between()), "no kill landed inside the rewrite: {seen:?}");
}
