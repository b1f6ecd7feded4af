//! Relocalisation of a 640x480 JPEG query through the service's own path (`Service::localize`) against real
//! maps of ~10k and ~100k observations, and with `SCONE_BENCH_1M=1` the largest the training scenes give
//! (727,987 observations: they run out before 1M). Per level: time per stage and total, HNSW against exact
//! search on the same map in the same run, recall@1/@2 of the index against exact search on the query's own
//! embeddings, time to ready after a restart (snapshot + index dump), and memory per observation (RSS growth
//! over the open; the exact row opens the map data without its graph while the HNSW row's map is still open,
//! so the difference of the two rows is the graph's). Then a sweep of `store.localize.max_query_keypoints`
//! over every query of the level, and AddKeyframe on a copy of the level's map (the first 20 queries added
//! as keyframes: the plan alone, then the whole write).
//! The index of one point per landmark (`store.index.points = "landmarks"`) is measured in a process of its
//! own on a copy of the level's map with its own dump (made once, in the build process): the same row and
//! recall (against exact search over the same points) with the service's default stage 1 (since session 45,
//! the strongest 100 query keypoints, every keypoint below 100 inliers), the row again with PnP by EPnP's
//! RANSAC instead of USAC, the row with every query keypoint searched (the default before), and every query
//! of the level with several caps.
//! `SCONE_BENCH_ADD_ONLY=1` with `SCONE_BENCH_LEVEL=N` measures AddKeyframe alone at level N.
//!
//! Map: real, different frames, never repeated. The posed frames of the training scenes of `../shared/data`,
//! in this order: `7scenes-redkitchen` (every frame but the held-out ones, triangulated with its poses),
//! `sun3d-studyroom` (with depth), `strecha-castle-P30`, `liberty-internet`, `middlebury-templeRing` (stamps
//! 1-31, the ones in one world frame), each scene 10 km from the others so no landmark of one falls where
//! another's are. A level's map is the shortest prefix of that order that holds its number of observations.
//! Queries: the held-out frames of `7scenes-redkitchen` (every 10th, starting at the 5th) inside the part of
//! the scene the map covers, JPEG-encoded (quality 90).
//!
//! Maps are built once per model and kept under `$SCONE_PREFIX/bench/reloc` (default `~/.cache/scone`; one of
//! an older format is upgraded by the build process); an interrupted build resumes from the keyframes its
//! write-ahead log holds. `SCONE_BENCH_REBUILD=1` builds
//! again. Run: `cargo bench --bench reloc` (needs `../shared/data` or `$SCONE_DATA`; prints a note without it).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Vector3};
use opencv::core::Vector;
use opencv::prelude::*;
use rayon::prelude::*;
use scone::camera::Camera;
use scone::describe::decode::{decode_depth_png, ImageLimitSettings, TUM_DEPTH_SCALE};
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::features::KeypointLimitSettings;
use scone::describe::pipeline::Describer;
use scone::map::builder::{plan, BuildSettings, Depth, KeyframeInput};
use scone::map::index::{exact_search, EmbeddingIndex, IndexPoints, IndexSettings};
use scone::map::localize::{localize, LocalizeSettings};
use scone::map::model::MapData;
use scone::map::storage::format::FORMAT_VERSION;
use scone::map::storage::snapshot::snapshot_version;
use scone::map::store::{MapStore, ModelInfo, StoreSettings};
use scone::offline::scene::Scene;
use scone::pose::{rotation_error_deg, PnpMethod};
use scone::service::{FrameInput, FrameSource, Service};

mod common;
use common::{median, rss_mb};

/// Scenes the map is made of, in order: the training scenes.
const MAP_SCENES: [&str; 5] =
    ["7scenes-redkitchen", "sun3d-studyroom", "strecha-castle-P30", "liberty-internet", "middlebury-templeRing"];
/// Distance between the scenes' worlds, scene units.
const SCENE_OFFSET: f64 = 10_000.0;

/// Frame `f` of `redkitchen` is a query (held out of every map).
fn is_query(f: usize) -> bool {
    f % 10 == 5
}

