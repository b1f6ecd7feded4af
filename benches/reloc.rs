//! Relocalisation of a 640x480 JPEG query against maps of ~10k, ~100k (and ~1M with `SCONE_BENCH_1M=1`)
//! observations, through the service's own path (`Service::localize`): time per stage and total, HNSW against
//! exact search on the same map in the same run, time to ready after a restart (snapshot + index dump), and
//! memory per observation.
//!
//! Map: the even frames of `rgbd-slambook-5` (640x480, depth) written as keyframes again and again with their
//! ground-truth poses until the map holds the target number of observations (the same way as `scone map
//! write-scene --repeat`); queries: the odd frames, JPEG-encoded (quality 90), not in the map.
//! Run: `cargo bench --bench reloc` (needs `../shared/data` or `$SCONE_DATA`; prints a note without it).

use std::sync::Arc;
use std::time::Instant;

use opencv::core::Vector;
use opencv::prelude::*;
use scone::decode::{decode_depth_png, ImageLimits};
use scone::embedding::{Embedder, EmbedderConfig};
use scone::features::{ExtractorConfig, KeypointLimits};
use scone::map::builder::{Depth, KeyframeInput};
use scone::map::index::IndexParams;
use scone::map::store::{MapStore, ModelInfo, StoreConfig};
use scone::offline::scene::Scene;
use scone::pipeline::Describer;
use scone::service::{FrameInput, FrameSource, Service};

mod common;
use common::rss_mb;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let root = common::shared_data();
    let Ok(scene) = Scene::load(&root.join("scenes/rgbd-slambook-5")) else {
        eprintln!("reloc bench: no shared data at {}; nothing measured", root.display());
        return;
    };
    scone::features::set_opencv_threads(1).unwrap();
    let embedder = Arc::new(Embedder::load(&EmbedderConfig::default()).unwrap());
    let info = ModelInfo { model_id: embedder.model_id().to_string(), k: embedder.k(), dim: embedder.dim() };
    let describer = Describer { extractor: ExtractorConfig::default(), limits: ImageLimits::default(), embedder };
    let limits = ImageLimits::default();
    let mapped: Vec<_> = scene
        .frames
        .iter()
        .step_by(2)
        .map(|f| {
            let d = describer.describe_image(&std::fs::read(&f.rgb).unwrap()).unwrap();
            let depth = decode_depth_png(&std::fs::read(f.depth.as_ref().unwrap()).unwrap(), &limits).unwrap();
            (d, depth, f.pose.unwrap())
        })
        .collect();
    let queries: Vec<Vec<u8>> = scene
        .frames
        .iter()
        .skip(1)
        .step_by(2)
        .map(|f| {
            let img = opencv::imgcodecs::imread(f.rgb.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
            let mut buf = Vector::<u8>::new();
            let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 90]);
            opencv::imgcodecs::imencode(".jpg", &img, &mut buf, &params).unwrap();
            assert_eq!((img.cols(), img.rows()), (640, 480));
            buf.to_vec()
        })
        .collect();
    let mut targets = vec![10_000usize, 100_000];
    if std::env::var("SCONE_BENCH_SMALL").is_ok() {
        targets = vec![10_000];
    }
    if std::env::var("SCONE_BENCH_1M").is_ok() {
        targets.push(1_000_000);
    }
    println!("{} map frames, {} query frames (640x480 JPEG)", mapped.len(), queries.len());
    println!(
        "| observations | search | decode ms | extract ms | embed ms | search ms | PnP ms | total p50 ms | \
         localised | build s | ready after restart s | RSS MB/1k obs |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for target in targets {
        let dir = std::env::temp_dir().join(format!("scone-bench-reloc-{target}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let config = |index: IndexParams| StoreConfig {
            data_dir: dir.clone(),
            compact_every: usize::MAX,
            index,
            ..StoreConfig::default()
        };
        // Build once with the default (HNSW above the threshold) index, then snapshot + dump.
        let rss0 = rss_mb();
        let t = Instant::now();
        {
            let store = MapStore::open(config(IndexParams::default()), info.clone()).unwrap();
            store.create("m").unwrap();
            let mut id = 0u64;
            while store.summary("m").unwrap().observations < target {
                let (d, depth, pose) = &mapped[id as usize % mapped.len()];
                let input = KeyframeInput {
                    id,
                    pose: *pose,
                    camera: scene.camera,
                    features: &d.features,
                    embeddings: &d.embeddings,
                    depth: Some(Depth { image: depth, scale: 1.0 / 5000.0 }),
                    external: None,
                };
                store.add_keyframe("m", &input).unwrap();
                id += 1;
            }
            store.flush().unwrap();
        }
        let build = t.elapsed().as_secs_f64();
        for (label, index) in [
            ("HNSW", IndexParams::default()),
            ("exact", IndexParams { exact_below: usize::MAX, ..IndexParams::default() }),
        ] {
            let rss_before = rss_mb();
            let t = Instant::now();
            let store = MapStore::open(config(index), info.clone()).unwrap();
            let ready = t.elapsed().as_secs_f64();
            let observations = store.summary("m").unwrap().observations;
            let rss_per_k = (rss_mb() - rss_before.min(rss0)) / observations as f64 * 1000.0;
            let service = Service::new(describer.clone(), KeypointLimits::default(), Default::default());
            service.attach_store(Arc::new(store));
            let runs = match (label, target) {
                ("HNSW", _) => 20,
                (_, t) if t >= 1_000_000 => 2,
                _ => 6,
            };
            let mut stages: std::collections::BTreeMap<&str, Vec<f64>> = Default::default();
            let mut totals = Vec::new();
            let mut localised = 0;
            for i in 0..=runs {
                let frame = FrameInput {
                    source: FrameSource::Image(queries[i % queries.len()].clone()),
                    camera: Some(scene.camera),
                };
                let t = Instant::now();
                let o = service.localize("m", frame, None).unwrap();
                if i == 0 {
                    continue; // warm-up
                }
                totals.push(t.elapsed().as_secs_f64() * 1e3);
                localised += o.pose.is_some() as usize;
                for (s, v) in o.times.0 {
                    stages.entry(s).or_default().push(v * 1e3);
                }
            }
            let m = |s: &str| stages.get(s).map_or(0.0, |v| median(v.clone()));
            println!(
                "| {observations} | {label} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {localised}/{runs} | {} | {} | {} |",
                m("decode"),
                m("extract"),
                m("embed"),
                m("search"),
                m("pnp"),
                median(totals),
                if label == "HNSW" { format!("{build:.1}") } else { "-".into() },
                if label == "HNSW" { format!("{ready:.2}") } else { format!("{ready:.2} (no graph)") },
                if label == "HNSW" { format!("{rss_per_k:.2}") } else { "-".into() },
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
