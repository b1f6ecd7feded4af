//! The SConE path per image against FAST + FREAK, interleaved: on a shared host whose speed drifts within a
//! minute, criterion's one-function-after-another runs put FAST + FREAK and the path in different weather
//! (session 48 saw FAST + FREAK at 13-19 ms between three runs of a few minutes). Here every round times each
//! variant in turn on the same image, `SCONE_BENCH_REPS` times each (default 15, median kept), and the ratio
//! is taken within the round; the summary is the median over `SCONE_BENCH_ROUNDS` rounds (default 20).
//!
//! Variants, each at the extraction the model declares (`$SCONE_MODEL` or the embedded one):
//! - `fast_freak`: FAST + FREAK alone (the baseline);
//! - `pipelined`: `pipeline::describe_decoded` on 2 sessions of 1 thread (the service's default shape): FREAK
//!   overlapped with the ring contexts and the model;
//! - `serial_2threads`: the stages in turn, the model on 1 session of 2 threads (the shape before session 48);
//! - `serial_1thread`: the stages in turn on 1 session of 1 thread (a request on a busy server).
//!
//! Run: `cargo bench --bench path`.

use std::hint::black_box;
use std::path::PathBuf;
use std::time::Instant;

use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::embedding::{default_model_path, Embedder, EmbedderSettings};
use scone::describe::features;
use scone::describe::pipeline::{self, StageTimes};

mod common;
use common::median;

fn main() {
    features::set_opencv_threads(1).unwrap();
    let env = |name: &str, default: usize| std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default);
    let (rounds, reps) = (env("SCONE_BENCH_ROUNDS", 20), env("SCONE_BENCH_REPS", 15));
    let model = std::env::var_os("SCONE_MODEL").map(PathBuf::from).unwrap_or_else(default_model_path);
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg");
    let img = decode_grey(&std::fs::read(path).unwrap(), &ImageLimitSettings::default()).unwrap();
    let load = |sessions, intra_threads| {
        Embedder::load(&EmbedderSettings { model: model.clone(), sessions, intra_threads, ..Default::default() })
            .unwrap()
    };
    let (two_sessions, two_threads, one_thread) = (load(2, 1), load(1, 2), load(1, 1));
    let cfg = two_sessions.extraction();
    let serial = |e: &Embedder| {
        let f = pipeline::extract_for(&img, &cfg, e).unwrap();
        e.embed(&f).unwrap()
    };
    type Variant<'a> = (&'static str, Box<dyn Fn() + 'a>);
    let variants: Vec<Variant> = vec![
        ("fast_freak", Box::new(|| drop(black_box(features::extract(&img, &cfg).unwrap())))),
        (
            "pipelined",
            Box::new(|| {
                drop(black_box(
                    pipeline::describe_decoded(&img, &cfg, &two_sessions, &mut StageTimes::default()).unwrap(),
                ))
            }),
        ),
        ("serial_2threads", Box::new(|| drop(black_box(serial(&two_threads))))),
        ("serial_1thread", Box::new(|| drop(black_box(serial(&one_thread))))),
    ];
    let n = features::extract(&img, &cfg).unwrap().len();
    println!(
        "{n} keypoints, model {}, {rounds} rounds of {reps} runs per variant (median per round, ms)\n",
        model.display()
    );
    for (_, f) in &variants {
        f(); // warm-up
    }
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    let mut ratios: Vec<Vec<f64>> = vec![Vec::new(); variants.len()];
    println!("| round | {} |", variants.iter().map(|(name, _)| *name).collect::<Vec<_>>().join(" | "));
    println!("|---|{}", "---|".repeat(variants.len()));
    for r in 0..rounds {
        let round: Vec<f64> = variants
            .iter()
            .map(|(_, f)| {
                median(
                    (0..reps)
                        .map(|_| {
                            let t = Instant::now();
                            f();
                            t.elapsed().as_secs_f64() * 1e3
                        })
                        .collect(),
                )
            })
            .collect();
        let cells: Vec<String> = round
            .iter()
            .enumerate()
            .map(|(i, t)| if i == 0 { format!("{t:.2}") } else { format!("{t:.2} ({:.2}x)", t / round[0]) })
            .collect();
        println!("| {} | {} |", r + 1, cells.join(" | "));
        for (i, t) in round.iter().enumerate() {
            times[i].push(*t);
            ratios[i].push(t / round[0]);
        }
    }
    println!("\n| variant | median ms | median ratio to fast_freak (same round) | range of the ratio |");
    println!("|---|---|---|---|");
    for (i, (name, _)) in variants.iter().enumerate() {
        let (lo, hi) = ratios[i].iter().fold((f64::MAX, f64::MIN), |(l, h), &x| (l.min(x), h.max(x)));
        println!("| {name} | {:.2} | {:.2}x | {lo:.2}-{hi:.2}x |", median(times[i].clone()), median(ratios[i].clone()));
    }
}
