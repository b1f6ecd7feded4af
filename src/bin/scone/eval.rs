//! `scone eval ...`: the evaluation protocol on real scenes.

use std::path::PathBuf;

use clap::Subcommand;

use scone::describe::features::ExtractorSettings;
use scone::offline::eval::homography;
use scone::offline::eval::methods::Method;
use scone::offline::eval::pairs::{self, PairsConfig};
use scone::offline::eval::reloc;
use scone::offline::scene::Scene;

use crate::args::{load_embedder, ExtractorArgs, ReportArgs};

#[derive(Subcommand)]
pub enum EvalCommand {
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
        /// Ratio-test threshold, in (0, 1].
        #[arg(long, default_value_t = scone::matching::DEFAULT_RATIO, value_parser = ratio_arg)]
        ratio: f32,
        /// Keep only mutual nearest neighbours.
        #[arg(long)]
        mutual: bool,
        /// Ratio test: candidates within this many pixels of the nearest neighbour's keypoint are the same
        /// corner, not competitors (0 = OpenCV's plain test). Default 2, or 0 with --single-scale.
        #[arg(long)]
        same_corner_px: Option<f32>,
        /// How the scone method picks its matches (scone-plain is always the plain embedding). Default: the
        /// model's declared matcher, as MatchPair (union for the embedded model).
        #[arg(long, value_enum)]
        scone_matcher: Option<scone::matching::SconeMatcher>,
        /// The embedding's own ratio-test threshold in the fused matchers (union, both); FREAK's part there
        /// keeps --ratio. Default: --ratio.
        #[arg(long, value_parser = ratio_arg)]
        scone_ratio: Option<f32>,
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
        /// Methods to compare (scone, freak, sift; dog-freak and fast-sift swap their detectors and descriptors).
        #[arg(long, value_delimiter = ',', default_value = "scone,freak,sift")]
        methods: Vec<Method>,
        /// Every S-th frame goes into the map.
        #[arg(long, default_value_t = 3)]
        map_stride: usize,
        /// Instead: the map is the contiguous block A:B of the posed frames (fractions, e.g. 0:0.5), the queries
        /// all the others (far from the map), binned by their viewing angle to it.
        #[arg(long, value_parser = parse_block)]
        map_block: Option<(f64, f64)>,
        /// Scenes whose keyframes are added to the map as distractors (moved far away in space).
        #[arg(long, value_delimiter = ',')]
        distractors: Vec<PathBuf>,
        /// Distractor observations to add (0: none).
        #[arg(long, default_value_t = 0)]
        distractor_observations: usize,
        /// Every N-th frame of the distractor scenes.
        #[arg(long, default_value_t = 5)]
        distractor_stride: usize,
        /// Multiplies the success thresholds (for scenes whose units are not metres).
        #[arg(long, default_value_t = 1.0)]
        unit_scale: f64,
        /// Localise without the queries' focal length (estimated with the pose).
        #[arg(long)]
        unknown_focal: bool,
        /// With --unknown-focal: the principal point is the image centre, not the scene's.
        #[arg(long)]
        centre_principal_point: bool,
        /// Multiplies the pose covariance (default: the service's `store.localize.covariance_scale`).
        #[arg(long)]
        covariance_scale: Option<f64>,
        /// Stage 1 searches only this many query keypoints, the strongest (default: the service's
        /// `store.localize.max_query_keypoints`).
        #[arg(long)]
        max_query_keypoints: Option<usize>,
        /// With stage 1 capped, a query whose pose has fewer inliers than this is searched again with every
        /// keypoint (default: the service's `store.localize.full_search_below_inliers`).
        #[arg(long)]
        full_search_below_inliers: Option<usize>,
        /// Also localise every query with stage 1 capped at each of these keypoint counts, on the same map
        /// (one graph), with the same fallback; each is a row of its own.
        #[arg(long, value_delimiter = ',')]
        also_caps: Vec<usize>,
        /// Exactly these parts of the staged pipeline on (`none`: stage 1 as the service runs it, and map
        /// building without the known poses); without the flag, the service's defaults.
        #[arg(long, value_delimiter = ',')]
        stages: Option<Vec<StageArg>>,
        /// Frames of other scenes localised against the map (each pose is a false one).
        #[arg(long, value_delimiter = ',')]
        foreign: Vec<PathBuf>,
        /// Every N-th frame of the foreign scenes.
        #[arg(long, default_value_t = 5)]
        foreign_stride: usize,
        /// What the index's graph holds once distractors make the map large (`store.index.points`; the
        /// service's default).
        #[arg(long, value_enum, default_value = "landmarks")]
        index_points: scone::map::index::IndexPoints,
        /// Tracks of N frames instead of single frames: each query with its N - 1 nearest query frames, their
        /// relative poses from the ground truth with a tracker's error (LocalizeTrack, rigid); 0 or 1: single frames.
        #[arg(long, default_value_t = 0)]
        track: usize,
        /// The tracker's translation error, as a share of each frame's distance from the query.
        #[arg(long, default_value_t = 0.01)]
        track_translation_share: f64,
        /// The tracker's rotation error per frame of the track, degrees.
        #[arg(long, default_value_t = 0.5)]
        track_degrees_per_frame: f64,
        /// The PnP estimator (default: the service's `store.localize.ransac.pnp`).
        #[arg(long, value_enum)]
        pnp: Option<scone::pose::PnpMethod>,
        /// PnP's iteration cap (default: the service's `store.localize.ransac.max_iters`).
        #[arg(long)]
        pnp_iters: Option<i32>,
        /// Inliers a pose needs (default: the service's `store.localize.min_inliers`).
        #[arg(long)]
        min_inliers: Option<usize>,
        /// Also localise every query with each of these PnP estimators on the same map, each a row of its own
        /// (METHOD:ITERS, e.g. p3p:2000,usac-magsac:2000).
        #[arg(long, value_delimiter = ',')]
        also_pnp: Vec<reloc::PnpVariant>,
        /// Write each single-frame query's matches (correct or not) and where it was lost to this folder, one
        /// JSON file per method and query, for pictures.
        #[arg(long)]
        dump_matches: Option<PathBuf>,
        #[command(flatten)]
        report: ReportArgs,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
    /// Matching under exact homographies (HPatches layout: 1.png..N.png and H_1_k): corner error of a
    /// MAGSAC++ homography, mean matching accuracy and correct matches per method, binned by zoom and rotation.
    Homography {
        /// Sequence folders, or folders of sequences.
        #[arg(long, value_delimiter = ',', required = true)]
        data: Vec<PathBuf>,
        /// Methods to compare.
        #[arg(long, value_delimiter = ',', default_value = "scone,scone-plain,freak,orb,sift")]
        methods: Vec<Method>,
        /// Ratio-test threshold, in (0, 1].
        #[arg(long, default_value_t = scone::matching::DEFAULT_RATIO, value_parser = ratio_arg)]
        ratio: f32,
        /// Ratio test's same-corner radius in pixels (0 = OpenCV's plain test).
        #[arg(long, default_value_t = scone::matching::SAME_CORNER_PX)]
        same_corner_px: f32,
        /// How the scone method picks its matches (scone-plain is always the plain embedding). Default: the
        /// model's declared matcher, as MatchPair (union for the embedded model).
        #[arg(long, value_enum)]
        scone_matcher: Option<scone::matching::SconeMatcher>,
        /// The embedding's own ratio-test threshold in the fused matchers (union, both); FREAK's part there
        /// keeps --ratio. Default: --ratio.
        #[arg(long, value_parser = ratio_arg)]
        scone_ratio: Option<f32>,
        /// MAGSAC++ inlier threshold of the fitted homography, pixels.
        #[arg(long, default_value_t = 3.0)]
        ransac_px: f64,
        /// A match is correct within this many pixels of the true homography's image.
        #[arg(long, default_value_t = 3.0)]
        correct_px: f64,
        /// Also measure the neighbour share of these constellation rules (the candidates for zoom).
        #[arg(long, value_delimiter = ',', value_enum)]
        neighbour_rules: Vec<scone::describe::constellation::NeighbourRule>,
        #[command(flatten)]
        report: ReportArgs,
        #[command(flatten)]
        extractor: ExtractorArgs,
    },
    /// Map merging: two mapping runs of a scene, each in its own random world frame, merged as MergeMaps
    /// does (transform estimated); the transform's and the merged keyframes' errors against the truth.
    Merge {
        /// Scene directories in the TUM RGB-D layout.
        #[arg(long, value_delimiter = ',')]
        scenes: Vec<PathBuf>,
        /// How the frames are split into the two runs.
        #[arg(long, value_delimiter = ',', default_value = "interleaved,overlap")]
        splits: Vec<scone::offline::eval::merge::Split>,
        /// Seeds of the two world frames (one run per seed).
        #[arg(long, value_delimiter = ',', default_value = "1")]
        seeds: Vec<u64>,
        #[command(flatten)]
        report: ReportArgs,
    },
}

