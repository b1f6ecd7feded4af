//! Nearest-neighbour search over real SConE embeddings: exact (brute force) against hnsw_rs at 10k, 100k (and 1M
//! with `SCONE_BENCH_1M=1`) observations, in the same run. Embeddings: every image of `../shared/data/scenes`
//! (or `$SCONE_DATA`; ~2M embeddings today, so the 1M set is real too; were there fewer, it would be topped up
//! with noisy copies); queries are embeddings of three HPatches graffiti images, which are not in the indexed
//! set (the first 1,500 embeddings: about one image's keypoints).
//! Reports build time, the graph's links per point (over all layers; each is an `Arc` allocation in hnsw_rs,
//! ~40 bytes with its pointer, the part of the graph's memory M sets), query time per
//! query, and recall@1 / recall@2 against the exact answer, for M = 16 (the default) and M = 8.
//! Run: `cargo bench --bench index` (needs the shared data; prints a note and exits without it).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use rand::{Rng, SeedableRng};

use scone::camera::Camera;
use scone::camera::Pose;
use scone::describe::decode::ImageLimitSettings;
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::features::{Keypoint, DESCRIPTOR_BYTES};
use scone::describe::pipeline::Describer;
use scone::map::index::{exact_search, EmbeddingIndex, IndexSettings};
use scone::map::model::{Keyframe, MapData, MapMeta, NewObservation, Record};

mod common;

fn images() -> Vec<PathBuf> {
    let root = common::shared_data().join("scenes");
    let mut out = Vec::new();
    let Ok(scenes) = std::fs::read_dir(&root) else { return out };
    let mut scenes: Vec<_> = scenes.flatten().map(|e| e.path()).collect();
    scenes.sort();
    for s in scenes {
        let dir = if s.join("rgb").is_dir() { s.join("rgb") } else { s.clone() };
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .filter(|p| matches!(p.extension().and_then(|e| e.to_str()), Some("png" | "jpg")))
            .collect();
        files.sort();
        out.extend(files);
    }
    out
}

fn map_of(embeddings: &[f32], dim: usize) -> MapData {
    let n = embeddings.len() / dim;
    let mut data = MapData::new(MapMeta { id: "bench".into(), model_id: "m".into(), k: 20, dim, created_unix_ms: 0 });
    let keypoints = vec![Keypoint { x: 1.0, y: 1.0, size: 7.0, angle: 0.0, response: 1.0, octave: 0 }; n];
    data.apply(&Record::AddKeyframe {
        keyframe: Keyframe {
            id: 0,
            pose: Pose { translation: [0.0; 3], rotation: [0.0, 0.0, 0.0, 1.0] },
            camera: Camera { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0, width: 1, height: 1 },
            keypoints,
            descriptors: vec![0; n * DESCRIPTOR_BYTES],
            embeddings: embeddings.to_vec(),
        },
        new_landmarks: (0..n as u64).map(|i| (i, [0.0; 3])).collect(),
        observations: (0..n as u64).map(|i| NewObservation { landmark: i, keyframe: 0, keypoint: i as u32 }).collect(),
    })
    .unwrap();
    data
}

