//! Faults injected at every write site of the local backend and the index dump (`fail` points, configured
//! per test and limited to the test's own directory): a failed write leaves the stored files as they were,
//! and later writes follow good data. The object-storage backend's write sites are covered against moto in
//! `tests/it/object_store.rs`, and a real full volume with the server in `tests/it/full_disk.rs`.

use std::path::{Path, PathBuf};

use fail::FailScenario;

use super::{hnsw_map, keyframe_record, meta, write};
use crate::error::MapError;
use crate::map::index::EmbeddingIndex;
use crate::map::model::MapData;
use crate::map::storage::backend::MapBackend;
use crate::map::storage::local::{LocalBackend, LocalJournal};
use crate::test_dir::temp_dir;

/// The file of the dump in `dir` whose name ends with `suffix` (there must be exactly one).
pub(crate) fn dump_file(dir: &Path, suffix: &str) -> PathBuf {
    let found: Vec<PathBuf> = files(dir).into_iter().filter(|p| p.to_string_lossy().ends_with(suffix)).collect();
    assert_eq!(found.len(), 1, "dump files ending in {suffix}: {found:?}");
    found.into_iter().next().unwrap()
}

/// Every file in `dir` (not recursive), sorted.
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    v
}

fn name_of(dir: &Path) -> String {
    dir.file_name().unwrap().to_string_lossy().into_owned()
}

/// Sets the fail point `site` to fail writes to paths containing every part of `parts`.
fn inject(site: &str, parts: &[&str]) {
    fail::cfg(site, &format!("return({})", parts.join(","))).unwrap();
}

fn is_full(e: &MapError) -> bool {
    matches!(e, MapError::StorageFull { .. })
}

#[test]
fn a_failed_append_leaves_the_log_as_it_was_and_later_writes_follow_good_data() {
    let _scenario = FailScenario::setup();
    let dir = temp_dir("fault-append");
    let mut data = MapData::new(meta(8));
    let mut log = LocalJournal::create(&dir, &data, 0).unwrap();
    write(&mut log, &mut data, keyframe_record(0, 10, 0, 8, 1));
    let before = std::fs::read(dir.join("log.bin")).unwrap();

    inject("map-append", &[&name_of(&dir)]);
    let failed = keyframe_record(1, 10, 10, 8, 2);
    let e = log.append(data.version + 1, &failed).unwrap_err();
    assert!(is_full(&e), "{e}");
    assert_eq!(std::fs::read(dir.join("log.bin")).unwrap(), before, "the failed append left bytes in the log");
    fail::remove("map-append");

    // Space is back: the next writes are acknowledged and replay after a restart, nothing cut or corrupt.
    write(&mut log, &mut data, keyframe_record(2, 10, 20, 8, 3));
    write(&mut log, &mut data, keyframe_record(3, 10, 30, 8, 4));
    drop(log);
    let (loaded, _, report) = LocalJournal::open(&dir, 0).unwrap();
    assert_eq!((report.replayed, report.truncated_bytes), (3, 0));
    assert_eq!(loaded, data);
}

#[test]
fn a_failed_create_leaves_nothing_and_the_id_stays_free() {
    let _scenario = FailScenario::setup();
    let root = temp_dir("fault-create");
    let backend = LocalBackend::new(&root, 0).unwrap();
    let data = MapData::new(meta(8));
    for file in ["snapshot.bin", "log.bin"] {
        inject("map-write", &[&name_of(&root), file]);
        let e = backend.create("m", &data).unwrap_err();
        assert!(is_full(&e), "{e}");
        fail::remove("map-write");
        assert!(!backend.exists("m").unwrap() && backend.list().unwrap().is_empty());
        assert!(files(&root.join("maps")).is_empty(), "left behind: {:?}", files(&root.join("maps")));
    }
    let mut log = backend.create("m", &data).unwrap();
    log.append(1, &keyframe_record(0, 5, 0, 8, 1), &data.stats()).unwrap();
    drop(log);
    assert_eq!(backend.open("m").unwrap().0.keyframes.len(), 1);
}

#[test]
fn what_an_interrupted_create_or_delete_left_is_removed_at_start() {
    let root = temp_dir("fault-leftovers");
    let maps = root.join("maps");
    for left in [".creating-m-00000000000000aa", ".deleted-n-1234"] {
        std::fs::create_dir_all(maps.join(left)).unwrap();
        std::fs::write(maps.join(left).join("snapshot.bin"), b"partial").unwrap();
    }
    let backend = LocalBackend::new(&root, 0).unwrap();
    assert!(files(&maps).is_empty(), "{:?}", files(&maps));
    assert!(backend.list().unwrap().is_empty());
}

