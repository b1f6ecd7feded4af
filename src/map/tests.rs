//! Unit tests of the map data, storage and index.

use std::path::PathBuf;

use crate::features::{Keypoint, DESCRIPTOR_BYTES};
use crate::map::index::{exact_search, EmbeddingIndex, IndexParams};
use crate::map::model::{Keyframe, MapData, MapMeta, NewObservation, Pose, Record};
use crate::map::storage::{decode_snapshot, encode_snapshot, MapLog};
use crate::scene::Camera;

pub(crate) fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("scone-{name}-{}-{:?}", std::process::id(), std::thread::current().id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn meta(dim: usize) -> MapMeta {
    MapMeta { id: "m".into(), model_id: "sha256:test".into(), k: 20, dim, created_unix_ms: 1 }
}

/// Deterministic pseudo-random unit vectors.
fn vectors(n: usize, dim: usize, seed: u64) -> Vec<f32> {
    let mut s = seed.wrapping_mul(2654435761).wrapping_add(1);
    let mut out = Vec::with_capacity(n * dim);
    for _ in 0..n {
        let mut v: Vec<f32> = (0..dim)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s % 20001) as f32 / 10000.0 - 1.0
            })
            .collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter_mut().for_each(|x| *x /= norm);
        out.extend(v);
    }
    out
}

pub(crate) fn keyframe_record(id: u64, n: usize, first_landmark: u64, dim: usize, seed: u64) -> Record {
    let keypoints: Vec<Keypoint> =
        (0..n).map(|i| Keypoint { x: i as f32, y: 2.0, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }).collect();
    let emb = vectors(n, dim, seed);
    Record::AddKeyframe {
        keyframe: Keyframe {
            id,
            pose: Pose { translation: [id as f64, 0.0, 0.0], rotation: [0.0, 0.0, 0.0, 1.0] },
            camera: Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 },
            keypoints,
            descriptors: vec![id as u8; n * DESCRIPTOR_BYTES],
            embeddings: emb,
        },
        new_landmarks: (0..n as u64).map(|i| (first_landmark + i, [i as f64, 1.0, 5.0])).collect(),
        observations: (0..n)
            .map(|i| NewObservation { landmark: first_landmark + i as u64, keyframe: id, keypoint: i as u32 })
            .collect(),
    }
}

fn write(log: &mut MapLog, data: &mut MapData, r: Record) {
    data.check(&r).unwrap();
    log.append(data.version + 1, &r).unwrap();
    data.apply(&r);
}

#[test]
fn log_replays_to_the_same_map() {
    let dir = temp_dir("replay");
    let mut data = MapData::new(meta(8));
    let mut log = MapLog::create(&dir, &data, 0).unwrap();
    for k in 0..5 {
        write(&mut log, &mut data, keyframe_record(k, 10, k * 10, 8, k));
    }
    write(&mut log, &mut data, Record::RemoveKeyframe { id: 2 });
    drop(log);
    let (loaded, _, report) = MapLog::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 6);
    assert_eq!(report.truncated_bytes, 0);
    assert_eq!(loaded, data);
    assert_eq!(loaded.live_observations(), 40);
}

/// A map directory with two logged keyframe records (10 observations each, dimension 8).
fn logged_map(name: &str) -> PathBuf {
    let dir = temp_dir(name);
    let mut data = MapData::new(meta(8));
    let mut log = MapLog::create(&dir, &data, 0).unwrap();
    write(&mut log, &mut data, keyframe_record(0, 10, 0, 8, 1));
    write(&mut log, &mut data, keyframe_record(1, 10, 10, 8, 2));
    dir
}

#[test]
fn torn_last_record_is_cut_and_the_map_loads() {
    let dir = logged_map("torn");
    let path = dir.join("log.bin");
    let full = std::fs::read(&path).unwrap();
    // Simulate a crash in the middle of appending the second record.
    let cut = full.len() - 37;
    std::fs::write(&path, &full[..cut]).unwrap();
    let (loaded, mut log, report) = MapLog::open(&dir, 0).unwrap();
    assert_eq!(loaded.keyframes.len(), 1);
    assert!(report.truncated_bytes > 0);
    // The log accepts new records after the cut, and they replay.
    let mut data = loaded;
    write(&mut log, &mut data, keyframe_record(7, 4, 100, 8, 3));
    drop(log);
    let (again, _, report) = MapLog::open(&dir, 0).unwrap();
    assert_eq!(report.truncated_bytes, 0);
    assert_eq!(again, data);
}

#[test]
fn corruption_before_the_end_is_reported_with_the_file() {
    let dir = logged_map("corrupt");
    let path = dir.join("log.bin");
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[40] ^= 0xff; // inside the first record's payload
    std::fs::write(&path, &bytes).unwrap();
    let err = MapLog::open(&dir, 0).unwrap_err().to_string();
    assert!(err.contains("log.bin") && err.contains("checksum"), "{err}");
}

#[test]
fn compaction_keeps_everything_and_restarts_the_log() {
    let dir = temp_dir("compact");
    let mut data = MapData::new(meta(8));
    let mut log = MapLog::create(&dir, &data, 2).unwrap();
    write(&mut log, &mut data, keyframe_record(0, 5, 0, 8, 1));
    write(&mut log, &mut data, keyframe_record(1, 5, 5, 8, 2));
    assert!(log.wants_compaction());
    log.compact(&data).unwrap();
    write(&mut log, &mut data, keyframe_record(2, 5, 10, 8, 3));
    drop(log);
    let (loaded, _, report) = MapLog::open(&dir, 2).unwrap();
    assert_eq!(report.replayed, 1);
    assert_eq!(loaded, data);
}

