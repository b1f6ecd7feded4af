//! `scone map ...`: maps on disk, through the same store the service uses.

use std::cell::RefCell;
use std::path::PathBuf;

use clap::Subcommand;

use scone::describe::decode::ImageLimitSettings;
use scone::describe::pipeline::{embed, Describer};
use scone::map::builder::{BuildSettings, Depth, KeyframeInput};
use scone::map::store::{MapStore, ModelInfo, StoreSettings};
use scone::offline::progress::Progress;
use scone::offline::scene::Scene;

use crate::args::{load_embedder, ReportArgs};

#[derive(Subcommand)]
pub enum MapCommand {
    /// Write a scene's frames as keyframes (ground-truth poses, depth when present) into a map, printing
    /// "ack <keyframe>" once each write is durable.
    WriteScene {
        #[arg(long)]
        data_dir: PathBuf,
        #[arg(long)]
        map: String,
        #[arg(long)]
        scene: PathBuf,
        /// Every S-th frame.
        #[arg(long, default_value_t = 1)]
        stride: usize,
        /// Write the scene this many times (keyframe ids continue), for long write streams.
        #[arg(long, default_value_t = 1)]
        repeat: usize,
        #[arg(long)]
        model: Option<PathBuf>,
    },
    /// Import a COLMAP text model (cameras.txt with PINHOLE / SIMPLE_PINHOLE cameras, images.txt,
    /// points3D.txt) into a map: each image becomes a keyframe (id = IMAGE_ID) whose landmarks are its
    /// POINTS2D with a 3D point, one landmark per POINT3D_ID. Prints "ack <keyframe> ..." once each write is
    /// durable, then a JSON summary. Images the map has already are skipped, so a re-run resumes.
    ImportColmap {
        #[arg(long)]
        data_dir: PathBuf,
        #[arg(long)]
        map: String,
        /// Directory of the text model (COLMAP's `sparse/0` after `colmap model_converter --output_type TXT`).
        #[arg(long)]
        model_dir: PathBuf,
        /// Directory the images.txt NAMEs are relative to.
        #[arg(long)]
        images: PathBuf,
        /// An observation takes the nearest keypoint within this many pixels.
        #[arg(long, default_value_t = BuildSettings::default().external_radius_px)]
        radius_px: f64,
        #[arg(long)]
        model: Option<PathBuf>,
    },
    /// Merge map SOURCE into map TARGET (as the MergeMaps RPC: the transform estimated from the source
    /// keyframes localised in the target), printing "merged <target keyframes>" once the merge is durable.
    Merge {
        #[arg(long)]
        data_dir: PathBuf,
        #[arg(long)]
        target: String,
        #[arg(long)]
        source: String,
        #[arg(long)]
        model: Option<PathBuf>,
    },
    /// Re-embed every keyframe of map MAP with the current model, from the keypoints and FREAK descriptors it
    /// stores: after a model upgrade, a map made by the earlier model answers queries again. Prints the map's
    /// summary as JSON once the re-embedding is durable.
    Reembed {
        #[arg(long)]
        data_dir: PathBuf,
        #[arg(long)]
        map: String,
        #[arg(long)]
        model: Option<PathBuf>,
    },
    /// Print the maps of a data directory as JSON (and any held back with the reason).
    Info {
        #[arg(long)]
        data_dir: PathBuf,
        #[arg(long)]
        model: Option<PathBuf>,
    },
}

fn open_store(data_dir: PathBuf, model: Option<PathBuf>) -> anyhow::Result<(MapStore, Describer)> {
    open_store_with(StoreSettings { data_dir, ..StoreSettings::default() }, model)
}

fn open_store_with(config: StoreSettings, model: Option<PathBuf>) -> anyhow::Result<(MapStore, Describer)> {
    let report = ReportArgs { model, json: None, embed_threads: 2 };
    let embedder = std::sync::Arc::new(load_embedder(true, &report)?.expect("requested"));
    let info = ModelInfo { model_id: embedder.model_id().to_string(), k: embedder.k(), dim: embedder.dim() };
    let store = MapStore::open(config, info)?;
    let describer = Describer { extractor: embedder.extraction(), limits: ImageLimitSettings::default(), embedder };
    Ok((store, describer))
}

