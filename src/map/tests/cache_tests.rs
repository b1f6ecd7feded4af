//! The store's lazy mode over object storage: two or three stores ("replicas") on one in-memory bucket, as
//! the deployment runs them on one S3 bucket. The same behaviour against moto and real `scone serve`
//! processes behind a proxy is in `tests/it/replicas.rs`.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use nalgebra::Isometry3;
use object_store::memory::InMemory;
use object_store::{ObjectStore, ObjectStoreExt};

use crate::camera::Camera;
use crate::describe::features::{Features, Keypoint, DESCRIPTOR_BYTES};
use crate::error::MapError;
use crate::map::builder::{ExternalObservation, KeyframeInput};
use crate::map::storage::backend::MapBackend;
use crate::map::storage::s3::ObjectStorageBackend;
use crate::map::store::{CacheSettings, MapStore, ModelInfo, StoreSettings};
use crate::map::tests::vectors;
use crate::test_dir::{temp_dir, TestDir};

const DIM: usize = 8;

fn camera() -> Camera {
    Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 }
}

/// A keyframe of `cols x rows` keypoints on a grid, each with an external landmark in front of the camera
/// (ids from `first_landmark`), and pseudo-random unit embeddings.
struct Frame {
    features: Features,
    embeddings: Vec<f32>,
    external: Vec<ExternalObservation>,
}

fn frame(cols: usize, rows: usize, first_landmark: u64, seed: u64) -> Frame {
    let c = camera();
    let mut keypoints = Vec::new();
    let mut external = Vec::new();
    for j in 0..rows {
        for i in 0..cols {
            let (x, y) = (8.0 + i as f64 * (620.0 / cols as f64), 8.0 + j as f64 * (460.0 / rows as f64));
            keypoints.push(Keypoint { x: x as f32, y: y as f32, size: 7.0, angle: 0.0, response: 1.0, octave: 0 });
            let z = 4.0 + (i + j) as f64 * 0.01;
            external.push(ExternalObservation {
                x,
                y,
                landmark_id: first_landmark + (j * cols + i) as u64,
                point: [(x - c.cx) / c.fx * z, (y - c.cy) / c.fy * z, z],
            });
        }
    }
    let n = keypoints.len();
    let embeddings = vectors(n, DIM, seed);
    let features = Features {
        width: 640,
        height: 480,
        keypoints,
        descriptors: vec![[0u8; DESCRIPTOR_BYTES]; n],
        context: Vec::new(),
    };
    Frame { features, embeddings, external }
}

fn add(store: &MapStore, map: &str, id: u64, f: &Frame) -> Result<u64, MapError> {
    let input = KeyframeInput {
        id,
        pose: Isometry3::identity(),
        camera: camera(),
        features: &f.features,
        embeddings: &f.embeddings,
        depth: None,
        external: Some(&f.external),
    };
    let held = store.get(map)?;
    store.add_keyframe(&held, &input).map(|a| a.version)
}

struct Bucket {
    mem: Arc<InMemory>,
    dir: TestDir,
}

impl Bucket {
    fn new(name: &str) -> Self {
        Self { mem: Arc::new(InMemory::new()), dir: temp_dir(name) }
    }

    /// A replica: its own cache directory, the shared bucket, lazy mode with `cache`.
    fn replica(&self, name: &str, cache: CacheSettings, compact_every: usize, exact_below: usize) -> MapStore {
        let store: Arc<dyn ObjectStore> = Arc::clone(&self.mem) as Arc<dyn ObjectStore>;
        let backend =
            ObjectStorageBackend::new(store, "memory://", "replicas", &self.dir.join(name), compact_every).unwrap();
        let mut config = StoreSettings { data_dir: self.dir.join(name), compact_every, ..StoreSettings::default() };
        config.cache = CacheSettings { lazy: Some(true), ..cache };
        config.index.exact_below = exact_below;
        let model = ModelInfo { model_id: "sha256:test".into(), k: 20, dim: DIM };
        MapStore::open_with_backend(config, model, Arc::new(backend) as Arc<dyn MapBackend>).unwrap()
    }
}

fn always_check() -> CacheSettings {
    CacheSettings { freshness_ms: 0, ..CacheSettings::default() }
}

fn version(store: &MapStore, map: &str) -> u64 {
    store.summary(map).unwrap().version
}

