//! Arguments several commands share: extraction settings, the model and report of an evaluation.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use scone::describe::constellation::DEFAULT_K;
use scone::describe::embedding::{Embedder, EmbedderSettings};
use scone::describe::features::{self, ExtractorSettings};
use scone::settings::ExtractorOverrides;

/// Model and output of an evaluation.
#[derive(Args, Clone)]
pub struct ReportArgs {
    /// SConE model (default: the committed one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Write the full report (every pair or query) as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// ONNX Runtime intra-op threads for the SConE embedding (with --opencv-threads 1, the evaluation keeps
    /// to one core, e.g. beside a training run).
    #[arg(long, default_value_t = 2)]
    pub embed_threads: usize,
}

impl ReportArgs {
    pub fn write_json(&self, report: &impl serde::Serialize) -> anyhow::Result<()> {
        if let Some(path) = &self.json {
            std::fs::write(path, serde_json::to_vec_pretty(report)?)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        Ok(())
    }
}

/// Extraction settings on the command line; unset flags keep [`ExtractorSettings::default`] (revision 3), or
/// with a model, the extraction it declares ([`ExtractorArgs::config_for`]).
#[derive(Args, Clone)]
pub struct ExtractorArgs {
    /// FAST threshold.
    #[arg(long)]
    pub fast_threshold: Option<i32>,
    /// Keypoints kept at most.
    #[arg(long)]
    pub max_keypoints: Option<usize>,
    /// Pyramid levels (1 = single-scale FAST, as in the paper).
    #[arg(long)]
    pub levels: Option<u32>,
    /// Downscale factor between pyramid levels.
    #[arg(long)]
    pub scale_factor: Option<f64>,
    /// Grid cell size for bucketing in pixels (0 = off).
    #[arg(long)]
    pub grid_cell: Option<u32>,
    /// Constellation size.
    #[arg(long, default_value_t = DEFAULT_K)]
    pub k: usize,
    /// OpenCV threads (0 = all cores).
    #[arg(long, default_value_t = 0)]
    pub opencv_threads: usize,
}

impl ExtractorArgs {
    pub fn config(&self) -> anyhow::Result<ExtractorSettings> {
        self.config_over(ExtractorSettings::default())
    }

    /// The flags over the extraction `embedder` declares (revision 2's for a model that declares none); over
    /// the default without a model.
    pub fn config_for(&self, embedder: Option<&Embedder>) -> anyhow::Result<ExtractorSettings> {
        self.config_over(embedder.map_or_else(ExtractorSettings::default, Embedder::extraction))
    }

    fn config_over(&self, d: ExtractorSettings) -> anyhow::Result<ExtractorSettings> {
        let cfg = ExtractorOverrides {
            fast_threshold: self.fast_threshold,
            max_keypoints: self.max_keypoints,
            levels: self.levels,
            scale_factor: self.scale_factor,
            grid_cell: self.grid_cell,
        }
        .over(d);
        cfg.validate()?;
        anyhow::ensure!(self.k >= 1 && self.k <= 64, "--k must be in 1..=64");
        features::set_opencv_threads(self.opencv_threads)?;
        Ok(cfg)
    }
}

/// The model, when a method needs it or `--model` names one (whose declared extraction the evaluation then
/// runs, for every method alike).
pub fn load_embedder(needed: bool, report: &ReportArgs) -> anyhow::Result<Option<Embedder>> {
    if !needed && report.model.is_none() {
        return Ok(None);
    }
    // One session: `--embed-threads` is then every thread the model takes (1 keeps the evaluation on one core).
    let mut ec =
        EmbedderSettings { sessions: 1, intra_threads: report.embed_threads.max(1), ..EmbedderSettings::default() };
    if let Some(m) = report.model.clone() {
        ec.model = m;
    }
    Ok(Some(Embedder::load(&ec)?))
}
