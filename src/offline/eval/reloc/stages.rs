//! The stages of one method's evaluation: the scene described, the map built from its map frames (and the
//! distractor scenes' keyframes) with the service's map-building code and index, the queries localised and
//! measured against their ground truth, and the foreign scenes' frames localised against the map.

use std::time::Instant;

use opencv::prelude::*;

use crate::camera::{Camera, PoseConvention};
use crate::describe::decode::{decode_depth_png, decode_grey, GreyImage, ImageLimitSettings};
use crate::describe::embedding::Embedder;
use crate::describe::features::Features;
use crate::map::builder::{plan_keyframe, BuildSettings, Depth, KeyframeInput};
use crate::map::index::{EmbeddingIndex, IndexSettings};
use crate::map::localize::Localization;
use crate::map::localize::{localize, within_confidence_tolerance, LocalizeSettings};
use crate::map::model::{MapData, MapMeta};
use crate::offline::eval::methods::{describe, Described, Method};
use crate::offline::eval::reloc::diagnose::{diagnose, Diagnosis, QueryTruth};
use crate::offline::eval::reloc::protocol::RelocConfig;
use crate::offline::eval::reloc::report::{MapFigures, QueryRecord};
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;
use crate::pose::{pose_covariance, pose_difference, rotation_error_deg};

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Where distractor keyframes are put: this far from the evaluated scene (scene units), one offset per
/// distractor scene, so their landmarks never fall where the scene's are.
const DISTRACTOR_OFFSET: f64 = 1.0e4;

/// The features the service would hold for `d`: its keypoints and, for SConE, their FREAK bits (a keyframe's
/// payload keeps them, and the stages that join FREAK's matches read them).
pub(super) fn features_of(d: &Described) -> Result<Features, BoxError> {
    let mut descriptors = Vec::new();
    if let Some(bits) = &d.freak {
        for r in 0..bits.rows() {
            let row = bits.at_row::<u8>(r)?;
            descriptors.push(row.try_into().map_err(|_| format!("FREAK row of {} bytes", row.len()))?);
        }
    }
    Ok(Features { width: d.width, height: d.height, keypoints: d.keypoints.clone(), descriptors, context: Vec::new() })
}

/// Vectors a method's descriptors are compared as, row-major, with their dimension.
pub(super) fn vectors(method: Method, d: &Described) -> Result<(Vec<f32>, usize), BoxError> {
    let rows = d.descriptors.rows() as usize;
    if rows == 0 {
        return Ok((Vec::new(), if method.freak_bits() { 512 } else { d.descriptors.cols().max(1) as usize }));
    }
    match method {
        m if m.freak_bits() => {
            let mut out = Vec::with_capacity(rows * 512);
            for r in 0..rows as i32 {
                for byte in d.descriptors.at_row::<u8>(r)? {
                    for bit in 0..8 {
                        out.push(if byte >> bit & 1 == 1 { 1.0 } else { -1.0 });
                    }
                }
            }
            Ok((out, 512))
        }
        _ => {
            let cols = d.descriptors.cols() as usize;
            let mut out = Vec::with_capacity(rows * cols);
            for r in 0..rows as i32 {
                out.extend_from_slice(d.descriptors.at_row::<f32>(r)?);
            }
            Ok((out, cols))
        }
    }
}

/// The scene as one method sees it: every frame described, with its descriptors as the vectors a map holds.
pub(super) struct MethodView<'a> {
    pub scene: &'a Scene,
    pub method: Method,
    pub described: Vec<Described>,
    pub vectors: Vec<(Vec<f32>, usize)>,
}

/// A method's map of the scene (and of the distractors), with its index.
pub(super) struct BuiltMap {
    pub data: MapData,
    pub index: EmbeddingIndex,
    pub distractor_observations: usize,
    /// Landmarks of the evaluated scene (before the distractors').
    pub scene_landmarks: usize,
    /// Building the map and its index.
    pub build_seconds: f64,
}

impl BuiltMap {
    pub fn figures(&self) -> MapFigures {
        MapFigures {
            keyframes: self.data.keyframes.len(),
            landmarks: self.data.landmarks.len(),
            observations: self.data.observations.len(),
            distractor_observations: self.distractor_observations,
            scene_landmarks: self.scene_landmarks,
            build_seconds: self.build_seconds,
        }
    }
}

