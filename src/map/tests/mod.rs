//! Unit tests of the map data, storage and index; the cache, the storage faults, the keyframe payloads and
//! the relocalisation stages have a file each beside this one.

use std::path::PathBuf;

use crate::camera::Camera;
use crate::camera::Pose;
use crate::describe::features::{Keypoint, DESCRIPTOR_BYTES};
use crate::map::encoding::{encode_bincode1, Encoding};
use crate::map::index::{exact_search, EmbeddingIndex, IndexSettings};
use crate::map::model::{Keyframe, MapData, MapMeta, NewObservation, Record};
use crate::map::storage::local::LocalJournal;
use crate::map::storage::snapshot::{decode_snapshot, encode_snapshot};

use crate::test_dir::{temp_dir, TestDir};

mod cache_tests;
mod external_tests;
mod fault_tests;
mod payload_tests;
mod stage_tests;
mod upgrade_tests;

pub(crate) fn meta(dim: usize) -> MapMeta {
    MapMeta { id: "m".into(), model_id: "sha256:test".into(), k: 20, dim, created_unix_ms: 1 }
}

/// Deterministic pseudo-random unit vectors.
pub(crate) fn vectors(n: usize, dim: usize, seed: u64) -> Vec<f32> {
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

/// Opens the map in `dir` while every atomic write of its file `file` (`snapshot.bin` or `log.bin`) fails as on a
/// full volume (fail point `map-write`), as a crash at that step of the upgrade would leave it: the open
/// succeeds and reads the map; returns it and whether the journal still waits for its rewrite.
pub(crate) fn open_while_writing_fails(dir: &std::path::Path, file: &str) -> (MapData, bool) {
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    fail::cfg("map-write", &format!("return({name},{file})")).unwrap();
    let (data, log, _) = LocalJournal::open(dir, 0).unwrap();
    fail::remove("map-write");
    (data, log.needs_upgrade())
}

pub(crate) fn write(log: &mut LocalJournal, data: &mut MapData, r: Record) {
    data.check(&r).unwrap();
    log.append(data.version + 1, &r).unwrap();
    data.apply(&r).unwrap();
}

#[test]
fn log_replays_to_the_same_map() {
    let dir = temp_dir("replay");
    let mut data = MapData::new(meta(8));
    let mut log = LocalJournal::create(&dir, &data, 0).unwrap();
    for k in 0..5 {
        write(&mut log, &mut data, keyframe_record(k, 10, k * 10, 8, k));
    }
    write(&mut log, &mut data, Record::RemoveKeyframe { id: 2 });
    drop(log);
    let (loaded, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 6);
    assert_eq!(report.truncated_bytes, 0);
    assert_eq!(loaded, data);
    assert_eq!(loaded.live_observations(), 40);
}

/// A snapshot file decodes as it is read to what its bytes decode to (format 2 and format 1), and a damaged one
/// is refused with the reason: the payload's checksum (a bit flipped anywhere, a length prefix included), its
/// length against the header's, the magic.
#[test]
fn a_snapshot_decoded_as_it_is_read_is_its_bytes_decoded_and_damage_is_refused() {
    use crate::map::storage::snapshot::{frame_snapshot, read_snapshot, MapDataV1};
    let dir = temp_dir("read-snapshot");
    let mut data = MapData::new(meta(8));
    for k in 0..4 {
        data.apply(&keyframe_record(k, 30, k * 30, 8, k)).unwrap();
    }
    data.apply(&Record::RemoveKeyframe { id: 1 }).unwrap();
    let path = dir.join("snapshot.bin");
    let bytes = encode_snapshot(&data).unwrap();
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(read_snapshot(&path).unwrap(), data);
    assert_eq!(read_snapshot(&path).unwrap(), decode_snapshot(&bytes, &path).unwrap());
    let v1 = MapDataV1 {
        meta: data.meta.clone(),
        keyframes: data.keyframes.iter().map(|(&i, k)| (i, Keyframe::clone(&k.load().unwrap()))).collect(),
        landmarks: data.landmarks.clone(),
        observations: data.observations.clone(),
        embeddings: data.embeddings.clone(),
        next_landmark: data.next_landmark,
        version: data.version,
    };
    let old = frame_snapshot(1, &encode_bincode1(&v1));
    std::fs::write(&path, &old).unwrap();
    assert_eq!(read_snapshot(&path).unwrap(), decode_snapshot(&old, &path).unwrap());
    let refused = |b: &[u8]| {
        std::fs::write(&path, b).unwrap();
        read_snapshot(&path).unwrap_err().to_string()
    };
    // The core follows the 32-byte header and the payload section. Its first 8 bytes are the map id's u64
    // length prefix, little-endian: flipped at its last byte, a decode that trusted it would allocate and read
    // far past the file.
    let core = 32 + u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
    for at in [core, core + 7, (core + bytes.len()) / 2, bytes.len() - 1] {
        let mut b = bytes.clone();
        b[at] ^= 0x80;
        assert!(refused(&b).contains("checksum mismatch"), "byte {at}: {}", refused(&b));
    }
    // A payload byte: the payload's own checksum refuses the map.
    let mut b = bytes.clone();
    b[40] ^= 0x80;
    assert!(refused(&b).contains("checksum mismatch"), "{}", refused(&b));
    assert!(refused(&bytes[..bytes.len() - 5]).contains("header says"));
    for at in [12, 19, 20, 27] {
        let mut b = bytes.clone();
        b[at] ^= 0x80;
        assert!(refused(&b).contains("header says"), "byte {at}: {}", refused(&b));
    }
    assert!(refused(&bytes[..20]).contains("bad magic"));
    let mut b = bytes.clone();
    b[0] = b'X';
    assert!(refused(&b).contains("bad magic"));
}

/// Keyframe descriptors read and written as bytes (`serde_bytes`) encode to the bytes a plain `Vec<u8>` gave,
/// so the maps, logs and exports of formats 1 to 3 (bincode 1) decode the same; JSON keeps its array of numbers.
#[test]
fn descriptors_as_bytes_encode_as_before() {
    #[derive(serde::Serialize)]
    struct Before<'a> {
        id: u64,
        pose: &'a Pose,
        camera: &'a Camera,
        keypoints: &'a Vec<Keypoint>,
        descriptors: &'a Vec<u8>,
        embeddings: &'a Vec<f32>,
    }
    let Record::AddKeyframe { keyframe: k, .. } = keyframe_record(3, 20, 0, 8, 9) else { unreachable!() };
    let before = Before {
        id: k.id,
        pose: &k.pose,
        camera: &k.camera,
        keypoints: &k.keypoints,
        descriptors: &k.descriptors,
        embeddings: &k.embeddings,
    };
    let old = encode_bincode1(&before);
    assert_eq!(encode_bincode1(&k), old);
    assert_eq!(Encoding::Bincode1.decode::<Keyframe>(&old).unwrap(), k);
    assert_eq!(serde_json::to_value(&k).unwrap(), serde_json::to_value(&before).unwrap());
    let json = serde_json::to_string(&before).unwrap();
    assert_eq!(serde_json::from_str::<Keyframe>(&json).unwrap(), k);
}

