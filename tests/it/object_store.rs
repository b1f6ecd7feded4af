//! The object-storage map backend against an S3 API on loopback: moto's server mode, an S3 *emulator* (a
//! Python program from PyPI, `scripts/setup-s3-test`), not Amazon S3. It honours `If-None-Match: *` and
//! `If-Match` on PUT, which the backend's protocol rests on. The tests never skip: a missing virtualenv is
//! created by running the setup script (PyPI only).

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::TryStreamExt;
use object_store::aws::AmazonS3Builder;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use scone::describe::decode::{decode_depth_png, ImageLimitSettings};
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::pipeline::{Described, Describer};
use scone::map::builder::{Depth, KeyframeInput};
use scone::map::model::{MapData, Record};
use scone::map::storage::backend::MapBackend;
use scone::map::storage::s3::S3Settings;
use scone::map::storage::s3::{ObjectStorageBackend, S3Credentials};
use scone::map::storage::BackendSettings;
use scone::map::store::{CacheSettings, MapStore, ModelInfo, StoreSettings};
use scone::offline::scene::Scene;
use scone::pose::rotation_error_deg;
use scone::MapError;

use crate::common::{fixture, temp_dir};

pub(crate) const KEY_ID: &str = "testing";
pub(crate) const SECRET: &str = "testing";
pub(crate) const PREFIX: &str = "it";

/// A moto server on a free loopback port, stopped on drop.
pub(crate) struct Moto {
    child: Child,
    pub(crate) endpoint: String,
}

fn moto_server() -> PathBuf {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let status = Command::new("bash").arg(root.join("scripts/setup-s3-test")).status().expect("runs bash");
    assert!(status.success(), "scripts/setup-s3-test failed: cannot test the object-storage backend");
    let prefix = std::env::var_os("SCONE_PREFIX")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(std::env::var_os("HOME").expect("HOME is set")).join(".cache/scone"));
    prefix.join("venv-s3/bin/moto_server")
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap()
}