impl<'a> MethodView<'a> {
    /// Describes every image of `scene` (decoded in `images`) with `method`, one step of `progress` each.
    pub fn describe(
        scene: &'a Scene,
        images: &[GreyImage],
        method: Method,
        cfg: &RelocConfig,
        embedder: Option<&Embedder>,
        progress: &mut Progress,
    ) -> Result<Self, BoxError> {
        let described: Vec<Described> = images
            .iter()
            .map(|im| describe(method, im, &cfg.extractor, embedder))
            .inspect(|_| progress.step())
            .collect::<Result<_, _>>()?;
        let vectors: Vec<(Vec<f32>, usize)> = described.iter().map(|d| vectors(method, d)).collect::<Result<_, _>>()?;
        Ok(Self { scene, method, described, vectors })
    }

    /// The map of `map_frames` (their ground-truth poses, depth where the scene has it), then the distractor
    /// scenes' keyframes up to `cfg.distractor_observations`, and its index: one step of `progress` per map
    /// frame.
    pub fn build_map(
        &self,
        map_frames: &[usize],
        cfg: &RelocConfig,
        build: &BuildSettings,
        embedder: Option<&Embedder>,
        progress: &mut Progress,
    ) -> Result<BuiltMap, BoxError> {
        let (scene, limits) = (self.scene, ImageLimitSettings::default());
        let dim = self.vectors.iter().map(|v| v.1).max().unwrap_or(1);
        let mut data = MapData::new(MapMeta {
            id: format!("eval-{}", self.method.name()),
            model_id: embedder.map(|e| e.model_id().to_string()).unwrap_or_default(),
            k: 20,
            dim,
            created_unix_ms: 0,
        });
        let t0 = Instant::now();
        for &i in map_frames {
            progress.step();
            let d = &self.described[i];
            let features = features_of(d)?;
            let depth_mat = match &scene.frames[i].depth {
                Some(p) => Some(decode_depth_png(&std::fs::read(p)?, &limits)?),
                None => None,
            };
            let input = KeyframeInput {
                id: i as u64,
                pose: scene.frames[i].pose.unwrap(),
                camera: scene.camera,
                features: &features,
                embeddings: &self.vectors[i].0,
                depth: depth_mat.as_ref().map(|m| Depth { image: m, scale: crate::describe::decode::TUM_DEPTH_SCALE }),
                external: None,
            };
            let record = plan_keyframe(&data, &input, build)?;
            data.check(&record).map_err(|e| format!("frame {i}: {e}"))?;
            data.apply(&record).map_err(|e| format!("frame {i}: {e}"))?;
        }
        let (scene_observations, scene_landmarks) = (data.observations.len(), data.landmarks.len());
        for (si, dir) in cfg.distractors.iter().enumerate() {
            if data.observations.len() - scene_observations >= cfg.distractor_observations {
                break;
            }
            add_distractors(&mut data, dir, si, scene_observations, self.method, cfg, build, embedder)?;
        }
        let distractor_observations = data.observations.len() - scene_observations;
        // Exact search on the scene alone (the descriptors compared, not the index); the service's index
        // (HNSW above `exact_below`) once distractors make the map large, as a deployment's is.
        let params = if distractor_observations > 0 {
            IndexSettings { points: cfg.index_points, ..IndexSettings::default() }
        } else {
            IndexSettings { exact_below: usize::MAX, ..IndexSettings::default() }
        };
        let mut index = EmbeddingIndex::new(params);
        index.sync(&data);
        let build_seconds = t0.elapsed().as_secs_f64();
        Ok(BuiltMap { data, index, distractor_observations, scene_landmarks, build_seconds })
    }

