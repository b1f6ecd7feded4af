use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, Parser, Subcommand};

use scone::constellation::{self, DEFAULT_K};
use scone::decode::{decode_grey, ImageLimits};
use scone::embedding::{Embedder, EmbedderConfig};
use scone::features::{self, ExtractorConfig};
use scone::map::builder::{BuildParams, Depth, KeyframeInput};
use scone::map::store::{MapStore, ModelInfo, StoreConfig};
use scone::offline::eval::methods::Method;
use scone::offline::eval::pairs::{self, PairsConfig};
use scone::offline::scene::Scene;
use scone::pipeline::Describer;

#[derive(Parser)]
#[command(name = "scone", version, about = "SConE image matching and relocalisation")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the gRPC + HTTP service (settings: defaults, then --config / SCONE_CONFIG, then SCONE_<SECTION>__<KEY>
    /// environment variables, then these flags).
    Serve {
        /// TOML settings file.
        #[arg(long, env = "SCONE_CONFIG")]
        config: Option<PathBuf>,
        /// gRPC listen address.
        #[arg(long)]
        grpc_addr: Option<std::net::SocketAddr>,
        /// HTTP listen address.
        #[arg(long)]
        http_addr: Option<std::net::SocketAddr>,
        /// Directory of the maps.
        #[arg(long)]
        data_dir: Option<PathBuf>,
        /// SConE ONNX model.
        #[arg(long)]
        model: Option<PathBuf>,
        /// Print the effective settings (without keys) as JSON and exit.
        #[arg(long)]
        print_settings: bool,
    },
    /// Extract FAST + FREAK features and constellations from one image and print a summary as JSON.
    Extract {
        /// PNG or JPEG file.
        image: PathBuf,
        /// Also write the features and constellations to this .npz (the export layout, one frame).
        #[arg(long)]
        out: Option<PathBuf>,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
    /// Evaluate on a real scene (the paper's protocol).
    #[command(subcommand)]
    Eval(EvalCommand),
    /// Maps on disk, through the same store the service uses.
    #[command(subcommand)]
    Map(MapCommand),
    /// Export a scene's features and constellations to an .npz file for training.
    Features {
        /// Scene directory in the TUM RGB-D layout.
        #[arg(long)]
        scene: PathBuf,
        /// Output .npz file.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
}

#[derive(Subcommand)]
enum MapCommand {
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
        #[arg(long, default_value_t = BuildParams::default().external_radius_px)]
        radius_px: f64,
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

#[derive(Subcommand)]
enum EvalCommand {
    /// Relative pose between the first frame of each window and every later frame, per method.
    Pairs {
        /// Scene directory in the TUM RGB-D layout.
        #[arg(long)]
        scene: PathBuf,
        /// Methods to compare.
        #[arg(long, value_delimiter = ',', default_value = "scone,freak,freak-gms,orb,sift")]
        methods: Vec<Method>,
        /// Frames per window; the first is the reference.
        #[arg(long, default_value_t = 100)]
        window: usize,
        /// RANSAC seeds to average over.
        #[arg(long, default_value_t = 5)]
        seeds: u64,
        /// Ratio-test threshold.
        #[arg(long, default_value_t = 0.8)]
        ratio: f32,
        /// Keep only mutual nearest neighbours.
        #[arg(long)]
        mutual: bool,
        /// Ratio test: candidates within this many pixels of the nearest neighbour's keypoint are the same
        /// corner, not competitors (0 = OpenCV's plain test). Default 2, or 0 with --single-scale.
        #[arg(long)]
        same_corner_px: Option<f32>,
        /// How the scone method picks its matches (scone-plain is always the plain embedding).
        #[arg(long, value_enum, default_value_t = scone::matching::SconeMatcher::default())]
        scone_matcher: scone::matching::SconeMatcher,
        /// RANSAC inlier threshold in pixels.
        #[arg(long, default_value_t = 1.0)]
        ransac_px: f64,
        /// RANSAC iteration cap. Default 10,000, or OpenCV's 1,000 with --single-scale.
        #[arg(long)]
        ransac_iters: Option<i32>,
        /// RANSAC confidence: the search stops once it is this sure that no better model is left to find.
        /// Default 0.9999, or OpenCV's 0.999 with --single-scale.
        #[arg(long)]
        ransac_confidence: Option<f64>,
        /// Leave out of the essential-matrix estimation correspondences within this many pixels of an earlier
        /// one in both images (0 = off).
        #[arg(long)]
        duplicate_px: Option<f64>,
        /// Essential-matrix estimator. Default usac-accurate, or ransac with --single-scale.
        #[arg(long, value_enum)]
        essential: Option<scone::pose::EssentialMethod>,
        /// Match precision: a match with depth at the reference keypoint is correct within this many pixels.
        #[arg(long, default_value_t = 4.0)]
        depth_px: f64,
        /// Match precision without depth: symmetric epipolar distance threshold in pixels.
        #[arg(long, default_value_t = 2.0)]
        epipolar_px: f64,
        /// Also score apart the pairs whose ground-truth baseline is under this (scene units), by rotation
        /// alone (0 = off).
        #[arg(long, default_value_t = 0.0)]
        short_baseline: f64,
        /// Use OpenCV's single-scale FAST (threshold 20, 2,000 strongest), as the data README's baselines.
        #[arg(long)]
        single_scale: bool,
        #[command(flatten)]
        report: ReportArgs,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
    /// Relocalisation: build a map from every S-th frame (ground-truth poses, depth when present), localise the rest.
    Reloc {
        /// Scene directory in the TUM RGB-D layout.
        #[arg(long)]
        scene: PathBuf,
        /// Methods to compare (scone, freak, sift).
        #[arg(long, value_delimiter = ',', default_value = "scone,freak,sift")]
        methods: Vec<Method>,
        /// Every S-th frame goes into the map.
        #[arg(long, default_value_t = 3)]
        map_stride: usize,
        #[command(flatten)]
        report: ReportArgs,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
}

/// Model and output of an evaluation.
#[derive(Args, Clone)]
struct ReportArgs {
    /// SConE model (default: the committed one).
    #[arg(long)]
    model: Option<PathBuf>,
    /// Write the full report (every pair or query) as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// ONNX Runtime intra-op threads for the SConE embedding (with --opencv-threads 1, the evaluation keeps
    /// to one core, e.g. beside a training run).
    #[arg(long, default_value_t = 2)]
    embed_threads: usize,
}

impl ReportArgs {
    fn write_json(&self, report: &impl serde::Serialize) -> anyhow::Result<()> {
        if let Some(path) = &self.json {
            std::fs::write(path, serde_json::to_vec_pretty(report)?)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        Ok(())
    }
}

/// Extraction settings on the command line; unset flags keep [`ExtractorConfig::default`].
#[derive(Args, Clone)]
struct ExtractorArgs {
    /// FAST threshold.
    #[arg(long)]
    fast_threshold: Option<i32>,
    /// Keypoints kept at most.
    #[arg(long)]
    max_keypoints: Option<usize>,
    /// Pyramid levels (1 = single-scale FAST, as in the paper).
    #[arg(long)]
    levels: Option<u32>,
    /// Downscale factor between pyramid levels.
    #[arg(long)]
    scale_factor: Option<f64>,
    /// Grid cell size for bucketing in pixels (0 = off).
    #[arg(long)]
    grid_cell: Option<u32>,
    /// Constellation size.
    #[arg(long, default_value_t = DEFAULT_K)]
    k: usize,
    /// OpenCV threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    opencv_threads: usize,
}

impl ExtractorArgs {
    fn config(&self) -> anyhow::Result<ExtractorConfig> {
        let d = ExtractorConfig::default();
        let cfg = ExtractorConfig {
            fast_threshold: self.fast_threshold.unwrap_or(d.fast_threshold),
            max_keypoints: self.max_keypoints.unwrap_or(d.max_keypoints),
            levels: self.levels.unwrap_or(d.levels),
            scale_factor: self.scale_factor.unwrap_or(d.scale_factor),
            grid_cell: self.grid_cell.unwrap_or(d.grid_cell),
        };
        cfg.validate()?;
        anyhow::ensure!(self.k >= 1 && self.k <= 64, "--k must be in 1..=64");
        features::set_opencv_threads(self.opencv_threads)?;
        Ok(cfg)
    }
}

fn load_embedder(needed: bool, report: &ReportArgs) -> anyhow::Result<Option<Embedder>> {
    if !needed {
        return Ok(None);
    }
    let mut ec = EmbedderConfig { intra_threads: report.embed_threads.max(1), ..EmbedderConfig::default() };
    if let Some(m) = report.model.clone() {
        ec.model = m;
    }
    Ok(Some(Embedder::load(&ec)?))
}

fn open_store(data_dir: PathBuf, model: Option<PathBuf>) -> anyhow::Result<(MapStore, Describer)> {
    open_store_with(StoreConfig { data_dir, ..StoreConfig::default() }, model)
}

fn open_store_with(config: StoreConfig, model: Option<PathBuf>) -> anyhow::Result<(MapStore, Describer)> {
    let report = ReportArgs { model, json: None, embed_threads: EmbedderConfig::default().intra_threads };
    let embedder = std::sync::Arc::new(load_embedder(true, &report)?.expect("requested"));
    let info = ModelInfo { model_id: embedder.model_id().to_string(), k: embedder.k(), dim: embedder.dim() };
    let store = MapStore::open(config, info)?;
    let describer = Describer { extractor: ExtractorConfig::default(), limits: ImageLimits::default(), embedder };
    Ok((store, describer))
}

fn run_map(cmd: MapCommand) -> anyhow::Result<()> {
    use std::io::Write;
    match cmd {
        MapCommand::WriteScene { data_dir, map, scene, stride, repeat, model } => {
            let (store, describer) = open_store(data_dir, model)?;
            if store.get(&map).is_err() {
                store.create(&map)?;
            }
            let s = Scene::load(&scene)?;
            let limits = ImageLimits::default();
            let mut stdout = std::io::stdout().lock();
            let mut next_id = store.summary(&map)?.keyframes as u64;
            for _ in 0..repeat.max(1) {
                for (i, frame) in s.frames.iter().enumerate().filter(|(i, _)| i % stride.max(1) == 0) {
                    let Some(pose) = frame.pose else { continue };
                    let d = describer.describe_image(&std::fs::read(&frame.rgb)?)?;
                    let depth = match &frame.depth {
                        Some(p) => Some(scone::decode::decode_depth_png(&std::fs::read(p)?, &limits)?),
                        None => None,
                    };
                    let input = KeyframeInput {
                        id: next_id,
                        pose,
                        camera: s.camera,
                        features: &d.features,
                        embeddings: &d.embeddings,
                        depth: depth.as_ref().map(|m| Depth { image: m, scale: 1.0 / 5000.0 }),
                        external: None,
                    };
                    let added = store.add_keyframe(&map, &input)?;
                    writeln!(stdout, "ack {} frame {i} landmarks {}", added.keyframe, added.new_landmarks)?;
                    stdout.flush()?;
                    next_id += 1;
                }
            }
            // A clean exit snapshots the map and dumps its index, as the service does at shutdown.
            store.flush()?;
        }
        MapCommand::ImportColmap { data_dir, map, model_dir, images, radius_px, model } => {
            let build = BuildParams { external_radius_px: radius_px, ..BuildParams::default() };
            build.validate().map_err(|e| anyhow::anyhow!("--radius-px: {e}"))?;
            let colmap = scone::offline::colmap::ColmapModel::read(&model_dir)?;
            let (store, describer) = open_store_with(StoreConfig { data_dir, build, ..StoreConfig::default() }, model)?;
            let mut stdout = std::io::stdout().lock();
            let mut failed: Option<std::io::Error> = None;
            let summary = scone::offline::colmap::import(&store, &describer, &map, &colmap, &images, &mut |i| {
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
            store.flush()?;
        }
        MapCommand::Info { data_dir, model } => {
            let (store, _) = open_store(data_dir, model)?;
            let held: Vec<_> =
                store.held_back().into_iter().map(|(m, r)| serde_json::json!({"map": m, "reason": r})).collect();
            println!(
                "{}",
                serde_json::to_string_pretty(&serde_json::json!({"maps": store.list(), "held_back": held}))?
            );
        }
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    match cli.command {
        Command::Serve { config, grpc_addr, http_addr, data_dir, model, print_settings } => {
            let overrides = scone::settings::Overrides { grpc_addr, http_addr, data_dir, model };
            let settings = scone::settings::Settings::load(config.as_deref(), &overrides)?;
            if print_settings {
                println!("{}", serde_json::to_string_pretty(&settings.redacted())?);
                return Ok(());
            }
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .thread_name("scone-io")
                .enable_all()
                .build()?;
            runtime.block_on(scone::server::run(settings))?;
        }
        Command::Extract { image, out, extractor } => {
            let cfg = extractor.config()?;
            let bytes = std::fs::read(&image).with_context(|| format!("reading {}", image.display()))?;
            let t0 = std::time::Instant::now();
            let grey = decode_grey(&bytes, &ImageLimits::default())?;
            let f = features::extract(&grey, &cfg)?;
            let c = constellation::build(&f.keypoints, extractor.k);
            let ms = t0.elapsed().as_secs_f64() * 1e3;
            let per_level = (0..cfg.levels as i32)
                .map(|l| f.keypoints.iter().filter(|k| k.octave == l).count())
                .collect::<Vec<_>>();
            let summary = serde_json::json!({
                "image": image,
                "width": f.width,
                "height": f.height,
                "keypoints": f.len(),
                "keypoints_per_level": per_level,
                "constellations": c.len(),
                "k": c.k,
                "milliseconds": (ms * 10.0).round() / 10.0,
                "extractor": cfg,
            });
            println!("{}", serde_json::to_string_pretty(&summary)?);
            if let Some(out) = out {
                let name = image.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                scone::offline::training_features::export_image(&name, &f, &c, &cfg, &out)?;
            }
        }
        Command::Eval(EvalCommand::Pairs {
            scene,
            methods,
            window,
            seeds,
            ratio,
            mutual,
            same_corner_px,
            scone_matcher,
            ransac_px,
            ransac_iters,
            ransac_confidence,
            duplicate_px,
            essential,
            depth_px,
            epipolar_px,
            short_baseline,
            single_scale,
            report: out,
            extractor,
        }) => {
            // --single-scale is OpenCV's own pipeline, plain ratio test and plain RANSAC (with OpenCV's
            // iteration cap and confidence) included.
            let base = if single_scale {
                scone::pose::RansacParams::opencv(ransac_px)
            } else {
                scone::pose::RansacParams { threshold_px: ransac_px, ..Default::default() }
            };
            let ransac = scone::pose::RansacParams {
                essential: essential.unwrap_or(base.essential),
                max_iters: ransac_iters.unwrap_or(base.max_iters),
                confidence: ransac_confidence.unwrap_or(base.confidence),
                duplicate_px: duplicate_px.unwrap_or(base.duplicate_px),
                ..base
            };
            let same_corner_px =
                same_corner_px.unwrap_or(if single_scale { 0.0 } else { scone::matching::SAME_CORNER_PX });
            anyhow::ensure!(
                same_corner_px.is_finite() && same_corner_px >= 0.0,
                "--same-corner-px must be a finite number >= 0"
            );
            ransac.validate().map_err(|e| {
                anyhow::anyhow!("--ransac-px / --ransac-iters / --ransac-confidence / --duplicate-px: {e}")
            })?;
            let mut cfg = extractor.config()?;
            if single_scale {
                cfg = ExtractorConfig::single_scale(20, 2000);
            }
            let s = Scene::load(&scene)?;
            let embedder =
                load_embedder(methods.iter().any(|m| matches!(m, Method::Scone | Method::SconePlain)), &out)?;
            let pc = PairsConfig {
                methods,
                window,
                seeds,
                ratio,
                mutual,
                same_corner_px,
                scone_matcher,
                ransac,
                extractor: cfg,
                depth_px,
                epipolar_px,
                short_baseline,
            };
            let report = pairs::evaluate(&s, &pc, embedder.as_ref()).map_err(|e| anyhow::anyhow!("{e}"))?;
            print!("{}", pairs::markdown(&report));
            out.write_json(&report)?;
        }
        Command::Eval(EvalCommand::Reloc { scene, methods, map_stride, report: out, extractor }) => {
            let cfg = extractor.config()?;
            for m in &methods {
                anyhow::ensure!(
                    matches!(m, Method::Scone | Method::Freak | Method::Sift),
                    "eval reloc compares scone, freak and sift"
                );
            }
            let s = Scene::load(&scene)?;
            let embedder = load_embedder(methods.contains(&Method::Scone), &out)?;
            let rc = scone::offline::eval::reloc::RelocConfig {
                methods,
                stride: map_stride,
                extractor: cfg,
                ..Default::default()
            };
            let report = scone::offline::eval::reloc::evaluate(&s, &rc, embedder.as_ref())
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            print!("{}", scone::offline::eval::reloc::markdown(&report));
            out.write_json(&report)?;
        }
        Command::Map(cmd) => run_map(cmd)?,
        Command::Features { scene, out, extractor } => {
            let cfg = extractor.config()?;
            let s = Scene::load(&scene)?;
            let summary =
                scone::offline::training_features::export_scene(&s, &cfg, extractor.k, &ImageLimits::default(), &out)?;
            println!("{}", serde_json::to_string_pretty(&summary)?);
        }
    }
    Ok(())
}
