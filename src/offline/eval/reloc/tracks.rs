//! Tracks instead of single frames (`--track N`): each query with its `N - 1` nearest query frames by
//! sequence position, located together by the service's track estimator ([`crate::pose::track_pose`]), their
//! poses relative to the query from the ground truth with a tracker's error added ([`TrackNoise`]). The query's
//! pose in the map is the answer measured; foreign scenes are localised as tracks of consecutive frames.

use std::time::Instant;

use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};

use crate::camera::PoseConvention;
use crate::describe::decode::{decode_grey, ImageLimitSettings};
use crate::describe::embedding::Embedder;
use crate::map::localize::{localize, within_confidence_tolerance, LocalizeSettings};
use crate::offline::eval::methods::describe;
use crate::offline::eval::reloc::protocol::{RelocConfig, TrackNoise};
use crate::offline::eval::reloc::report::QueryRecord;
use crate::offline::eval::reloc::stages::{distance_to_map, features_of, vectors, BuiltMap, MethodView};
use crate::offline::progress::Progress;
use crate::offline::scene::Scene;
use crate::pose::{
    pose_covariance, pose_difference, rotation_error_deg, track_pose, AbsolutePose, TrackFrame, TrackPose, TrackScale,
};

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// The service's track estimator as the protocol runs it: rigid, its seed, told of the error it added.
fn locate(frames: &[TrackFrame], loc: &LocalizeSettings, cfg: &RelocConfig) -> Result<Option<TrackPose>, BoxError> {
    let told = cfg.track_noise.told();
    Ok(track_pose(frames, TrackScale::Rigid, &loc.ransac, loc.min_inliers, cfg.track_noise.seed, &told)?)
}

/// The track of query `query`: it and its `n - 1` nearest frames of `queries` by sequence position.
pub(super) fn track_of(query: usize, queries: &[usize], n: usize) -> Vec<usize> {
    let mut others: Vec<usize> = queries.iter().copied().filter(|&j| j != query).collect();
    others.sort_by_key(|&j| (j.abs_diff(query), j));
    std::iter::once(query).chain(others.into_iter().take(n.saturating_sub(1))).collect()
}

/// Camera-to-track poses of `poses` (camera-to-world, the first is the track's frame) as a tracker reports
/// them: the truth relative to the first, with `noise` added (frame k: a translation error of
/// `translation_share` of its distance from the first, a rotation of `k * degrees_per_frame`, both about
/// random directions drawn from `seed`).
pub(super) fn tracked_poses(poses: &[Isometry3<f64>], noise: &TrackNoise, seed: u64) -> Vec<Isometry3<f64>> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let direction = |rng: &mut rand::rngs::StdRng| loop {
        let v = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        if (1e-3..=1.0).contains(&v.norm()) {
            return Unit::new_normalize(v);
        }
    };
    let first = poses[0].inverse();
    poses
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let truth = first * p;
            if k == 0 {
                return truth;
            }
            let shift = direction(&mut rng).into_inner() * noise.translation_share * truth.translation.vector.norm();
            let turn = UnitQuaternion::from_axis_angle(
                &direction(&mut rng),
                (k as f64 * noise.degrees_per_frame).to_radians(),
            );
            Isometry3::from_parts(Translation3::from(truth.translation.vector + shift), turn * truth.rotation)
        })
        .collect()
}

