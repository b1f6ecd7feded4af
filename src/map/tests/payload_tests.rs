//! Keyframe payloads off the heap: a snapshot's payloads stay in its file and are read back
//! checked; a map of format 2 opens, upgrades (crash-safe at each step) and localises as before, on both
//! backends.

use std::path::Path;
use std::sync::Arc;

use fail::FailScenario;

use super::{keyframe_record, meta, open_while_writing_fails, write};
use crate::camera::Camera;
use crate::describe::features::Features;
use crate::error::MapError;
use crate::map::encoding::Encoding;
use crate::map::index::{EmbeddingIndex, IndexSettings};
use crate::map::localize::{localize, LocalizeSettings};
use crate::map::model::{MapData, NewObservation, Record};
use crate::map::storage::backend::{MapBackend, MapJournal};
use crate::map::storage::format::{encode_record_bincode1, FORMAT_VERSION};
use crate::map::storage::local::LocalJournal;
use crate::map::storage::s3::ObjectStorageBackend;
use crate::map::storage::snapshot::{encode_snapshot_v2, snapshot_version};
use crate::test_dir::temp_dir;

const DIM: usize = 48;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

/// Keyframe 0 of `n` keypoints at pixels of a camera at the origin looking along +z, each seeing a landmark
/// in front of it (so a query of the same keypoints localises); only the first `observed` keypoints observe.
fn seen_keyframe(n: usize, observed: usize) -> Record {
    let cam = camera();
    let Record::AddKeyframe { mut keyframe, .. } = keyframe_record(0, n, 0, DIM, 5) else { unreachable!() };
    for (i, k) in keyframe.keypoints.iter_mut().enumerate() {
        (k.x, k.y) = (((i * 37) % 600 + 20) as f32, ((i * 91) % 440 + 20) as f32);
    }
    let point = |i: usize| {
        let k = &keyframe.keypoints[i];
        let z = 4.0 + (i % 7) as f64;
        [(k.x as f64 - cam.cx) / cam.fx * z, (k.y as f64 - cam.cy) / cam.fy * z, z]
    };
    let new_landmarks = (0..observed).map(|i| (i as u64, point(i))).collect();
    let observations =
        (0..observed).map(|i| NewObservation { landmark: i as u64, keyframe: 0, keypoint: i as u32 }).collect();
    Record::AddKeyframe { keyframe, new_landmarks, observations }
}

/// A keyframe that also observes keypoint `keypoint` of keyframe `of` (a new landmark of both).
fn observing(id: u64, of: u64, keypoint: u32) -> Record {
    let Record::AddKeyframe { keyframe, mut new_landmarks, mut observations } =
        keyframe_record(id, 10, 1000 * id, DIM, id)
    else {
        unreachable!()
    };
    new_landmarks[0].1 = [0.1, 0.2, 5.0];
    observations.push(NewObservation { landmark: 1000 * id, keyframe: of, keypoint });
    Record::AddKeyframe { keyframe, new_landmarks, observations }
}

/// Everything of a map but its keyframes' payloads.
#[allow(clippy::type_complexity)]
fn parts(d: &MapData) -> (u64, Vec<u64>, Vec<(u64, bool)>, Vec<f32>, usize, u64) {
    let observations = d.observations.iter().map(|o| (o.landmark, o.live)).collect();
    (
        d.version,
        d.keyframes.keys().copied().collect(),
        observations,
        d.embeddings.clone(),
        d.landmarks.len(),
        d.next_landmark,
    )
}

fn stored_everywhere(data: &MapData) -> bool {
    data.keyframes.values().all(|k| k.inline_keyframe().is_none())
}

/// What `localize` finds for a query of keyframe 0's own keypoints and embeddings (exact search).
fn localized(data: &MapData) -> (Vec<(usize, u64)>, Option<[f64; 7]>) {
    localized_by(data, &data.keyframes[&0].load().unwrap())
}

/// What `localize` finds in `data` for a query of `k`'s keypoints and embeddings (exact search).
fn localized_by(data: &MapData, k: &crate::map::model::Keyframe) -> (Vec<(usize, u64)>, Option<[f64; 7]>) {
    let features = Features {
        width: 640,
        height: 480,
        keypoints: k.keypoints.clone(),
        descriptors: Vec::new(),
        context: Vec::new(),
    };
    let mut index = EmbeddingIndex::new(IndexSettings::default());
    index.sync(data);
    let out = localize(data, &index, &features, &k.embeddings, &camera(), None, &LocalizeSettings::default()).unwrap();
    let pose = out.pose.map(|p| {
        let (t, r) = (p.camera_to_world.translation.vector, p.camera_to_world.rotation.coords);
        [t.x, t.y, t.z, r.x, r.y, r.z, r.w]
    });
    (out.matches.iter().map(|m| (m.keypoint, m.landmark)).collect(), pose)
}