/// Standard normal samples (Box-Muller), to avoid another dependency for one distribution.
fn rand_distr_normal() -> impl Fn(&mut rand::rngs::StdRng) -> f32 {
    |rng| {
        let u1: f32 = rng.random::<f32>().max(1e-12);
        let u2: f32 = rng.random();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f32::consts::PI * u2).cos()
    }
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let files = images();
    if files.len() < 20 {
        eprintln!("index bench: no shared data found; nothing measured");
        return;
    }
    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let d = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    let dim = d.embedder.dim();
    // Queries: HPatches graffiti, a scene left out of the indexed set (the kitchen's neighbouring frames would
    // be near copies of each other); every other image is indexed.
    let is_query = |p: &&PathBuf| p.to_string_lossy().contains("hpatches-v_graffiti");
    let query_files: Vec<&PathBuf> = files.iter().filter(is_query).take(3).collect();
    let map_files: Vec<&PathBuf> = files.iter().filter(|p| !is_query(p)).collect();
    let mut pool = Vec::new();
    for f in &map_files {
        pool.extend(d.describe_image(&std::fs::read(f).unwrap()).unwrap().embeddings);
    }
    let mut queries = Vec::new();
    for f in query_files {
        queries.extend(d.describe_image(&std::fs::read(f).unwrap()).unwrap().embeddings);
    }
    // The first 1,500 query embeddings: about one image's keypoints.
    let queries: Vec<&[f32]> = queries.chunks_exact(dim).take(1500).collect();
    assert!(!queries.is_empty(), "index bench: no HPatches graffiti images to query with");
    let batch: Vec<f32> = queries.concat();
    if std::env::var("SCONE_BENCH_1M").is_ok() {
        // 1M observations from the real ones: each copy perturbed with Gaussian noise (sigma 0.05 per
        // dimension, about 0.35 in L2, the distance between views of one point) and re-normalised.
        let base = pool.clone();
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        let normal = rand_distr_normal();
        while pool.len() < 1_000_000 * dim {
            for row in base.chunks_exact(dim) {
                let mut v: Vec<f32> = row.iter().map(|x| x + 0.05 * normal(&mut rng)).collect();
                let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                v.iter_mut().for_each(|x| *x /= n);
                pool.extend(v);
            }
        }
    }
    println!(
        "{} real embeddings from {} images; {} queries from HPatches graffiti (not indexed)",
        pool.len() / dim,
        map_files.len(),
        queries.len()
    );
    println!(
        "| observations | M | exact ms/query | HNSW build s | links per point | ef | HNSW ms/query | speed-up | \
         recall@1 | recall@2 | 1,500 queries batched (search_many) ms |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for size in [10_000usize, 100_000, 1_000_000] {
        if size * dim > pool.len() {
            println!("| {size} | (only {} embeddings available) |", pool.len() / dim);
            continue;
        }
        let data = map_of(&pool[..size * dim], dim);
        let t = Instant::now();
        let truth: Vec<Vec<usize>> =
            queries.iter().map(|q| exact_search(&data, q, 2, None).iter().map(|h| h.observation).collect()).collect();
        let exact_ms = t.elapsed().as_secs_f64() * 1e3 / queries.len() as f64;
        // M = 16 is the default; M = 8 halves the base layer's links (hnsw_rs keeps 2M there), the memory lever.
        for m in [16usize, 8] {
            let t = Instant::now();
            let mut index = EmbeddingIndex::new(IndexSettings { exact_below: 0, m, ..IndexSettings::default() });
            index.sync(&data);
            let build = t.elapsed().as_secs_f64();
            let (points, links) = index.graph_shape().unwrap();
            let links = links as f64 / points as f64;
            for ef in [16usize, 32, 64] {
                index.set_ef_search(ef);
                let t = Instant::now();
                let got: Vec<Vec<usize>> = queries
                    .iter()
                    .map(|q| index.search(&data, q, 2, None).iter().map(|h| h.observation).collect())
                    .collect();
                let hnsw_ms = t.elapsed().as_secs_f64() * 1e3 / queries.len() as f64;
                let r1 = got.iter().zip(&truth).filter(|(g, t)| g.first() == t.first()).count() as f64
                    / queries.len() as f64;
                let r2 = got
                    .iter()
                    .zip(&truth)
                    .map(|(g, t)| t.iter().filter(|x| g.contains(x)).count() as f64 / t.len().max(1) as f64)
                    .sum::<f64>()
                    / queries.len() as f64;
                let t = Instant::now();
                let reps = 3;
                for _ in 0..reps {
                    std::hint::black_box(index.search_many(&data, &batch, 4, None));
                }
                let batch_ms = t.elapsed().as_secs_f64() * 1e3 / reps as f64;
                println!(
                "| {size} | {m} | {exact_ms:.3} | {build:.1} | {links:.1} | {ef} | {hnsw_ms:.3} | {:.1}x | {r1:.3} | \
                 {r2:.3} | {batch_ms:.1} |",
                exact_ms / hnsw_ms
            );
            }
        }
    }
}