/// A map directory with two logged keyframe records (10 observations each, dimension 8).
fn logged_map(name: &str) -> TestDir {
    let dir = temp_dir(name);
    let mut data = MapData::new(meta(8));
    let mut log = LocalJournal::create(&dir, &data, 0).unwrap();
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
    let (loaded, mut log, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(loaded.keyframes.len(), 1);
    assert!(report.truncated_bytes > 0);
    // The log accepts new records after the cut, and they replay.
    let mut data = loaded;
    write(&mut log, &mut data, keyframe_record(7, 4, 100, 8, 3));
    drop(log);
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
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
    let err = LocalJournal::open(&dir, 0).unwrap_err().to_string();
    assert!(err.contains("log.bin") && err.contains("checksum"), "{err}");
}

#[test]
fn compaction_keeps_everything_and_restarts_the_log() {
    let dir = temp_dir("compact");
    let mut data = MapData::new(meta(8));
    let mut log = LocalJournal::create(&dir, &data, 2).unwrap();
    write(&mut log, &mut data, keyframe_record(0, 5, 0, 8, 1));
    write(&mut log, &mut data, keyframe_record(1, 5, 5, 8, 2));
    assert!(log.wants_compaction());
    log.compact(&data).unwrap();
    write(&mut log, &mut data, keyframe_record(2, 5, 10, 8, 3));
    drop(log);
    let (loaded, _, report) = LocalJournal::open(&dir, 2).unwrap();
    assert_eq!(report.replayed, 1);
    assert_eq!(loaded, data);
}

#[test]
fn snapshot_format_checks_magic_version_and_checksum() {
    let mut data = MapData::new(meta(4));
    data.apply(&keyframe_record(0, 3, 0, 4, 9)).unwrap();
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
    data.apply(&keyframe_record(0, 3, 0, 8, 1)).unwrap();
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
        data.apply(&keyframe_record(k, 200, k * 200, 48, k + 1)).unwrap();
    }
    data.apply(&Record::RemoveKeyframe { id: 1 }).unwrap();
    let queries = vectors(20, 48, 77);
    for q in queries.chunks(48) {
        let hits = exact_search(&data, q, 5, None);
        assert_eq!(hits.iter().map(|h| h.observation).collect::<Vec<_>>(), brute(&data, q, 5));
        assert!(hits.iter().all(|h| data.observations[h.observation].keyframe != 1));
    }
}