#[test]
fn a_map_made_on_one_replica_is_seen_written_and_deleted_through_another() {
    let bucket = Bucket::new("cache-replicas");
    let a = bucket.replica("a", always_check(), 0, 100_000);
    let b = bucket.replica("b", always_check(), 0, 100_000);
    a.create("m").unwrap();
    add(&a, "m", 1, &frame(10, 10, 0, 1)).unwrap();
    // B knows nothing of it until asked; then it loads it from the bucket.
    let listed = b.list().unwrap();
    assert_eq!(listed.len(), 1);
    assert_eq!(
        (listed[0].id.as_str(), listed[0].keyframes, listed[0].landmarks, listed[0].loaded),
        ("m", 1, 100, false)
    );
    assert_eq!(version(&b, "m"), 1);
    assert!(b.list().unwrap()[0].loaded);
    assert!(matches!(b.create("m"), Err(MapError::MapExists { .. })));
    // A's next write is seen by B's next read (freshness 0: every read checks), applied from the new segment.
    add(&a, "m", 2, &frame(10, 10, 100, 2)).unwrap();
    let changed = b.cache_stats().changed.load(Ordering::Relaxed);
    assert_eq!(version(&b, "m"), 2);
    assert_eq!(b.cache_stats().changed.load(Ordering::Relaxed), changed + 1);
    assert_eq!(b.summary("m").unwrap().landmarks, 200);
    // B can now write (its copy follows the bucket), and A sees that write in turn.
    add(&b, "m", 3, &frame(10, 10, 200, 3)).unwrap();
    assert_eq!(version(&a, "m"), 3);
    add(&a, "m", 4, &frame(10, 10, 300, 4)).unwrap();
    // Deleted through A: gone for B at its next request, and B may create the id afresh.
    a.delete("m").unwrap();
    assert!(matches!(b.get("m"), Err(MapError::UnknownMap { .. })));
    assert!(b.list().unwrap().is_empty());
    b.create("m").unwrap();
    assert_eq!(version(&a, "m"), 0, "A loads B's new map, not its old copy");
    // Deleted and made again through B while A holds a copy: A's check finds another map under the id (a
    // new map uid) and loads it, rather than applying B's records to its old copy.
    add(&a, "m", 1, &frame(10, 10, 0, 5)).unwrap();
    assert_eq!(version(&b, "m"), 1);
    b.delete("m").unwrap();
    b.create("m").unwrap();
    add(&b, "m", 7, &frame(5, 5, 0, 6)).unwrap();
    let loads = a.cache_stats().loads.load(Ordering::Relaxed);
    let s = a.summary("m").unwrap();
    assert_eq!((s.version, s.keyframes, s.landmarks), (1, 1, 25), "A serves B's new map");
    assert_eq!(a.cache_stats().loads.load(Ordering::Relaxed), loads + 1);
}

#[test]
fn a_compaction_elsewhere_reloads_and_within_the_bound_the_copy_is_served() {
    let bucket = Bucket::new("cache-compaction");
    let a = bucket.replica("a", always_check(), 2, 100_000);
    let slow = CacheSettings { freshness_ms: 3_600_000, ..CacheSettings::default() };
    let b = bucket.replica("b", slow, 2, 100_000);
    a.create("m").unwrap();
    add(&a, "m", 1, &frame(5, 5, 0, 1)).unwrap();
    assert_eq!(version(&b, "m"), 1);
    // Two more writes: A compacts (a new snapshot), which B can only follow by loading the map again...
    add(&a, "m", 2, &frame(5, 5, 25, 2)).unwrap();
    add(&a, "m", 3, &frame(5, 5, 50, 3)).unwrap();
    // ...but B checks at most once an hour: it serves its copy, as the bound allows.
    assert_eq!(version(&b, "m"), 1);
    let c = bucket.replica("c", always_check(), 2, 100_000);
    assert_eq!(version(&c, "m"), 3);
    add(&a, "m", 4, &frame(5, 5, 75, 4)).unwrap();
    add(&a, "m", 5, &frame(5, 5, 100, 5)).unwrap();
    let loads = c.cache_stats().loads.load(Ordering::Relaxed);
    assert_eq!(version(&c, "m"), 5);
    assert_eq!(c.cache_stats().loads.load(Ordering::Relaxed), loads + 1, "the new snapshot was loaded");
}