impl MethodView<'_> {
    /// One frame as the track estimator takes it: its matches against `map` and its own pose.
    fn track_frame(
        &self,
        i: usize,
        camera_to_track: Isometry3<f64>,
        map: &BuiltMap,
        loc: &LocalizeSettings,
    ) -> Result<(TrackFrame, usize, f64), BoxError> {
        let d = &self.described[i];
        let features = features_of(d)?;
        let t = Instant::now();
        let out = localize(&map.data, &map.index, &features, &self.vectors[i].0, &self.scene.camera, None, loc)?;
        let seconds = t.elapsed().as_secs_f64() + d.seconds;
        let points2d = out.matches.iter().map(|m| features.keypoints[m.keypoint]).map(|k| (k.x, k.y)).collect();
        let frame =
            TrackFrame { camera_to_track, camera: self.scene.camera, points3d: out.points, points2d, own: out.pose };
        Ok((frame, out.matches.len(), seconds))
    }

    /// Every query localised as the first frame of its track (`cfg.track` frames) against `map`, measured
    /// against its ground truth: one step of `progress` each.
    pub fn localise_tracks(
        &self,
        query_frames: &[usize],
        map_frames: &[usize],
        map: &BuiltMap,
        cfg: &RelocConfig,
        loc: &LocalizeSettings,
        progress: &mut Progress,
    ) -> Result<Vec<QueryRecord>, BoxError> {
        let scene = self.scene;
        let mut recs = Vec::new();
        for &q in query_frames {
            progress.step();
            let members = track_of(q, query_frames, cfg.track);
            let truth: Vec<Isometry3<f64>> = members.iter().map(|&j| scene.frames[j].pose.unwrap()).collect();
            let tracked = tracked_poses(&truth, &cfg.track_noise, cfg.track_noise.seed ^ q as u64);
            let (mut frames, mut matches, mut seconds) = (Vec::new(), 0, 0.0);
            for (&j, q_track) in members.iter().zip(tracked) {
                let (f, m, s) = self.track_frame(j, q_track, map, loc)?;
                frames.push(f);
                matches += m;
                seconds += s;
            }
            let t = Instant::now();
            let estimate = locate(&frames, loc, cfg)?;
            seconds += t.elapsed().as_secs_f64();
            let gt = truth[0];
            let (baseline_to_map, angle_to_map_deg) = distance_to_map(scene, map_frames, &gt);
            let first = estimate.as_ref().map(|t| {
                let covariance_w2c = t.covariance_w2c.map(|c| c * loc.covariance_scale);
                let inliers = t.frames[0].inliers.clone();
                AbsolutePose {
                    camera_to_world: t.camera_to_map(&frames[0].camera_to_track),
                    inliers,
                    reprojection_error: t.reprojection_error,
                    covariance_w2c,
                    focal: scene.camera.fx,
                }
            });
            let correct = {
                let gt_cw = gt.inverse();
                frames[0]
                    .points3d
                    .iter()
                    .zip(&frames[0].points2d)
                    .filter(|(p, k)| {
                        scene
                            .camera
                            .project(&(gt_cw * Point3::from(**p)))
                            .is_some_and(|(u, v)| (u - k.0 as f64).hypot(v - k.1 as f64) <= cfg.precision_px)
                    })
                    .count()
            };
            let (localised, te, re) = match &first {
                Some(p) => (
                    true,
                    (p.camera_to_world.translation.vector - gt.translation.vector).norm(),
                    rotation_error_deg(
                        &p.camera_to_world.rotation.to_rotation_matrix(),
                        &gt.rotation.to_rotation_matrix(),
                    ),
                ),
                None => (false, f64::INFINITY, 180.0),
            };
            let mahalanobis2 = first.as_ref().and_then(|p| {
                let sigma = pose_covariance(PoseConvention::default(), &p.camera_to_world, p.covariance_w2c.as_ref()?);
                let e = pose_difference(&gt, &p.camera_to_world);
                sigma.try_inverse().map(|inv| (e.transpose() * inv * e)[0])
            });
            recs.push(QueryRecord {
                frame: scene.frames[q].stamp.clone(),
                localised,
                translation_error: te,
                rotation_error_deg: re,
                matches,
                correct_matches: correct,
                inliers: estimate.as_ref().map_or(0, |t| t.inlier_count()),
                confidence: first.as_ref().map_or(0.0, |p| crate::map::localize::confidence(p, &frames[0].points3d)),
                seconds,
                baseline_to_map,
                angle_to_map_deg,
                focal: first.as_ref().map(|p| p.focal),
                mahalanobis2,
                within_confidence_tolerance: first
                    .as_ref()
                    .map(|p| within_confidence_tolerance(p, &frames[0].points3d, &gt)),
                stage1_cap: None,
                pnp: None,
                diagnosis: None,
            });
        }
        Ok(recs)
    }
}