#[test]
fn a_failed_compaction_keeps_every_acknowledged_record_and_no_temporary_file() {
    let _scenario = FailScenario::setup();
    // The snapshot fails (nothing replaced), then the fresh log fails (the snapshot is replaced, the old log
    // stays and its records up to the snapshot are skipped at load).
    for file in ["snapshot.bin", "log.bin"] {
        let dir = temp_dir("fault-compact");
        let mut data = MapData::new(meta(8));
        let mut log = LocalJournal::create(&dir, &data, 2).unwrap();
        write(&mut log, &mut data, keyframe_record(0, 5, 0, 8, 1));
        write(&mut log, &mut data, keyframe_record(1, 5, 5, 8, 2));
        inject("map-write", &[&name_of(&dir), file]);
        let e = log.compact(&data).unwrap_err();
        assert!(is_full(&e), "{file}: {e}");
        fail::remove("map-write");
        let names: Vec<String> = files(&dir).iter().map(|p| name_of(p)).collect();
        assert_eq!(names, ["log.bin", "snapshot.bin"], "{file}");
        write(&mut log, &mut data, keyframe_record(2, 5, 10, 8, 3));
        drop(log);
        let (loaded, _, report) = LocalJournal::open(&dir, 2).unwrap();
        assert_eq!(report.truncated_bytes, 0, "{file}");
        assert_eq!(loaded, data, "{file}");
    }
}

#[test]
fn a_failed_index_dump_keeps_the_previous_dump_whole() {
    let _scenario = FailScenario::setup();
    for (site, parts) in [("index-dump", vec![]), ("map-write", vec!["index.json"])] {
        let dir = temp_dir("fault-dump");
        let (mut data, params, index) = hnsw_map(5, 3);
        index.dump(&dir, &data).unwrap();
        let before: Vec<(PathBuf, Vec<u8>)> =
            files(&dir).into_iter().map(|p| (p.clone(), std::fs::read(p).unwrap())).collect();
        data.apply(&keyframe_record(9, 100, 5000, 48, 9)).unwrap();
        let mut grown = EmbeddingIndex::load_or_build(params, &dir, &data);
        grown.sync(&data);
        let mut p = parts.clone();
        let name = name_of(&dir);
        p.push(&name);
        inject(site, &p);
        let e = grown.dump(&dir, &data).unwrap_err();
        assert!(is_full(&e), "{site}: {e}");
        fail::remove(site);
        let after: Vec<(PathBuf, Vec<u8>)> =
            files(&dir).into_iter().map(|p| (p.clone(), std::fs::read(p).unwrap())).collect();
        assert_eq!(after, before, "{site}: the failed dump changed the directory");
        // The previous dump still loads, and the observations after it are inserted.
        let loaded = EmbeddingIndex::load_or_build(params, &dir, &data);
        assert!(loaded.loaded_from_dump(), "{site}");
        assert_eq!(loaded.graph_shape().unwrap().0, data.live_observations(), "{site}");
    }
}

/// Regression: a graph loaded from a dump was dumped by hnsw_rs under another name (`index-NNNN`), while
/// `index.json` kept naming the old files with the new count: the next start loaded the old graph and never
/// searched the keyframes added in between.
#[test]
fn regression_a_dump_after_a_reload_is_the_dump_the_manifest_names() {
    let dir = temp_dir("dump-again");
    let (mut data, params, index) = hnsw_map(5, 7);
    index.dump(&dir, &data).unwrap();
    for round in 0..3u64 {
        let mut reloaded = EmbeddingIndex::load_or_build(params, &dir, &data);
        assert!(reloaded.loaded_from_dump(), "round {round}");
        assert_eq!(reloaded.graph_shape().unwrap().0, data.live_observations(), "round {round}");
        data.apply(&keyframe_record(100 + round, 300, 10_000 + 300 * round, 48, 40 + round)).unwrap();
        reloaded.sync(&data);
        reloaded.dump(&dir, &data).unwrap();
        // One dump on disk (the replaced ones deleted), and it is the one the manifest names.
        dump_file(&dir, ".hnsw.graph");
        dump_file(&dir, ".hnsw.data");
    }
    let last = EmbeddingIndex::load_or_build(params, &dir, &data);
    assert!(last.loaded_from_dump());
    assert_eq!(last.graph_shape().unwrap().0, data.live_observations());
    let newest = data.observations.len() - 1;
    assert_eq!(last.search(&data, data.embedding(newest), 1, None)[0].observation, newest);
}

#[test]
fn a_dump_built_from_other_embeddings_is_not_loaded() {
    let dir = temp_dir("dump-other");
    let (data, params, index) = hnsw_map(5, 11);
    index.dump(&dir, &data).unwrap();
    // Same model, same counts, other embeddings: the files' checksums match their manifest, the map does not.
    let (other, _, _) = hnsw_map(5, 12);
    let loaded = EmbeddingIndex::load_or_build(params, &dir, &other);
    assert!(loaded.is_approximate() && !loaded.loaded_from_dump());
    // A manifest whose count of points does not match the graph's is not used either.
    let json = std::fs::read_to_string(dir.join("index.json")).unwrap();
    let edited = json.replace(&format!("\"in_graph\":{}", data.observations.len()), "\"in_graph\":1000");
    assert_ne!(edited, json);
    std::fs::write(dir.join("index.json"), edited).unwrap();
    assert!(!EmbeddingIndex::load_or_build(params, &dir, &data).loaded_from_dump());
    std::fs::write(dir.join("index.json"), json).unwrap();
    assert!(EmbeddingIndex::load_or_build(params, &dir, &data).loaded_from_dump());
}
