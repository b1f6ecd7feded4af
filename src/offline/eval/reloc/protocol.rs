//! The protocol of a relocalisation evaluation: its settings (which methods, how the map and the queries are
//! chosen, distractors, foreign scenes, the stages of the pipeline turned on) and the split of the scene's posed
//! frames into the map and the queries.

use serde::{Deserialize, Serialize};

use crate::describe::features::ExtractorSettings;
use crate::map::builder::BuildSettings;
use crate::map::index::{IndexPoints, IndexSettings};
use crate::map::localize::LocalizeSettings;
use crate::offline::eval::methods::Method;
use crate::pose::PnpMethod;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RelocConfig {
    pub methods: Vec<Method>,
    pub stride: usize,
    pub extractor: ExtractorSettings,
    pub build: BuildSettings,
    pub localize: LocalizeSettings,
    pub precision_px: f64,
    /// Map from a contiguous block `[a, b)` of the posed frames (fractions) instead of every `stride`-th.
    #[serde(default)]
    pub map_block: Option<(f64, f64)>,
    /// Other scenes whose keyframes are added to the map as distractors.
    #[serde(default)]
    pub distractors: Vec<std::path::PathBuf>,
    /// Distractor observations to add (0: none). Distractor scenes are walked frame by frame (every
    /// `distractor_stride`-th) until the count is reached.
    #[serde(default)]
    pub distractor_observations: usize,
    #[serde(default = "one")]
    pub distractor_stride: usize,
    /// Multiplies the success thresholds (1 for scenes in metres).
    #[serde(default = "one_f")]
    pub unit_scale: f64,
    /// Localise the queries without their focal length (estimated with the pose).
    #[serde(default)]
    pub unknown_focal: bool,
    /// With `unknown_focal`: the principal point is the image centre too (a client that knows nothing of its
    /// camera), not the scene's.
    #[serde(default)]
    pub centre_principal_point: bool,
    /// Frames of other scenes localised against the map: every one localised is a false pose.
    #[serde(default)]
    pub foreign: Vec<std::path::PathBuf>,
    /// Every N-th frame of the foreign scenes.
    #[serde(default = "five")]
    pub foreign_stride: usize,
    /// What the index's graph holds once distractors make the map large: the service's default (reports
    /// written before the setting read as one point per observation, which they ran with).
    #[serde(default)]
    pub index_points: IndexPoints,
    /// Tracks instead of single frames: each query is localised with its `track - 1` nearest query
    /// frames by sequence position, their poses relative to it from the ground truth with [`TrackNoise`]
    /// added (0 or 1: single frames).
    #[serde(default)]
    pub track: usize,
    #[serde(default)]
    pub track_noise: TrackNoise,
    /// Stage 1 caps also run on the same map, each a summary of its own (`max_query_keypoints` = K, the rest of
    /// `localize` as it is, its fallback included): caps compared on one graph, since every build of the HNSW
    /// graph differs a little (hnsw_rs inserts in parallel). Single frames only.
    #[serde(default)]
    pub also_caps: Vec<usize>,
    /// Other PnP estimators also run on the same map, each a summary of its own (the rest of `localize` as it
    /// is): estimators compared on one graph. Single frames only.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub also_pnp: Vec<PnpVariant>,
    /// Each single-frame query's matches and diagnosis written under this folder, for pictures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dump_matches: Option<std::path::PathBuf>,
}

/// A PnP estimator with its iteration cap (`also_pnp`), written `METHOD:ITERS` on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct PnpVariant {
    pub method: PnpMethod,
    pub max_iters: i32,
}

impl std::str::FromStr for PnpVariant {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        use clap::ValueEnum;
        let (m, n) = s.split_once(':').ok_or_else(|| format!("{s:?}: expected METHOD:ITERS, e.g. p3p:2000"))?;
        let method = PnpMethod::from_str(m, true).map_err(|e| format!("{s:?}: {e}"))?;
        let max_iters: i32 = n.parse().map_err(|_| format!("{s:?}: {n:?} is not a number of iterations"))?;
        if max_iters < 1 {
            return Err(format!("{s:?}: at least one iteration"));
        }
        Ok(Self { method, max_iters })
    }
}

/// The error a tracker makes, added to a track's relative poses (seeded by `seed` and the query).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackNoise {
    /// Translation error as a share of the distance from the track's first frame (in a random direction).
    pub translation_share: f64,
    /// Rotation error per frame of the track, degrees (frame k of the track: k times it, about a random axis).
    pub degrees_per_frame: f64,
    pub seed: u64,
}

impl TrackNoise {
    /// The tracker's error as the estimator is told of it: the error added, as a client states its tracker's.
    pub fn told(&self) -> crate::pose::TrackerError {
        crate::pose::TrackerError {
            translation_share: self.translation_share,
            degrees_per_frame: self.degrees_per_frame,
        }
    }
}