/// A map of `keyframes` x 250 observations with an HNSW index (exact search only below 1,000).
pub(crate) fn hnsw_map(keyframes: u64, seed: u64) -> (MapData, IndexSettings, EmbeddingIndex) {
    let mut data = MapData::new(meta(48));
    for k in 0..keyframes {
        data.apply(&keyframe_record(k, 250, k * 250, 48, k + seed)).unwrap();
    }
    let params = IndexSettings { exact_below: 1000, ..IndexSettings::default() };
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
    index.dump(&dir, &data).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && reloaded.loaded_from_dump());
    let q = data.embedding(3).to_vec();
    assert_eq!(reloaded.search(&data, &q, 3, None), index.search(&data, &q, 3, None));
    // Tombstones are filtered, and new observations are searchable before the next sync.
    data.apply(&Record::RemoveKeyframe { id: 0 }).unwrap();
    data.apply(&keyframe_record(99, 10, 10_000, 48, 5)).unwrap();
    let q = data.embedding(3).to_vec();
    assert!(reloaded.search(&data, &q, 3, None).iter().all(|h| h.observation != 3));
    let newest = data.observations.len() - 1;
    let q = data.embedding(newest).to_vec();
    assert_eq!(reloaded.search(&data, &q, 1, None)[0].observation, newest);
}

/// The reload (hnsw_rs with third_party/hnsw_rs's patch: links built per point, in parallel) gives back the
/// graph that was dumped: the same points, each layer's links the same, in order of distance.
#[test]
fn a_reloaded_graph_has_the_links_it_was_dumped_with() {
    let dir = temp_dir("hnsw-links");
    let (data, params, index) = hnsw_map(12, 23);
    index.dump(&dir, &data).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.loaded_from_dump());
    let (built, loaded) = (index.graph_links(), reloaded.graph_links());
    assert_eq!(built.len(), data.observations.len());
    assert_eq!(built.len(), loaded.len());
    let as_set = |l: &[(usize, f32)]| {
        let mut v: Vec<(usize, u32)> = l.iter().map(|&(o, d)| (o, d.to_bits())).collect();
        v.sort_unstable();
        v
    };
    let mut links = 0;
    for ((o1, l1), (o2, l2)) in built.iter().zip(&loaded) {
        assert_eq!(o1, o2);
        assert_eq!(l1.len(), l2.len());
        for (a, b) in l1.iter().zip(l2) {
            assert_eq!(as_set(a), as_set(b), "point {o1}");
            assert!(b.windows(2).all(|w| w[0].1 <= w[1].1), "point {o1}: links out of order");
            links += b.len();
        }
    }
    assert!(links > 10 * built.len(), "{links} links for {} points", built.len());
}

#[test]
fn a_dump_from_another_model_or_damaged_is_rebuilt() {
    let dir = temp_dir("hnsw-model");
    let (data, params, index) = hnsw_map(5, 1);
    let mut other = data.clone();
    other.meta.model_id = "sha256:other".into();
    index.dump(&dir, &other).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && !reloaded.loaded_from_dump(), "another model's dump was used");
    // A dump of the right model with a damaged graph file is rebuilt too.
    index.dump(&dir, &data).unwrap();
    let graph = crate::map::tests::fault_tests::dump_file(&dir, ".hnsw.graph");
    let mut bytes = std::fs::read(&graph).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x55;
    std::fs::write(&graph, bytes).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.is_approximate() && !reloaded.loaded_from_dump(), "a damaged dump was used");
}

