//! SConE on a 640x480 photograph, against FAST + FREAK alone in the same run and at the same extraction: the
//! whole path (extraction, the model's context: constellations or ring contexts, ONNX Runtime), the ring
//! contexts alone, inference alone at 1 and 2 intra-op threads (with the constellations it builds, for a
//! constellation model), the service's default shape of 2 sessions x 1 thread (`inference_2sessions`: a set
//! in halves; `path_pipelined_2sessions`: FREAK overlapped with the model; `cargo bench --bench path` times it
//! against FAST + FREAK interleaved), and matching SConE embeddings (L2) against FREAK (Hamming), brute force, with the
//! plain and the same-corner ratio test, and MatchPair's matchers (freak, rerank, scale-aware) between the
//! photograph and a mild and a 2x zoomed view of it. Also the relative-pose estimators (plain RANSAC against
//! USAC_ACCURATE) on 300 synthetic correspondences, 25 % outliers.
//! Model: the embedded one (`models/scone-ring-e1-real-bits.onnx`), or `$SCONE_MODEL`; extraction: the one the
//! model declares (8 levels and 2,000 keypoints for the embedded model; revision 2's 6 and 1,500 for
//! `models/scone-freak-k20.onnx`), with `$SCONE_BENCH_LEVELS` and `$SCONE_BENCH_KEYPOINTS` over it;
//! `SCONE_BENCH_SPINNING=1` lets ONNX Runtime's idle threads spin (`[model] spinning`, off by default). The group's
//! name (`scone_640x480_1000kp`) predates both: it was 1,000 keypoints once, and stays for the commands in
//! BENCHMARKS.md. Run: `cargo bench --bench embedding`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{criterion_group, criterion_main, Criterion};

use scone::camera::Camera;
use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::embedding::{default_model_path, Embedder, EmbedderSettings};
use scone::describe::features::{self, ExtractorSettings};
use scone::describe::pipeline;
use scone::matching::{match_hamming, match_l2, match_scone, RatioTest, SconeFrame, SconeMatcher};
use scone::pose::{absolute_pose, relative_pose, EssentialMethod, PnpMethod, RansacSettings};