/// Tracks of `cfg.track` consecutive frames (every `foreign_stride`-th start) of the foreign scenes, with their
/// ground-truth relative poses, localised against the map: (tracks, localised).
pub(super) fn foreign_tracks(
    map: &BuiltMap,
    method: crate::offline::eval::methods::Method,
    cfg: &RelocConfig,
    loc: &LocalizeSettings,
    embedder: Option<&Embedder>,
) -> Result<(usize, usize), BoxError> {
    let limits = ImageLimitSettings::default();
    let (mut tracks, mut localised) = (0, 0);
    for dir in &cfg.foreign {
        let other = Scene::load(dir)?;
        let posed: Vec<usize> = (0..other.frames.len()).filter(|&i| other.frames[i].pose.is_some()).collect();
        for start in (0..posed.len().saturating_sub(cfg.track.saturating_sub(1))).step_by(cfg.foreign_stride.max(1)) {
            let members = &posed[start..(start + cfg.track).min(posed.len())];
            let truth: Vec<Isometry3<f64>> = members.iter().map(|&j| other.frames[j].pose.unwrap()).collect();
            let tracked = tracked_poses(&truth, &cfg.track_noise, cfg.track_noise.seed ^ start as u64);
            let mut frames = Vec::new();
            for (&j, q_track) in members.iter().zip(tracked) {
                let bytes = std::fs::read(&other.frames[j].rgb)
                    .map_err(|e| format!("{}: {e}", other.frames[j].rgb.display()))?;
                let d = describe(method, &decode_grey(&bytes, &limits)?, &cfg.extractor, embedder)?;
                let (v, _) = vectors(method, &d)?;
                let features = features_of(&d)?;
                let out = localize(&map.data, &map.index, &features, &v, &other.camera, None, loc)?;
                let points2d = out.matches.iter().map(|m| features.keypoints[m.keypoint]).map(|k| (k.x, k.y)).collect();
                frames.push(TrackFrame {
                    camera_to_track: q_track,
                    camera: other.camera,
                    points3d: out.points,
                    points2d,
                    own: out.pose,
                });
            }
            tracks += 1;
            let t = locate(&frames, loc, cfg)?;
            localised += usize::from(t.is_some());
        }
    }
    Ok((tracks, localised))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_track_is_the_query_and_its_nearest_queries() {
        assert_eq!(track_of(10, &[1, 4, 9, 10, 12, 30], 3), vec![10, 9, 12]);
        assert_eq!(track_of(1, &[1, 4, 9], 5), vec![1, 4, 9]);
    }

    #[test]
    fn tracked_poses_are_the_truth_relative_to_the_first_with_the_stated_error() {
        let p = |x: f64, yaw: f64| {
            Isometry3::from_parts(Translation3::new(x, 1.0, 2.0), UnitQuaternion::from_euler_angles(0.0, yaw, 0.0))
        };
        let truth = [p(0.0, 0.0), p(1.0, 0.1), p(3.0, 0.2)];
        let exact = tracked_poses(&truth, &TrackNoise { translation_share: 0.0, degrees_per_frame: 0.0, seed: 1 }, 1);
        assert!((exact[0].translation.vector.norm()) < 1e-12);
        assert!((exact[2].translation.vector - Vector3::new(3.0, 0.0, 0.0)).norm() < 1e-9);
        let noisy = tracked_poses(&truth, &TrackNoise::default(), 1);
        for k in 1..3 {
            let shift = (noisy[k].translation.vector - exact[k].translation.vector).norm();
            assert!((shift - 0.01 * exact[k].translation.vector.norm()).abs() < 1e-9, "{k}: {shift}");
            let turn = noisy[k].rotation.angle_to(&exact[k].rotation).to_degrees();
            assert!((turn - 0.5 * k as f64).abs() < 1e-6, "{k}: {turn}");
        }
    }
}
