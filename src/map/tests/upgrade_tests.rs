//! The upgrade of a map written in format 3 (bincode 1) to format 4 (postcard), on the committed fixture
//! `tests/fixtures/map-format3` (a snapshot and two log records made by the format-3 writer): it opens with
//! every keyframe, is rewritten, reopens the same, and a crash at either step of the rewrite loses nothing.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use fail::FailScenario;

use crate::map::encoding::Encoding;
use crate::map::model::MapData;
use crate::map::storage::backend::MapBackend;
use crate::map::storage::format::{read_frame, LogEntry, FORMAT_VERSION, LOG_HEADER};
use crate::map::storage::local::LocalJournal;
use crate::map::storage::s3::ObjectStorageBackend;
use crate::map::storage::snapshot::{encode_snapshot_v3, read_snapshot, snapshot_version};
use crate::map::tests::open_while_writing_fails;
use crate::test_dir::{temp_dir, TestDir};

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/map-format3/maps/format3")
}

/// A copy of the fixture's map directory.
fn copy_of_fixture(name: &str) -> TestDir {
    let dir = temp_dir(name);
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(fixture().join(f), dir.join(f)).unwrap();
    }
    dir
}

fn versions(dir: &Path) -> (u32, u32) {
    let log = std::fs::read(dir.join("log.bin")).unwrap();
    (snapshot_version(&dir.join("snapshot.bin")).unwrap(), u32::from_le_bytes(log[8..12].try_into().unwrap()))
}

/// The fixture's records, decoded in format 3's encoding as its log's header says.
fn fixture_records() -> Vec<(u64, crate::map::model::Record)> {
    let path = fixture().join("log.bin");
    let buf = std::fs::read(&path).unwrap();
    assert_eq!(u32::from_le_bytes(buf[8..12].try_into().unwrap()), 3);
    let (mut pos, mut out) = (LOG_HEADER as usize, Vec::new());
    while pos < buf.len() {
        let LogEntry::Record { seq, record, end } = read_frame(&buf, pos, 3, &path).unwrap() else {
            panic!("the fixture's log is whole")
        };
        out.push((seq, *record));
        pos = end;
    }
    out
}

/// The fixture's map read without rewriting anything: its format-3 snapshot, then its log's records.
fn fixture_map() -> MapData {
    let snapshot = fixture().join("snapshot.bin");
    assert_eq!(snapshot_version(&snapshot).unwrap(), 3);
    let mut data = read_snapshot(&snapshot).unwrap();
    for (seq, record) in fixture_records() {
        assert_eq!(seq, data.version + 1);
        data.check(&record).unwrap();
        data.apply(&record).unwrap();
    }
    data
}

#[test]
fn the_format_3_fixture_opens_with_every_keyframe_is_rewritten_in_format_4_and_reopens_the_same() {
    let expected = fixture_map();
    assert_eq!(expected.keyframes.keys().copied().collect::<Vec<_>>(), [0, 1, 2, 3]);
    assert_eq!((expected.version, expected.observations.len()), (4, 959));
    let dir = copy_of_fixture("upgrade-fixture");
    let before = std::fs::metadata(dir.join("snapshot.bin")).unwrap().len();
    let (data, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!(report.replayed, 2);
    assert_eq!(versions(&dir), (FORMAT_VERSION, FORMAT_VERSION));
    assert_eq!(std::fs::metadata(dir.join("log.bin")).unwrap().len(), LOG_HEADER, "the log is folded in");
    // Equal keyframes have equal payloads: those of the snapshot were read from the format-3 file in bincode
    // and written again in postcard, those of the log came from its records.
    assert_eq!(data, expected);
    assert!(data.keyframes.values().all(|k| k.inline_keyframe().is_none()), "the payloads left memory");
    let after = std::fs::metadata(dir.join("snapshot.bin")).unwrap().len();
    eprintln!("snapshot of the fixture: {before} bytes in format 3 (2 keyframes), {after} in format 4 (4 keyframes)");
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, &again), (0, &expected));
    assert_eq!(read_snapshot(&dir.join("snapshot.bin")).unwrap(), expected);
}

#[test]
fn the_format_3_encoder_of_the_tests_writes_the_fixture_s_snapshot_byte_for_byte() {
    // The tests that make format-3 maps of their own (larger than the fixture) write what the format-3
    // writer wrote: its snapshot, read and encoded again, and its records, framed again.
    let snapshot = std::fs::read(fixture().join("snapshot.bin")).unwrap();
    assert!(encode_snapshot_v3(&read_snapshot(&fixture().join("snapshot.bin")).unwrap()).unwrap() == snapshot);
    let log = std::fs::read(fixture().join("log.bin")).unwrap();
    let mut framed = log[..LOG_HEADER as usize].to_vec();
    for (seq, record) in fixture_records() {
        framed.extend_from_slice(&crate::map::storage::format::encode_record_bincode1(seq, &record));
    }
    assert!(framed == log);
}

