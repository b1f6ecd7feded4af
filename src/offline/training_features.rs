//! Training-data export: the service's own extraction run over a scene, written as one `.npz` file.
//!
//! Layout (all arrays row-major; `NNNN` is the frame's index in `rgb.txt`, zero-padded to 4 digits):
//!
//! | key | dtype | shape | content |
//! |---|---|---|---|
//! | `meta_json` | uint8 | (bytes) | UTF-8 JSON: format version, scene, extractor settings, k, per-frame stamp/file/size/count |
//! | `fNNNN_keypoints` | float32 | (N, 6) | x, y, size, angle (degrees), response, octave |
//! | `fNNNN_descriptors` | uint8 | (N, 64) | FREAK bits, least significant bit first |
//! | `fNNNN_neighbours` | int32 | (N, k) | constellation member indices, nearest first |
//! | `fNNNN_mask` | uint8 | (N, k) | 1 = real neighbour, 0 = padding |
//! | `fNNNN_relative` | float32 | (N, k, 4) | u, v, dθ, ln scale ratio (see `constellation`) |
//! | `fNNNN_context` | uint8 | (N, 113) | the ring context (see `context`), from version 2 |
//!
//! Python: `z = np.load(path); meta = json.loads(bytes(z["meta_json"]))`.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use ndarray::{Array1, Array2, Array3};
use ndarray_npy::NpzWriter;
use serde::Serialize;

use crate::describe::constellation::{self, Constellations, GEOMETRY_DIM};
use crate::describe::decode::{decode_grey, ImageLimitSettings};
use crate::describe::features::{extract, ExtractorSettings, Features, DESCRIPTOR_BYTES};
use crate::describe::ring_context::SAMPLES;
use crate::error::SceneError;
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;

/// Version of the export layout; bumped on any change of keys, dtypes or meanings.
pub const EXPORT_FORMAT_VERSION: u32 = 2;

#[derive(Debug, Serialize)]
struct FrameMeta {
    index: usize,
    stamp: String,
    file: String,
    width: u32,
    height: u32,
    keypoints: usize,
}

#[derive(Debug, Serialize)]
struct ExportMeta<'a> {
    format: &'static str,
    version: u32,
    scone_version: &'static str,
    scene: &'a str,
    extractor: &'a ExtractorSettings,
    k: usize,
    frames: Vec<FrameMeta>,
}

/// Per-frame summary returned by [`export_scene`].
#[derive(Debug, Clone, Serialize)]
pub struct ExportSummary {
    pub frames: usize,
    pub keypoints_min: usize,
    pub keypoints_max: usize,
    pub keypoints_mean: f64,
}

fn npz_err(path: &Path, e: impl std::fmt::Display) -> SceneError {
    SceneError::Invalid { path: path.into(), reason: format!("writing npz: {e}") }
}

/// Adds one frame's arrays to the archive.
fn write_frame(
    npz: &mut NpzWriter<BufWriter<File>>,
    out: &Path,
    index: usize,
    f: &Features,
    c: &Constellations,
) -> Result<(), SceneError> {
    let n = f.len();
    let k = c.k;
    let kp = Array2::from_shape_fn((n, 6), |(i, j)| {
        let p = &f.keypoints[i];
        [p.x, p.y, p.size, p.angle, p.response, p.octave as f32][j]
    });
    let desc = Array2::from_shape_vec((n, DESCRIPTOR_BYTES), f.descriptors.as_flattened().to_vec())
        .map_err(|e| npz_err(out, e))?;
    let nb = Array2::from_shape_vec((n, k), c.neighbours.iter().map(|&j| j as i32).collect())
        .map_err(|e| npz_err(out, e))?;
    let mask = Array2::from_shape_vec((n, k), c.mask.clone()).map_err(|e| npz_err(out, e))?;
    let rel = Array3::from_shape_vec((n, k, GEOMETRY_DIM), c.relative.as_flattened().to_vec())
        .map_err(|e| npz_err(out, e))?;
    let name = |what: &str| format!("f{index:04}_{what}");
    npz.add_array(name("keypoints"), &kp).map_err(|e| npz_err(out, e))?;
    npz.add_array(name("descriptors"), &desc).map_err(|e| npz_err(out, e))?;
    npz.add_array(name("neighbours"), &nb).map_err(|e| npz_err(out, e))?;
    npz.add_array(name("mask"), &mask).map_err(|e| npz_err(out, e))?;
    npz.add_array(name("relative"), &rel).map_err(|e| npz_err(out, e))?;
    if f.context.len() == n {
        let ctx =
            Array2::from_shape_vec((n, SAMPLES), f.context.as_flattened().to_vec()).map_err(|e| npz_err(out, e))?;
        npz.add_array(name("context"), &ctx).map_err(|e| npz_err(out, e))?;
    }
    Ok(())
}

/// Writes one image's features and constellations to `out` in the layout above (a single frame, index 0).
pub fn export_image(
    name: &str,
    features: &Features,
    constellations: &Constellations,
    config: &ExtractorSettings,
    out: &Path,
) -> Result<(), SceneError> {
    let file = File::create(out).map_err(|source| SceneError::Io { path: out.into(), source })?;
    let mut npz = NpzWriter::new(BufWriter::new(file));
    write_frame(&mut npz, out, 0, features, constellations)?;
    let meta = ExportMeta {
        format: "scone-features",
        version: EXPORT_FORMAT_VERSION,
        scone_version: env!("CARGO_PKG_VERSION"),
        scene: name,
        extractor: config,
        k: constellations.k,
        frames: vec![FrameMeta {
            index: 0,
            stamp: "0".into(),
            file: name.into(),
            width: features.width,
            height: features.height,
            keypoints: features.len(),
        }],
    };
    finish(npz, out, &meta)?;
    Ok(())
}

