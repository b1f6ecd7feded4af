//! `scone extract` and `scone features`: the service's extraction on one image or a whole scene.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use scone::describe::constellation;
use scone::describe::decode::{decode_grey, ImageLimitSettings};
use scone::describe::features;
use scone::offline::scene::Scene;

use crate::args::ExtractorArgs;

/// Extract FAST + FREAK features and constellations from one image and print a summary as JSON.
#[derive(Args)]
pub struct ExtractArgs {
    /// PNG or JPEG file.
    pub image: PathBuf,
    /// Also write the features and constellations to this .npz (the export layout, one frame).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub extractor: ExtractorArgs,
}

/// Export a scene's features and constellations to an .npz file for training.
#[derive(Args)]
pub struct FeaturesArgs {
    /// Scene directory in the TUM RGB-D layout.
    #[arg(long)]
    pub scene: PathBuf,
    /// Output .npz file.
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub extractor: ExtractorArgs,
}

pub fn extract(args: ExtractArgs) -> anyhow::Result<()> {
    let ExtractArgs { image, out, extractor } = args;
    let cfg = extractor.config()?;
    let bytes = std::fs::read(&image).with_context(|| format!("reading {}", image.display()))?;
    let t0 = std::time::Instant::now();
    let grey = decode_grey(&bytes, &ImageLimitSettings::default())?;
    let mut f = features::extract(&grey, &cfg)?;
    f.sample_context(&grey)?;
    let c = constellation::build(&f.keypoints, extractor.k);
    let ms = t0.elapsed().as_secs_f64() * 1e3;
    let per_level =
        (0..cfg.levels as i32).map(|l| f.keypoints.iter().filter(|k| k.octave == l).count()).collect::<Vec<_>>();
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
    Ok(())
}

pub fn export(args: FeaturesArgs) -> anyhow::Result<()> {
    let FeaturesArgs { scene, out, extractor } = args;
    let cfg = extractor.config()?;
    let s = Scene::load(&scene)?;
    let summary =
        scone::offline::training_features::export_scene(&s, &cfg, extractor.k, &ImageLimitSettings::default(), &out)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