    /// Every query frame localised against `map` (with or without its focal length, as `cfg` says) and measured
    /// against its ground truth: one step of `progress` each.
    pub fn localise_queries(
        &self,
        query_frames: &[usize],
        map_frames: &[usize],
        map: &BuiltMap,
        cfg: &RelocConfig,
        loc: &LocalizeSettings,
        progress: &mut Progress,
    ) -> Result<Vec<QueryRecord>, BoxError> {
        let (scene, data) = (self.scene, &map.data);
        let query_camera = match (cfg.unknown_focal, cfg.centre_principal_point) {
            (false, _) => scene.camera,
            (true, false) => Camera { fx: 0.0, fy: 0.0, ..scene.camera },
            (true, true) => Camera { fx: 0.0, fy: 0.0, cx: 0.0, cy: 0.0, ..scene.camera }.with_defaults(),
        };
        let mut recs = Vec::new();
        for &i in query_frames {
            progress.step();
            let d = &self.described[i];
            let features = features_of(d)?;
            let t = Instant::now();
            let out = localize(data, &map.index, &features, &self.vectors[i].0, &query_camera, None, loc)?;
            let seconds = t.elapsed().as_secs_f64() + d.seconds;
            let gt = scene.frames[i].pose.unwrap();
            let (baseline_to_map, angle_to_map_deg) = distance_to_map(scene, map_frames, &gt);
            // Matches are judged with the scene's camera (a query localised without its focal length too).
            let truth = QueryTruth {
                truth: &gt,
                camera: &scene.camera,
                keypoints: &features.keypoints,
                precision_px: cfg.precision_px,
                within: (0.25 * cfg.unit_scale, 2.0),
            };
            let correct = out.matches.iter().filter(|m| truth.error_px(data, m) <= cfg.precision_px).count();
            let (localised, te, re, inliers) = match &out.pose {
                Some(p) => (
                    true,
                    (p.camera_to_world.translation.vector - gt.translation.vector).norm(),
                    rotation_error_deg(
                        &p.camera_to_world.rotation.to_rotation_matrix(),
                        &gt.rotation.to_rotation_matrix(),
                    ),
                    p.inliers.len(),
                ),
                None => (false, f64::INFINITY, 180.0, 0),
            };
            let within_confidence_tolerance =
                out.pose.as_ref().map(|p| within_confidence_tolerance(p, &out.points, &gt));
            let diagnosis = match cfg.track < 2 && !query_camera.focal_unknown() {
                true => {
                    let d = diagnose(data, &truth, &out, correct, loc)?;
                    if let Some(dir) = &cfg.dump_matches {
                        dump_matches(dir, self, i, &out, &truth, data, &d)?;
                    }
                    Some(d)
                }
                false => None,
            };
            let mahalanobis2 = out.pose.as_ref().and_then(|p| {
                let sigma = pose_covariance(PoseConvention::default(), &p.camera_to_world, p.covariance_w2c.as_ref()?);
                let e = pose_difference(&gt, &p.camera_to_world);
                sigma.try_inverse().map(|inv| (e.transpose() * inv * e)[0])
            });
            recs.push(QueryRecord {
                frame: scene.frames[i].stamp.clone(),
                localised,
                translation_error: te,
                rotation_error_deg: re,
                matches: out.matches.len(),
                correct_matches: correct,
                inliers,
                confidence: out.confidence,
                seconds,
                baseline_to_map,
                angle_to_map_deg,
                focal: out.pose.as_ref().map(|p| p.focal),
                mahalanobis2,
                within_confidence_tolerance,
                stage1_cap: None,
                pnp: None,
                diagnosis,
            });
        }
        Ok(recs)
    }
}

/// Writes one query's matches for a picture (`dump_matches`): `DIR/<method>--<frame>.json` with the image, the
/// matches in the estimator's order (keypoint, correct or not) and the diagnosis.
fn dump_matches(
    dir: &std::path::Path,
    view: &MethodView,
    frame: usize,
    out: &Localization,
    q: &QueryTruth,
    data: &MapData,
    diagnosis: &Diagnosis,
) -> Result<(), BoxError> {
    let matches: Vec<serde_json::Value> = out
        .matches
        .iter()
        .map(|m| {
            let k = &q.keypoints[m.keypoint];
            serde_json::json!({"x": k.x, "y": k.y, "correct": q.error_px(data, m) <= q.precision_px})
        })
        .collect();
    let inliers: Vec<usize> = out.pose.as_ref().map(|p| p.inliers.clone()).unwrap_or_default();
    let f = &view.scene.frames[frame];
    let doc = serde_json::json!({
        "scene": view.scene.name, "frame": f.stamp, "image": f.rgb, "method": view.method.name(),
        "keypoints": q.keypoints.len(), "matches": matches, "inliers": inliers, "diagnosis": diagnosis,
    });
    std::fs::create_dir_all(dir)?;
    let name = format!("{}--{}.json", view.method.name(), f.stamp.replace('/', "_"));
    std::fs::write(dir.join(name), serde_json::to_vec(&doc)?)?;
    Ok(())
}