fn finish(mut npz: NpzWriter<BufWriter<File>>, out: &Path, meta: &ExportMeta) -> Result<File, SceneError> {
    let json = serde_json::to_vec(meta).map_err(|e| npz_err(out, e))?;
    npz.add_array("meta_json", &Array1::from_vec(json)).map_err(|e| npz_err(out, e))?;
    let writer = npz.finish().map_err(|e| npz_err(out, e))?;
    let file = writer.into_inner().map_err(|e| npz_err(out, e.error()))?;
    file.sync_all().map_err(|source| SceneError::Io { path: out.into(), source })?;
    Ok(file)
}

/// Extracts features and constellations for every frame of `scene` and writes them to `out`.
pub fn export_scene(
    scene: &Scene,
    config: &ExtractorSettings,
    k: usize,
    limits: &ImageLimitSettings,
    out: &Path,
) -> Result<ExportSummary, SceneError> {
    config.validate().map_err(|source| SceneError::Feature { frame: "(settings)".into(), source })?;
    // One partial file per process: two exports of one scene at once (two training runs filling one cache)
    // must not write into the same file, or the one renamed first would hold both.
    let tmp = out.with_extension(format!("npz.{}.partial", std::process::id()));
    let written = write_scene(scene, config, k, limits, out, &tmp);
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    let summary = written?;
    std::fs::rename(&tmp, out).map_err(|source| SceneError::Io { path: out.into(), source })?;
    Ok(summary)
}

/// [`export_scene`]'s work, into the partial file `tmp`.
fn write_scene(
    scene: &Scene,
    config: &ExtractorSettings,
    k: usize,
    limits: &ImageLimitSettings,
    out: &Path,
    tmp: &Path,
) -> Result<ExportSummary, SceneError> {
    let file = File::create(tmp).map_err(|source| SceneError::Io { path: tmp.into(), source })?;
    let mut npz = NpzWriter::new(BufWriter::new(file));
    let mut frames = Vec::with_capacity(scene.frames.len());
    let mut progress = Progress::new(format!("features {}", scene.name), scene.frames.len());
    for (index, frame) in scene.frames.iter().enumerate() {
        progress.step();
        let bytes = std::fs::read(&frame.rgb).map_err(|source| SceneError::Io { path: frame.rgb.clone(), source })?;
        let feature_err = |source| SceneError::Feature { frame: frame.stamp.clone(), source };
        let image = decode_grey(&bytes, limits).map_err(feature_err)?;
        let mut features = extract(&image, config).map_err(feature_err)?;
        features.sample_context(&image).map_err(feature_err)?;
        let constellations = constellation::build(&features.keypoints, k);
        write_frame(&mut npz, out, index, &features, &constellations)?;
        tracing::debug!(frame = %frame.stamp, keypoints = features.len(), "extracted");
        frames.push(FrameMeta {
            index,
            stamp: frame.stamp.clone(),
            file: frame.rgb.strip_prefix(&scene.root).unwrap_or(&frame.rgb).to_string_lossy().into_owned(),
            width: features.width,
            height: features.height,
            keypoints: features.len(),
        });
    }
    let counts: Vec<usize> = frames.iter().map(|f| f.keypoints).collect();
    let summary = ExportSummary {
        frames: counts.len(),
        keypoints_min: counts.iter().copied().min().unwrap_or(0),
        keypoints_max: counts.iter().copied().max().unwrap_or(0),
        keypoints_mean: counts.iter().sum::<usize>() as f64 / counts.len().max(1) as f64,
    };
    let meta = ExportMeta {
        format: "scone-features",
        version: EXPORT_FORMAT_VERSION,
        scone_version: env!("CARGO_PKG_VERSION"),
        scene: &scene.name,
        extractor: config,
        k,
        frames,
    };
    finish(npz, tmp, &meta)?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture_copy(dir: &Path) -> std::path::PathBuf {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/rendered");
        let dst = dir.join("scene");
        std::fs::create_dir_all(dst.join("rgb")).unwrap();
        for f in ["rgb.txt", "groundtruth.txt", "camera.txt"] {
            std::fs::copy(src.join(f), dst.join(f)).unwrap();
        }
        for e in std::fs::read_dir(src.join("rgb")).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), dst.join("rgb").join(e.file_name())).unwrap();
        }
        dst
    }

    fn leftovers(dir: &Path) -> Vec<String> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".partial"))
            .collect()
    }

    #[test]
    fn a_scene_export_is_renamed_into_place_and_a_failed_one_leaves_nothing() {
        let dir = crate::test_dir::temp_dir("export");
        let scene_dir = fixture_copy(&dir);
        let out = dir.join("scene.features.npz");
        let (config, limits) = (ExtractorSettings::default(), ImageLimitSettings::default());
        let summary = export_scene(&Scene::load(&scene_dir).unwrap(), &config, 20, &limits, &out).unwrap();
        assert_eq!(summary.frames, 10);
        assert!(out.exists());
        assert!(leftovers(&dir).is_empty());

        std::fs::write(scene_dir.join("rgb/000003.png"), b"not a png").unwrap();
        let failed = dir.join("failed.features.npz");
        let e = export_scene(&Scene::load(&scene_dir).unwrap(), &config, 20, &limits, &failed).unwrap_err();
        assert!(e.to_string().contains("000003"), "{e}");
        assert!(!failed.exists());
        assert!(leftovers(&dir).is_empty(), "{:?}", leftovers(&dir));
    }
}
