//! LocalizeTrack against Localize, in one run (issue 43's latency bar: a 3-frame track's p50 at most 2.5 times
//! one frame's): a map of every other posed frame of a real scene (TUM fr3/long_office_household from
//! `../shared/data`, or `$SCONE_BENCH_SCENE`; the committed rendered fixture when neither is there), then every
//! other frame localised alone, and as the first frame of a track with its two nearest query frames (their
//! ground-truth poses relative to it), through the service as a request runs it (`Service::localize`,
//! `Service::localize_track`), interleaved query by query. Prints a markdown table: p50 and p90 of each, their
//! ratio, and how many were located.
//!
//! Run: `cargo bench --bench track`.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use scone::describe::decode::ImageLimitSettings;
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::features::KeypointLimitSettings;
use scone::describe::pipeline::Describer;
use scone::map::store::{MapStore, ModelInfo, StoreSettings};
use scone::offline::scene::Scene;
use scone::service::{
    FrameInput, FrameSource, KeyframeRequest, PoseConvention, Service, TrackFrameInput, TrackRequest, TrackScale,
    TrackerError,
};

fn scene_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("SCONE_BENCH_SCENE") {
        return PathBuf::from(d);
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let tum = root.join("../shared/data/scenes/tum-fr3-long-office");
    if tum.is_dir() {
        tum
    } else {
        root.join("tests/fixtures/rendered")
    }
}

fn percentile(mut v: Vec<f64>, p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    scone::describe::features::set_opencv_threads(1).unwrap();
    let dir = scene_dir();
    let scene = Scene::load(&dir).unwrap();
    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let describer = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    let data = std::env::temp_dir().join(format!("scone-bench-track-{}", std::process::id()));
    let config = StoreSettings { data_dir: data.clone(), ..StoreSettings::default() };
    let e = &describer.embedder;
    let info = ModelInfo { model_id: e.model_id().to_string(), k: e.k(), dim: e.dim() };
    let store = Arc::new(MapStore::open(config, info).unwrap());
    store.create("m").unwrap();
    let service = Service::new(describer, KeypointLimitSettings::default(), Default::default()).unwrap();
    service.attach_store(store);
    let map = service.map("m").unwrap();
    let frame = |i: usize| FrameInput {
        source: FrameSource::Image(std::fs::read(&scene.frames[i].rgb).unwrap()),
        camera: Some(scene.camera),
        distortion: Default::default(),
    };
    let posed: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
    for &i in posed.iter().step_by(2) {
        let request = KeyframeRequest {
            id: i as u64,
            frame: frame(i),
            pose: scone::camera::Pose::from_isometry(&scene.frames[i].pose.unwrap()),
            convention: PoseConvention::default(),
            depth_png: scene.frames[i].depth.as_ref().map(|d| std::fs::read(d).unwrap()),
            depth_scale: None,
            external_landmarks: Vec::new(),
        };
        service.add_keyframe(&map, request).unwrap();
    }
    let queries: Vec<usize> = posed.iter().copied().skip(1).step_by(2).collect();
    let (mut single, mut track, mut estimate) = (Vec::new(), Vec::new(), Vec::new());
    let (mut single_located, mut track_located) = (0, 0);
    for (n, &q) in queries.iter().enumerate() {
        let t = Instant::now();
        let o = service.localize(&map, frame(q), None).unwrap();
        let one = t.elapsed().as_secs_f64() * 1e3;
        let mut others: Vec<usize> = queries.iter().copied().filter(|&j| j != q).collect();
        others.sort_by_key(|&j| (j.abs_diff(q), j));
        let members: Vec<usize> = std::iter::once(q).chain(others.into_iter().take(2)).collect();
        let first = scene.frames[q].pose.unwrap().inverse();
        let frames = members
            .iter()
            .map(|&j| TrackFrameInput {
                frame: frame(j),
                pose: scone::camera::Pose::from_isometry(&(first * scene.frames[j].pose.unwrap())),
            })
            .collect();
        let request = TrackRequest {
            frames,
            convention: PoseConvention::default(),
            scale: TrackScale::Rigid,
            prior: None,
            tracker: TrackerError::default(),
        };
        let t = Instant::now();
        let r = service.localize_track(&map, request).unwrap();
        let three = t.elapsed().as_secs_f64() * 1e3;
        if n == 0 {
            continue; // warm-up
        }
        single.push(one);
        track.push(three);
        estimate.extend(r.times.0.iter().filter(|(s, _)| *s == "track").map(|(_, v)| v * 1e3));
        single_located += usize::from(o.pose.is_some());
        track_located += usize::from(r.map_from_track.is_some());
    }
    let _ = std::fs::remove_dir_all(&data);
    let (s50, t50) = (percentile(single.clone(), 0.5), percentile(track.clone(), 0.5));
    println!("{} ({} map keyframes, {} queries, interleaved)\n", dir.display(), posed.len().div_ceil(2), single.len());
    println!("| query | p50 ms | p90 ms | located |\n|---|---|---|---|");
    println!(
        "| one frame (Localize) | {s50:.1} | {:.1} | {single_located}/{} |",
        percentile(single.clone(), 0.9),
        single.len()
    );
    println!(
        "| 3-frame track (LocalizeTrack) | {t50:.1} | {:.1} | {track_located}/{} |",
        percentile(track.clone(), 0.9),
        track.len()
    );
    println!(
        "\ntrack p50 / frame p50: {:.2}x; the joint estimate alone: p50 {:.1} ms",
        t50 / s50,
        percentile(estimate, 0.5)
    );
}