#[test]
fn a_crash_at_either_step_of_the_fixture_s_rewrite_loses_nothing() {
    let _scenario = FailScenario::setup();
    let expected = fixture_map();
    // A crash while the new snapshot is written (a full volume there): the old files stay whole. A crash after
    // it, before the fresh log: the new snapshot covers the old log's records, read in bincode and skipped.
    for (site_part, after_crash) in [("snapshot.bin", (3, 3)), ("log.bin", (FORMAT_VERSION, 3))] {
        let dir = copy_of_fixture("upgrade-fixture-crash");
        // A failed rewrite is not the open's error: the map is read from the files as they are.
        let opened = open_while_writing_fails(&dir, site_part);
        assert_eq!(opened, (expected.clone(), true), "the injected fault at {site_part}");
        assert_eq!(versions(&dir), after_crash, "after a crash at {site_part}");
        let (data, _, report) = LocalJournal::open(&dir, 0).unwrap();
        let replayed = if site_part == "snapshot.bin" { 2 } else { 0 };
        assert_eq!((versions(&dir), report.replayed, &data), ((FORMAT_VERSION, FORMAT_VERSION), replayed, &expected));
        let (again, _, _) = LocalJournal::open(&dir, 0).unwrap();
        assert_eq!(again, expected);
    }
}

#[test]
fn a_map_whose_rewrite_fails_at_open_is_read_as_it_is_and_its_next_write_waits_for_the_rewrite() {
    let _scenario = FailScenario::setup();
    let expected = fixture_map();
    let dir = copy_of_fixture("upgrade-full-volume");
    let name = dir.file_name().unwrap().to_string_lossy().into_owned();
    let before = (std::fs::read(dir.join("snapshot.bin")).unwrap(), std::fs::read(dir.join("log.bin")).unwrap());
    // A full volume when the open rewrites the snapshot: the map opens from its format-3 files, untouched.
    fail::cfg("map-write", &format!("return({name},snapshot.bin)")).unwrap();
    let (mut data, mut log, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, &data, log.needs_upgrade()), (2, &expected, true));
    let after = (std::fs::read(dir.join("snapshot.bin")).unwrap(), std::fs::read(dir.join("log.bin")).unwrap());
    assert!(after == before, "the old files stay as they were");
    // No record goes into a log whose header promises format 3; the write's compaction fails while the volume
    // is full, and succeeds once it is not.
    let removal = crate::map::model::Record::RemoveKeyframe { id: 3 };
    assert!(log.append(data.version + 1, &removal).is_err());
    assert!(log.compact(&data).is_err());
    fail::remove("map-write");
    log.compact(&data).unwrap();
    assert_eq!((versions(&dir), log.needs_upgrade()), ((FORMAT_VERSION, FORMAT_VERSION), false));
    data.apply(&removal).unwrap();
    log.append(data.version, &removal).unwrap();
    drop(log);
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, again.keyframes.len()), (1, expected.keyframes.len() - 1));
}

#[test]
fn through_the_store_a_map_whose_rewrite_failed_answers_reads_and_its_next_write_rewrites_it_first() {
    use crate::map::storage::local::LocalBackend;
    use crate::map::store::{MapStore, ModelInfo, StoreSettings};
    let _scenario = FailScenario::setup();
    let expected = fixture_map();
    let data_dir = temp_dir("upgrade-store");
    let dir = data_dir.join("maps/format3");
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(fixture().join(f), dir.join(f)).unwrap();
    }
    let name = data_dir.file_name().unwrap().to_string_lossy().into_owned();
    fail::cfg("map-write", &format!("return({name},snapshot.bin)")).unwrap();
    let config = StoreSettings { data_dir: data_dir.to_path_buf(), compact_every: 0, ..StoreSettings::default() };
    let model = ModelInfo { model_id: expected.meta.model_id.clone(), k: 0, dim: expected.meta.dim };
    let backend = Arc::new(LocalBackend::new(&data_dir, 0).unwrap()) as Arc<dyn MapBackend>;
    let store = MapStore::open_with_backend(config, model, backend).unwrap();
    // The map is served (not held back) from its format-3 files while the volume refuses the rewrite.
    let map = store.get("format3").unwrap();
    assert_eq!(store.summary("format3").unwrap().keyframes, expected.keyframes.len());
    assert_eq!(versions(&dir), (3, 3));
    // A write fails with the volume's error and leaves the files as they were; once there is room, the write
    // rewrites the map in the current format and then logs its record.
    assert!(store.remove_keyframe(&map, 3).is_err());
    assert_eq!(versions(&dir), (3, 3));
    fail::remove("map-write");
    store.remove_keyframe(&map, 3).unwrap();
    assert_eq!(versions(&dir), (FORMAT_VERSION, FORMAT_VERSION));
    drop((map, store));
    let (again, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, again.keyframes.len()), (1, expected.keyframes.len() - 1));
}