#[test]
fn snapshot_format_checks_magic_version_and_checksum() {
    let mut data = MapData::new(meta(4));
    data.apply(&keyframe_record(0, 3, 0, 4, 9));
    let bytes = encode_snapshot(&data).unwrap();
    let p = PathBuf::from("export.scone");
    assert_eq!(decode_snapshot(&bytes, &p).unwrap(), data);
    let mut bad = bytes.clone();
    *bad.last_mut().unwrap() ^= 1;
    assert!(decode_snapshot(&bad, &p).unwrap_err().to_string().contains("checksum"));
    let mut wrong_version = bytes.clone();
    wrong_version[8] = 99;
    assert!(decode_snapshot(&wrong_version, &p).unwrap_err().to_string().contains("version"));
    assert!(decode_snapshot(b"PNG....", &p).unwrap_err().to_string().contains("magic"));
}

#[test]
fn records_that_do_not_fit_are_refused_before_logging() {
    let mut data = MapData::new(meta(8));
    data.apply(&keyframe_record(0, 3, 0, 8, 1));
    assert!(data.check(&keyframe_record(0, 3, 10, 8, 1)).is_err(), "duplicate keyframe id");
    assert!(data.check(&Record::RemoveKeyframe { id: 9 }).is_err());
    let Record::AddKeyframe { mut keyframe, new_landmarks, observations } = keyframe_record(5, 3, 20, 8, 1) else {
        unreachable!()
    };
    keyframe.pose.rotation = [f64::NAN, 0.0, 0.0, 1.0];
    assert!(data.check(&Record::AddKeyframe { keyframe, new_landmarks, observations }).is_err(), "NaN pose");
}

fn brute(data: &MapData, q: &[f32], k: usize) -> Vec<usize> {
    let mut all: Vec<(f32, usize)> = (0..data.observations.len())
        .filter(|&i| data.observations[i].live)
        .map(|i| (crate::map::index::l2_squared(q, data.embedding(i)), i))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    all.into_iter().take(k).map(|x| x.1).collect()
}

#[test]
fn exact_search_equals_brute_force_and_skips_tombstones() {
    let mut data = MapData::new(meta(48));
    for k in 0..4 {
        data.apply(&keyframe_record(k, 200, k * 200, 48, k + 1));
    }
    data.apply(&Record::RemoveKeyframe { id: 1 });
    let queries = vectors(20, 48, 77);
    for q in queries.chunks(48) {
        let hits = exact_search(&data, q, 5, None);
        assert_eq!(hits.iter().map(|h| h.observation).collect::<Vec<_>>(), brute(&data, q, 5));
        assert!(hits.iter().all(|h| data.observations[h.observation].keyframe != 1));
    }
}

/// A map of `keyframes` x 250 observations with an HNSW index (exact search only below 1,000).
fn hnsw_map(keyframes: u64, seed: u64) -> (MapData, IndexParams, EmbeddingIndex) {
    let mut data = MapData::new(meta(48));
    for k in 0..keyframes {
        data.apply(&keyframe_record(k, 250, k * 250, 48, k + seed));
    }
    let params = IndexParams { exact_below: 1000, ..IndexParams::default() };
    let mut index = EmbeddingIndex::new(params);
    index.sync(&data);
    (data, params, index)
}

#[test]
fn hnsw_index_finds_near_duplicates_and_survives_a_dump() {
    let dir = temp_dir("hnsw");
    let (mut data, params, index) = hnsw_map(6, 11);
    assert!(index.is_approximate());
    // Queries: slightly perturbed copies of stored embeddings must find their original.
    let mut found = 0;
    for i in (0..data.observations.len()).step_by(7) {
        let q: Vec<f32> =
            data.embedding(i).iter().enumerate().map(|(j, v)| v + if j == 0 { 0.01 } else { 0.0 }).collect();
        found += (index.search(&data, &q, 1, None)[0].observation == i) as usize;
    }
    let total = data.observations.len().div_ceil(7);
    assert!(found as f64 >= 0.95 * total as f64, "recall {found}/{total}");
    index.dump(&dir, &data.meta.model_id).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && reloaded.loaded_from_dump());
    let q = data.embedding(3).to_vec();
    assert_eq!(reloaded.search(&data, &q, 3, None), index.search(&data, &q, 3, None));
    // Tombstones are filtered, and new observations are searchable before the next sync.
    data.apply(&Record::RemoveKeyframe { id: 0 });
    data.apply(&keyframe_record(99, 10, 10_000, 48, 5));
    let q = data.embedding(3).to_vec();
    assert!(reloaded.search(&data, &q, 3, None).iter().all(|h| h.observation != 3));
    let newest = data.observations.len() - 1;
    let q = data.embedding(newest).to_vec();
    assert_eq!(reloaded.search(&data, &q, 1, None)[0].observation, newest);
}

#[test]
fn a_dump_from_another_model_or_damaged_is_rebuilt() {
    let dir = temp_dir("hnsw-model");
    let (data, params, index) = hnsw_map(5, 1);
    index.dump(&dir, "sha256:other").unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && !reloaded.loaded_from_dump(), "another model's dump was used");
    // A dump of the right model with a damaged graph file is rebuilt too.
    index.dump(&dir, &data.meta.model_id).unwrap();
    let graph = dir.join("index.hnsw.graph");
    let mut bytes = std::fs::read(&graph).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x55;
    std::fs::write(&graph, bytes).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && !reloaded.loaded_from_dump(), "a damaged dump was used");
}