impl Moto {
    pub(crate) fn start() -> Self {
        let bin = moto_server();
        let port = TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let child = Command::new(&bin)
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap_or_else(|e| panic!("cannot start {}: {e}", bin.display()));
        let moto = Moto { child, endpoint: format!("http://127.0.0.1:{port}") };
        let t = Instant::now();
        let http = reqwest::Client::new();
        runtime().block_on(async {
            while http.get(&moto.endpoint).send().await.is_err() {
                assert!(t.elapsed() < Duration::from_secs(60), "moto did not answer on {}", moto.endpoint);
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        });
        moto
    }

    /// Creates a bucket (object_store cannot): a plain `PUT /<bucket>`.
    pub(crate) fn bucket(&self, name: &str) -> String {
        let r = runtime().block_on(reqwest::Client::new().put(format!("{}/{name}", self.endpoint)).send()).unwrap();
        assert!(r.status().is_success(), "creating bucket {name}: {}", r.status());
        name.to_string()
    }

    fn config(&self, bucket: &str, cache: &Path) -> S3Settings {
        S3Settings {
            bucket: bucket.into(),
            prefix: PREFIX.into(),
            region: Some("us-east-1".into()),
            endpoint: Some(self.endpoint.clone()),
            allow_http: true,
            cache_dir: Some(cache.to_path_buf()),
        }
    }

    /// A map store on the bucket, as one replica would open it (`cache` is its local cache).
    fn store(&self, bucket: &str, cache: &Path, compact_every: usize, model: ModelInfo) -> MapStore {
        let s3 = self.config(bucket, cache);
        let creds = S3Credentials::Static { access_key_id: KEY_ID.into(), secret_access_key: SECRET.into() };
        let backend = ObjectStorageBackend::s3(&s3, cache, compact_every, creds).unwrap();
        // Every map loaded at open, and no freshness checks: these tests are about the storage protocol (what
        // a replica that does not re-check sees, what its conditional writes do). The cache is in
        // `src/map/tests/cache_tests.rs` and `replicas.rs`.
        let config = StoreSettings {
            data_dir: cache.to_path_buf(),
            compact_every,
            backend: BackendSettings::S3(s3),
            cache: CacheSettings { lazy: Some(false), freshness_ms: 3_600_000, ..CacheSettings::default() },
            ..StoreSettings::default()
        };
        MapStore::open_with_backend(config, model, Arc::new(backend)).unwrap()
    }

    /// Direct access to the bucket, to look at and damage objects.
    fn raw(&self, bucket: &str) -> impl ObjectStore {
        AmazonS3Builder::new()
            .with_bucket_name(bucket)
            .with_endpoint(&self.endpoint)
            .with_allow_http(true)
            .with_region("us-east-1")
            .with_access_key_id(KEY_ID)
            .with_secret_access_key(SECRET)
            .build()
            .unwrap()
    }
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn keys(store: &impl ObjectStore, under: &str) -> Vec<String> {
    let mut v: Vec<String> = runtime()
        .block_on(store.list(Some(&ObjectPath::from(under))).map_ok(|o| o.location.to_string()).try_collect::<Vec<_>>())
        .unwrap();
    v.sort();
    v
}

/// The fixture scene, described once, with its depth images.
struct Frames {
    scene: Scene,
    described: Vec<Described>,
    depths: Vec<opencv::core::Mat>,
    model: ModelInfo,
}

fn frames() -> Frames {
    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let model = ModelInfo { model_id: embedder.model_id().into(), k: embedder.k(), dim: embedder.dim() };
    let describer = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let described =
        scene.frames.iter().map(|f| describer.describe_image(&std::fs::read(&f.rgb).unwrap()).unwrap()).collect();
    let depths = scene
        .frames
        .iter()
        .map(|f| {
            decode_depth_png(&std::fs::read(f.depth.as_ref().unwrap()).unwrap(), &ImageLimitSettings::default())
                .unwrap()
        })
        .collect();
    Frames { scene, described, depths, model }
}

impl Frames {
    fn add(&self, store: &MapStore, map: &str, id: u64, i: usize) -> Result<u64, MapError> {
        let input = KeyframeInput {
            id,
            pose: self.scene.frames[i].pose.unwrap(),
            camera: self.scene.camera,
            features: &self.described[i].features,
            embeddings: &self.described[i].embeddings,
            depth: Some(Depth { image: &self.depths[i], scale: 1.0 / 5000.0 }),
            external: None,
        };
        store.add_keyframe(&store.get(map).unwrap(), &input).map(|a| a.version)
    }

    /// Localises frame `i` (not in the map) and checks the pose within 5 cm and 1 degree.
    fn localises(&self, store: &MapStore, map: &str, i: usize) {
        let d = &self.described[i];
        let loc =
            store.localize(&store.get(map).unwrap(), &d.features, &d.embeddings, &self.scene.camera, None).unwrap();
        let pose = loc.pose.expect("held-out frame not localised");
        let gt = self.scene.frames[i].pose.unwrap();
        let dt = (pose.camera_to_world.translation.vector - gt.translation.vector).norm();
        let dr =
            rotation_error_deg(&pose.camera_to_world.rotation.to_rotation_matrix(), &gt.rotation.to_rotation_matrix());
        assert!(dt < 0.05 && dr < 1.0, "pose off by {dt} m, {dr} deg");
    }
}

fn data(store: &MapStore, map: &str) -> MapData {
    store.get(map).unwrap().read(|d, _| d.clone())
}

#[test]
fn a_map_in_object_storage_reloads_equal_localises_compacts_and_deletes() {
    let moto = Moto::start();
    let bucket = moto.bucket("scone-lifecycle");
    let f = frames();
    let tmp = temp_dir("lifecycle");
    // Replica A writes, compacting every 3 records; frame 3 is held out.
    let a = moto.store(&bucket, &tmp.join("a"), 3, f.model.clone());
    a.create("m").unwrap();
    for i in (0..f.scene.frames.len()).step_by(2) {
        f.add(&a, "m", i as u64, i).unwrap();
    }
    let written = data(&a, "m");
    assert_eq!(written.version, 5);
    // Compacted at version 3: the manifest names the snapshot of version 3 and two segments; the replaced
    // snapshot and segments are gone.
    let objects = keys(&moto.raw(&bucket), "it/maps/m");
    let manifest: serde_json::Value = serde_json::from_slice(
        &runtime()
            .block_on(async {
                moto.raw(&bucket).get(&ObjectPath::from("it/maps/m/manifest.json")).await?.bytes().await
            })
            .unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["snapshot"]["version"], 3, "{manifest}");
    assert_eq!(manifest["segments"].as_array().unwrap().len(), 2, "{manifest}");
    assert_eq!(objects.len(), 7, "manifest, one snapshot, two segments, the index dump: {objects:?}");
    // The map is past the exact-search threshold: its HNSW dump sits in A's local cache and, as of the
    // snapshot, in the bucket (named by the manifest).
    assert!(a.summary("m").unwrap().approximate_index);
    assert!(tmp.join("a/m/index.json").exists());
    assert_eq!(manifest["index"]["version"], 3, "{manifest}");
    assert_eq!(objects.iter().filter(|o| o.contains("/index/00000000000000000003-")).count(), 3);

    // Replica B, with an empty cache (it downloads the index dump), sees the same map and localises with it.
    let b = moto.store(&bucket, &tmp.join("b"), 3, f.model.clone());
    assert_eq!(data(&b, "m"), written);
    assert!(b.get("m").unwrap().read(|_, index| index.loaded_from_dump()), "B's cache was empty: it downloaded");
    f.localises(&b, "m", 3);
    drop(b);

    // Compaction at shutdown (flush), then a reopen sees the same map from the snapshot alone.
    assert!(a.flush().is_empty());
    let objects = keys(&moto.raw(&bucket), "it/maps/m");
    assert_eq!(objects.len(), 5, "manifest, snapshot and its index dump: {objects:?}");
    drop(a);
    let c = moto.store(&bucket, &tmp.join("a"), 3, f.model.clone());
    assert_eq!(data(&c, "m"), written);
    assert!(c.get("m").unwrap().read(|_, index| index.loaded_from_dump()), "A's cache holds the dump");
    f.localises(&c, "m", 3);

    // Delete: gone from the bucket and from a fresh replica; the id can be used again.
    c.delete("m").unwrap();
    assert!(keys(&moto.raw(&bucket), "it").is_empty());
    assert!(!tmp.join("a/m").exists(), "the local cache of the map is removed too");
    let d = moto.store(&bucket, &tmp.join("d"), 3, f.model.clone());
    assert!(d.list().unwrap().is_empty());
    d.create("m").unwrap();
    assert_eq!(d.summary("m").unwrap().keyframes, 0);
}

#[test]
fn a_second_writer_is_refused_by_the_conditional_write_and_reloads_the_map() {
    let moto = Moto::start();
    let bucket = moto.bucket("scone-writers");
    let f = frames();
    let tmp = temp_dir("writers");
    let first = moto.store(&bucket, &tmp.join("first"), 0, f.model.clone());
    first.create("m").unwrap();
    f.add(&first, "m", 0, 0).unwrap();
    // Both replicas load the map at version 1; the first writes again, then the second tries.
    let second = moto.store(&bucket, &tmp.join("second"), 0, f.model.clone());
    f.add(&first, "m", 2, 2).unwrap();
    let before = keys(&moto.raw(&bucket), "it");
    let e = f.add(&second, "m", 4, 4).unwrap_err();
    assert!(matches!(e, MapError::WriterConflict { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains("'m'") && msg.contains("another writer"), "{msg}");
    assert_eq!(keys(&moto.raw(&bucket), "it"), before, "the refused writer left nothing behind");
    // What is stored is exactly what the first writer acknowledged.
    let check = moto.store(&bucket, &tmp.join("check"), 0, f.model.clone());
    assert_eq!(data(&check, "m"), data(&first, "m"));
    assert_eq!(data(&check, "m").version, 2);
    // The refused replica reloaded the map: it holds what the first acknowledged, and the client's retry of
    // the refused write succeeds on it.
    assert_eq!(data(&second, "m"), data(&first, "m"));
    assert_eq!(f.add(&second, "m", 4, 4).unwrap(), 3);
    // Now the first one's copy is stale: refused the same way, then reloaded.
    assert!(matches!(f.add(&first, "m", 6, 6), Err(MapError::WriterConflict { .. })));
    assert_eq!(data(&first, "m"), data(&second, "m"));
    let check = moto.store(&bucket, &tmp.join("check"), 0, f.model.clone());
    assert_eq!(data(&check, "m"), data(&second, "m"));
    assert_eq!(data(&check, "m").keyframes.keys().copied().collect::<Vec<_>>(), vec![0, 2, 4]);
    // A replica that only loaded a map does not rewrite it when it flushes at shutdown.
    let before = keys(&moto.raw(&bucket), "it");
    assert!(check.flush().is_empty());
    assert_eq!(keys(&moto.raw(&bucket), "it"), before);
    // Two replicas creating the same id: the create-only manifest PUT (If-None-Match: *) lets one win.
    let creds = || S3Credentials::Static { access_key_id: KEY_ID.into(), secret_access_key: SECRET.into() };
    let cache = tmp.join("raw");
    let (x, y) = (
        ObjectStorageBackend::s3(&moto.config(&bucket, &cache), &cache, 0, creds()).unwrap(),
        ObjectStorageBackend::s3(&moto.config(&bucket, &cache), &cache, 0, creds()).unwrap(),
    );
    let empty = data(&first, "m");
    x.create("n", &empty).unwrap();
    assert!(matches!(y.create("n", &empty), Err(MapError::MapExists { .. })));
    assert_eq!(keys(&moto.raw(&bucket), "it/maps/n").len(), 2, "the loser removed its snapshot");
    assert!(matches!(second.create("n"), Err(MapError::MapExists { .. })));
}

#[test]
fn an_orphan_segment_is_ignored_and_a_corrupt_segment_holds_back_only_its_map() {
    let moto = Moto::start();
    let bucket = moto.bucket("scone-damage");
    let f = frames();
    let tmp = temp_dir("damage");
    let a = moto.store(&bucket, &tmp.join("a"), 0, f.model.clone());
    for map in ["good", "bad"] {
        a.create(map).unwrap();
        f.add(&a, map, 0, 0).unwrap();
        f.add(&a, map, 2, 2).unwrap();
    }
    let good = data(&a, "good");
    drop(a);
    let raw = moto.raw(&bucket);
    let rt = runtime();
    // A crash between the segment PUT and the manifest PUT: a valid next record that no manifest names.
    let orphan = ObjectPath::from("it/maps/good/segments/00000000000000000003-00000000deadbeef.rec");
    let bytes = scone::map::storage::format::encode_segment(3, &Record::RemoveKeyframe { id: 0 }).unwrap();
    rt.block_on(raw.put(&orphan, bytes.into())).unwrap();
    // One flipped byte in a segment of the other map.
    let segment = keys(&raw, "it/maps/bad/segments").into_iter().next().unwrap();
    let path = ObjectPath::from(segment.as_str());
    let mut bytes = rt.block_on(async { raw.get(&path).await?.bytes().await }).unwrap().to_vec();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    rt.block_on(raw.put(&path, bytes.into())).unwrap();

    let b = moto.store(&bucket, &tmp.join("b"), 0, f.model.clone());
    let held = b.held_back();
    assert_eq!(held.len(), 1, "{held:?}");
    assert_eq!(held[0].0, "bad");
    // The damaged object by its name, not where it is stored (the full key goes to the log; issue 16).
    let name = segment.rsplit('/').next().unwrap();
    assert!(held[0].1.contains(&format!("{name} is corrupt")) && held[0].1.contains("checksum"), "{}", held[0].1);
    assert!(!held[0].1.contains(&bucket), "{}", held[0].1);
    assert!(b.summary("bad").unwrap_err().to_string().contains("unavailable"));
    // The orphan changed nothing, and the next write takes sequence number 3 under its own name.
    assert_eq!(data(&b, "good"), good);
    f.localises(&b, "good", 3);
    assert_eq!(f.add(&b, "good", 4, 4).unwrap(), 3);
    let c = moto.store(&bucket, &tmp.join("c"), 0, f.model.clone());
    assert_eq!(data(&c, "good"), data(&b, "good"));
    // A held-back map can still be deleted.
    b.delete("bad").unwrap();
    assert!(keys(&raw, "it/maps/bad").is_empty());
}

/// The server binary picks the backend from its settings (environment variables here) and the credentials
/// from the standard AWS variables; writes go through the CPU pool's threads; SIGTERM flushes.
#[test]
fn scone_serve_stores_maps_in_the_bucket_its_settings_name() {
    let moto = Moto::start();
    let bucket = moto.bucket("scone-serve");
    let tmp = temp_dir("serve");
    let scene = Scene::load(&fixture("rendered")).unwrap();
    let env = [
        ("SCONE_STORE__DATA_DIR", tmp.join("data").display().to_string()),
        ("SCONE_STORE__BACKEND__KIND", "s3".into()),
        ("SCONE_STORE__BACKEND__BUCKET", bucket.clone()),
        ("SCONE_STORE__BACKEND__PREFIX", PREFIX.into()),
        ("SCONE_STORE__BACKEND__ENDPOINT", moto.endpoint.clone()),
        ("SCONE_STORE__BACKEND__ALLOW_HTTP", "true".into()),
        ("AWS_REGION", "us-east-1".into()),
        ("AWS_ACCESS_KEY_ID", KEY_ID.into()),
        ("AWS_SECRET_ACCESS_KEY", "secret-that-must-not-be-printed".into()),
    ];
    let scone = |args: &[&str]| {
        let mut c = Command::new(env!("CARGO_BIN_EXE_scone"));
        c.current_dir(env!("CARGO_MANIFEST_DIR")).args(args).envs(env.iter().map(|(k, v)| (k, v)));
        c
    };
    let out = scone(&["serve", "--print-settings"]).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let printed: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(printed["store"]["backend"]["kind"], "s3");
    assert_eq!(printed["store"]["backend"]["bucket"], bucket.as_str());
    assert!(!String::from_utf8_lossy(&out.stdout).contains("secret-that"));

    let mut child = scone(&["serve", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let line = BufReader::new(child.stdout.take().unwrap()).lines().next().expect("server printed nothing").unwrap();
    let base = line.rsplit(' ').next().unwrap().to_string();
    assert!(base.starts_with("http://127.0.0.1:"), "{line}");
    let http = reqwest::Client::new();
    runtime().block_on(async {
        let t = Instant::now();
        while http.get(format!("{base}/readyz")).send().await.map(|r| r.status() != 200).unwrap_or(true) {
            assert!(t.elapsed() < Duration::from_secs(60), "server not ready");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let r = http.post(format!("{base}/v1/maps")).json(&serde_json::json!({"map_id": "served"})).send().await;
        assert_eq!(r.unwrap().status(), 201);
        let f = &scene.frames[0];
        let p = f.pose.unwrap();
        let (q, t, c) = (p.rotation.quaternion(), p.translation.vector, scene.camera);
        let request = serde_json::json!({
            "keyframe_id": 0,
            "pose": {"tx": t.x, "ty": t.y, "tz": t.z, "qx": q.i, "qy": q.j, "qz": q.k, "qw": q.w},
            "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
        });
        let part = |p: &Path| reqwest::multipart::Part::bytes(std::fs::read(p).unwrap()).mime_str("image/png").unwrap();
        let form = reqwest::multipart::Form::new()
            .text("request", request.to_string())
            .part("image", part(&f.rgb))
            .part("depth", part(f.depth.as_ref().unwrap()));
        let r = http.post(format!("{base}/v1/maps/served/keyframes")).multipart(form).send().await.unwrap();
        assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    });
    let status = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
    assert!(status.success());
    assert!(child.wait().unwrap().success(), "the server did not shut down cleanly");

    let model = {
        let e = Embedder::load(&EmbedderSettings::default()).unwrap();
        ModelInfo { model_id: e.model_id().into(), k: e.k(), dim: e.dim() }
    };
    let store = moto.store(&bucket, &tmp.join("check"), 0, model);
    let summary = store.summary("served").unwrap();
    assert_eq!((summary.keyframes, summary.version), (1, 1));
    // The shutdown flush compacted the map into one snapshot, with its index dump (three files).
    let objects = keys(&moto.raw(&bucket), "it/maps/served");
    assert_eq!(objects.len(), 5, "{objects:?}");
}

/// Issue 26: a PUT that fails at each write site of object storage (an injected fault: `fail` point
/// `s3-put`, the request never reaches moto) refuses that write or compaction and leaves the stored map as
/// acknowledged; the writes after it are acknowledged and a fresh replica loads them all.
#[test]
fn a_failed_put_at_every_write_site_leaves_the_stored_map_as_acknowledged() {
    let _scenario = fail::FailScenario::setup();
    let moto = Moto::start();
    let bucket = moto.bucket("scone-faults");
    let f = frames();
    let tmp = temp_dir("s3-faults");
    // No compaction on writes: the snapshot and index sites are reached by flush.
    let a = moto.store(&bucket, &tmp.join("a"), 0, f.model.clone());
    a.create("m").unwrap();
    f.add(&a, "m", 0, 0).unwrap();
    let fresh = |name: &str| moto.store(&bucket, &tmp.join(name), 0, f.model.clone());
    for (n, site) in ["it/maps/m/segments/", "it/maps/m/manifest.json"].into_iter().enumerate() {
        fail::cfg("s3-put", &format!("return({site})")).unwrap();
        let e = f.add(&a, "m", 2, 2).unwrap_err();
        assert!(!matches!(e, MapError::WriterConflict { .. }), "{site}: a failed PUT fenced the writer: {e}");
        fail::remove("s3-put");
        assert_eq!(data(&a, "m").version, 1, "{site}: the refused write was applied");
        assert_eq!(data(&fresh(&format!("check{n}")), "m"), data(&a, "m"), "{site}");
    }
    for i in [2, 4, 6, 8] {
        f.add(&a, "m", i as u64, i).unwrap();
    }
    assert!(a.summary("m").unwrap().approximate_index, "the map needs an index for the dump's site");
    let acknowledged = data(&a, "m");
    // The snapshot's PUT fails: the map is not compacted, its segments keep every write.
    fail::cfg("s3-put", "return(it/maps/m/snapshots/)").unwrap();
    let failed = a.flush();
    fail::remove("s3-put");
    assert_eq!(failed.len(), 1, "{failed:?}");
    assert_eq!(data(&fresh("check-snapshot"), "m"), acknowledged);
    // The index dump's upload fails: the compaction goes through without it, and a replica rebuilds the graph.
    fail::cfg("s3-put", "return(it/maps/m/index/)").unwrap();
    assert!(a.flush().is_empty());
    fail::remove("s3-put");
    let b = fresh("b");
    assert_eq!(data(&b, "m"), acknowledged);
    assert!(!b.get("m").unwrap().read(|_, index| index.loaded_from_dump()), "no dump was uploaded");
    f.localises(&b, "m", 3);
    f.localises(&a, "m", 3);
}