#[test]
fn a_snapshot_keeps_the_payloads_in_its_file_and_each_read_checks_them() {
    let dir = temp_dir("payload-stored");
    let mut data = MapData::new(meta(DIM));
    let mut log = LocalJournal::create(&dir, &data, 0).unwrap();
    write(&mut log, &mut data, seen_keyframe(120, 60));
    write(&mut log, &mut data, keyframe_record(1, 30, 500, DIM, 2));
    assert!(data.keyframes.values().all(|k| k.inline_keyframe().is_some()));
    let inline_bytes = data.memory_bytes();
    let before = data.clone();
    log.compact(&data).unwrap();
    data.store_payloads(&log.take_stored_payloads().unwrap());
    assert!(stored_everywhere(&data));
    assert_eq!(data, before, "the payloads read back are the ones written");
    assert!(inline_bytes - data.memory_bytes() > 120 * (64 + 4 * DIM), "{inline_bytes} -> {}", data.memory_bytes());
    // A keyframe's new observation of a stored keyframe reads its embedding from the file.
    write(&mut log, &mut data, observing(2, 0, 100));
    let first = data.keyframes[&0].load().unwrap();
    assert_eq!(data.embedding(data.observations.len() - 1), first.embedding(100, DIM));
    let (opened, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, &opened), (1, &data));
    assert!(opened.keyframes[&0].inline_keyframe().is_none() && opened.keyframes[&2].inline_keyframe().is_some());
    log.compact(&data).unwrap();
    data.store_payloads(&log.take_stored_payloads().unwrap());
    drop(log);
    let (opened, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, &opened), (0, &data));
    assert!(stored_everywhere(&opened));

    // One payload byte damaged under a loaded map (the same file, rewritten in place): each read of that
    // payload fails. Loaded again, the map is refused.
    let (mut damaged, _, _) = LocalJournal::open(&dir, 0).unwrap();
    let path = dir.join("snapshot.bin");
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[32 + 40] ^= 0x20;
    std::fs::write(&path, &bytes).unwrap();
    let e = LocalJournal::open(&dir, 0).unwrap_err();
    assert!(matches!(&e, MapError::Corrupt { reason, .. } if reason.contains("checksum mismatch")), "{e}");
    let e = damaged.keyframes[&0].load().unwrap_err();
    assert!(matches!(&e, MapError::Corrupt { reason, .. } if reason.contains("checksum mismatch")), "{e}");
    assert!(damaged.keyframes[&1].load().is_ok());
    // A record that needs it fails as a whole, and leaves the map as it was (compared without the keyframes'
    // payloads: a damaged payload equals nothing, itself included).
    let untouched = parts(&damaged);
    let r = observing(3, 0, 101);
    damaged.check(&r).unwrap();
    assert!(matches!(damaged.apply(&r), Err(MapError::Corrupt { .. })));
    assert!(parts(&damaged) == untouched, "a failed apply changed the map");
    damaged.apply(&keyframe_record(4, 10, 4000, DIM, 4)).unwrap();
}

/// A format-2 map directory holding `snapshot` (format 2) and a format-2 log of `records` after it.
fn format_2_map(dir: &Path, snapshot: &MapData, records: &[Record]) {
    std::fs::write(dir.join("snapshot.bin"), encode_snapshot_v2(snapshot).unwrap()).unwrap();
    let mut log = b"SCONELOG".to_vec();
    log.extend_from_slice(&2u32.to_le_bytes());
    for (i, r) in records.iter().enumerate() {
        log.extend_from_slice(&encode_record_bincode1(snapshot.version + 1 + i as u64, r));
    }
    std::fs::write(dir.join("log.bin"), &log).unwrap();
}

fn versions(dir: &Path) -> (u32, u32) {
    let log = std::fs::read(dir.join("log.bin")).unwrap();
    (snapshot_version(&dir.join("snapshot.bin")).unwrap(), u32::from_le_bytes(log[8..12].try_into().unwrap()))
}

