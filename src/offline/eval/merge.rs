//! `scone eval merge`: two maps of one scene, each in its own random world frame, merged as `MergeMaps` does.
//!
//! The scene's posed frames (every 5th held out as queries) are split into two mapping runs: `interleaved`
//! (alternate frames, so the runs overlap everywhere) or `overlap` (the first 60 % and the last 60 % of the
//! sequence, so they share the middle fifth only). Each run is built by the service's map-building code from
//! its frames' ground-truth poses moved by a seeded similarity (rotation, translation, scale 0.3-3.3), without
//! depth (depth is metric, a scaled world is not). The second is merged into the first with the transform
//! estimated. Reported: the transform's error against the true one (scale, rotation, and where it puts the
//! second run's cameras), the merged keyframes' pose error against the ground truth in the first run's frame,
//! and the held-out queries localised within (5 % of the path extent, 2°) against each run and the merged map.

use std::cell::RefCell;

use serde::{Deserialize, Serialize};

use nalgebra::{Isometry3, Point3, Similarity3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};

use crate::describe::decode::{decode_grey, ImageLimitSettings};
use crate::describe::embedding::Embedder;
use crate::describe::features::Features;
use crate::map::builder::{plan_keyframe, BuildSettings, KeyframeInput};
use crate::map::index::{EmbeddingIndex, IndexSettings};
use crate::map::localize::{localize, LocalizeSettings};
use crate::map::merge::plan_merge;
use crate::map::model::{MapData, MapMeta};
use crate::offline::eval::stats::{markdown_table, median};
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// How the scene's frames are split into two mapping runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Split {
    Interleaved,
    Overlap,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MergeReport {
    pub scene: String,
    pub split: Split,
    pub seed: u64,
    pub path_extent: f64,
    pub keyframes: (usize, usize),
    pub localised: usize,
    pub inliers: usize,
    pub landmarks_fused: usize,
    pub landmarks_added: usize,
    /// |estimated scale / true scale - 1|.
    pub scale_error: f64,
    pub rotation_error_deg: f64,
    /// Median and largest distance between the second run's camera centres put by the estimated transform and
    /// by the true one, as a fraction of the path extent.
    pub median_centre_error: f64,
    pub max_centre_error: f64,
    /// Median rotation error of every merged keyframe against its ground truth, degrees.
    pub median_keyframe_rotation_deg: f64,
    pub queries: usize,
    /// Held-out queries localised within (5 % of the path extent, 2°): first run, second run, merged.
    pub success: (usize, usize, usize),
    pub merge_seconds: f64,
    /// The error when the merge fails (too few keyframes localised).
    pub error: Option<String>,
}

/// A seeded world frame: rotation up to 3 rad, translation within 10 scene units, scale 0.3-3.3.
fn world_frame(rng: &mut rand::rngs::StdRng) -> Similarity3<f64> {
    let axis = Vector3::new(rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5);
    let rotation = UnitQuaternion::from_scaled_axis(axis.normalize() * (0.5 + 2.5 * rng.random::<f64>()));
    let t = Vector3::new(rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>()) * 20.0 - Vector3::repeat(10.0);
    Similarity3::from_parts(Translation3::from(t), rotation, 0.3 + 3.0 * rng.random::<f64>())
}

fn moved(s: &Similarity3<f64>, p: &Isometry3<f64>) -> Isometry3<f64> {
    crate::map::merge::moved_pose(s, p)
}

