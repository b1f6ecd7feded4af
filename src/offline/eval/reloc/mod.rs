//! `scone eval reloc`: relocalisation against a map built from part of a scene.
//!
//! The map is built from every `stride`-th frame with its ground-truth pose (and depth where the scene has
//! it) by the service's map-building code; every other frame is localised against it. Per method: the share
//! of queries within (0.25 m, 2 deg), (0.5 m, 5 deg) and (5 m, 10 deg), median errors of the localised
//! queries, the share not localised, and 2D-3D match precision (a match is correct when the landmark projects
//! with the query's ground-truth pose within `precision_px` of the keypoint).
//!
//! Methods share the map code: SConE embeddings (L2), FREAK bits as ±1 vectors (L2 on them ranks exactly as
//! Hamming, so the search is an exact popcount search; the ratio test is applied to Hamming distances by
//! using sqrt(ratio) on L2), and SIFT (L2); DoG+FREAK as FREAK and FAST+SIFT as SIFT. All searches here are
//! exact, so the comparison is about the descriptors, not the index.
//!
//! **Far maps and distractors** (the harder protocol; flags of `scone eval reloc`):
//! * `map_block = (a, b)`: the map is the posed frames from fraction `a` to `b` of the sequence (a contiguous
//!   block), and the queries are all the others, so most queries are far from every map keyframe. Each query
//!   records its distance to the map: the baseline to the nearest map camera centre and the viewing angle to
//!   the most similarly oriented map keyframe; the summary bins the queries by that angle (`ANGLE_BINS`).
//! * `distractors`: keyframes of other real scenes are added to the same map, far away from it in space (so
//!   their landmarks can only be wrong matches), until the map holds `distractor_observations` of their
//!   observations; the nearest neighbours must then be found among many look-alikes. With distractors the
//!   index is the service's (HNSW above `IndexSettings::exact_below` observations), as a deployment's is.
//! * `unit_scale`: the success thresholds are multiplied by it (scenes whose units are not metres).
//!
//! **What a client without calibration gets, and how sure a pose is**:
//! * `unknown_focal`: every query is localised without its focal length, as Localize does for a client that
//!   leaves `fx`, `fy` out (with `centre_principal_point`, the principal point is the image centre as well);
//!   each record keeps the focal length used, and the summary the median relative error against the scene's.
//! * Every localised query records `mahalanobis2`, the squared Mahalanobis distance of the true pose under the
//!   pose's covariance (`localize.covariance_scale` applied): the summary's `covariance_coverage` is the share
//!   of localised queries within the 95 % ellipsoid (`pose::CHI2_6_95`), which should be close to 0.95.

//!
//! **Tracks** (`track`): each query is localised together with its nearest query frames, their poses
//! relative to it from the ground truth with a tracker's error added (`track_noise`); foreign scenes as tracks
//! of consecutive frames.
//!
//! Rooms: `protocol.rs` (the settings and the split of the frames), `stages.rs` (a method's map, queries and
//! foreign frames), `tracks.rs` (the same for tracks), `report.rs` (records and summaries), `tables.rs` (the markdown); here, the run over the
//! methods.

use crate::describe::decode::{decode_grey, ImageLimitSettings};
use crate::describe::embedding::Embedder;
use crate::map::localize::LocalizeSettings;
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;
use crate::pose::RansacSettings;

mod diagnose;
mod protocol;
mod report;
mod stages;
mod tables;
#[cfg(test)]
mod tests;
mod tracks;

pub use diagnose::{Diagnosis, LostAt};
pub use protocol::{check_block, with_stages, PnpVariant, RelocConfig, Stage, TrackNoise};
pub use report::{BinSummary, QueryRecord, RelocReport, RelocSummary, ANGLE_BINS};
pub use tables::markdown;

use protocol::split_frames;
use report::summarise;
use stages::{foreign_poses, MethodView};
use tracks::foreign_tracks;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

pub fn evaluate(scene: &Scene, cfg: &RelocConfig, embedder: Option<&Embedder>) -> Result<RelocReport, BoxError> {
    let limits = ImageLimitSettings::default();
    let posed: Vec<usize> = (0..scene.frames.len()).filter(|&i| scene.frames[i].pose.is_some()).collect();
    let (map_frames, query_frames) = split_frames(&posed, cfg)?;
    let centres: Vec<_> = posed.iter().map(|&i| scene.frames[i].pose.unwrap().translation.vector).collect();
    let path_extent = centres.iter().flat_map(|a| centres.iter().map(move |b| (a - b).norm())).fold(0.0f64, f64::max);
    let mut images = Vec::new();
    for f in &scene.frames {
        let bytes = std::fs::read(&f.rgb).map_err(|e| format!("{}: {e}", f.rgb.display()))?;
        images.push(decode_grey(&bytes, &limits)?);
    }
    if cfg.track >= 2 && !(cfg.also_caps.is_empty() && cfg.also_pnp.is_empty()) {
        return Err("stage 1 caps and estimators on the same map (also_caps, also_pnp) are for single frames".into());
    }
    let mut summaries = Vec::new();
    let mut queries = Vec::new();
    let variants = 1 + cfg.also_caps.len() + cfg.also_pnp.len();
    let per_method = images.len() + map_frames.len() + variants * query_frames.len();
    let mut progress = Progress::new("eval reloc", cfg.methods.len() * per_method);
    for &method in &cfg.methods {
        let (build, localize) = cfg.settings_for(method);
        let view = MethodView::describe(scene, &images, method, cfg, embedder, &mut progress)?;
        let map = view.build_map(&map_frames, cfg, &build, embedder, &mut progress)?;
        let scene_focal = (scene.camera.fx + scene.camera.fy) / 2.0;
        // The configuration's own settings, then each of `also_caps` and `also_pnp` on the same map, so the same
        // graph: those rows differ from the first only by the cap or the estimator.
        let variants = std::iter::once((None, None))
            .chain(cfg.also_caps.iter().map(|&c| (Some(c), None)))
            .chain(cfg.also_pnp.iter().map(|&p| (None, Some(p))));
        for (cap, pnp) in variants {
            let mut localize =
                LocalizeSettings { max_query_keypoints: cap.unwrap_or(localize.max_query_keypoints), ..localize };
            if let Some(p) = pnp {
                localize.ransac = RansacSettings { pnp: p.method, max_iters: p.max_iters, ..localize.ransac };
            }
            // Pictures are of the configuration's own answers.
            let variant_cfg =
                (cap.is_some() || pnp.is_some()).then(|| RelocConfig { dump_matches: None, ..cfg.clone() });
            let cfg = variant_cfg.as_ref().unwrap_or(cfg);
            let (mut records, foreign) = if cfg.track >= 2 {
                let records = view.localise_tracks(&query_frames, &map_frames, &map, cfg, &localize, &mut progress)?;
                (records, foreign_tracks(&map, method, cfg, &localize, embedder)?)
            } else {
                let records = view.localise_queries(&query_frames, &map_frames, &map, cfg, &localize, &mut progress)?;
                (records, foreign_poses(&map.data, &map.index, method, cfg, &localize, embedder)?)
            };
            records.iter_mut().for_each(|r| (r.stage1_cap, r.pnp) = (cap, pnp));
            let summary = summarise(method, &records, map.figures(), foreign, scene_focal, cfg.unit_scale);
            summaries.push(RelocSummary { stage1_cap: cap, pnp, ..summary });
            queries.extend(records.into_iter().map(|r| (method, r)));
        }
    }
    Ok(RelocReport { scene: scene.name.clone(), path_extent, config: cfg.clone(), summaries, queries })
}