#[test]
fn a_format_2_map_opens_upgrades_at_any_crash_point_and_localises_the_same() {
    let _scenario = FailScenario::setup();
    let mut old = MapData::new(meta(DIM));
    old.apply(&seen_keyframe(150, 120)).unwrap();
    let later = [keyframe_record(1, 40, 900, DIM, 7), observing(2, 0, 130)];
    let mut expected = old.clone();
    for r in &later {
        expected.check(r).unwrap();
        expected.apply(r).unwrap();
    }
    let answer = localized(&expected);
    assert!(answer.1.is_some() && answer.0.len() >= 80, "the test map must localise: {answer:?}");

    // A crash while the new snapshot is written (a full volume there): the old files stay whole. A crash
    // after it, before the fresh log: the new snapshot covers the old log's records, which are skipped.
    for (site_part, snapshot_after) in [("snapshot.bin", 2), ("log.bin", FORMAT_VERSION)] {
        let dir = temp_dir("payload-upgrade-crash");
        format_2_map(&dir, &old, &later);
        // The failed rewrite is not the open's error: the map is read from its files as they are.
        let opened = open_while_writing_fails(&dir, site_part);
        assert_eq!(opened, (expected.clone(), true), "the injected fault at {site_part}");
        assert_eq!(versions(&dir), (snapshot_after, 2), "after a crash at {site_part}");
        let (data, _, _) = LocalJournal::open(&dir, 0).unwrap();
        assert_eq!((versions(&dir), &data), ((FORMAT_VERSION, FORMAT_VERSION), &expected));
    }

    let dir = temp_dir("payload-upgrade");
    format_2_map(&dir, &old, &later);
    let (data, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 2);
    assert_eq!(versions(&dir), (FORMAT_VERSION, FORMAT_VERSION));
    assert!(stored_everywhere(&data), "the upgrade leaves no payload in memory");
    assert_eq!(data, expected);
    assert_eq!(localized(&data), answer);
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, localized(&again)), (0, answer));
}

#[test]
fn object_storage_keeps_payloads_in_a_cached_copy_and_reads_a_format_2_snapshot() {
    use object_store::memory::InMemory;
    use object_store::{ObjectStore, ObjectStoreExt};
    let mem = Arc::new(InMemory::new());
    let cache = temp_dir("payload-objects");
    let store: Arc<dyn ObjectStore> = Arc::clone(&mem) as Arc<dyn ObjectStore>;
    let b = ObjectStorageBackend::new(store, "memory://", "p", &cache, 0).unwrap();
    let mut data = MapData::new(meta(DIM));
    data.apply(&seen_keyframe(80, 80)).unwrap();
    let mut j = b.create("m", &data).unwrap();
    let expected = data.clone();
    data.store_payloads(&j.take_stored_payloads().unwrap());
    assert!(stored_everywhere(&data) && data == expected);
    let (loaded, _, _) = b.open("m").unwrap();
    assert!(stored_everywhere(&loaded) && loaded == expected);
    let copies: Vec<_> = std::fs::read_dir(cache.join("m")).unwrap().flatten().map(|e| e.file_name()).collect();
    assert_eq!(copies.iter().filter(|n| n.to_string_lossy().starts_with("snapshot-")).count(), 1, "{copies:?}");

    // The snapshot object rewritten in format 2 (a bucket of the previous build): it opens, its payloads
    // off the heap (the copy in the current format), and the bucket is left to its writer.
    let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
    let under = object_store::path::Path::from("p/maps/m/snapshots");
    let objects: Vec<_> =
        rt.block_on(futures_util::TryStreamExt::try_collect::<Vec<_>>(mem.list(Some(&under)))).unwrap();
    let key = objects[0].location.clone();
    let v2 = encode_snapshot_v2(&expected).unwrap();
    rt.block_on(mem.put(&key, v2.clone().into())).unwrap();
    let (loaded, _, _) = b.open("m").unwrap();
    assert!(stored_everywhere(&loaded) && loaded == expected);
    assert_eq!(localized(&loaded), localized(&expected));
    let stored = rt.block_on(async { mem.get(&key).await.unwrap().bytes().await.unwrap() });
    assert_eq!(stored.as_ref(), v2.as_slice());
}

