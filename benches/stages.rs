//! Where the SConE path's time goes on one thread: every stage of an image's description timed apart, their
//! sum set against the path timed whole, and FAST + FREAK beside them, all in the same rounds.
//!
//! The path here is what one request costs a busy server: decode, then FAST on the pyramid, FREAK, the ring
//! contexts and the model one after the other on one thread (one ONNX Runtime session of one intra-op thread,
//! the ring sampled without its second thread). Stages: `decode` (JPEG to grey), `pyramid` (the levels'
//! resizes), `fast` (OpenCV's FAST on each level), `grid` (border filter and grid budget), `freak` (OpenCV's
//! FREAK), `freak_output` (its keypoints and descriptors copied into the feature set), `integral` (the
//! integral image the ring is read from), `ring` (the ring contexts), `assembly` (the model's input tensors),
//! `inference` (ONNX Runtime's run), `output` (the embeddings copied out); `unaccounted` is the staged run's
//! wall time less the sum of its stages.
//!
//! Each round times each variant in turn, `SCONE_BENCH_REPS` runs each (default 15); the figures are medians
//! over `SCONE_BENCH_ROUNDS` rounds (default 10) of each round's medians. Run: `cargo bench --bench stages`.

use std::collections::BTreeMap;
use std::hint::black_box;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::embedding::{default_model_path, Embedder, EmbedderSettings};
use scone::describe::features::{self, ExtractorSettings, Features};
use scone::describe::ring_context::RingSampler;

mod common;
use common::median;

const STAGES: [&str; 11] = [
    "decode",
    "pyramid",
    "fast",
    "grid",
    "freak",
    "freak_output",
    "integral",
    "ring",
    "assembly",
    "inference",
    "output",
];

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The CPU's model name and the vector extensions that decide these figures.
fn cpu() -> String {
    let info = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let field = |name: &str| {
        info.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_once(':'))
            .map(|(_, v)| v.trim().to_string())
            .unwrap_or_default()
    };
    let flags = field("flags");
    let have: Vec<&str> = ["avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni"]
        .into_iter()
        .filter(|f| flags.split_whitespace().any(|x| x == *f))
        .collect();
    format!("{} ({})", field("model name"), if have.is_empty() { "no AVX2".into() } else { have.join(", ") })
}

/// One description, timed whole: the path the stages account for.
fn path(bytes: &[u8], cfg: &ExtractorSettings, embedder: &Embedder) -> Vec<f32> {
    let image = decode_grey(bytes, &ImageLimitSettings::default()).unwrap();
    let mut candidates = features::detect(&image, cfg).unwrap();
    let mut f = features::describe(&image, &mut candidates).unwrap();
    f.sample_context_from(&RingSampler::new(&image).unwrap(), false);
    embedder.lease().embed(&f).unwrap()
}

/// The same description with each stage's time added to `stages`; returns the embeddings.
fn staged(
    bytes: &[u8],
    cfg: &ExtractorSettings,
    embedder: &Embedder,
    stages: &mut BTreeMap<&'static str, f64>,
) -> Vec<f32> {
    let mut add = |name: &'static str, d: Duration| *stages.entry(name).or_default() += ms(d);
    let t = Instant::now();
    let image = decode_grey(bytes, &ImageLimitSettings::default()).unwrap();
    add("decode", t.elapsed());
    let mut candidates = features::detect_staged(&image, cfg, &mut add).unwrap();
    let mut f: Features = features::describe_staged(&image, &mut candidates, &mut add).unwrap();
    let t = Instant::now();
    let sampler = RingSampler::new(&image).unwrap();
    add("integral", t.elapsed());
    let t = Instant::now();
    f.sample_context_from(&sampler, false);
    add("ring", t.elapsed());
    embedder.lease().embed_rings_staged(&f, &mut add).unwrap()
}

fn main() {
    features::set_opencv_threads(1).unwrap();
    let env = |name: &str, default: usize| std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default);
    let (rounds, reps) = (env("SCONE_BENCH_ROUNDS", 10), env("SCONE_BENCH_REPS", 15));
    let model = std::env::var_os("SCONE_MODEL").map(PathBuf::from).unwrap_or_else(default_model_path);
    let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg")).unwrap();
    let embedder =
        Embedder::load(&EmbedderSettings { model: model.clone(), sessions: 1, intra_threads: 1, ..Default::default() })
            .unwrap();
    assert!(embedder.needs_context(), "the stages bench runs a ring-context model");
    let cfg = embedder.extraction();
    let image = decode_grey(&bytes, &ImageLimitSettings::default()).unwrap();
    // The staged run computes what the path computes.
    assert_eq!(staged(&bytes, &cfg, &embedder, &mut BTreeMap::new()), path(&bytes, &cfg, &embedder));
    let n = features::extract(&image, &cfg).unwrap().len();
    println!("CPU: {}", cpu());
    println!("{n} keypoints, model {}, {rounds} rounds of {reps} runs per variant\n", model.display());

    let (mut base, mut whole, mut total) = (Vec::new(), Vec::new(), Vec::new());
    let mut per_stage: BTreeMap<&'static str, Vec<f64>> = BTreeMap::new();
    for _ in 0..rounds {
        let time = |f: &mut dyn FnMut()| {
            median(
                (0..reps)
                    .map(|_| {
                        let t = Instant::now();
                        f();
                        ms(t.elapsed())
                    })
                    .collect(),
            )
        };
        base.push(time(&mut || drop(black_box(features::extract(&image, &cfg).unwrap()))));
        whole.push(time(&mut || drop(black_box(path(&bytes, &cfg, &embedder)))));
        let mut runs: Vec<BTreeMap<&'static str, f64>> = Vec::new();
        total.push(time(&mut || {
            let mut s = BTreeMap::new();
            drop(black_box(staged(&bytes, &cfg, &embedder, &mut s)));
            runs.push(s);
        }));
        for name in STAGES {
            per_stage.entry(name).or_default().push(median(runs.iter().map(|r| r[name]).collect()));
        }
    }
    let (base, whole, total) = (median(base), median(whole), median(total));
    let stages: Vec<(&str, f64)> = STAGES.iter().map(|&s| (s, median(per_stage[s].clone()))).collect();
    let sum: f64 = stages.iter().map(|s| s.1).sum();
    println!("| stage | median ms | share of the path |");
    println!("|---|---|---|");
    for (name, t) in &stages {
        println!("| {name} | {t:.2} | {:.1} % |", 100.0 * t / whole);
    }
    println!(
        "| unaccounted (staged run less its stages) | {:.2} | {:.1} % |",
        total - sum,
        100.0 * (total - sum) / whole
    );
    println!("| **sum of the stages** | **{sum:.2}** | {:.1} % |", 100.0 * sum / whole);
    println!("\n| figure | ms | ratio to FAST + FREAK |");
    println!("|---|---|---|");
    println!("| FAST + FREAK (decoded image) | {base:.2} | 1.00x |");
    println!("| the path, timed whole (with decode) | {whole:.2} | {:.2}x |", whole / base);
    let decode = stages[0].1;
    println!("| the path less decode | {:.2} | {:.2}x |", whole - decode, (whole - decode) / base);
    println!("| the staged run | {total:.2} | {:.2}x |", total / base);
    println!("\nsum of the stages / the path timed whole: {:.3}", sum / whole);
}