struct MapFrame {
    scene: usize,
    frame: usize,
}

/// The map's frames in order.
fn map_frames(scenes: &[Scene]) -> Vec<MapFrame> {
    let mut out = Vec::new();
    for (s, scene) in scenes.iter().enumerate() {
        for (f, frame) in scene.frames.iter().enumerate() {
            // templeRing's stamps 32-47 sit in another world frame than 1-31.
            let other_frame =
                MAP_SCENES[s] == "middlebury-templeRing" && frame.stamp.parse::<u32>().map_or(true, |t| t > 31);
            if frame.pose.is_some() && !(s == 0 && is_query(f)) && !other_frame {
                out.push(MapFrame { scene: s, frame: f });
            }
        }
    }
    out
}

fn config(dir: &Path, index: IndexSettings) -> StoreSettings {
    StoreSettings { data_dir: dir.to_path_buf(), compact_every: usize::MAX, index, ..StoreSettings::default() }
}

/// What a finished build wrote next to its map.
#[derive(serde::Serialize, serde::Deserialize)]
struct Built {
    /// Map frames used (a prefix of [`map_frames`]).
    frames: usize,
    observations: usize,
    /// Of the last build run (a resumed build counts only its own part).
    build_seconds: f64,
    #[serde(default)]
    resumed: bool,
}

/// Builds (or resumes, or reuses) the map of one level; returns its directory and what the build wrote.
fn prepare(
    target: usize,
    scenes: &[Scene],
    frames: &[MapFrame],
    describer: &Describer,
    info: &ModelInfo,
) -> (PathBuf, Built, bool) {
    // Keyed by the model and the frame list: a changed list (scenes, held-out rule, data) never reuses a map.
    let list: String = frames
        .iter()
        .map(|f| format!("{}/{}\n", scenes[f.scene].name, scenes[f.scene].frames[f.frame].stamp))
        .collect();
    let dir = common::prefix().join("bench/reloc").join(format!(
        "{}-{target}-{:08x}",
        info.model_id,
        crc32fast::hash(list.as_bytes())
    ));
    let done = dir.join("built.json");
    if std::env::var_os("SCONE_BENCH_REBUILD").is_some() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    if let Some(b) = std::fs::read(&done).ok().and_then(|b| serde_json::from_slice::<Built>(&b).ok()) {
        per_landmark_copy(&dir, info);
        return (dir, b, false);
    }
    std::fs::create_dir_all(&dir).unwrap();
    eprintln!("reloc bench: building the {target} map in {}", dir.display());
    let limits = ImageLimitSettings::default();
    let t = Instant::now();
    let store = MapStore::open(config(&dir, per_observation_settings()), info.clone()).unwrap();
    if store.summary("m").is_err() {
        store.create("m").unwrap();
    }
    // Keyframe ids are positions in `frames`, written in order: the keyframes already there are a prefix.
    let mut next = store.summary("m").unwrap().keyframes;
    let resumed = next > 0;
    if next > 0 {
        eprintln!("reloc bench: resuming the {target} map at frame {next}");
    }
    let mut progress =
        scone::offline::progress::Progress::new(format!("reloc bench: {target} map, observations"), target);
    while store.summary("m").unwrap().observations < target {
        progress.set(store.summary("m").unwrap().observations);
        let Some(mf) = frames.get(next) else {
            eprintln!("reloc bench: the training scenes ran out of frames before {target} observations");
            break;
        };
        let scene = &scenes[mf.scene];
        let f = &scene.frames[mf.frame];
        let d = describer.describe_image(&std::fs::read(&f.rgb).unwrap()).unwrap();
        let depth = f.depth.as_ref().map(|p| decode_depth_png(&std::fs::read(p).unwrap(), &limits).unwrap());
        let pose = f.pose.unwrap();
        let offset = Vector3::new(SCENE_OFFSET * mf.scene as f64, 0.0, 0.0);
        let input = KeyframeInput {
            id: next as u64,
            pose: Isometry3::from_parts((pose.translation.vector + offset).into(), pose.rotation),
            camera: scene.camera,
            features: &d.features,
            embeddings: &d.embeddings,
            depth: depth.as_ref().map(|m| Depth { image: m, scale: TUM_DEPTH_SCALE }),
            external: None,
        };
        store.add_keyframe(&store.get("m").unwrap(), &input).unwrap();
        next += 1;
        if next.is_multiple_of(100) {
            eprintln!(
                "reloc bench: {target} map: {next} frames, {} observations",
                store.summary("m").unwrap().observations
            );
        }
    }
    assert!(store.flush().is_empty(), "the map was not snapshotted");
    let s = store.summary("m").unwrap();
    let built = Built { frames: next, observations: s.observations, build_seconds: t.elapsed().as_secs_f64(), resumed };
    scone::map::storage::format::write_atomic(&done, &serde_json::to_vec(&built).unwrap()).unwrap();
    per_landmark_copy(&dir, info);
    (dir, built, true)
}

