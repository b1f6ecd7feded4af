//! Feature extraction on a 640x480 photograph, stage by stage: decode, FAST (pyramid + bucketing),
//! FREAK, constellations (k = 20), and the whole path; plus single-scale FAST for comparison.
//! Run: `. scripts/env.sh && cargo bench --bench extraction` (docs/development.md, "Benchmarks").

use criterion::{criterion_group, criterion_main, Criterion};
use opencv::core::{KeyPoint, Vector};
use std::hint::black_box;

use scone::describe::constellation;
use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::features::{self, describe, detect, ExtractorSettings};

fn bench(c: &mut Criterion) {
    features::set_opencv_threads(1).unwrap();
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg");
    let bytes = std::fs::read(path).unwrap();
    let limits = ImageLimitSettings::default();
    let img = decode_grey(&bytes, &limits).unwrap();
    let mut g = c.benchmark_group("extraction_640x480");
    for (name, cfg) in
        [("pyramid", ExtractorSettings::default()), ("single_scale", ExtractorSettings::single_scale(20, 1500))]
    {
        let kps = detect(&img, &cfg).unwrap();
        let f = features::extract(&img, &cfg).unwrap();
        eprintln!("{name}: {} keypoints detected, {} described", kps.len(), f.len());
        g.bench_function(format!("{name}/fast"), |b| b.iter(|| detect(black_box(&img), &cfg).unwrap()));
        g.bench_function(format!("{name}/freak"), |b| {
            b.iter_batched(
                || kps.clone(),
                |mut k: Vector<KeyPoint>| describe(black_box(&img), &mut k).unwrap(),
                criterion::BatchSize::SmallInput,
            )
        });
        g.bench_function(format!("{name}/constellations_k20"), |b| {
            b.iter(|| constellation::build(black_box(&f.keypoints), 20))
        });
        g.bench_function(format!("{name}/total"), |b| {
            b.iter(|| {
                let img = decode_grey(black_box(&bytes), &limits).unwrap();
                let f = features::extract(&img, &cfg).unwrap();
                constellation::build(&f.keypoints, 20)
            })
        });
    }
    g.bench_function("decode_jpeg", |b| b.iter(|| decode_grey(black_box(&bytes), &limits).unwrap()));
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(4));
    targets = bench
}
criterion_main!(benches);