#[test]
fn object_storage_reads_the_fixture_s_format_3_snapshot_and_its_next_compaction_writes_format_4() {
    use object_store::memory::InMemory;
    use object_store::{ObjectStore, ObjectStoreExt};
    let mem = Arc::new(InMemory::new());
    let cache = temp_dir("upgrade-objects");
    let b = ObjectStorageBackend::new(Arc::clone(&mem) as Arc<dyn ObjectStore>, "memory://", "p", &cache, 0).unwrap();
    // A bucket of the previous build: the fixture's snapshot as the snapshot object, its records after it.
    let snapshot = read_snapshot(&fixture().join("snapshot.bin")).unwrap();
    let mut j = b.create("m", &snapshot).unwrap();
    let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
    let under = object_store::path::Path::from("p/maps/m/snapshots");
    let objects: Vec<_> =
        rt.block_on(futures_util::TryStreamExt::try_collect::<Vec<_>>(mem.list(Some(&under)))).unwrap();
    let format3 = std::fs::read(fixture().join("snapshot.bin")).unwrap();
    rt.block_on(mem.put(&objects[0].location, format3.into())).unwrap();
    let mut expected = snapshot;
    for (seq, record) in fixture_records() {
        expected.apply(&record).unwrap();
        j.append(seq, &record, &expected.stats()).unwrap();
    }
    drop(j);
    let (mut loaded, mut j, report) = b.open("m").unwrap();
    assert_eq!((report.replayed, &loaded), (2, &fixture_map()));
    // The copy of a format-3 snapshot keeps its payloads in bincode, read as such; the writer's next
    // compaction (after a write: a replica that only read does not compact) writes them again in postcard.
    let removal = crate::map::model::Record::RemoveKeyframe { id: 3 };
    loaded.apply(&removal).unwrap();
    j.append(loaded.version, &removal, &loaded.stats()).unwrap();
    j.compact(&loaded).unwrap();
    drop(j);
    let objects: Vec<_> =
        rt.block_on(futures_util::TryStreamExt::try_collect::<Vec<_>>(mem.list(Some(&under)))).unwrap();
    assert_eq!(objects.len(), 1, "the replaced snapshot is deleted");
    let (bytes, _) = rt.block_on(async { (mem.get(&objects[0].location).await.unwrap().bytes().await.unwrap(), ()) });
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), FORMAT_VERSION);
    let (again, _, report) = b.open("m").unwrap();
    assert_eq!((report.replayed, &again), (0, &loaded));
    assert_eq!(again.keyframes.keys().copied().collect::<Vec<_>>(), [0, 1, 2]);
    assert_eq!(Encoding::of_format(FORMAT_VERSION), Encoding::CURRENT);
}

#[test]
fn a_format_4_core_of_garbage_behind_a_valid_checksum_is_an_error_not_a_panic_or_a_huge_allocation() {
    use crate::map::storage::snapshot::{decode_snapshot, encode_snapshot_spans};
    use rand::{Rng, SeedableRng};
    // What an import could carry: a well-formed header and payload section, and a core whose checksum matches
    // bytes that are not a map (random, or lengths claiming far more elements than the file holds).
    let good = encode_snapshot_spans(&fixture_map()).unwrap().bytes;
    let core_at = 32 + u64::from_le_bytes(good[12..20].try_into().unwrap()) as usize;
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    for trial in 0..200 {
        let mut bytes = good[..core_at].to_vec();
        let len = rng.random_range(1..4096);
        let mut core: Vec<u8> = (0..len).map(|_| rng.random()).collect();
        if trial % 4 == 0 {
            core[..10].fill(0xff); // a varint length near 2^64
        }
        bytes.extend_from_slice(&core);
        bytes[20..28].copy_from_slice(&(core.len() as u64).to_le_bytes());
        bytes[28..32].copy_from_slice(&crc32fast::hash(&core).to_le_bytes());
        let err = decode_snapshot(&bytes, Path::new("garbage")).unwrap_err().to_string();
        assert!(!err.contains("checksum") && !err.contains("header"), "trial {trial} stopped before decoding: {err}");
    }
    assert_eq!(decode_snapshot(&good, Path::new("good")).unwrap(), fixture_map(), "the same framing decodes a map");
}