#[test]
fn a_section_still_to_arrive_is_waited_for_fetched_again_after_a_failure_and_never_after_damage() {
    use crate::map::payload::{PayloadFile, Span};
    use std::sync::atomic::{AtomicUsize, Ordering};
    let dir = temp_dir("payload-arriving");
    let path = dir.join("copy");
    let section = b"first payload, then the second".to_vec();
    std::fs::write(&path, vec![0u8; 4 + section.len()]).unwrap();
    let span =
        |a: usize, b: usize| Span { offset: a as u64, len: (b - a) as u64, crc: crc32fast::hash(&section[a..b]) };
    let spans = [span(0, 13), span(13, section.len())];
    // The first fetch fails (storage down) after 300 ms, the second writes the section after 50; the readers
    // below arrive while they run.
    let calls = Arc::new(AtomicUsize::new(0));
    let fetch = {
        let (calls, path, section) = (Arc::clone(&calls), path.clone(), section.clone());
        Box::new(move || {
            let n = calls.fetch_add(1, Ordering::SeqCst);
            std::thread::sleep(std::time::Duration::from_millis(if n == 0 { 300 } else { 50 }));
            if n == 0 {
                return Err(MapError::Io { path: path.clone(), source: std::io::Error::other("storage down") });
            }
            let file = std::fs::File::options().write(true).open(&path);
            let written = file.and_then(|f| std::os::unix::fs::FileExt::write_all_at(&f, &section, 4));
            written.map_err(|source| MapError::Io { path: path.clone(), source })
        })
    };
    let file = PayloadFile::arriving(&path, 4, section.len() as u64, Encoding::CURRENT, fetch).unwrap();
    // Readers at once while the first fetch fails: the one that ran it gets its error, the others that waited
    // for it fail too, and none fetches again.
    let failed: Vec<MapError> = std::thread::scope(|s| {
        let readers: Vec<_> = (0..4)
            .map(|i| {
                let file = &file;
                s.spawn(move || {
                    std::thread::sleep(std::time::Duration::from_millis(10 * i));
                    file.read_raw(spans[0]).unwrap_err()
                })
            })
            .collect();
        readers.into_iter().map(|r| r.join().unwrap()).collect()
    });
    assert_eq!(calls.load(Ordering::SeqCst), 1, "{failed:?}");
    assert_eq!(failed.iter().filter(|e| matches!(e, MapError::Io { .. })).count(), 1, "{failed:?}");
    assert!(failed.iter().all(|e| matches!(e, MapError::Io { .. } | MapError::StorageUnavailable { .. })));
    let read: Vec<Vec<u8>> = std::thread::scope(|s| {
        let readers: Vec<_> = (0..6)
            .map(|i| {
                s.spawn({
                    let file = &file;
                    move || file.read_raw(spans[i % 2])
                })
            })
            .collect();
        readers.into_iter().map(|r| r.join().unwrap().unwrap()).collect()
    });
    assert_eq!(calls.load(Ordering::SeqCst), 2, "the readers shared one fetch");
    for (i, bytes) in read.iter().enumerate() {
        let s = spans[i % 2];
        assert_eq!(bytes.as_slice(), &section[s.offset as usize..(s.offset + s.len) as usize]);
    }
    file.arrive().unwrap();
    assert_eq!(calls.load(Ordering::SeqCst), 2);

    // A fetch that finds the section damaged is final: every read says so, none fetches again.
    let damaged_calls = Arc::new(AtomicUsize::new(0));
    let fetch = {
        let (calls, path) = (Arc::clone(&damaged_calls), path.clone());
        Box::new(move || {
            calls.fetch_add(1, Ordering::SeqCst);
            Err(MapError::Corrupt { path: path.clone(), reason: "payload at byte 4: bad span or checksum".into() })
        })
    };
    let file = PayloadFile::arriving(&path, 4, section.len() as u64, Encoding::CURRENT, fetch).unwrap();
    for s in spans.iter().chain(&spans) {
        let e = file.read_raw(*s).unwrap_err();
        assert!(matches!(&e, MapError::Corrupt { reason, .. } if reason.contains("bad span")), "{e}");
    }
    assert_eq!(damaged_calls.load(Ordering::SeqCst), 1);
}

#[test]
fn object_storage_loads_a_map_before_its_payload_section_and_reports_a_damaged_one_at_each_read() {
    use object_store::memory::InMemory;
    use object_store::{ObjectStore, ObjectStoreExt};
    let mem = Arc::new(InMemory::new());
    let cache = temp_dir("payload-section-later");
    let b = ObjectStorageBackend::new(Arc::clone(&mem) as Arc<dyn ObjectStore>, "memory://", "p", &cache, 0).unwrap();
    let mut data = MapData::new(meta(DIM));
    data.apply(&seen_keyframe(80, 80)).unwrap();
    data.apply(&keyframe_record(1, 30, 500, DIM, 2)).unwrap();
    b.create("m", &data).unwrap();
    let answer = localized(&data);

    // One byte of a payload damaged in the bucket: the map loads from its core and localises as before; each
    // read of a payload names the object and the damage.
    let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
    let under = object_store::path::Path::from("p/maps/m/snapshots");
    let objects: Vec<_> =
        rt.block_on(futures_util::TryStreamExt::try_collect::<Vec<_>>(mem.list(Some(&under)))).unwrap();
    let key = objects[0].location.clone();
    let mut bytes = rt.block_on(async { mem.get(&key).await.unwrap().bytes().await.unwrap() }).to_vec();
    bytes[32 + 40] ^= 0x20;
    rt.block_on(mem.put(&key, bytes.into())).unwrap();
    let (loaded, _, _) = b.open("m").unwrap();
    assert_eq!(parts(&loaded), parts(&data));
    assert!(stored_everywhere(&loaded));
    assert_eq!(localized_by(&loaded, &data.keyframes[&0].load().unwrap()), answer);
    for _ in 0..2 {
        for id in [0, 1] {
            let e = loaded.keyframes[&id].load().unwrap_err();
            let named = format!("{e}");
            assert!(matches!(&e, MapError::Corrupt { .. }) && named.contains("bad span or checksum"), "{named}");
            assert!(named.contains("snapshots/"), "the error names the object: {named}");
        }
    }
}
