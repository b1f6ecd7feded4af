//! Time to ready of a cold replica over object storage: a map of ~100k observations from real, different
//! frames (`sun3d-studyroom` with its depth, then `7scenes-redkitchen` triangulated from its poses) is written
//! into a bucket of moto's server mode (an S3 *emulator* on loopback, not Amazon S3) and compacted, which
//! uploads the HNSW dump with the snapshot. Then a replica with an empty cache answers its first request for
//! the map, once with the dump in the bucket (download + load) and once without it (the graph rebuilt from
//! the map data), in the same run; then it waits for the snapshot's payload section, which arrives after the
//! map is ready; plus the memory the loaded map takes against the cache's estimate.
//! Run: `cargo bench --bench replica` (needs `../shared/data` or `$SCONE_DATA`; prints a note without it).
//! `SCONE_BENCH_OBSERVATIONS` changes the map size (default 100000). For trying a change to the load:
//! `SCONE_BENCH_S3_ENDPOINT` names an emulator already running, whose bucket keeps the map for the next run
//! (which uses it as it is, whatever its size); such a run leaves out the rebuilt row, which would delete the
//! bucket's dump. `SCONE_BENCH_REBUILD=0` leaves that row out of any run, and `RUST_LOG=scone=info` prints each
//! load's parts ("map opened").

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::TryStreamExt;
use object_store::aws::AmazonS3Builder;
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use scone::describe::decode::{decode_depth_png, ImageLimitSettings, TUM_DEPTH_SCALE};
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::pipeline::Describer;
use scone::map::builder::{Depth, KeyframeInput};
use scone::map::storage::s3::S3Settings;
use scone::map::storage::BackendSettings;
use scone::map::store::{CacheSettings, MapStore, ModelInfo, StoreSettings};
use scone::offline::scene::Scene;
use scone::MapError;

const KEY: &str = "bench";

mod common;
use common::rss_mb;