pub fn evaluate(scene: &Scene, split: Split, seed: u64, embedder: &Embedder) -> Result<MergeReport, BoxError> {
    let limits = ImageLimitSettings::default();
    let extractor = embedder.extraction();
    let posed: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
    let queries: Vec<usize> = posed.iter().copied().filter(|i| i % 5 == 4).collect();
    let mapped: Vec<usize> = posed.iter().copied().filter(|i| i % 5 != 4).collect();
    let n = mapped.len();
    let (run_a, run_b): (Vec<usize>, Vec<usize>) = match split {
        Split::Interleaved => {
            (mapped.iter().copied().step_by(2).collect(), mapped.iter().copied().skip(1).step_by(2).collect())
        }
        Split::Overlap => (mapped[..n * 3 / 5].to_vec(), mapped[n * 2 / 5..].to_vec()),
    };
    let centres: Vec<Vector3<f64>> = posed.iter().map(|&i| scene.frames[i].pose.unwrap().translation.vector).collect();
    let path_extent = centres.iter().flat_map(|a| centres.iter().map(move |b| (a - b).norm())).fold(0.0, f64::max);
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let (frame_a, frame_b) = (world_frame(&mut rng), world_frame(&mut rng));

    // Each posed frame described, each run's keyframes planned, the queries localised against both runs and the
    // merged map, and the merge.
    let steps = posed.len() + run_a.len() + run_b.len() + 3 * queries.len() + 1;
    let progress = RefCell::new(Progress::new(format!("eval merge {} {split:?} seed {seed}", scene.name), steps));
    let mut described = std::collections::HashMap::new();
    for &i in &posed {
        progress.borrow_mut().step();
        let bytes = std::fs::read(&scene.frames[i].rgb)?;
        let f = crate::describe::pipeline::extract_for(&decode_grey(&bytes, &limits)?, &extractor, embedder)?;
        let e = crate::describe::pipeline::embed(embedder, &f)?;
        described.insert(i, (f, e));
    }
    let meta = |id: &str| MapMeta {
        id: id.into(),
        model_id: embedder.model_id().into(),
        k: embedder.k(),
        dim: embedder.dim(),
        created_unix_ms: 0,
    };
    let build = |frames: &[usize], s: &Similarity3<f64>, id: &str| -> Result<MapData, BoxError> {
        let mut data = MapData::new(meta(id));
        for &i in frames {
            progress.borrow_mut().step();
            let (f, e) = &described[&i];
            let input = KeyframeInput {
                id: i as u64,
                pose: moved(s, &scene.frames[i].pose.unwrap()),
                camera: scene.camera,
                features: f,
                embeddings: e,
                depth: None,
                external: None,
            };
            let record = plan_keyframe(&data, &input, &BuildSettings::default())?;
            data.check(&record)?;
            data.apply(&record)?;
        }
        Ok(data)
    };
    let mut a = build(&run_a, &frame_a, "a")?;
    let b = build(&run_b, &frame_b, "b")?;
    let index_of = |d: &MapData| {
        let mut index = EmbeddingIndex::new(IndexSettings::default());
        index.sync(d);
        index
    };
    let params = LocalizeSettings::default();
    let success = |data: &MapData, index: &EmbeddingIndex, s: &Similarity3<f64>| -> Result<usize, BoxError> {
        let mut ok = 0;
        for &q in &queries {
            progress.borrow_mut().step();
            let (f, e) = &described[&q];
            let features = Features { descriptors: vec![], ..f.clone() };
            let out = localize(data, index, &features, e, &scene.camera, None, &params)?;
            let Some(p) = out.pose else { continue };
            let truth = moved(s, &scene.frames[q].pose.unwrap());
            let dt = (p.camera_to_world.translation.vector - truth.translation.vector).norm() / s.scaling();
            if dt <= 0.05 * path_extent && p.camera_to_world.rotation.angle_to(&truth.rotation).to_degrees() <= 2.0 {
                ok += 1;
            }
        }
        Ok(ok)
    };
    let (index_a, index_b) = (index_of(&a), index_of(&b));
    let before = (success(&a, &index_a, &frame_a)?, success(&b, &index_b, &frame_b)?);
    let mut report = MergeReport {
        scene: scene.name.clone(),
        split,
        seed,
        path_extent,
        keyframes: (run_a.len(), run_b.len()),
        localised: 0,
        inliers: 0,
        landmarks_fused: 0,
        landmarks_added: 0,
        scale_error: f64::NAN,
        rotation_error_deg: f64::NAN,
        median_centre_error: f64::NAN,
        max_centre_error: f64::NAN,
        median_keyframe_rotation_deg: f64::NAN,
        queries: queries.len(),
        success: (before.0, before.1, 0),
        merge_seconds: 0.0,
        error: None,
    };
    progress.borrow_mut().step();
    let t = std::time::Instant::now();
    let plan = match plan_merge(&a, &index_a, &b, None, &params) {
        Ok(p) => p,
        Err(e) => {
            report.error = Some(e.to_string());
            return Ok(report);
        }
    };
    report.merge_seconds = t.elapsed().as_secs_f64();
    let truth = frame_a * frame_b.inverse();
    let est = plan.transform;
    let centre_errors: Vec<f64> = run_b
        .iter()
        .map(|&i| {
            let c = Point3::from(moved(&frame_b, &scene.frames[i].pose.unwrap()).translation.vector);
            (est * c - truth * c).norm() / frame_a.scaling() / path_extent
        })
        .collect();
    let a_ids: std::collections::HashSet<u64> = a.keyframes.keys().copied().collect();
    a.apply(&plan.record)?;
    // A merged keyframe's frame: its own id for the first run's, less the offset for the second run's.
    let keyframe_rotations: Vec<f64> = a
        .keyframes
        .values()
        .map(|k| {
            let frame = if a_ids.contains(&k.id) { k.id } else { k.id - plan.keyframe_id_offset };
            let want = moved(&frame_a, &scene.frames[frame as usize].pose.unwrap());
            k.pose.isometry().rotation.angle_to(&want.rotation).to_degrees()
        })
        .collect();
    let merged_index = index_of(&a);
    report.success.2 = success(&a, &merged_index, &frame_a)?;
    report.localised = plan.localised;
    report.inliers = plan.inliers;
    report.landmarks_fused = plan.landmarks_fused;
    report.landmarks_added = plan.landmarks_added;
    report.scale_error = (est.scaling() / truth.scaling() - 1.0).abs();
    report.rotation_error_deg = est.isometry.rotation.angle_to(&truth.isometry.rotation).to_degrees();
    report.median_centre_error = median(&centre_errors);
    report.max_centre_error = centre_errors.iter().copied().fold(0.0, f64::max);
    report.median_keyframe_rotation_deg = median(&keyframe_rotations);
    Ok(report)
}