/// Settings of the index with one point per landmark.
fn per_landmark_settings() -> IndexSettings {
    IndexSettings { points: IndexPoints::Landmarks, ..IndexSettings::default() }
}

/// Settings of the index with one point per observation (the default before issue 31: the kept map's dump,
/// and the rows comparable with earlier runs).
fn per_observation_settings() -> IndexSettings {
    IndexSettings { points: IndexPoints::Observations, ..IndexSettings::default() }
}

/// The level's map again under `<dir>/per-landmark` (its snapshot and log, not its index dump), with the
/// index dump of one point per landmark: made once (in the build process), then reloaded as the other map is.
fn per_landmark_copy(dir: &Path, info: &ModelInfo) -> PathBuf {
    let copy = dir.join("per-landmark");
    // A map kept from a build before the current format is upgraded here, in the build's own process.
    for (d, index) in [(dir, per_observation_settings()), (&copy, per_landmark_settings())] {
        if snapshot_version(&d.join("maps/m/snapshot.bin")).is_ok_and(|v| v < FORMAT_VERSION) {
            MapStore::open(config(d, index), info.clone()).unwrap();
        }
    }
    if copy.join("built").exists() {
        return copy;
    }
    let _ = std::fs::remove_dir_all(&copy);
    std::fs::create_dir_all(copy.join("maps/m")).unwrap();
    for f in ["snapshot.bin", "log.bin"] {
        std::fs::copy(dir.join("maps/m").join(f), copy.join("maps/m").join(f)).unwrap();
    }
    let t = Instant::now();
    let store = MapStore::open(config(&copy, per_landmark_settings()), info.clone()).unwrap();
    assert!(store.flush().is_empty(), "the per-landmark map was not dumped");
    eprintln!("reloc bench: one point per landmark: graph built in {:.0} s", t.elapsed().as_secs_f64());
    std::fs::write(copy.join("built"), b"").unwrap();
    copy
}

