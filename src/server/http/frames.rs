//! Handlers of the frame routes: Describe, MatchPair and Localize. MatchPair and Localize answer with a
//! picture instead of JSON when asked (`?render=png` or `Accept: image/png`; [`Render`]).

use std::sync::Arc;

use axum::extract::{Request, State};
use axum::http::{header, Uri};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use base64::Engine;

use super::body::{
    frame_input, json_body, parse_json, query_pairs, read_body, wants_picture, ApiPath, Body, IntrinsicsQuery, Render,
    FRAME_BODIES, JSON_OR_MULTIPART,
};
use super::error::{ApiErrors, ApiResult};
use super::wire::{self, examples};
use crate::camera::quaternion_xyzw;
use crate::matching::DEFAULT_RATIO;
use crate::render::{self, Backdrop};
use crate::server::app::{App, MapId, NoMap};
use crate::server::auth::Authorized;
use crate::server::http::plumbing::call;
use crate::service::{
    FrameInput, FrameSource, PairOptions, PoseConvention, Prior, ServiceError, Similarity, TrackFrameInput,
    TrackRequest, TrackScale, TrackerError,
};

/// What a frame is drawn on: its image, or a blank canvas of its keypoint set's size.
fn backdrop(f: &FrameInput) -> Backdrop<'_> {
    match &f.source {
        FrameSource::Image(bytes) => Backdrop::Image(bytes),
        FrameSource::Keypoints(k) => Backdrop::Blank { width: k.width, height: k.height },
    }
}

/// A copy of the frame kept for drawing after the service consumed the original.
fn keep_for_picture(wanted: bool, f: &FrameInput) -> Option<FrameInput> {
    wanted.then(|| f.clone())
}

fn png(bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "no-store")], bytes).into_response()
}

/// A picture with the counts a page shows beside it.
fn png_with_counts(bytes: Vec<u8>, matches: usize, inliers: usize) -> Response {
    let mut resp = png(bytes);
    let h = resp.headers_mut();
    h.insert("x-scone-matches", matches.into());
    h.insert("x-scone-inliers", inliers.into());
    resp
}

/// Keypoints, FREAK descriptors and SConE embeddings of one frame (rpc Matching.Describe).
#[utoipa::path(post, path = "/v1/describe", tag = "matching",
    request_body(description = "A frame: raw image body, multipart, or JSON (base64 image or keypoints)", content(
        (wire::DescribeRequest = "application/json", example = examples::describe),
        (wire::FrameForm = "multipart/form-data"),
        (wire::Binary = "image/jpeg"),
        (wire::Binary = "image/png"),
        (wire::Binary = "application/octet-stream"))),
    responses((status = 200, description = "The frame's description", body = wire::DescribeResponse), ApiErrors))]
pub async fn describe(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    req: Request,
) -> ApiResult<Json<wire::DescribeResponse>> {
    let body = read_body(req, app.settings.server.max_request_bytes, FRAME_BODIES).await?;
    let out = call(&app, authorized, NoMap, move |a, ()| {
        let j: wire::DescribeRequest = parse_json(&body.json)?;
        let f = frame_input(j.frame, body.image, &[], "frame")?;
        let d = a.service.describe(f.source)?;
        a.metrics.stages(&d.times);
        Ok(wire::DescribeResponse {
            width: d.features.width,
            height: d.features.height,
            keypoints: d.features.keypoints.iter().map(Into::into).collect(),
            descriptors_base64: base64::engine::general_purpose::STANDARD.encode(d.features.descriptors.concat()),
            embeddings: d.embeddings,
            dim: d.dim,
            model_id: d.model_id,
            context_base64: base64::engine::general_purpose::STANDARD.encode(d.features.context.concat()),
            extraction: a.service.extraction().into(),
        })
    })
    .await?;
    Ok(Json(out))
}

/// Matches between two frames and their relative pose (rpc Matching.MatchPair); with `?render=png` or
/// `Accept: image/png`, the two frames side by side with the matches drawn (inliers green, outliers red).
#[utoipa::path(post, path = "/v1/match", tag = "matching",
    params(wire::RenderQuery),
    request_body(description = "Two frames: multipart (image1, image2) or JSON", content(
        (wire::MatchRequest = "application/json", example = examples::match_pair),
        (wire::PairForm = "multipart/form-data"))),
    responses(
        (status = 200, description = "Matches and relative pose, or their picture", content(
            (wire::MatchResponse = "application/json"),
            (wire::Binary = "image/png")),
            headers(("x-scone-matches" = usize, description = "With a picture: putative matches drawn"),
                    ("x-scone-inliers" = usize, description = "With a picture: inliers of the relative pose"))),
        ApiErrors))]
