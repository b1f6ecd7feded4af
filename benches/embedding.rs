//! SConE on a 640x480 photograph with 1,000 keypoints, against FAST + FREAK alone in the same run:
//! the whole path (extraction + constellations + ONNX Runtime), inference alone at 1 and 2 intra-op
//! threads, and matching 1,000 x 1,000 SConE embeddings (L2) against FREAK (Hamming), brute force.
//! Model: `models/scone-freak-k20.onnx`, or `$SCONE_MODEL`.
//! Run: `cargo bench --bench embedding`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{criterion_group, criterion_main, Criterion};

use scone::constellation;
use scone::decode::{decode_grey, ImageLimits};
use scone::embedding::{default_model_path, Embedder, EmbedderConfig};
use scone::features::{self, ExtractorConfig};
use scone::matching::{match_hamming, match_l2, RatioTest};

fn bench(c: &mut Criterion) {
    features::set_opencv_threads(1).unwrap();
    let model = std::env::var_os("SCONE_MODEL").map(PathBuf::from).unwrap_or_else(default_model_path);
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg");
    let bytes = std::fs::read(path).unwrap();
    let img = decode_grey(&bytes, &ImageLimits::default()).unwrap();
    let cfg = ExtractorConfig { max_keypoints: 1000, ..ExtractorConfig::default() };
    let f = features::extract(&img, &cfg).unwrap();
    let cons = constellation::build(&f.keypoints, 20);
    eprintln!("{} keypoints, model {}", f.len(), model.display());
    let mut g = c.benchmark_group("scone_640x480_1000kp");
    g.bench_function("fast_freak", |b| b.iter(|| features::extract(black_box(&img), &cfg).unwrap()));
    for threads in [1usize, 2] {
        let e = Embedder::load(&EmbedderConfig { model: model.clone(), intra_threads: threads, ..Default::default() })
            .unwrap();
        g.bench_function(format!("inference_{threads}thread"), |b| b.iter(|| e.embed(black_box(&f), &cons).unwrap()));
        g.bench_function(format!("fast_freak_constellations_inference_{threads}thread"), |b| {
            b.iter(|| {
                let f = features::extract(black_box(&img), &cfg).unwrap();
                let c = constellation::build(&f.keypoints, 20);
                e.embed(&f, &c).unwrap()
            })
        });
        if threads == 1 {
            let emb = e.embed(&f, &cons).unwrap();
            g.bench_function("match_scone_l2_1000x1000", |b| {
                b.iter(|| match_l2(black_box(&emb), &emb, e.dim(), &RatioTest::plain(0.8), &[]).unwrap())
            });
            g.bench_function("match_freak_hamming_1000x1000", |b| {
                b.iter(|| match_hamming(black_box(&f), &f, &RatioTest::plain(0.8)).unwrap())
            });
            // The project's default ratio test looks past same-corner candidates (10 neighbours instead of 2).
            let points = f.points();
            g.bench_function("match_scone_l2_same_corner_1000x1000", |b| {
                b.iter(|| match_l2(black_box(&emb), &emb, e.dim(), &RatioTest::new(0.8), &points).unwrap())
            });
            g.bench_function("match_freak_hamming_same_corner_1000x1000", |b| {
                b.iter(|| match_hamming(black_box(&f), &f, &RatioTest::new(0.8)).unwrap())
            });
        }
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(4));
    targets = bench
}
criterion_main!(benches);