fn jpeg(path: &Path) -> Vec<u8> {
    let img = opencv::imgcodecs::imread(path.to_str().unwrap(), opencv::imgcodecs::IMREAD_COLOR).unwrap();
    assert_eq!((img.cols(), img.rows()), (640, 480));
    let mut buf = Vector::<u8>::new();
    let params = Vector::<i32>::from_slice(&[opencv::imgcodecs::IMWRITE_JPEG_QUALITY, 90]);
    opencv::imgcodecs::imencode(".jpg", &img, &mut buf, &params).unwrap();
    buf.to_vec()
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    let root = common::shared_data();
    let scenes: Vec<Scene> = match MAP_SCENES.iter().map(|s| Scene::load(&root.join("scenes").join(s))).collect() {
        Ok(s) => s,
        Err(e) => {
            eprintln!("reloc bench: no shared data at {} ({e}); nothing measured", root.display());
            return;
        }
    };
    scone::describe::features::set_opencv_threads(1).unwrap();
    let embedder = Arc::new(Embedder::load(&EmbedderSettings::default()).unwrap());
    let info = ModelInfo { model_id: embedder.model_id().to_string(), k: embedder.k(), dim: embedder.dim() };
    let describer = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    let frames = map_frames(&scenes);
    let kitchen = &scenes[0];
    let camera: Camera = kitchen.camera;

    let Some(target) = std::env::var("SCONE_BENCH_LEVEL").ok().and_then(|t| t.parse::<usize>().ok()) else {
        return run_levels();
    };
    if std::env::var_os("SCONE_BENCH_BUILD_ONLY").is_some() {
        // A map built in the measuring process would leave it pages and freed memory to reuse, flattering
        // that level's memory and time to ready: the parent builds in a process of its own first.
        prepare(target, &scenes, &frames, &describer, &info);
        return;
    }
    let mut rows = Vec::new();
    let mut notes = Vec::new();
    let mut sweeps = Vec::new();
    let mut adds = Vec::new();
    // Maps stay open until the level is done, so a later measurement does not reuse their freed memory.
    let mut open_maps = Vec::new();
    {
        let (dir, built, fresh) = prepare(target, &scenes, &frames, &describer, &info);
        // A run that died while the exact row had the dump's manifest aside puts it back.
        let (manifest, aside) = (dir.join("maps/m/index.json"), dir.join("maps/m/index.json.aside"));
        if aside.exists() && !manifest.exists() {
            std::fs::rename(&aside, &manifest).unwrap();
        }
        // Queries: held-out kitchen frames inside the part of the kitchen the map holds.
        let kitchen_frames = frames[..built.frames].iter().filter(|f| f.scene == 0).map(|f| f.frame).max().unwrap();
        let query_frames: Vec<usize> = (0..kitchen.frames.len())
            .filter(|&f| is_query(f) && f < kitchen_frames && kitchen.frames[f].pose.is_some())
            .collect();
        let queries: Vec<(Vec<u8>, Isometry3<f64>)> =
            query_frames.iter().map(|&f| (jpeg(&kitchen.frames[f].rgb), kitchen.frames[f].pose.unwrap())).collect();
        // Described once, before any measurement, for the recall, the sweep and the lever.
        let described: Vec<Described> =
            queries.iter().map(|(jpg, gt)| (describer.describe_image(jpg).unwrap(), *gt)).collect();
        notes.push(format!(
            "{target}: {} map frames ({} of the kitchen), {} observations, {} queries, build {:.0} s{}{}",
            built.frames,
            frames[..built.frames].iter().filter(|f| f.scene == 0).count(),
            built.observations,
            queries.len(),
            built.build_seconds,
            if built.resumed { " (resumed; the last part)" } else { "" },
            if fresh { " (this run)" } else { " (an earlier run; kept under the prefix)" },
        ));
        if std::env::var_os("SCONE_BENCH_ADD_ONLY").is_some() {
            // AddKeyframe alone (while working on map building).
            println!("@add {}", add_keyframes(&dir, &info, &described, &camera, built.observations));
            return;
        }
        // The exact row comes right after the HNSW row, before much is allocated and freed, so its RSS growth
        // is the map data's. The last row is stage 1 alone (before issue 27), the defaults' latency baseline.
        // The per-landmark index is measured in a process of its own (`run_levels`), its map opened first, so
        // neither row's memory is lowered by what the other freed; three times: with the service's default stage 1
        // (capped since session 45, with the fallback), with EPnP instead of USAC, then every query keypoint
        // searched, the map opened again for each. `None`: the service's default cap.
        let per_landmark = std::env::var_os(PER_LANDMARK_ENV).is_some();
        let row_list = if per_landmark {
            vec![
                (PER_LANDMARK, per_landmark_settings(), None),
                (PER_LANDMARK_EPNP, per_landmark_settings(), None),
                (PER_LANDMARK_EVERY, per_landmark_settings(), Some(usize::MAX)),
            ]
        } else {
            vec![
                (PER_OBSERVATION, per_observation_settings(), Some(usize::MAX)),
                ("exact", IndexSettings { exact_below: usize::MAX, ..IndexSettings::default() }, Some(usize::MAX)),
                ("HNSW per observation, 800 query keypoints", per_observation_settings(), Some(800)),
                ("HNSW per observation, stage 1 only", per_observation_settings(), Some(usize::MAX)),
            ]
        };
        for (label, index, cap) in row_list {
            if label == PER_LANDMARK_EVERY || label == PER_LANDMARK_EPNP {
                // The same map directory: the first store lets go of it (its memory figure is the first open's).
                open_maps.clear();
            }
            // The exact row opens the map without its graph (the dump set aside), so its time to ready is the
            // map data's alone.
            if label == "exact" {
                std::fs::rename(&manifest, &aside).unwrap();
            }
            let rss_before = rss_mb();
            let t = Instant::now();
            let map_dir = if per_landmark { dir.join("per-landmark") } else { dir.clone() };
            let mut cfg = config(&map_dir, index);
            // A row's own cap stands alone (no fallback), as these rows were measured before it existed.
            if let Some(cap) = cap {
                (cfg.localize.max_query_keypoints, cfg.localize.full_search_below_inliers) = (cap, 0);
            }
            if label.ends_with("stage 1 only") {
                cfg.localize = cfg.localize.stage_one_only();
            }
            if label == PER_LANDMARK_EPNP {
                cfg.localize.ransac.pnp = PnpMethod::Epnp;
            }
            let store = MapStore::open(cfg, info.clone()).unwrap();
            let ready = t.elapsed().as_secs_f64();
            if label == "exact" {
                std::fs::rename(&aside, &manifest).unwrap();
            }
            let rss_per_obs_kb = (rss_mb() - rss_before) * 1024.0 / built.observations as f64;
            let (observations, estimate_kb, payload_kb, from_dump) = store.get("m").unwrap().read(|data, index| {
                let payload: usize = data.keyframes.values().map(|k| k.memory_bytes()).sum();
                let n = data.observations.len() as f64;
                (
                    data.observations.len(),
                    (data.memory_bytes() + index.memory_bytes(data.meta.dim)) as f64 / n / 1024.0,
                    payload as f64 / n / 1024.0,
                    index.loaded_from_dump(),
                )
            });
            // Recall of the index against exact search over the same points (every observation, or each
            // landmark's representative), on the first queries' own embeddings (k = 2).
            let recall = if label == PER_OBSERVATION || label == PER_LANDMARK {
                let sample = if target >= 1_000_000 { 1 } else { 3 };
                let embeddings: Vec<f32> =
                    described.iter().take(sample).flat_map(|(d, _)| d.embeddings.iter().copied()).collect();
                let (r1, r2, n) = store.get("m").unwrap().read(|data, index| {
                    let dim = data.meta.dim;
                    let per: Vec<(usize, usize)> = embeddings
                        .par_chunks_exact(dim)
                        .map(|q| {
                            let a = index.search(data, q, 2, None);
                            let point = |i: usize| index.admissible(data, i);
                            let e = exact_search(data, q, 2, Some(&point));
                            let top1 =
                                usize::from(a.first().map(|h| h.observation) == e.first().map(|h| h.observation));
                            let both = e.iter().filter(|h| a.iter().any(|x| x.observation == h.observation)).count();
                            (top1, both)
                        })
                        .collect();
                    let n = per.len();
                    (per.iter().map(|p| p.0).sum::<usize>(), per.iter().map(|p| p.1).sum::<usize>(), n)
                });
                format!("{:.3} / {:.3}", r1 as f64 / n as f64, r2 as f64 / (2 * n) as f64)
            } else {
                "-".into()
            };
            let service =
                Service::new(describer.clone(), KeypointLimitSettings::default(), Default::default()).unwrap();
            let store = Arc::new(store);
            service.attach_store(store.clone());
            let runs = match (label, target) {
                ("exact", t) if t >= 1_000_000 => 2,
                ("exact", _) => 6,
                _ => 20,
            };
            let mut stages: std::collections::BTreeMap<&str, Vec<f64>> = Default::default();
            let mut totals = Vec::new();
            let (mut localised, mut within) = (0, 0);
            for i in 0..=runs {
                let (jpg, gt) = &queries[i % queries.len()];
                let frame = FrameInput {
                    source: FrameSource::Image(jpg.clone()),
                    camera: Some(camera),
                    distortion: Default::default(),
                };
                let t = Instant::now();
                let o = service.localize(&service.map("m").unwrap(), frame, None).unwrap();
                if i == 0 {
                    continue; // warm-up
                }
                totals.push(t.elapsed().as_secs_f64() * 1e3);
                if let Some(p) = &o.pose {
                    localised += 1;
                    within += usize::from(is_within(&p.camera_to_world, gt).0);
                }
                for (s, v) in o.times.0 {
                    stages.entry(s).or_default().push(v * 1e3);
                }
            }
            let m = |s: &str| stages.get(s).map_or(0.0, |v| median(v.clone()));
            rows.push(format!(
                "| {observations} | {label} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {localised}/{runs} | {within}/{runs} | {recall} | {} | {} |",
                m("decode"),
                m("extract"),
                m("embed"),
                m("search"),
                m("pnp"),
                m("stages"),
                median(totals),
                match label {
                    PER_OBSERVATION | PER_LANDMARK | PER_LANDMARK_EVERY | PER_LANDMARK_EPNP => {
                        format!("{ready:.2}{}", if from_dump { "" } else { " (graph rebuilt)" })
                    }
                    "exact" => format!("{ready:.2} (map data only)"),
                    _ => "-".into(),
                },
                match label {
                    PER_OBSERVATION | PER_LANDMARK => {
                        format!("{rss_per_obs_kb:.2} (estimate {estimate_kb:.2}; keyframes, payloads in memory {payload_kb:.2})")
                    }
                    "exact" => format!("{rss_per_obs_kb:.2} (map data only)"),
                    _ => "-".into(),
                },
            ));
            open_maps.push(store);
        }
        // Then the sweep on the HNSW row's map and AddKeyframe; or every query against the per-landmark map.
        let (store, observations) = (&open_maps[0], built.observations);
        if per_landmark {
            let label = "all, one point per landmark";
            // Every keypoint, session 41's cap, session 43's with the fallback, and session 45's default.
            let caps = [(usize::MAX, 0), (800, 0), (200, 100), (100, 100)];
            sweeps.push(sweep(store, &described, &camera, observations, &caps, label));
        } else {
            let caps: Vec<(usize, usize)> = CAPS.iter().map(|&c| (c, 0)).collect();
            sweeps.push(sweep(store, &described, &camera, observations, &caps, "all"));
            adds.push(add_keyframes(&dir, &info, &described, &camera, observations));
        }
    }
    // One level per process (see `run_levels`): hand the lines to the parent.
    for (tag, lines) in [("row", rows), ("note", notes), ("sweep", sweeps.concat()), ("add", adds)] {
        for l in lines {
            println!("@{tag} {l}");
        }
    }
}