/// Keyframe `id` with `n` keypoints, each a further view of landmark `i` (made by [`keyframe_record`]).
fn views_record(id: u64, n: usize, dim: usize, seed: u64) -> Record {
    let Record::AddKeyframe { keyframe, .. } = keyframe_record(id, n, 0, dim, seed) else { unreachable!() };
    let observations =
        (0..n).map(|i| NewObservation { landmark: i as u64, keyframe: id, keypoint: i as u32 }).collect();
    Record::AddKeyframe { keyframe, new_landmarks: Vec::new(), observations }
}

/// Every landmark with a live view has one representative, a live view of its own, and searches return
/// representatives only.
fn assert_representatives(data: &MapData, index: &EmbeddingIndex) {
    let mut found = 0;
    for (&lm, l) in &data.landmarks {
        let views: Vec<usize> =
            l.observations.iter().map(|&o| o as usize).filter(|&o| data.observations[o].live).collect();
        let Some(&any) = views.first() else { continue };
        let hits = index.search(data, data.embedding(any), 3, None);
        assert!(hits.iter().all(|h| {
            let o = &data.observations[h.observation];
            o.live && index.search(data, data.embedding(h.observation), 1, None)[0].observation == h.observation
        }));
        found += usize::from(data.observations[hits[0].observation].landmark == lm);
    }
    assert!(found as f64 >= 0.9 * data.landmarks.len() as f64, "{found} of {} landmarks", data.landmarks.len());
}

#[test]
fn one_point_per_landmark_follows_new_views_removals_and_a_dump() {
    use crate::map::index::IndexPoints;
    let dir = temp_dir("hnsw-landmarks");
    // Half the points will be replaced ones: the rebuild share is raised so they stay (tested at the end).
    let params = IndexSettings {
        exact_below: 100,
        points: IndexPoints::Landmarks,
        rebuild_dead_share: 0.6,
        ..IndexSettings::default()
    };
    let mut data = MapData::new(meta(48));
    let mut index = EmbeddingIndex::new(params);
    data.apply(&keyframe_record(0, 300, 0, 48, 1)).unwrap();
    index.sync(&data);
    assert_eq!(index.graph_shape().unwrap().0, 300);
    // Views close to the first (the same vectors, nudged), so a landmark's views lie near each other.
    let first = data.keyframes[&0].load().unwrap().embeddings.clone();
    let nudged = |id: u64, step: f32| {
        let mut r = views_record(id, 300, 48, 9);
        if let Record::AddKeyframe { keyframe, .. } = &mut r {
            keyframe.embeddings = first.iter().map(|v| v + step).collect();
        }
        r
    };
    // Two and three views: the first view stays the representative (no new points).
    for (k, step) in [(1, 0.02), (2, 0.01)] {
        data.apply(&nudged(k, step)).unwrap();
        index.sync(&data);
        assert_eq!(index.graph_shape().unwrap().0, 300, "after keyframe {k}");
    }
    // Four views: chosen again. Views 0 and 3 lie at the ends of the line, 1 and 2 (shifts 0.02 and 0.01)
    // between: they tie as the medoid, and the first, keyframe 1's, replaces keyframe 0's.
    data.apply(&nudged(3, 0.03)).unwrap();
    index.sync(&data);
    assert_eq!(index.graph_shape().unwrap().0, 600);
    let hit = index.search(&data, data.embedding(0), 1, None)[0].observation;
    assert_eq!((data.observations[hit].landmark, data.observations[hit].keyframe), (0, 1));
    assert_representatives(&data, &index);
    // The dump keeps the representatives; another setting's dump is not used.
    index.dump(&dir, &data).unwrap();
    let reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(reloaded.loaded_from_dump());
    for i in (0..data.observations.len()).step_by(13) {
        let q = data.embedding(i);
        assert_eq!(reloaded.search(&data, q, 3, None), index.search(&data, q, 3, None));
    }
    let other =
        EmbeddingIndex::load_or_build(IndexSettings { points: IndexPoints::Observations, ..params }, &dir, &data);
    assert!(!other.loaded_from_dump());
    // Removing keyframe 1 takes every representative: each landmark gets another, none from keyframe 1.
    let mut index = reloaded;
    data.apply(&Record::RemoveKeyframe { id: 1 }).unwrap();
    index.sync(&data);
    assert_representatives(&data, &index);
    for i in (0..data.observations.len()).step_by(5) {
        let hits = index.search(&data, data.embedding(i), 2, None);
        assert!(hits.iter().all(|h| data.observations[h.observation].keyframe != 1));
    }
    // At the default share, the replaced points (over half) have the graph rebuilt with one per landmark.
    let rebuilt = EmbeddingIndex::load_or_build(IndexSettings { rebuild_dead_share: 0.3, ..params }, &dir, &data);
    assert!(!rebuilt.loaded_from_dump());
    assert_eq!(rebuilt.graph_shape().unwrap().0, 300);
    assert_representatives(&data, &rebuilt);
}