pub async fn match_pair(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    Render(picture): Render,
    req: Request,
) -> ApiResult<Response> {
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    call(&app, authorized, NoMap, move |a, ()| {
        let j: wire::MatchRequest = parse_json(&body.json)?;
        let f1 = frame_input(j.frame1, body.image, &[], "frame1")?;
        let f2 = frame_input(j.frame2, body.image2, &[], "frame2")?;
        let (keep1, keep2) = (keep_for_picture(picture, &f1), keep_for_picture(picture, &f2));
        let options = PairOptions {
            ratio: j.ratio.unwrap_or(DEFAULT_RATIO),
            mutual: j.mutual,
            matcher: j.matcher.map(Into::into),
        };
        let o = a.service.match_pair(f1, f2, options)?;
        a.metrics.stages(&o.times);
        if let (Some(f1), Some(f2)) = (keep1, keep2) {
            let pairs: Vec<(usize, usize)> = o.matches.iter().map(|m| (m.query, m.train)).collect();
            let pose = o.pose.as_ref().map(|p| (p.rotation.angle().to_degrees(), p.translation.into()));
            let caption = render::pair_caption(o.matcher.name(), options.ratio, pairs.len(), o.inlier_count(), pose);
            let drawn = render::pair(
                &backdrop(&f1),
                &backdrop(&f2),
                &o.points1,
                &o.points2,
                &pairs,
                &o.inlier_flags(),
                &caption,
            )
            .map_err(ServiceError::from)?;
            return Ok(png_with_counts(drawn, pairs.len(), o.inlier_count()));
        }
        let matches = o
            .matches
            .iter()
            .zip(o.inlier_flags())
            .map(|(m, inlier)| wire::PairMatch { index1: m.query, index2: m.train, distance: m.distance, inlier })
            .collect();
        let convention: PoseConvention = j.pose_convention.map(Into::into).unwrap_or_default();
        let pose = o.pose.as_ref().map(|p| {
            let (r, t) = convention.relative_from_opencv(&p.rotation, &p.translation);
            let [qx, qy, qz, qw] = quaternion_xyzw(&r);
            wire::RelativePose { qx, qy, qz, qw, tx: t.x, ty: t.y, tz: t.z }
        });
        Ok(Json(wire::MatchResponse { matcher: o.matcher.into(), matches, pose, inliers: o.inlier_count() })
            .into_response())
    })
    .await
}

/// The camera-to-world pose of a frame against a map (rpc Relocalization.Localize); with `?render=png` or
/// `Accept: image/png`, the frame with its 2D-3D matches (inliers green, outliers red) and the inlier
/// landmarks reprojected at the estimated pose (cyan rings, residuals in yellow).
#[utoipa::path(post, path = "/v1/maps/{map_id}/localize", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office"), IntrinsicsQuery, wire::RenderQuery,
        wire::ConventionQuery),
    request_body(description = "A frame: raw image body (intrinsics in the query), multipart, or JSON", content(
        (wire::LocalizeRequest = "application/json", example = examples::localize),
        (wire::FrameForm = "multipart/form-data"),
        (wire::Binary = "image/jpeg"),
        (wire::Binary = "image/png"),
        (wire::Binary = "application/octet-stream"))),
    responses(
        (status = 200, description = "A pose or localized=false, or their picture", content(
            (wire::LocalizeResponse = "application/json"),
            (wire::Binary = "image/png"))),
        ApiErrors))]
pub async fn localize(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(map_id): ApiPath<String>,
    req: Request,
) -> ApiResult<Response> {
    let uri = req.uri().clone();
    let accept = req.headers().get(header::ACCEPT).and_then(|v| v.to_str().ok()).map(str::to_string);
    let body = read_body(req, app.settings.server.max_request_bytes, FRAME_BODIES).await?;
    call(&app, authorized, MapId(map_id.clone()), move |a, map| {
        let LocalizeCall { frame: f, prior, convention, picture } = LocalizeCall::parse(&uri, accept.as_deref(), body)?;
        let kept = keep_for_picture(picture, &f);
        let o = a.service.localize(&map, f, prior)?;
        a.metrics.stages(&o.times);
        if let Some(f) = kept {
            let inliers = o.pose.as_ref().map_or(0, |p| p.inliers.len());
            let pose = o
                .pose
                .as_ref()
                .map(|p| (p.camera_to_world.translation.vector.into(), p.reprojection_error, o.confidence));
            let caption = render::localization_caption(&map_id, o.matches.len(), inliers, pose);
            let drawn = render::localization(&backdrop(&f), &o.drawn_points(), &caption).map_err(ServiceError::from)?;
            return Ok(png(drawn));
        }
        Ok(Json(wire::LocalizeResponse {
            localized: o.pose.is_some(),
            pose: o
                .pose
                .as_ref()
                .map(|p| wire::Pose::from_isometry(&convention.from_opencv_camera_to_world(&p.camera_to_world))),
            matches: o.matches.len(),
            inliers: o.pose.as_ref().map_or(0, |p| p.inliers.len()),
            reprojection_error: o.pose.as_ref().map_or(0.0, |p| p.reprojection_error),
            confidence: o.confidence,
            focal_length: o.pose.as_ref().map_or(0.0, |p| p.focal),
            focal_estimated: o.focal_estimated,
            covariance: o.covariance(convention),
        })
        .into_response())
    })
    .await
}