#[test]
fn maps_beyond_the_memory_budget_are_evicted_least_recently_used_first_and_reload() {
    let bucket = Bucket::new("cache-budget");
    // Three maps of about 0.4 MiB (estimated; 1,500 observations, below the exact threshold: no graph) each;
    // a 1 MiB budget holds two.
    let budget = CacheSettings { memory_budget_mb: 1, ..CacheSettings::default() };
    let writer = bucket.replica("w", CacheSettings { memory_budget_mb: 0, ..CacheSettings::default() }, 0, 100_000);
    for (i, id) in ["m1", "m2", "m3"].iter().enumerate() {
        writer.create(id).unwrap();
        add(&writer, id, 1, &frame(60, 25, 0, i as u64)).unwrap();
    }
    let r = bucket.replica("r", budget, 0, 100_000);
    let bytes = |store: &MapStore| store.loaded_bytes();
    r.get("m1").unwrap();
    let one = bytes(&r);
    assert!(one > (1 << 20) / 3 && one < 1 << 19, "a map is estimated at {one} bytes");
    r.get("m2").unwrap();
    r.get("m1").unwrap(); // m2 is now the least recently used
    r.get("m3").unwrap();
    let loaded: Vec<String> = r.loaded().into_iter().map(|m| m.id).collect();
    assert_eq!(loaded, vec!["m1", "m3"]);
    assert_eq!(r.cache_stats().evictions.load(Ordering::Relaxed), 1);
    assert!(bytes(&r) <= 1 << 20);
    // Asked for again, the evicted map loads again, and another goes.
    let misses = r.cache_stats().misses.load(Ordering::Relaxed);
    assert_eq!(version(&r, "m2"), 1);
    assert_eq!(r.cache_stats().misses.load(Ordering::Relaxed), misses + 1);
    assert_eq!(r.loaded().len(), 2);
    // A map that a request holds is not evicted from under it.
    let held = r.get("m2").unwrap();
    r.get("m1").unwrap();
    r.get("m3").unwrap();
    assert!(r.loaded().iter().any(|m| m.id == "m2"), "the held map stayed");
    drop(held);
    // The listing names every stored map, loaded or not.
    let listed: Vec<(String, usize)> = r.list().unwrap().into_iter().map(|m| (m.id, m.observations)).collect();
    assert_eq!(listed, vec![("m1".into(), 1500), ("m2".into(), 1500), ("m3".into(), 1500)]);
}

#[test]
fn a_cold_replica_downloads_the_index_dump_instead_of_rebuilding() {
    let bucket = Bucket::new("cache-dump");
    // HNSW from 150 observations; compaction (and its dump) every 3 writes.
    let a = bucket.replica("a", always_check(), 3, 150);
    a.create("m").unwrap();
    for k in 0..3u64 {
        add(&a, "m", k, &frame(10, 10, k * 100, k)).unwrap();
    }
    let loaded_from_dump = |store: &MapStore| store.get("m").unwrap().read(|_, index| index.loaded_from_dump());
    let cold = bucket.replica("cold", always_check(), 3, 150);
    assert!(cold.summary("m").unwrap().approximate_index);
    assert!(loaded_from_dump(&cold), "the cold replica used the dump from the bucket");
    // When the dump cannot be downloaded (its objects are gone), a cold replica rebuilds the graph and serves
    // the same map.
    let listed = bucket.mem.list(Some(&"replicas/maps/m/index".into()));
    let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
    let objects: Vec<_> = rt.block_on(futures_util::TryStreamExt::try_collect::<Vec<_>>(listed)).unwrap();
    assert_eq!(objects.len(), 3, "graph, data and the dump's manifest");
    let another = bucket.replica("another", always_check(), 3, 150);
    for o in &objects {
        rt.block_on(bucket.mem.delete(&o.location)).unwrap();
    }
    assert!(!loaded_from_dump(&another));
    // The same map data (the exports differ: each carries its own replica's graph).
    let data = |store: &MapStore| store.get("m").unwrap().read(|d, _| d.clone());
    assert_eq!(data(&a), data(&another), "the same map");
    assert!(another.summary("m").unwrap().approximate_index);
}

#[test]
fn a_re_embedding_made_elsewhere_rebuilds_the_readers_index() {
    let bucket = Bucket::new("cache-reembed");
    let a = bucket.replica("a", always_check(), 0, 50);
    let b = bucket.replica("b", always_check(), 0, 50);
    a.create("m").unwrap();
    add(&a, "m", 1, &frame(10, 10, 0, 1)).unwrap();
    assert!(b.summary("m").unwrap().approximate_index, "B holds an HNSW graph of the old embeddings");
    // A re-embeds every keyframe (here: the embeddings negated); B applies the record at its next read.
    a.reembed("m", &|kf| Ok(kf.embeddings.iter().map(|x| -x).collect())).unwrap();
    let query: Vec<f32> = frame(10, 10, 0, 1).embeddings[..DIM].iter().map(|x| -x).collect();
    let (found, exact) = b.get("m").unwrap().read(|data, index| {
        let found: Vec<usize> = index.search(data, &query, 5, None).iter().map(|h| h.observation).collect();
        let exact: Vec<usize> =
            crate::map::index::exact_search(data, &query, 5, None).iter().map(|h| h.observation).collect();
        (found, exact)
    });
    assert_eq!(found[0], exact[0], "B searches the new embeddings");
    assert_eq!(found[0], 0, "the query is observation 0's new embedding");
}