fn bench(c: &mut Criterion) {
    features::set_opencv_threads(1).unwrap();
    let model = std::env::var_os("SCONE_MODEL").map(PathBuf::from).unwrap_or_else(default_model_path);
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg");
    let bytes = std::fs::read(path).unwrap();
    let img = decode_grey(&bytes, &ImageLimitSettings::default()).unwrap();
    // `SCONE_BENCH_LEVELS` / `SCONE_BENCH_KEYPOINTS`: another extraction (a model trained for it), the same for
    // FAST + FREAK in the run; the group keeps its name.
    let env = |name: &str, default: usize| std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default);
    let declared =
        Embedder::load(&EmbedderSettings { model: model.clone(), ..Default::default() }).unwrap().extraction();
    let cfg = ExtractorSettings {
        max_keypoints: env("SCONE_BENCH_KEYPOINTS", declared.max_keypoints),
        levels: env("SCONE_BENCH_LEVELS", declared.levels as usize) as u32,
        ..declared
    };
    let f = features::extract(&img, &cfg).unwrap();
    eprintln!("{} keypoints, model {}", f.len(), model.display());
    let mut g = c.benchmark_group("scone_640x480_1000kp");
    g.bench_function("fast_freak", |b| b.iter(|| features::extract(black_box(&img), &cfg).unwrap()));
    // The ring contexts of those keypoints (what a ring-context model adds to the extraction).
    g.bench_function("ring_context", |b| {
        b.iter(|| {
            let mut f = f.clone();
            f.sample_context(black_box(&img)).unwrap();
            f
        })
    });
    // The service's shape on 2 cores: two sessions of one thread. Embedding splits a set over both when both are
    // idle; describing an image overlaps FREAK with the ring contexts and the model (`pipeline::describe_decoded`).
    {
        let e = Embedder::load(&EmbedderSettings {
            model: model.clone(),
            sessions: 2,
            intra_threads: 1,
            spinning: std::env::var_os("SCONE_BENCH_SPINNING").is_some_and(|v| v == "1"),
            ..Default::default()
        })
        .unwrap();
        let f = pipeline::extract_for(&img, &cfg, &e).unwrap();
        g.bench_function("inference_2sessions", |b| b.iter(|| e.embed(black_box(&f)).unwrap()));
        g.bench_function("path_pipelined_2sessions", |b| {
            b.iter(|| pipeline::describe_decoded(black_box(&img), &cfg, &e, &mut Default::default()).unwrap())
        });
    }
    for threads in [1usize, 2] {
        let e = Embedder::load(&EmbedderSettings {
            model: model.clone(),
            sessions: 1,
            intra_threads: threads,
            spinning: std::env::var_os("SCONE_BENCH_SPINNING").is_some_and(|v| v == "1"),
            ..Default::default()
        })
        .unwrap();
        let f = pipeline::extract_for(&img, &cfg, &e).unwrap();
        g.bench_function(format!("inference_{threads}thread"), |b| b.iter(|| e.embed(black_box(&f)).unwrap()));
        // The name predates ring-context models: the whole SConE path, whichever context the model reads.
        g.bench_function(format!("fast_freak_constellations_inference_{threads}thread"), |b| {
            b.iter(|| {
                let f = pipeline::extract_for(black_box(&img), &cfg, &e).unwrap();
                e.embed(&f).unwrap()
            })
        });
        if threads == 1 {
            let emb = e.embed(&f).unwrap();
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
            // MatchPair's matchers on two views of the photograph: a mild change (10 degrees, 1.1x: rerank's
            // path) and a zoom of 2 (scale-aware answers with union there).
            let frame = |img: &scone::describe::decode::GreyImage| {
                let f = pipeline::extract_for(img, &cfg, &e).unwrap();
                let emb = e.embed(&f).unwrap();
                (f, emb)
            };
            let (fa, ea) = frame(&img);
            let freak_a = fa.descriptor_mat().unwrap();
            let (pa, sa) = (fa.points(), fa.keypoints.iter().map(|k| k.size).collect::<Vec<f32>>());
            for (name, zoom, degrees) in [("mild", 1.1, 10.0), ("zoom2", 2.0, 25.0)] {
                let (fb, eb) = frame(&warped(&img, zoom, degrees));
                let freak_b = fb.descriptor_mat().unwrap();
                let (pb, sb) = (fb.points(), fb.keypoints.iter().map(|k| k.size).collect::<Vec<f32>>());
                let a = SconeFrame { embeddings: &ea, dim: e.dim(), freak: &freak_a, points: &pa, sizes: &sa };
                let b = SconeFrame { embeddings: &eb, dim: e.dim(), freak: &freak_b, points: &pb, sizes: &sb };
                for matcher in [SconeMatcher::Freak, SconeMatcher::Rerank, SconeMatcher::ScaleAware] {
                    g.bench_function(format!("pair_{name}_{}", matcher.name()), |bn| {
                        bn.iter(|| match_scone(matcher, black_box(&a), &b, &RatioTest::new(0.8)).unwrap())
                    });
                }
            }
        }
    }
    g.finish();

    let (p1, p2) = synthetic_pair(300, 0.25);
    let cam = Camera { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 };
    let opencv = RansacSettings::opencv(1.0);
    let mut g = c.benchmark_group("relative_pose_300_matches");
    for (name, params) in [
        ("ransac", opencv),
        ("usac_accurate_1000iters", RansacSettings { essential: EssentialMethod::UsacAccurate, ..opencv }),
        ("usac_accurate_default", RansacSettings::default()),
    ] {
        g.bench_function(name, |b| b.iter(|| relative_pose(black_box(&p1), &p2, &cam, &cam, &params).unwrap()));
    }
    g.finish();
    // A wide-baseline pair: 100 matches, 70 % of them wrong, where the iteration cap binds.
    let (p1, p2) = synthetic_pair(100, 0.7);
    let mut g = c.benchmark_group("relative_pose_100_matches_70pct_outliers");
    for (name, params) in [
        ("usac_accurate_1000iters", RansacSettings { essential: EssentialMethod::UsacAccurate, ..opencv }),
        ("usac_accurate_default", RansacSettings::default()),
    ] {
        g.bench_function(name, |b| b.iter(|| relative_pose(black_box(&p1), &p2, &cam, &cam, &params).unwrap()));
    }
    g.finish();
    // Relocalisation's PnP (pose::absolute_pose) on 300 2D-3D matches: a near query (80 % inliers) and far ones
    // (30 % and 10 %, where EPnP's 5-point samples run into the cap), the default (USAC) against EPnP.
    let mut g = c.benchmark_group("absolute_pose_300_matches");
    let usac = RansacSettings::relocalisation();
    let epnp = RansacSettings { pnp: PnpMethod::Epnp, ..usac };
    for inliers in [0.8, 0.3, 0.1] {
        let (p3, p2) = synthetic_query(300, inliers);
        for (name, params) in [("usac", usac), ("epnp", epnp)] {
            g.bench_function(format!("{name}_{:.0}pct_inliers", inliers * 100.0), |b| {
                b.iter(|| absolute_pose(black_box(&p3), &p2, &cam, &params, 15).unwrap())
            });
        }
    }
    g.finish();
}