/// Everything a Localize request says, parsed in one place: the query string (intrinsics for a raw image
/// body, `render`, `pose_convention`), the `Accept` header and the body (its JSON and image). Runs on the
/// CPU pool: a JSON body may carry a base64 image.
struct LocalizeCall {
    frame: FrameInput,
    prior: Option<Prior>,
    convention: PoseConvention,
    picture: bool,
}

impl LocalizeCall {
    fn parse(uri: &Uri, accept: Option<&str>, body: Body) -> Result<Self, ServiceError> {
        let pairs = query_pairs(uri)?;
        let picture = wants_picture(&pairs, accept)?;
        let query_intrinsics = IntrinsicsQuery::parse(&pairs)?.intrinsics()?;
        let query_convention = query_convention(&pairs)?;
        let j: wire::LocalizeRequest = parse_json(&body.json)?;
        let convention: PoseConvention = match (j.pose_convention, query_convention) {
            (Some(a), Some(b)) if a != b => {
                return Err(ServiceError::invalid("pose_convention", "the body and the query string disagree"))
            }
            (a, b) => a.or(b).map(Into::into).unwrap_or_default(),
        };
        let outer = [("intrinsics", j.intrinsics), ("the query string's intrinsics", query_intrinsics)];
        let frame = frame_input(j.frame, body.image, &outer, "frame")?;
        let prior = j.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius });
        Ok(Self { frame, prior, convention, picture })
    }
}

/// `?pose_convention=`, when the query string gives it.
fn query_convention(pairs: &[(String, String)]) -> Result<Option<wire::PoseConvention>, ServiceError> {
    let mut given = pairs.iter().filter(|(k, _)| k == "pose_convention").map(|(_, v)| v);
    match (given.next(), given.next()) {
        (Some(_), Some(_)) => Err(ServiceError::invalid("pose_convention", "is given more than once")),
        (Some(v), None) => serde_json::from_value(serde_json::Value::String(v.clone())).map(Some).map_err(|_| {
            ServiceError::invalid(
                "pose_convention",
                format!("'{v}' is not opencv_camera_to_world, opencv_world_to_camera or opengl_camera_to_world"),
            )
        }),
        (None, _) => Ok(None),
    }
}

/// A short track against a map (rpc Matching.LocalizeTrack): 2-10 frames with their poses relative to each
/// other, located together.
#[utoipa::path(post, path = "/v1/maps/{map_id}/localize-track", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    request_body(description = "Frames with poses: JSON (base64 images or keypoints), or multipart (request and \
        the images as parts track0, track1, ...)", content(
        (wire::LocalizeTrackRequest = "application/json", example = examples::localize_track),
        (wire::TrackForm = "multipart/form-data"))),
    responses((status = 200, description = "The track's transform into the map, or localized=false",
        body = wire::LocalizeTrackResponse), ApiErrors))]
pub async fn localize_track(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(map_id): ApiPath<String>,
    req: Request,
) -> ApiResult<Json<wire::LocalizeTrackResponse>> {
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    let out = call(&app, authorized, MapId(map_id), move |a, map| {
        let Some(json) = &body.json else {
            return Err(ServiceError::invalid(
                "body",
                "a track needs JSON (frames with their poses): send application/json or a multipart part 'request'",
            ));
        };
        let j: wire::LocalizeTrackRequest = json_body(json)?;
        let convention: PoseConvention = j.pose_convention.map(Into::into).unwrap_or_default();
        let mut images = body.track;
        let mut frames = Vec::with_capacity(j.frames.len());
        for (i, f) in j.frames.into_iter().enumerate() {
            let frame = frame_input(f.frame, images.remove(&i), &[], &format!("frames[{i}].frame"))?;
            frames.push(TrackFrameInput { frame, pose: f.pose.domain() });
        }
        if let Some(n) = images.keys().next() {
            return Err(ServiceError::invalid(format!("track{n}"), "names no frame of the request's frames"));
        }
        let request = TrackRequest {
            frames,
            convention,
            scale: if j.estimate_scale { TrackScale::Free } else { TrackScale::Rigid },
            prior: j.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius }),
            tracker: j.tracker_error.map_or_else(TrackerError::default, |e| TrackerError {
                translation_share: e.translation_share,
                degrees_per_frame: e.degrees_per_frame,
            }),
        };
        let o = a.service.localize_track(&map, request)?;
        a.metrics.stages(&o.times);
        Ok(wire::LocalizeTrackResponse {
            localized: o.map_from_track.is_some(),
            map_from_track: o.map_from_track.as_ref().map(|s| Similarity::from_nalgebra(s).into()),
            frames: o
                .frames
                .iter()
                .map(|f| wire::TrackFrameResult {
                    pose: f
                        .camera_to_map
                        .as_ref()
                        .map(|p| wire::Pose::from_isometry(&convention.from_opencv_camera_to_world(p))),
                    matches: f.matches,
                    inliers: f.inliers,
                    dropped: f.dropped,
                    localized_alone: f.localized_alone,
                })
                .collect(),
            inliers: o.inliers,
            reprojection_error: o.reprojection_error,
            confidence: o.confidence,
            covariance: o.covariance(convention),
            single_frame: o.single_frame,
        })
    })
    .await?;
    Ok(Json(out))
}
