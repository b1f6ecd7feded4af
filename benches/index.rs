//! Nearest-neighbour search over real SConE embeddings: exact (brute force) against hnsw_rs at 10k and 100k
//! observations, in the same run. Embeddings come from every image of `../shared/data/scenes` (or
//! `$SCONE_DATA`); queries are embeddings of the last images, which are not in the indexed set.
//! Reports build time, query time per query, and recall@1 / recall@2 against the exact answer.
//! Run: `cargo bench --bench index` (needs the shared data; prints a note and exits without it).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use scone::decode::ImageLimits;
use scone::embedding::{Embedder, EmbedderConfig};
use scone::features::{ExtractorConfig, Keypoint, DESCRIPTOR_BYTES};
use scone::map::index::{exact_search, EmbeddingIndex, IndexParams};
use scone::map::model::{Keyframe, MapData, MapMeta, NewObservation, Pose, Record};
use scone::pipeline::Describer;
use scone::scene::Camera;

fn images() -> Vec<PathBuf> {
    let root = std::env::var_os("SCONE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")))
        .join("scenes");
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
    });
    data
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
    let embedder = Arc::new(Embedder::load(&EmbedderConfig::default()).unwrap());
    let d = Describer { extractor: ExtractorConfig::default(), limits: ImageLimits::default(), embedder };
    let dim = d.embedder.dim();
    let (query_files, map_files) = files.split_at(3);
    let mut pool = Vec::new();
    for f in map_files {
        pool.extend(d.describe_image(&std::fs::read(f).unwrap()).unwrap().embeddings);
    }
    let mut queries = Vec::new();
    for f in query_files {
        queries.extend(d.describe_image(&std::fs::read(f).unwrap()).unwrap().embeddings);
    }
    let queries: Vec<&[f32]> = queries.chunks_exact(dim).take(1000).collect();
    println!(
        "{} real embeddings from {} images; {} queries from 3 other images",
        pool.len() / dim,
        map_files.len(),
        queries.len()
    );
    println!("| observations | exact ms/query | HNSW build s | ef | HNSW ms/query | speed-up | recall@1 | recall@2 |");
    println!("|---|---|---|---|---|---|---|---|");
    for size in [10_000usize, 100_000] {
        if size * dim > pool.len() {
            println!("| {size} | (only {} embeddings available) |", pool.len() / dim);
            continue;
        }
        let data = map_of(&pool[..size * dim], dim);
        let t = Instant::now();
        let truth: Vec<Vec<usize>> = queries
            .iter()
            .map(|q| exact_search(&data, q, 2, &|_| true).iter().map(|h| h.observation).collect())
            .collect();
        let exact_ms = t.elapsed().as_secs_f64() * 1e3 / queries.len() as f64;
        for ef in [64usize, 128] {
            let params = IndexParams { exact_below: 0, ef_search: ef, ..IndexParams::default() };
            let t = Instant::now();
            let mut index = EmbeddingIndex::new(params);
            index.sync(&data);
            let build = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let got: Vec<Vec<usize>> = queries
                .iter()
                .map(|q| index.search(&data, q, 2, &|_| true).iter().map(|h| h.observation).collect())
                .collect();
            let hnsw_ms = t.elapsed().as_secs_f64() * 1e3 / queries.len() as f64;
            let r1 =
                got.iter().zip(&truth).filter(|(g, t)| g.first() == t.first()).count() as f64 / queries.len() as f64;
            let r2 = got
                .iter()
                .zip(&truth)
                .map(|(g, t)| t.iter().filter(|x| g.contains(x)).count() as f64 / t.len().max(1) as f64)
                .sum::<f64>()
                / queries.len() as f64;
            println!(
                "| {size} | {exact_ms:.3} | {build:.1} | {ef} | {hnsw_ms:.3} | {:.1}x | {r1:.3} | {r2:.3} |",
                exact_ms / hnsw_ms
            );
        }
    }
}