#[test]
fn a_query_keypoint_cap_searches_the_strongest_keypoints_and_still_localises() {
    use crate::describe::features::Features;
    use crate::map::localize::{localize, LocalizeSettings};
    let (n, dim) = (200usize, 48usize);
    let cam = Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 };
    // Landmark i is seen at pixel (x_i, y_i) by a camera at the origin looking along +z.
    let pixel = |i: usize| (((i * 37) % 600 + 20) as f32, ((i * 91) % 440 + 20) as f32);
    let point = |i: usize| {
        let (x, y) = pixel(i);
        let z = 4.0 + (i % 7) as f64;
        [(x as f64 - cam.cx) / cam.fx * z, (y as f64 - cam.cy) / cam.fy * z, z]
    };
    let Record::AddKeyframe { keyframe, observations, .. } = keyframe_record(0, n, 0, dim, 5) else { unreachable!() };
    let new_landmarks = (0..n).map(|i| (i as u64, point(i))).collect();
    let mut data = MapData::new(meta(dim));
    data.apply(&Record::AddKeyframe { keyframe: keyframe.clone(), new_landmarks, observations }).unwrap();
    let index = EmbeddingIndex::new(IndexSettings::default());
    // The query: the same embeddings at the landmarks' pixels; responses a permutation of 0..n (73 is prime to
    // 200), so the strongest keypoints are scattered over the index range.
    let response = |i: usize| ((i * 73) % n) as f32;
    let query = |response: &dyn Fn(usize) -> f32| Features {
        width: 640,
        height: 480,
        keypoints: (0..n)
            .map(|i| {
                let (x, y) = pixel(i);
                Keypoint { x, y, size: 7.0, angle: 0.0, response: response(i), octave: 0 }
            })
            .collect(),
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; n],
        context: Vec::new(),
    };
    let features = query(&response);
    let every = LocalizeSettings { max_query_keypoints: usize::MAX, ..LocalizeSettings::default() };
    let all = localize(&data, &index, &features, &keyframe.embeddings, &cam, None, &every).unwrap();
    assert_eq!(all.matches.len(), n);
    // Stage 1 alone: guided search reads every keypoint (stage_tests.rs has the cap with all stages).
    let capped = LocalizeSettings { max_query_keypoints: 50, ..LocalizeSettings::default().stage_one_only() };
    let l = localize(&data, &index, &features, &keyframe.embeddings, &cam, None, &capped).unwrap();
    // Only the 50 strongest keypoints were searched, and matches name them by their index in the whole set.
    assert_eq!(l.matches.len(), 50);
    assert!(l.matches.iter().all(|m| response(m.keypoint) >= (n - 50) as f32 && m.landmark == m.keypoint as u64));
    let pose = l.pose.expect("50 exact matches localise");
    assert!(pose.camera_to_world.translation.vector.norm() < 1e-3);
    // Equal responses (client keypoints without scores) keep the order sent: the first 50.
    let flat = query(&|_| 0.0);
    let l = localize(&data, &index, &flat, &keyframe.embeddings, &cam, None, &capped).unwrap();
    let mut searched: Vec<usize> = l.matches.iter().map(|m| m.keypoint).collect();
    searched.sort_unstable();
    assert_eq!(searched, (0..50).collect::<Vec<_>>());
    // A cap below min_inliers (possible only in code; settings refuse it) still searches min_inliers.
    let tiny = LocalizeSettings { max_query_keypoints: 3, ..LocalizeSettings::default().stage_one_only() };
    let l = localize(&data, &index, &features, &keyframe.embeddings, &cam, None, &tiny).unwrap();
    assert_eq!(l.matches.len(), LocalizeSettings::default().min_inliers);
    // A cap below the inliers a pose needs is refused at configuration time.
    let too_low = LocalizeSettings { max_query_keypoints: 10, ..LocalizeSettings::default() };
    assert!(too_low.validate().unwrap_err().contains("min_inliers"));
    assert!(LocalizeSettings::default().validate().is_ok());
}