/// Runs every level in a process of its own (this binary again, with `SCONE_BENCH_LEVEL`), so no level's
/// memory figures are lowered by memory an earlier level freed, then prints the tables.
fn run_levels() {
    let mut targets = vec![10_000usize, 100_000];
    if std::env::var("SCONE_BENCH_SMALL").is_ok() {
        targets = vec![10_000];
    }
    if std::env::var("SCONE_BENCH_1M").is_ok() {
        targets.push(1_000_000);
    }
    let mut tagged: Vec<(String, String)> = Vec::new();
    for target in targets {
        let child = |build_only: bool, per_landmark: bool| {
            let mut c = std::process::Command::new(std::env::current_exe().unwrap());
            c.args(std::env::args().skip(1)).env("SCONE_BENCH_LEVEL", target.to_string());
            if build_only {
                c.env("SCONE_BENCH_BUILD_ONLY", "1");
            }
            if per_landmark {
                c.env(PER_LANDMARK_ENV, "1");
            }
            c.stderr(std::process::Stdio::inherit()).output().unwrap()
        };
        let built = child(true, false);
        let outs = if built.status.success() { vec![child(false, false), child(false, true)] } else { vec![built] };
        for out in outs {
            if !out.status.success() {
                eprintln!("reloc bench: a process of the {target} level failed; the tables below leave it out");
                continue;
            }
            for line in String::from_utf8_lossy(&out.stdout).lines() {
                if let Some((tag, rest)) = line.strip_prefix('@').and_then(|l| l.split_once(' ')) {
                    tagged.push((tag.to_string(), rest.to_string()));
                } else {
                    println!("{line}");
                }
            }
        }
    }
    let of = |tag: &str| tagged.iter().filter(|(t, _)| t == tag).map(|(_, l)| l.clone()).collect::<Vec<_>>();
    let (rows, notes, sweeps, adds) = (of("row"), of("note"), of("sweep"), of("add"));
    println!();
    for n in notes {
        println!("{n}");
    }
    println!();
    println!(
        "| observations | search | decode ms | extract ms | embed ms | search ms | PnP ms | stages 2-3 ms | \
         total p50 ms | localised | within (0.25 m, 2°) | recall@1 / @2 | ready after restart s | RSS KB/obs |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in rows {
        println!("{r}");
    }
    println!();
    println!("Query keypoints searched (the strongest by response), every query of the level, HNSW:");
    println!();
    println!(
        "| observations | query keypoints | queries | localised | within (0.25 m, 2°) | within (0.5 m, 5°) | \
         matches (median) | search ms (median) | stages 2-3 ms (median) | PnP ms (median) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in sweeps {
        println!("{r}");
    }
    println!();
    println!("AddKeyframe on a copy of the level's map: the held-out kitchen frames added as keyframes, in order:");
    println!();
    println!(
        "| observations | keyframes added | plan alone p50 ms | AddKeyframe p50 ms | p90 ms | max ms | observations \
         added (median) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for r in adds {
        println!("{r}");
    }
}