/// Baseline to the nearest map camera centre, and viewing angle to the most similarly oriented map keyframe.
pub(super) fn distance_to_map(scene: &Scene, map_frames: &[usize], pose: &nalgebra::Isometry3<f64>) -> (f64, f64) {
    let mut baseline = f64::INFINITY;
    let mut angle = f64::INFINITY;
    for &k in map_frames {
        let kp = scene.frames[k].pose.expect("map frames are posed");
        baseline = baseline.min((kp.translation.vector - pose.translation.vector).norm());
        angle = angle.min(kp.rotation.angle_to(&pose.rotation).to_degrees());
    }
    (baseline, angle)
}

/// Every `foreign_stride`-th frame of the foreign scenes localised against the map: (frames, localised).
pub(super) fn foreign_poses(
    data: &MapData,
    index: &EmbeddingIndex,
    method: Method,
    cfg: &RelocConfig,
    loc: &LocalizeSettings,
    embedder: Option<&Embedder>,
) -> Result<(usize, usize), BoxError> {
    let limits = ImageLimitSettings::default();
    let (mut frames, mut localised) = (0, 0);
    for dir in &cfg.foreign {
        let other = Scene::load(dir)?;
        for f in other.frames.iter().step_by(cfg.foreign_stride.max(1)) {
            let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
            let d = describe(method, &decode_grey(&bytes, &limits)?, &cfg.extractor, embedder)?;
            let (v, _) = vectors(method, &d)?;
            let out = localize(data, index, &features_of(&d)?, &v, &other.camera, None, loc)?;
            frames += 1;
            localised += usize::from(out.pose.is_some());
        }
    }
    Ok((frames, localised))
}

/// Adds keyframes of the scene in `dir` to `data`, moved [`DISTRACTOR_OFFSET`] away per scene, until the map
/// holds `cfg.distractor_observations` observations beyond the evaluated scene's `base`.
#[allow(clippy::too_many_arguments)]
fn add_distractors(
    data: &mut MapData,
    dir: &std::path::Path,
    scene_index: usize,
    base: usize,
    method: Method,
    cfg: &RelocConfig,
    build: &BuildSettings,
    embedder: Option<&Embedder>,
) -> Result<(), BoxError> {
    let limits = ImageLimitSettings::default();
    let other = Scene::load(dir)?;
    let offset = nalgebra::Vector3::new(DISTRACTOR_OFFSET * (scene_index + 1) as f64, 0.0, 0.0);
    for (fi, f) in other.frames.iter().enumerate().step_by(cfg.distractor_stride.max(1)) {
        if data.observations.len() - base >= cfg.distractor_observations {
            break;
        }
        let Some(pose) = f.pose else { continue };
        let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
        let d = describe(method, &decode_grey(&bytes, &limits)?, &cfg.extractor, embedder)?;
        let (v, dim) = vectors(method, &d)?;
        if dim != data.meta.dim && !v.is_empty() {
            return Err(format!("distractor {}: dimension {dim}, the map's is {}", other.name, data.meta.dim).into());
        }
        let features = features_of(&d)?;
        let depth = match &f.depth {
            Some(p) => Some(decode_depth_png(&std::fs::read(p)?, &limits)?),
            None => None,
        };
        let moved = nalgebra::Isometry3::from_parts((pose.translation.vector + offset).into(), pose.rotation);
        let input = KeyframeInput {
            id: 1_000_000 * (scene_index as u64 + 1) + fi as u64,
            pose: moved,
            camera: other.camera,
            features: &features,
            embeddings: &v,
            depth: depth.as_ref().map(|m| Depth { image: m, scale: crate::describe::decode::TUM_DEPTH_SCALE }),
            external: None,
        };
        let record = plan_keyframe(data, &input, build)?;
        data.check(&record).map_err(|e| format!("distractor frame {fi}: {e}"))?;
        data.apply(&record).map_err(|e| format!("distractor frame {fi}: {e}"))?;
    }
    Ok(())
}