/// A merge record adds its keyframes, landmarks and observations at once; it may observe only its own
/// keyframes, keeps points within the bound of poses, and survives a replay of the log like any record.
#[test]
fn a_merge_record_is_checked_applied_and_replayed_as_one() {
    let dir = temp_dir("merge-record");
    let mut data = MapData::new(meta(8));
    let mut log = LocalJournal::create(&dir, &data, 0).unwrap();
    // Keypoint 3 of keyframe 0 observes nothing, so only the merge's own rule can refuse observing it.
    let Record::AddKeyframe { keyframe, mut new_landmarks, mut observations } = keyframe_record(0, 4, 0, 8, 1) else {
        unreachable!()
    };
    new_landmarks.pop();
    observations.pop();
    write(&mut log, &mut data, Record::AddKeyframe { keyframe, new_landmarks, observations });
    let parts = |r: Record| match r {
        Record::AddKeyframe { keyframe, new_landmarks, observations } => (keyframe, new_landmarks, observations),
        _ => unreachable!(),
    };
    let (k1, l1, o1) = parts(keyframe_record(1, 4, 10, 8, 2));
    let (k2, l2, o2) = parts(keyframe_record(2, 4, 20, 8, 3));
    let merge = |landmarks: Vec<(u64, [f64; 3])>, observations: Vec<NewObservation>| Record::Merge {
        source: "other".into(),
        keyframes: vec![k1.clone(), k2.clone()],
        new_landmarks: landmarks,
        observations,
    };
    let good = merge([l1.clone(), l2.clone()].concat(), [o1.clone(), o2.clone()].concat());
    // Observing a keyframe the merge does not add, or a point beyond the bound: refused.
    let stray = NewObservation { landmark: 10, keyframe: 0, keypoint: 3 };
    let mut o_bad = [o1.clone(), o2.clone()].concat();
    o_bad[0] = stray;
    assert!(data.check(&merge([l1.clone(), l2.clone()].concat(), o_bad)).unwrap_err().contains("does not add"));
    let mut far = [l1, l2].concat();
    far[0].1 = [2e8, 0.0, 0.0];
    assert!(data.check(&merge(far, [o1, o2].concat())).unwrap_err().contains("beyond"));
    write(&mut log, &mut data, good);
    assert_eq!((data.keyframes.len(), data.landmarks.len(), data.live_observations()), (3, 11, 11));
    drop(log);
    let (replayed, _, _) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(replayed, data);
}

/// The per-keyframe observation lists (derived, not stored) follow every record, come back the same from a
/// snapshot, and a keyframe removed then added again under its id lists only its new observations.
#[test]
fn keyframe_observation_lists_follow_records_and_snapshots() {
    let mut data = MapData::new(meta(8));
    for r in [keyframe_record(0, 6, 0, 8, 1), keyframe_record(1, 4, 6, 8, 2)] {
        data.check(&r).unwrap();
        data.apply(&r).unwrap();
    }
    // Keyframe 1 also sees landmark 0 through its keypoint 3... which it observes already: refused.
    let twice = Record::AddKeyframe {
        keyframe: match keyframe_record(2, 2, 100, 8, 3) {
            Record::AddKeyframe { keyframe, .. } => keyframe,
            _ => unreachable!(),
        },
        new_landmarks: vec![],
        observations: vec![
            NewObservation { landmark: 0, keyframe: 2, keypoint: 0 },
            NewObservation { landmark: 1, keyframe: 1, keypoint: 3 },
        ],
    };
    assert!(data.check(&twice).unwrap_err().contains("keyframe 1 keypoint 3"));
    assert_eq!(data.keyframe_observations(0), &[0, 1, 2, 3, 4, 5]);
    assert_eq!(data.keypoint_landmarks(1).get(&3), Some(&9));
    let remove = Record::RemoveKeyframe { id: 0 };
    assert_eq!(data.stats_after(&remove).live_observations, 4);
    data.apply(&remove).unwrap();
    assert!(data.keyframe_observations(0).is_empty());
    let again = keyframe_record(0, 3, 200, 8, 4);
    data.check(&again).unwrap();
    data.apply(&again).unwrap();
    assert_eq!(data.keyframe_observations(0), &[10, 11, 12]);
    assert_eq!(data.live_observations(), 7);
    let p = PathBuf::from("x");
    assert_eq!(decode_snapshot(&encode_snapshot(&data).unwrap(), &p).unwrap(), data);
}