impl Default for TrackNoise {
    fn default() -> Self {
        Self { translation_share: 0.01, degrees_per_frame: 0.5, seed: 43 }
    }
}

/// The parts of the staged pipeline an evaluation can turn on one by one (`--stages`); the rest stay as today's pipeline.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Stage 2: matching against the covisibility vote's candidate keyframes.
    Candidates,
    /// Stage 2 with FREAK's matches joined to the embedding's.
    Freak,
    /// Stage 3: guided search by projection and the pose estimated again.
    Guided,
    /// Map building with the known poses (epipolar window, covisible candidates, tracks, FREAK matches).
    Build,
}

/// Settings with exactly `stages` of the staged pipeline on, over today's pipeline.
pub fn with_stages(
    build: BuildSettings,
    localize: LocalizeSettings,
    stages: &[Stage],
) -> (BuildSettings, LocalizeSettings) {
    let on = |s: Stage| stages.contains(&s);
    let build = if on(Stage::Build) { build.with_known_poses() } else { build.unguided() };
    let candidate_matching = on(Stage::Candidates) || on(Stage::Freak);
    // Without stage 2, every query keypoint is searched, as before issue 27 (a cap leans on stage 2).
    let localize = if candidate_matching { localize } else { localize.stage_one_only() };
    let localize = LocalizeSettings {
        candidate_matching,
        candidate_freak: on(Stage::Freak),
        guided_search: on(Stage::Guided),
        ..localize
    };
    (build, localize)
}

fn one() -> usize {
    1
}

fn five() -> usize {
    5
}

fn one_f() -> f64 {
    1.0
}

impl Default for RelocConfig {
    fn default() -> Self {
        Self {
            methods: vec![Method::Scone, Method::Freak, Method::Sift],
            stride: 3,
            extractor: ExtractorSettings::default(),
            build: BuildSettings::default(),
            localize: LocalizeSettings::default(),
            precision_px: 5.0,
            map_block: None,
            distractors: Vec::new(),
            distractor_observations: 0,
            distractor_stride: 1,
            unit_scale: 1.0,
            unknown_focal: false,
            centre_principal_point: false,
            foreign: Vec::new(),
            foreign_stride: 5,
            index_points: IndexSettings::default().points,
            track: 0,
            track_noise: TrackNoise::default(),
            also_caps: Vec::new(),
            also_pnp: Vec::new(),
            dump_matches: None,
        }
    }
}

impl RelocConfig {
    /// The map-building and localisation settings of `method`: every ratio test on distances, with FREAK's ±1
    /// vectors taking the square root (a ratio on Hamming distances).
    pub fn settings_for(&self, method: Method) -> (BuildSettings, LocalizeSettings) {
        let ratio_scale = |r: f32| if method.freak_bits() { r.sqrt() } else { r };
        let build = BuildSettings { ratio: ratio_scale(self.build.ratio), ..self.build };
        let localize = LocalizeSettings {
            ratio: ratio_scale(self.localize.ratio),
            candidate_ratio: ratio_scale(self.localize.candidate_ratio),
            guided_ratio: ratio_scale(self.localize.guided_ratio),
            ..self.localize
        };
        (build, localize)
    }
}

/// Checks a map block `a:b` (fractions of the posed frames): `0 <= a < b <= 1`.
pub fn check_block(a: f64, b: f64) -> Result<(), String> {
    if (0.0..1.0).contains(&a) && a < b && b <= 1.0 {
        Ok(())
    } else {
        Err(format!("map block {a}:{b}: needs 0 <= a < b <= 1"))
    }
}

/// The map's frames and the queries: every `stride`-th posed frame and the rest, or a contiguous block and the
/// rest.
pub(super) fn split_frames(posed: &[usize], cfg: &RelocConfig) -> Result<(Vec<usize>, Vec<usize>), BoxError> {
    let (map, queries): (Vec<usize>, Vec<usize>) = match cfg.map_block {
        Some((a, b)) => {
            check_block(a, b)?;
            let n = posed.len() as f64;
            let (lo, hi) = ((a * n).floor() as usize, ((b * n).ceil() as usize).min(posed.len()));
            let map = posed[lo..hi].to_vec();
            (map.clone(), posed.iter().copied().filter(|i| !map.contains(i)).collect())
        }
        None => {
            let stride = cfg.stride.max(2);
            posed.iter().copied().partition(|i| i % stride == 0)
        }
    };
    if map.is_empty() || queries.is_empty() {
        return Err(format!("{} map frames and {} queries: both must be non-empty", map.len(), queries.len()).into());
    }
    Ok((map, queries))
}