pub fn run(cmd: EvalCommand) -> anyhow::Result<()> {
    match cmd {
        EvalCommand::Pairs {
            scene,
            methods,
            window,
            seeds,
            ratio,
            mutual,
            same_corner_px,
            scone_matcher,
            scone_ratio,
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
        } => {
            // --single-scale is OpenCV's own pipeline, plain ratio test and plain RANSAC (with OpenCV's
            // iteration cap and confidence) included.
            let base = if single_scale {
                scone::pose::RansacSettings::opencv(ransac_px)
            } else {
                scone::pose::RansacSettings { threshold_px: ransac_px, ..Default::default() }
            };
            let ransac = scone::pose::RansacSettings {
                essential: essential.unwrap_or(base.essential),
                max_iters: ransac_iters.unwrap_or(base.max_iters),
                confidence: ransac_confidence.unwrap_or(base.confidence),
                duplicate_px: duplicate_px.unwrap_or(base.duplicate_px),
                ..base
            };
            let same_corner_px =
                same_corner_px.unwrap_or(if single_scale { 0.0 } else { scone::matching::SAME_CORNER_PX });
            check_same_corner(same_corner_px)?;
            ransac.validate().map_err(|e| {
                anyhow::anyhow!("--ransac-px / --ransac-iters / --ransac-confidence / --duplicate-px: {e}")
            })?;
            let embedder =
                load_embedder(methods.iter().any(|m| matches!(m, Method::Scone | Method::SconePlain)), &out)?;
            let mut cfg = extractor.config_for(embedder.as_ref())?;
            if single_scale {
                cfg = ExtractorSettings::single_scale(20, 2000);
            }
            let scone_matcher = matcher_for(scone_matcher, embedder.as_ref())?;
            let s = Scene::load(&scene)?;
            let pc = PairsConfig {
                methods,
                window,
                seeds,
                ratio,
                mutual,
                same_corner_px,
                scone_matcher,
                scone_ratio,
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
        EvalCommand::Homography {
            data,
            methods,
            ratio,
            same_corner_px,
            scone_matcher,
            scone_ratio,
            ransac_px,
            correct_px,
            neighbour_rules,
            report: out,
            extractor,
        } => {
            check_same_corner(same_corner_px)?;
            anyhow::ensure!(ransac_px > 0.0 && correct_px > 0.0, "--ransac-px and --correct-px must be > 0");
            let embedder =
                load_embedder(methods.iter().any(|m| matches!(m, Method::Scone | Method::SconePlain)), &out)?;
            let cfg = homography::HomographyConfig {
                methods,
                ratio,
                same_corner_px,
                scone_matcher: matcher_for(scone_matcher, embedder.as_ref())?,
                scone_ratio,
                ransac_px,
                correct_px,
                k: extractor.k,
                neighbour_rules,
                extractor: extractor.config_for(embedder.as_ref())?,
            };
            let dirs = homography::find_sequences(&data).map_err(|e| anyhow::anyhow!("{e}"))?;
            let report = homography::evaluate(&dirs, &cfg, embedder.as_ref()).map_err(|e| anyhow::anyhow!("{e}"))?;
            print!("{}", homography::markdown(&report));
            out.write_json(&report)?;
        }
        EvalCommand::Reloc {
            scene,
            methods,
            map_stride,
            map_block,
            distractors,
            distractor_observations,
            distractor_stride,
            unit_scale,
            unknown_focal,
            centre_principal_point,
            covariance_scale,
            max_query_keypoints,
            full_search_below_inliers,
            also_caps,
            stages,
            foreign,
            foreign_stride,
            index_points,
            track,
            track_translation_share,
            track_degrees_per_frame,
            pnp,
            pnp_iters,
            min_inliers,
            also_pnp,
            dump_matches,
            report: out,
            extractor,
        } => {
            anyhow::ensure!(unit_scale.is_finite() && unit_scale > 0.0, "--unit-scale must be positive");
            anyhow::ensure!(track <= 10, "--track: a track holds at most 10 frames");
            anyhow::ensure!(also_caps.is_empty() || track < 2, "--also-caps is for single frames, not --track");
            for m in &methods {
                anyhow::ensure!(
                    matches!(m, Method::Scone | Method::Freak | Method::Sift | Method::DogFreak | Method::FastSift),
                    "eval reloc compares scone, freak, sift, dog-freak and fast-sift"
                );
            }
            let embedder = load_embedder(methods.contains(&Method::Scone), &out)?;
            let cfg = extractor.config_for(embedder.as_ref())?;
            let s = Scene::load(&scene)?;
            let mut rc = reloc::RelocConfig {
                methods,
                stride: map_stride,
                extractor: cfg,
                map_block,
                distractors,
                distractor_observations,
                distractor_stride,
                unit_scale,
                unknown_focal,
                centre_principal_point,
                ..Default::default()
            };
            if let Some(c) = covariance_scale {
                rc.localize.covariance_scale = c;
            }
            // The stages first: an explicit cap or fallback applies over them (without stage 2 they search
            // every keypoint unless told otherwise).
            if let Some(stages) = stages {
                let on: Vec<reloc::Stage> = stages.iter().filter_map(|s| s.stage()).collect();
                (rc.build, rc.localize) = reloc::with_stages(rc.build, rc.localize, &on);
            }
            if let Some(k) = max_query_keypoints {
                rc.localize.max_query_keypoints = k;
            }
            if let Some(t) = full_search_below_inliers {
                rc.localize.full_search_below_inliers = t;
            }
            if let Some(p) = pnp {
                rc.localize.ransac.pnp = p;
            }
            if let Some(n) = pnp_iters {
                rc.localize.ransac.max_iters = n;
            }
            if let Some(n) = min_inliers {
                rc.localize.min_inliers = n;
            }
            rc.localize.ransac.validate().map_err(|e| anyhow::anyhow!("--pnp-iters: {e}"))?;
            rc.dump_matches = dump_matches;
            anyhow::ensure!(also_pnp.is_empty() || track < 2, "--also-pnp is for single frames, not --track");
            rc.also_pnp = also_pnp;
            for &k in &also_caps {
                let capped = scone::map::localize::LocalizeSettings { max_query_keypoints: k, ..rc.localize };
                capped.validate().map_err(|e| anyhow::anyhow!("--also-caps {k}: {e}"))?;
            }
            rc.foreign = foreign;
            rc.foreign_stride = foreign_stride;
            rc.also_caps = also_caps;
            rc.index_points = index_points;
            rc.track = track;
            rc.track_noise = reloc::TrackNoise {
                translation_share: track_translation_share,
                degrees_per_frame: track_degrees_per_frame,
                ..Default::default()
            };
            rc.localize.validate().map_err(|e| anyhow::anyhow!(e))?;
            let report = reloc::evaluate(&s, &rc, embedder.as_ref()).map_err(|e| anyhow::anyhow!("{e}"))?;
            print!("{}", reloc::markdown(&report));
            out.write_json(&report)?;
        }
        EvalCommand::Merge { scenes, splits, seeds, report } => run_merge(scenes, splits, seeds, report)?,
    }
    Ok(())
}

fn run_merge(
    scenes: Vec<PathBuf>,
    splits: Vec<scone::offline::eval::merge::Split>,
    seeds: Vec<u64>,
    out: ReportArgs,
) -> anyhow::Result<()> {
    use scone::offline::eval::merge;
    let embedder = load_embedder(true, &out)?.expect("requested");
    let mut reports = Vec::new();
    for scene in &scenes {
        let s = Scene::load(scene)?;
        for &split in &splits {
            for &seed in &seeds {
                reports.push(merge::evaluate(&s, split, seed, &embedder).map_err(|e| anyhow::anyhow!("{e}"))?);
            }
        }
    }
    print!("{}", merge::markdown(&reports));
    out.write_json(&reports)?;
    Ok(())
}

/// `--ratio` and `--scone-ratio`: a ratio-test threshold, in (0, 1]; refused while the arguments are parsed, so
/// clap's error names the flag.
fn ratio_arg(text: &str) -> Result<f32, String> {
    let r: f32 = text.parse().map_err(|e| format!("{e}"))?;
    if scone::matching::is_ratio(r) {
        Ok(r)
    } else {
        Err(format!("a ratio-test threshold must be in (0, 1], got {r}"))
    }
}

fn check_same_corner(px: f32) -> anyhow::Result<()> {
    anyhow::ensure!(px.is_finite() && px >= 0.0, "--same-corner-px must be a finite number >= 0");
    Ok(())
}

/// `--scone-matcher`, or the model's declared matcher.
fn matcher_for(
    flag: Option<scone::matching::SconeMatcher>,
    embedder: Option<&scone::describe::embedding::Embedder>,
) -> anyhow::Result<scone::matching::SconeMatcher> {
    match flag {
        Some(m) => Ok(m),
        None => scone::matching::SconeMatcher::declared(embedder.and_then(|e| e.declared_matcher()))
            .map_err(|e| anyhow::anyhow!(e)),
    }
}

/// `A:B` as two fractions.
fn parse_block(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s.split_once(':').ok_or("expected A:B, e.g. 0:0.5")?;
    let a: f64 = a.trim().parse().map_err(|_| format!("'{a}' is not a number"))?;
    let b: f64 = b.trim().parse().map_err(|_| format!("'{b}' is not a number"))?;
    reloc::check_block(a, b)?;
    Ok((a, b))
}

/// A value of `eval reloc --stages`: a part of the staged pipeline, or `none`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StageArg {
    None,
    Candidates,
    Freak,
    Guided,
    Build,
}

impl StageArg {
    fn stage(self) -> Option<scone::offline::eval::reloc::Stage> {
        use scone::offline::eval::reloc::Stage;
        match self {
            StageArg::None => None,
            StageArg::Candidates => Some(Stage::Candidates),
            StageArg::Freak => Some(Stage::Freak),
            StageArg::Guided => Some(Stage::Guided),
            StageArg::Build => Some(Stage::Build),
        }
    }
}