/// A query's features and embeddings with its ground-truth pose.
type Described = (scone::describe::pipeline::Described, Isometry3<f64>);

/// Whether `pose` is within (0.25 m, 2°) and within (0.5 m, 5°) of the ground truth `gt`.
fn is_within(pose: &Isometry3<f64>, gt: &Isometry3<f64>) -> (bool, bool) {
    let te = (pose.translation.vector - gt.translation.vector).norm();
    let re = rotation_error_deg(&pose.rotation.to_rotation_matrix(), &gt.rotation.to_rotation_matrix());
    (te <= 0.25 && re <= 2.0, te <= 0.5 && re <= 5.0)
}

/// Every query's outcome against one map and index.
#[derive(Default)]
struct Scored {
    search_ms: Vec<f64>,
    stages_ms: Vec<f64>,
    pnp_ms: Vec<f64>,
    matches: Vec<f64>,
    localised: usize,
    within: usize,
    within5: usize,
}

/// Localises every described query against `data` with `index` (the service's localisation, called directly).
fn score(
    data: &MapData,
    index: &EmbeddingIndex,
    described: &[Described],
    camera: &Camera,
    params: &LocalizeSettings,
) -> Scored {
    let mut out = Scored::default();
    for (d, gt) in described {
        let l = localize(data, index, &d.features, &d.embeddings, camera, None, params).unwrap();
        out.search_ms.push(l.search_s * 1e3);
        out.stages_ms.push(l.stages_s * 1e3);
        out.pnp_ms.push(l.pnp_s * 1e3);
        out.matches.push(l.matches.len() as f64);
        if let Some(p) = &l.pose {
            let (w, w5) = is_within(&p.camera_to_world, gt);
            out.localised += 1;
            out.within += usize::from(w);
            out.within5 += usize::from(w5);
        }
    }
    out
}