pub fn markdown(reports: &[MergeReport]) -> String {
    let headers = [
        "scene",
        "split",
        "keyframes",
        "localised / agree",
        "scale err.",
        "rotation err. (deg)",
        "centres, median / max (x extent)",
        "fused / added",
        "queries in (5 %, 2°): A / B / merged",
        "merge s",
    ];
    markdown_table(
        &headers,
        reports.iter().map(|r| {
            let split = format!("{:?}", r.split).to_lowercase();
            let kf = format!("{} + {}", r.keyframes.0, r.keyframes.1);
            match &r.error {
                Some(e) => vec![r.scene.clone(), split, kf, format!("failed: {e}")]
                    .into_iter()
                    .chain(std::iter::repeat_n(String::new(), 6))
                    .collect(),
                None => vec![
                    r.scene.clone(),
                    split,
                    kf,
                    format!("{} / {}", r.localised, r.inliers),
                    format!("{:.4}", r.scale_error),
                    format!("{:.3}", r.rotation_error_deg),
                    format!("{:.4} / {:.4}", r.median_centre_error, r.max_centre_error),
                    format!("{} / {}", r.landmarks_fused, r.landmarks_added),
                    format!("{} / {} / {} of {}", r.success.0, r.success.1, r.success.2, r.queries),
                    format!("{:.1}", r.merge_seconds),
                ],
            }
        }),
    )
}