pub fn run(cmd: MapCommand) -> anyhow::Result<()> {
    use std::io::Write;
    match cmd {
        MapCommand::WriteScene { data_dir, map, scene, stride, repeat, model } => {
            let (store, describer) = open_store(data_dir, model)?;
            if store.get(&map).is_err() {
                store.create(&map)?;
            }
            let held = store.get(&map)?;
            let s = Scene::load(&scene)?;
            let limits = ImageLimitSettings::default();
            let mut stdout = std::io::stdout().lock();
            let mut next_id = held.summary().keyframes as u64;
            let per_pass = s.frames.iter().step_by(stride.max(1)).filter(|f| f.pose.is_some()).count();
            let mut progress = Progress::new(format!("write-scene {map}"), per_pass * repeat.max(1));
            for _ in 0..repeat.max(1) {
                for (i, frame) in s.frames.iter().enumerate().filter(|(i, _)| i % stride.max(1) == 0) {
                    let Some(pose) = frame.pose else { continue };
                    progress.step();
                    let d = describer.describe_image(&std::fs::read(&frame.rgb)?)?;
                    let depth = match &frame.depth {
                        Some(p) => Some(scone::describe::decode::decode_depth_png(&std::fs::read(p)?, &limits)?),
                        None => None,
                    };
                    let input = KeyframeInput {
                        id: next_id,
                        pose,
                        camera: s.camera,
                        features: &d.features,
                        embeddings: &d.embeddings,
                        depth: depth
                            .as_ref()
                            .map(|m| Depth { image: m, scale: scone::describe::decode::TUM_DEPTH_SCALE }),
                        external: None,
                    };
                    let added = store.add_keyframe(&held, &input)?;
                    writeln!(stdout, "ack {} frame {i} landmarks {}", added.keyframe, added.new_landmarks)?;
                    stdout.flush()?;
                    next_id += 1;
                }
            }
            // A clean exit snapshots the map and dumps its index, as the service does at shutdown.
            flush(&store)?;
        }
        MapCommand::ImportColmap { data_dir, map, model_dir, images, radius_px, model } => {
            let build = BuildSettings { external_radius_px: radius_px, ..BuildSettings::default() };
            build.validate().map_err(|e| anyhow::anyhow!("--radius-px: {e}"))?;
            let colmap = scone::offline::colmap::ColmapModel::read(&model_dir)?;
            let (store, describer) =
                open_store_with(StoreSettings { data_dir, build, ..StoreSettings::default() }, model)?;
            let mut stdout = std::io::stdout().lock();
            let mut failed: Option<std::io::Error> = None;
            let mut progress = Progress::new(format!("import-colmap {map}"), colmap.images.len());
            let summary = scone::offline::colmap::import(&store, &describer, &map, &colmap, &images, &mut |i| {
                progress.step();
                let line = match &i.added {
                    Some(a) => format!(
                        "ack {} image {} landmarks {} observations {} rejected {} unassociated {}",
                        a.keyframe,
                        i.name,
                        a.new_landmarks,
                        a.observations,
                        a.external.rejected,
                        a.external.unassociated
                    ),
                    None => format!("skip {} image {} (in the map already)", i.image_id, i.name),
                };
                if let Err(e) = writeln!(stdout, "{line}").and_then(|_| stdout.flush()) {
                    failed.get_or_insert(e);
                }
            })?;
            if let Some(e) = failed {
                return Err(e.into());
            }
            writeln!(stdout, "{}", serde_json::to_string_pretty(&summary)?)?;
            flush(&store)?;
        }
        MapCommand::Merge { data_dir, target, source, model } => {
            let (store, _) = open_store(data_dir, model)?;
            let into = store.get(&target)?;
            let (plan, summary) = store.merge(&into, &source, None)?;
            let mut stdout = std::io::stdout().lock();
            writeln!(stdout, "merged {}", summary.keyframes)?;
            stdout.flush()?;
            eprintln!(
                "{} of {} source keyframes localised, {} agree; {} landmarks fused, {} added",
                plan.localised, plan.source_keyframes, plan.inliers, plan.landmarks_fused, plan.landmarks_added
            );
            flush(&store)?;
        }
        MapCommand::Reembed { data_dir, map, model } => {
            let (store, describer) = open_store(data_dir, model)?;
            let e = &describer.embedder;
            anyhow::ensure!(
                !e.needs_context(),
                "model {} ({}) reads each keypoint's ring context, which keyframes do not store, so map '{map}' \
                 cannot be re-embedded for it: build the map again from its images (scone map write-scene, or \
                 AddKeyframes), or serve the model the map was built with (--model / SCONE_MODEL__MODEL; the \
                 constellation model is models/scone-freak-k20.onnx)",
                e.model_id(),
                e.path().display()
            );
            let progress = RefCell::new(Progress::new(format!("reembed {map}"), store.summary(&map)?.keyframes));
            let summary = store.reembed(&map, &|keyframe| {
                progress.borrow_mut().step();
                Ok(embed(&describer.embedder, &keyframe.features()?)?)
            })?;
            drop(progress);
            println!("{}", serde_json::to_string_pretty(&summary)?);
            flush(&store)?;
        }
        MapCommand::Info { data_dir, model } => {
            let (store, _) = open_store(data_dir, model)?;
            let held: Vec<_> =
                store.held_back().into_iter().map(|(m, r)| serde_json::json!({"map": m, "reason": r})).collect();
            println!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({"maps": store.list()?, "held_back": held}))?
            );
        }
    }
    Ok(())
}

/// Snapshots the maps at the end of a command; one that could not be snapshotted fails the command (its
/// acknowledged writes are in its log all the same).
fn flush(store: &MapStore) -> anyhow::Result<()> {
    match store.flush().into_iter().next() {
        None => Ok(()),
        Some((map, e)) => {
            Err(anyhow::anyhow!("map {map} was not snapshotted ({e}); its log holds every acknowledged write"))
        }
    }
}