/// Most keyframes [`add_keyframes`] adds to one level's map.
const ADDED_KEYFRAMES: usize = 20;

/// AddKeyframe through the store (plan, check, log append with fsync, apply, index insert) on a copy of the
/// level's map, so the kept map stays as built: the first [`ADDED_KEYFRAMES`] held-out kitchen frames (real
/// frames the map does not hold, posed, no depth, so their landmarks are triangulated) as new keyframes.
fn add_keyframes(
    dir: &Path,
    info: &ModelInfo,
    described: &[Described],
    camera: &Camera,
    observations: usize,
) -> String {
    let copy = dir.with_extension("add-keyframes");
    let _ = std::fs::remove_dir_all(&copy);
    std::fs::create_dir_all(&copy).unwrap();
    let from = dir.join("per-landmark/maps");
    let status = std::process::Command::new("cp").arg("-r").arg(from).arg(&copy).status().unwrap();
    assert!(status.success(), "copying the map for AddKeyframe");
    let store = MapStore::open(config(&copy, per_landmark_settings()), info.clone()).unwrap();
    let first = store.summary("m").unwrap().keyframes as u64;
    let (mut times, mut plans, mut added) = (Vec::new(), Vec::new(), Vec::new());
    for (i, (d, gt)) in described.iter().take(ADDED_KEYFRAMES).enumerate() {
        let input = KeyframeInput {
            id: 1_000_000 + first + i as u64,
            pose: *gt,
            camera: *camera,
            features: &d.features,
            embeddings: &d.embeddings,
            depth: None,
            external: None,
        };
        // The plan alone (matching, triangulation), read-only, then the whole write.
        let t = Instant::now();
        store.get("m").unwrap().read(|data, _| plan(data, &input, &BuildSettings::default()).unwrap());
        plans.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        let a = store.add_keyframe(&store.get("m").unwrap(), &input).unwrap();
        times.push(t.elapsed().as_secs_f64() * 1e3);
        added.push(a.observations as f64);
    }
    drop(store);
    let _ = std::fs::remove_dir_all(&copy);
    let n = times.len();
    let mut sorted = times.clone();
    sorted.sort_by(f64::total_cmp);
    format!(
        "| {observations} | {n} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} |",
        median(plans),
        median(times),
        sorted[(n * 9 / 10).min(n - 1)],
        sorted[n - 1],
        median(added)
    )
}

