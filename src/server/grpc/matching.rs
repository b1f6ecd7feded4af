//! The `scone.v1.Matching` service: Describe, MatchPair, Localize and LocalizeTrack.

use tonic::{Request, Response, Status};

use super::api::{authorized, GrpcApi};
use super::convert::{convention, frame_input, invalid, keypoint_out, pose_out, similarity_out};
use crate::camera::quaternion_xyzw;
use crate::camera::Pose;
use crate::matching::{SconeMatcher, DEFAULT_RATIO};
use crate::server::app::{MapId, NoMap};
use crate::server::proto;
use crate::service::{
    PairOptions, Prior, ServiceError, Similarity, TrackFrameInput, TrackRequest, TrackScale, TrackerError,
};

#[tonic::async_trait]
impl proto::matching_server::Matching for GrpcApi {
    async fn describe(
        &self,
        req: Request<proto::DescribeRequest>,
    ) -> Result<Response<proto::DescribeResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, NoMap, move |a, ()| {
                let f = frame_input(r.frame, "frame")?;
                let d = a.service.describe(f.source)?;
                a.metrics.stages(&d.times);
                Ok(proto::DescribeResponse {
                    keypoints: d.features.keypoints.iter().map(keypoint_out).collect(),
                    descriptors: d.features.descriptors.concat(),
                    embeddings: d.embeddings,
                    dim: d.dim as u32,
                    model_id: d.model_id,
                    context: d.features.context.concat(),
                    extraction: Some(extraction_out(a.service.extraction())),
                })
            })
            .await?;
        Ok(Response::new(out))
    }

    async fn match_pair(
        &self,
        req: Request<proto::MatchPairRequest>,
    ) -> Result<Response<proto::MatchPairResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, NoMap, move |a, ()| {
                let matcher = match proto::PairMatcher::try_from(r.matcher) {
                    Ok(proto::PairMatcher::Default) => None,
                    Ok(proto::PairMatcher::Plain) => Some(SconeMatcher::Plain),
                    Ok(proto::PairMatcher::Union) => Some(SconeMatcher::Union),
                    Ok(proto::PairMatcher::Rerank) => Some(SconeMatcher::Rerank),
                    Ok(proto::PairMatcher::Freak) => Some(SconeMatcher::Freak),
                    Ok(proto::PairMatcher::ScaleAware) => Some(SconeMatcher::ScaleAware),
                    Ok(proto::PairMatcher::Joint) => Some(SconeMatcher::Joint),
                    Ok(proto::PairMatcher::Both) => Some(SconeMatcher::Both),
                    Err(_) => return Err(invalid("matcher", &format!("{} is not a PairMatcher", r.matcher))),
                };
                let conv = convention(r.pose_convention)?;
                let options = PairOptions {
                    ratio: if r.ratio == 0.0 { DEFAULT_RATIO } else { r.ratio },
                    mutual: r.mutual,
                    matcher,
                };
                let o = a.service.match_pair(
                    frame_input(r.frame1, "frame1")?,
                    frame_input(r.frame2, "frame2")?,
                    options,
                )?;
                a.metrics.stages(&o.times);
                let ran = match o.matcher {
                    SconeMatcher::Plain => proto::PairMatcher::Plain,
                    SconeMatcher::Union => proto::PairMatcher::Union,
                    SconeMatcher::Rerank => proto::PairMatcher::Rerank,
                    SconeMatcher::Freak => proto::PairMatcher::Freak,
                    SconeMatcher::ScaleAware => proto::PairMatcher::ScaleAware,
                    SconeMatcher::Joint => proto::PairMatcher::Joint,
                    SconeMatcher::Both => proto::PairMatcher::Both,
                };
                Ok(proto::MatchPairResponse {
                    matcher: ran as i32,
                    matches: o
                        .matches
                        .iter()
                        .zip(o.inlier_flags())
                        .map(|(m, inlier)| proto::Match {
                            index1: m.query as u32,
                            index2: m.train as u32,
                            distance: m.distance,
                            inlier,
                        })
                        .collect(),
                    inliers: o.inlier_count() as u32,
                    pose: o.pose.as_ref().map(|p| {
                        let (r, t) = conv.relative_from_opencv(&p.rotation, &p.translation);
                        let [qx, qy, qz, qw] = quaternion_xyzw(&r);
                        proto::RelativePose { qx, qy, qz, qw, tx: t.x, ty: t.y, tz: t.z }
                    }),
                })
            })
            .await?;
        Ok(Response::new(out))
    }

    async fn localize(
        &self,
        req: Request<proto::LocalizeRequest>,
    ) -> Result<Response<proto::LocalizeResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, MapId(r.map_id.clone()), move |a, map| {
                let conv = convention(r.pose_convention)?;
                let prior = r.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius });
                let o = a.service.localize(&map, frame_input(r.frame, "frame")?, prior)?;
                a.metrics.stages(&o.times);
                Ok(proto::LocalizeResponse {
                    localized: o.pose.is_some(),
                    pose: o.pose.as_ref().map(|p| pose_out(&conv.from_opencv_camera_to_world(&p.camera_to_world))),
                    matches: o.matches.len() as u32,
                    inliers: o.pose.as_ref().map_or(0, |p| p.inliers.len() as u32),
                    reprojection_error: o.pose.as_ref().map_or(0.0, |p| p.reprojection_error),
                    confidence: o.confidence,
                    focal_length: o.pose.as_ref().map_or(0.0, |p| p.focal),
                    focal_estimated: o.focal_estimated,
                    covariance: o.covariance(conv),
                })
            })
            .await?;
        Ok(Response::new(out))
    }

    async fn localize_track(
        &self,
        req: Request<proto::LocalizeTrackRequest>,
    ) -> Result<Response<proto::LocalizeTrackResponse>, Status> {
        let authorized = authorized(&req)?;
        let r = req.into_inner();
        let out = self
            .call(authorized, MapId(r.map_id.clone()), move |a, map| {
                let conv = convention(r.pose_convention)?;
                let frames = r
                    .frames
                    .into_iter()
                    .enumerate()
                    .map(|(i, f)| {
                        let p = f.pose.ok_or_else(|| invalid(&format!("frames[{i}].pose"), "is required"))?;
                        Ok(TrackFrameInput {
                            frame: frame_input(f.frame, &format!("frames[{i}].frame"))?,
                            pose: Pose { translation: [p.tx, p.ty, p.tz], rotation: [p.qx, p.qy, p.qz, p.qw] },
                        })
                    })
                    .collect::<Result<Vec<_>, ServiceError>>()?;
                let request = TrackRequest {
                    frames,
                    convention: conv,
                    scale: if r.estimate_scale { TrackScale::Free } else { TrackScale::Rigid },
                    prior: r.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius }),
                    tracker: r.tracker_error.map_or_else(TrackerError::default, |e| TrackerError {
                        translation_share: e.translation_share,
                        degrees_per_frame: e.degrees_per_frame,
                    }),
                };
                let o = a.service.localize_track(&map, request)?;
                a.metrics.stages(&o.times);
                Ok(proto::LocalizeTrackResponse {
                    localized: o.map_from_track.is_some(),
                    map_from_track: o.map_from_track.as_ref().map(|s| similarity_out(&Similarity::from_nalgebra(s))),
                    frames: o
                        .frames
                        .iter()
                        .map(|f| proto::TrackFrameResult {
                            pose: f.camera_to_map.as_ref().map(|p| pose_out(&conv.from_opencv_camera_to_world(p))),
                            matches: f.matches as u32,
                            inliers: f.inliers as u32,
                            dropped: f.dropped,
                            localized_alone: f.localized_alone,
                        })
                        .collect(),
                    inliers: o.inliers as u32,
                    reprojection_error: o.reprojection_error,
                    confidence: o.confidence,
                    covariance: o.covariance(conv),
                    single_frame: o.single_frame.map_or(-1, |f| f as i32),
                })
            })
            .await?;
        Ok(Response::new(out))
    }
}

/// The extraction a server runs, on the wire.
fn extraction_out(e: &crate::describe::features::ExtractorSettings) -> proto::Extraction {
    proto::Extraction {
        fast_threshold: e.fast_threshold,
        max_keypoints: e.max_keypoints as u32,
        levels: e.levels,
        scale_factor: e.scale_factor,
        grid_cell: e.grid_cell,
    }
}