struct Moto(Child);

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_moto(port: u16) -> Moto {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let ok = Command::new("bash").arg(root.join("scripts/setup-s3-test")).status().map(|s| s.success());
    assert!(ok.unwrap_or(false), "scripts/setup-s3-test failed");
    let child = Command::new(common::prefix().join("venv-s3/bin/moto_server"))
        .args(["-H", "127.0.0.1", "-p", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    Moto(child)
}

fn s3(endpoint: &str, bucket: &str) -> S3Settings {
    S3Settings {
        bucket: bucket.into(),
        prefix: "bench".into(),
        region: Some("us-east-1".into()),
        endpoint: Some(endpoint.into()),
        allow_http: true,
        cache_dir: None,
    }
}

fn store(endpoint: &str, bucket: &str, dir: &Path, model: &ModelInfo) -> MapStore {
    let config = StoreSettings {
        data_dir: dir.to_path_buf(),
        compact_every: usize::MAX,
        backend: BackendSettings::S3(s3(endpoint, bucket)),
        cache: CacheSettings { lazy: Some(true), memory_budget_mb: 0, ..CacheSettings::default() },
        ..StoreSettings::default()
    };
    MapStore::open(config, model.clone()).unwrap()
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let root = common::shared_data();
    let (Ok(sun3d), Ok(kitchen)) =
        (Scene::load(&root.join("scenes/sun3d-studyroom")), Scene::load(&root.join("scenes/7scenes-redkitchen")))
    else {
        eprintln!("replica bench: no shared data at {}; nothing measured", root.display());
        return;
    };
    let target: usize = std::env::var("SCONE_BENCH_OBSERVATIONS").ok().and_then(|v| v.parse().ok()).unwrap_or(100_000);
    scone::describe::features::set_opencv_threads(1).unwrap();
    if std::env::var_os("RUST_LOG").is_some() {
        tracing_subscriber::fmt().with_env_filter(tracing_subscriber::EnvFilter::from_default_env()).init();
    }
    let kept_emulator = std::env::var("SCONE_BENCH_S3_ENDPOINT").ok();
    let rebuild_row = kept_emulator.is_none() && std::env::var("SCONE_BENCH_REBUILD").map_or(true, |v| v != "0");
    // The static credentials of the emulator, through the variables `from_env` reads.
    std::env::set_var("AWS_ACCESS_KEY_ID", KEY);
    std::env::set_var("AWS_SECRET_ACCESS_KEY", KEY);
    std::env::set_var("AWS_REGION", "us-east-1");
    let (endpoint, _moto) = match kept_emulator {
        Some(endpoint) => (endpoint, None),
        None => {
            let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
            (format!("http://127.0.0.1:{port}"), Some(start_moto(port)))
        }
    };
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let http = reqwest::Client::new();
    let t = Instant::now();
    while rt.block_on(http.get(&endpoint).send()).is_err() {
        assert!(t.elapsed() < Duration::from_secs(60), "moto did not start");
        std::thread::sleep(Duration::from_millis(100));
    }
    let bucket = "replica-bench";
    // A bucket that is there already (an emulator kept running) is used again as it is.
    let made = rt.block_on(http.put(format!("{endpoint}/{bucket}")).send()).unwrap().status();
    assert!(made.is_success() || made.as_u16() == 409, "bucket: {made}");

    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let model = ModelInfo { model_id: embedder.model_id().to_string(), k: embedder.k(), dim: embedder.dim() };
    let describer = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    let limits = ImageLimitSettings::default();
    // The process before any map: the memory line counts from here (an allocator that returns memory to the
    // system, as mimalloc does, can leave the RSS lower after a load than before it, when the writer's map is
    // gone).
    let rss_start = rss_mb();
    let tmp = std::env::temp_dir().join(format!("scone-bench-replica-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);

    // The writer: every frame of sun3d-studyroom, then 7scenes-redkitchen, until the target.
    let t = Instant::now();
    let mut frames = [0usize; 2];
    let mut id = 0u64;
    let reused;
    {
        let writer = store(&endpoint, bucket, &tmp.join("writer"), &model);
        // The map an earlier run left in a kept emulator's bucket (and no frames added to it).
        reused = match writer.summary("m") {
            Ok(_) => true,
            Err(MapError::UnknownMap { .. }) => false,
            Err(e) => panic!("the bucket's map does not load: {e}"),
        };
        if !reused {
            writer.create("m").unwrap();
        }
        let mut progress = scone::offline::progress::Progress::new("replica bench: writer map, observations", target);
        'scenes: for (si, scene) in [&sun3d, &kitchen].into_iter().enumerate().filter(|_| !reused) {
            for f in &scene.frames {
                progress.set(writer.summary("m").unwrap().observations);
                if writer.summary("m").unwrap().observations >= target {
                    break 'scenes;
                }
                let Some(pose) = f.pose else { continue };
                let d = describer.describe_image(&std::fs::read(&f.rgb).unwrap()).unwrap();
                let depth = f.depth.as_ref().map(|p| decode_depth_png(&std::fs::read(p).unwrap(), &limits).unwrap());
                let input = KeyframeInput {
                    id,
                    pose,
                    camera: scene.camera,
                    features: &d.features,
                    embeddings: &d.embeddings,
                    depth: depth.as_ref().map(|m| Depth { image: m, scale: TUM_DEPTH_SCALE }),
                    external: None,
                };
                writer.add_keyframe(&writer.get("m").unwrap(), &input).unwrap();
                id += 1;
                frames[si] += 1;
            }
        }
        assert!(writer.flush().is_empty());
    }
    let build_s = t.elapsed().as_secs_f64();

    let raw = AmazonS3Builder::new()
        .with_bucket_name(bucket)
        .with_endpoint(&endpoint)
        .with_allow_http(true)
        .with_region("us-east-1")
        .with_access_key_id(KEY)
        .with_secret_access_key(KEY)
        .build()
        .unwrap();
    let objects: Vec<_> =
        rt.block_on(raw.list(Some(&ObjectPath::from("bench/maps/m"))).try_collect::<Vec<_>>()).unwrap();
    let mb = |part: &str| {
        objects.iter().filter(|o| o.location.as_ref().contains(part)).map(|o| o.size).sum::<u64>() as f64 / 1e6
    };
    let (snapshot_mb, index_mb) = (mb("/snapshots/"), mb("/index/"));
    assert!(index_mb > 0.0, "the compaction uploaded no index dump");
    // The snapshot's core (what a replica fetches before it is ready): its length is in the header's bytes 20-28.
    let snapshot = objects.iter().find(|o| o.location.as_ref().contains("/snapshots/")).expect("a snapshot");
    let header = rt.block_on(raw.get_range(&snapshot.location, 0..32)).unwrap();
    let core_mb = u64::from_le_bytes(header[20..28].try_into().unwrap()) as f64 / 1e6;

    // Cold replicas: an empty cache each, first request for the map.
    let cold = |name: &str| {
        let s = store(&endpoint, bucket, &tmp.join(name), &model);
        let t = Instant::now();
        let summary = s.summary("m").unwrap();
        let ready = t.elapsed().as_secs_f64();
        // The storage requests' share of it: GETs may overlap, so their summed time is an upper bound.
        let gets = s.operation_stats().into_iter().find(|o| o.operation == "get").expect("get is counted");
        // The payload section arrives after the map is ready: a read of a payload waits for it (and the next
        // cold replica does not download beside it).
        let (from_dump, payload) = s.get("m").unwrap().read(|data, index| {
            (index.loaded_from_dump(), data.keyframes.values().next().map(|k| k.load().map(|_| ())))
        });
        payload.expect("a keyframe").expect("the payload section arrived");
        let arrived = t.elapsed().as_secs_f64();
        let rss_mb_loaded = rss_mb() - rss_start;
        let estimate_mb = s.loaded_bytes() as f64 / 1e6;
        (ready, from_dump, summary, rss_mb_loaded, estimate_mb, (gets.calls, gets.seconds), arrived)
    };
    let runs: Vec<_> = (0..3).map(|run| cold(&format!("dump-{run}"))).collect();
    assert!(runs.iter().all(|r| r.1), "a cold replica did not use the dump");
    // The first run's map and memory; the three runs' times.
    let (_, _, summary, rss, estimate, ..) = &runs[0];
    let memory = (*rss, *estimate);
    let mut with_dump: Vec<_> = runs.iter().map(|&(ready, _, _, _, _, gets, arrived)| (ready, gets, arrived)).collect();
    with_dump.sort_by(|a, b| a.0.total_cmp(&b.0));
    let rebuild = rebuild_row.then(|| {
        for o in objects.iter().filter(|o| o.location.as_ref().contains("/index/")) {
            rt.block_on(raw.delete(&o.location)).unwrap();
        }
        let (rebuild, from_dump, ..) = cold("rebuild");
        assert!(!from_dump);
        rebuild
    });
    let obs = summary.observations as f64;
    if reused {
        println!(
            "map: {} keyframes, {} landmarks, {} observations, left in the bucket by an earlier run",
            summary.keyframes, summary.landmarks, summary.observations
        );
    } else {
        println!(
            "map: {} keyframes ({} frames of sun3d-studyroom with depth, {} of 7scenes-redkitchen triangulated), \
             {} landmarks, {} observations; built and written to the bucket in {build_s:.0} s",
            summary.keyframes, frames[0], frames[1], summary.landmarks, summary.observations
        );
    }
    println!(
        "bucket: snapshot {snapshot_mb:.1} MB (its core {core_mb:.1} MB), index dump {index_mb:.1} MB (moto on loopback)"
    );
    println!();
    println!("| cold replica, first request | time to ready s | vs rebuild |");
    println!("|---|---|---|");
    let against_rebuild =
        rebuild.map_or("(not rebuilt in this run)".to_string(), |r| format!("{:.3}", with_dump[1].0 / r));
    println!("| index dump downloaded (median of 3) | {:.2} | {against_rebuild} |", with_dump[1].0);
    if let Some(rebuild) = rebuild {
        println!("| index rebuilt from the map data | {rebuild:.2} | 1 |");
    }
    println!();
    let (ready, (calls, seconds), arrived) = with_dump[1];
    println!(
        "the median cold replica's storage requests until ready: {calls} GETs taking {seconds:.2} s summed (they \
         may overlap), of its {ready:.2} s; the rest is decoding the snapshot's core and loading the graph. Its \
         keyframes' payloads had all arrived {arrived:.2} s after the request"
    );
    println!();
    // Only the first load is measured (once its payloads arrived), from the RSS before the writer's map: what the
    // allocator kept of the writer's map and of the downloads is in it. Later loads reuse memory of earlier ones.
    println!(
        "memory with the first replica's map loaded: RSS +{:.0} MB over the process before any map = {:.0} B per \
         observation (what the allocator kept of the writer's map and the downloads included); the cache's \
         estimate {:.0} MB = {:.0} B per observation (estimate / RSS = {:.2})",
        memory.0,
        memory.0 * 1e6 / obs,
        memory.1,
        memory.1 * 1e6 / obs,
        memory.1 / memory.0
    );
    let _ = std::fs::remove_dir_all(&tmp);
}