/// Label of the row of one index point per observation (before issue 31)...
const PER_OBSERVATION: &str = "HNSW, one point per observation";
/// ...and of one point per landmark (the default since) with stage 1 as the service's default (since session
/// 45: the strongest 100 query keypoints searched, every keypoint below 100 inliers), ...
const PER_LANDMARK: &str = "HNSW, one point per landmark";
/// ...the same with every query keypoint searched (the default before session 45), ...
const PER_LANDMARK_EVERY: &str = "HNSW, one point per landmark, every query keypoint searched";
/// The default row with PnP by EPnP's RANSAC instead of USAC (the relocalisation default before USAC), on the
/// same map in the same process: what the estimator costs or saves per query.
const PER_LANDMARK_EPNP: &str = "HNSW, one point per landmark, EPnP's RANSAC";
/// ...measured in a child process with this variable set.
const PER_LANDMARK_ENV: &str = "SCONE_BENCH_PER_LANDMARK";

/// Query keypoint caps measured on one map: `usize::MAX` is every keypoint.
const CAPS: [usize; 6] = [usize::MAX, 1000, 800, 600, 400, 250];

/// Search and PnP of every query with each (cap, `full_search_below_inliers`) of `caps` (the service's
/// localisation, called on the map directly so one opened map serves every cap).
fn sweep(
    store: &MapStore,
    described: &[Described],
    camera: &Camera,
    observations: usize,
    caps: &[(usize, usize)],
    all: &str,
) -> Vec<String> {
    let map = store.get("m").unwrap();
    let mut rows = Vec::new();
    for &(cap, fallback) in caps {
        let params = LocalizeSettings {
            max_query_keypoints: cap,
            full_search_below_inliers: fallback,
            ..LocalizeSettings::default()
        };
        let Scored { search_ms, stages_ms, pnp_ms, matches, localised, within, within5 } =
            map.read(|data, index| score(data, index, described, camera, &params));
        let n = described.len();
        rows.push(format!(
            "| {observations} | {} | {n} | {localised} | {within} | {within5} | {:.0} | {:.1} | {:.1} | {:.1} |",
            match (cap, fallback) {
                (usize::MAX, _) => all.to_string(),
                (_, 0) => cap.to_string(),
                _ => format!("{cap}, all below {fallback} inliers"),
            },
            median(matches),
            median(search_ms),
            median(stages_ms),
            median(pnp_ms),
        ));
    }
    rows
}