/// `n` 2D-3D matches of a camera at the origin looking along +z at points 3-8 m ahead, 0.5 px noise, a share
/// `inliers` of them right and the rest with random pixels, in random order.
fn synthetic_query(n: usize, inliers: f64) -> (Vec<[f64; 3]>, Points) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    let (mut p3, mut p2) = (Vec::new(), Vec::new());
    for _ in 0..n {
        let (u, v, z) = (rng.random_range(0.0..640.0), rng.random_range(0.0..480.0), rng.random_range(3.0..8.0));
        p3.push([(u - 320.0) / 500.0 * z, (v - 240.0) / 500.0 * z, z]);
        p2.push(if rng.random_bool(inliers) {
            ((u + rng.random_range(-0.5..0.5)) as f32, (v + rng.random_range(-0.5..0.5)) as f32)
        } else {
            (rng.random_range(0.0..640.0) as f32, rng.random_range(0.0..480.0) as f32)
        });
    }
    (p3, p2)
}

/// `n` correspondences between two views of random points 4-8 m ahead (0.5 m baseline, 5° yaw), 0.3 px
/// noise, a share `outliers` of them replaced by random pixels.
type Points = Vec<(f32, f32)>;

/// `img` zoomed by `zoom` and turned by `degrees` about its centre (the same size).
fn warped(img: &scone::describe::decode::GreyImage, zoom: f64, degrees: f64) -> scone::describe::decode::GreyImage {
    use opencv::prelude::*;
    let m = img.mat();
    let centre = opencv::core::Point2f::new(m.cols() as f32 / 2.0, m.rows() as f32 / 2.0);
    let r = opencv::imgproc::get_rotation_matrix_2d(centre, degrees, zoom).unwrap();
    let mut out = opencv::core::Mat::default();
    opencv::imgproc::warp_affine_def(m, &mut out, &r, m.size().unwrap()).unwrap();
    let mut png = opencv::core::Vector::<u8>::new();
    opencv::imgcodecs::imencode_def(".png", &out, &mut png).unwrap();
    decode_grey(png.as_slice(), &ImageLimitSettings::default()).unwrap()
}

fn synthetic_pair(n: usize, outliers: f64) -> (Points, Points) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    let (yaw, tx) = (5f64.to_radians(), 0.5);
    let project = |x: f64, y: f64, z: f64| (320.0 + 500.0 * x / z, 240.0 + 500.0 * y / z);
    let (mut p1, mut p2) = (Vec::new(), Vec::new());
    while p1.len() < n {
        let z = rng.random_range(4.0..8.0);
        let (x, y) = (rng.random_range(-2.5..2.5), rng.random_range(-1.8..1.8));
        let (x2, z2) = (yaw.cos() * x + yaw.sin() * z - tx, -yaw.sin() * x + yaw.cos() * z);
        let (a, b) = (project(x, y, z), project(x2, y, z2));
        if !(0.0..640.0).contains(&b.0) || !(0.0..480.0).contains(&b.1) {
            continue;
        }
        let noise = |rng: &mut rand::rngs::StdRng| rng.random_range(-0.3..0.3);
        let b = if rng.random_bool(outliers) {
            (rng.random_range(0.0..640.0), rng.random_range(0.0..480.0))
        } else {
            (b.0 + noise(&mut rng), b.1 + noise(&mut rng))
        };
        p1.push(((a.0 + noise(&mut rng)) as f32, (a.1 + noise(&mut rng)) as f32));
        p2.push((b.0 as f32, b.1 as f32));
    }
    (p1, p2)
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(4));
    targets = bench
}
criterion_main!(benches);
