//! Handlers of the map routes: create, list, get, delete, contents, keyframes, export and import. (Localize,
//! a frame route under a map, is in [`super::frames`].)

use std::sync::Arc;

use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};

use super::body::{
    base64, bytes_within, frame_input, json_body, media_type, read_body, too_large, ApiPath, JSON_ONLY,
    JSON_OR_MULTIPART, MAP_FILE,
};
use super::error::{invalid, ApiError, ApiErrors, ApiResult};
use super::wire::{self, examples};
use crate::server::app::{App, MapId, NoMap};
use crate::server::auth::Authorized;
use crate::server::http::plumbing::call;
use crate::service::{ExternalObservation, KeyframeRequest, PoseConvention, ServiceError, DEFAULT_CONTENTS_LANDMARKS};

/// A new, empty map (rpc Maps.CreateMap).
#[utoipa::path(post, path = "/v1/maps", tag = "maps",
    request_body(content((wire::CreateMapRequest = "application/json", example = examples::create_map))),
    responses((status = 201, description = "The new map", body = wire::MapInfo), ApiErrors))]
pub async fn create_map(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<wire::MapInfo>)> {
    media_type(&headers, JSON_ONLY)?;
    let limit = app.settings.server.max_request_bytes;
    let body = bytes_within(req, limit, too_large(limit)).await?;
    let j: wire::CreateMapRequest = json_body(&body)?;
    let s = call(&app, authorized, NoMap, move |a, ()| a.service.create_map(&j.map_id)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}

/// The maps (with object storage every stored one) and those held back, with the reason (rpc Maps.ListMaps).
#[utoipa::path(get, path = "/v1/maps", tag = "maps",
    responses((status = 200, description = "Every map", body = wire::MapList), ApiErrors))]
pub async fn list_maps(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
) -> ApiResult<Json<wire::MapList>> {
    let listing = call(&app, authorized, NoMap, |a, ()| a.service.list_maps()).await?;
    Ok(Json(wire::MapList {
        maps: listing.maps.into_iter().map(Into::into).collect(),
        held_back: listing.held_back.into_iter().map(|(map_id, reason)| wire::HeldBack { map_id, reason }).collect(),
    }))
}

/// One map's statistics (rpc Maps.GetMap).
#[utoipa::path(get, path = "/v1/maps/{map_id}", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    responses((status = 200, description = "The map", body = wire::MapInfo), ApiErrors))]
pub async fn get_map(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Json<wire::MapInfo>> {
    let s = call(&app, authorized, MapId(id), |_, map| Ok(map.summary())).await?;
    Ok(Json(s.into()))
}

/// Deletes a map and everything stored for it (rpc Maps.DeleteMap).
#[utoipa::path(delete, path = "/v1/maps/{map_id}", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    responses((status = 204, description = "Deleted"), ApiErrors))]
pub async fn delete_map(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<StatusCode> {
    call(&app, authorized, NoMap, move |a, ()| a.service.delete_map(&id)).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// A map's contents for viewers: keyframe poses and intrinsics, and its landmarks (an even subsample of at
/// most `max_landmarks`). The console draws its 3D view from this.
#[utoipa::path(get, path = "/v1/maps/{map_id}/contents", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office"), wire::ContentsQuery),
    responses((status = 200, description = "Keyframes and landmarks", body = wire::MapContents), ApiErrors))]
pub async fn map_contents(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
    query: Result<Query<wire::ContentsQuery>, axum::extract::rejection::QueryRejection>,
) -> ApiResult<Json<wire::MapContents>> {
    let Query(q) = query.map_err(|e| invalid("query string", e.body_text()))?;
    let max = q.max_landmarks.unwrap_or(DEFAULT_CONTENTS_LANDMARKS);
    let convention: PoseConvention = q.pose_convention.map(Into::into).unwrap_or_default();
    let out = call(&app, authorized, MapId(id.clone()), move |a, map| {
        let c = a.service.map_contents(&map, max)?;
        Ok(wire::MapContents {
            map_id: id,
            version: c.version,
            keyframes: c
                .keyframes
                .iter()
                .map(|(kf, pose, cam)| wire::KeyframeView {
                    keyframe_id: *kf,
                    pose: wire::Pose::from_isometry(&convention.from_opencv_camera_to_world(&pose.isometry())),
                    intrinsics: wire::Intrinsics {
                        fx: cam.fx,
                        fy: cam.fy,
                        cx: cam.cx,
                        cy: cam.cy,
                        width: Some(cam.width),
                        height: Some(cam.height),
                        // Keyframes are stored undistorted.
                        distortion_model: None,
                        distortion: Vec::new(),
                    },
                })
                .collect(),
            landmarks: c
                .landmarks
                .iter()
                .map(|&(lid, [x, y, z], n)| wire::LandmarkView { id: lid, x, y, z, observations: n })
                .collect(),
            landmarks_total: c.landmarks_total,
        })
    })
    .await?;
    Ok(Json(out))
}

/// One posed keyframe (rpc Maps.AddKeyframes, one message), answered once the write is durable.
#[utoipa::path(post, path = "/v1/maps/{map_id}/keyframes", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    request_body(description = "A posed frame: multipart (request, image, depth) or JSON", content(
        (wire::KeyframeRequest = "application/json", example = examples::keyframe),
        (wire::KeyframeForm = "multipart/form-data"))),
    responses((status = 200, description = "Durable", body = wire::KeyframeAck), ApiErrors))]
pub async fn add_keyframe(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(map_id): ApiPath<String>,
    req: Request,
) -> ApiResult<Json<wire::KeyframeAck>> {
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    let out = call(&app, authorized, MapId(map_id), move |a, map| {
        let Some(json) = &body.json else {
            return Err(ServiceError::invalid(
                "body",
                "a keyframe needs JSON (keyframe_id, pose, intrinsics): send application/json or a multipart part 'request'",
            ));
        };
        let j: wire::KeyframeRequest = json_body(json)?;
        let f = frame_input(j.frame, body.image, &[("intrinsics", j.intrinsics)], "frame")?;
        let depth_png = match (body.depth, j.depth_png_base64) {
            (Some(d), None) => Some(d.to_vec()),
            (None, Some(b)) => Some(base64("depth_png_base64", &b)?),
            (None, None) => None,
            (Some(_), Some(_)) => return Err(ServiceError::invalid("depth", "give a depth part or depth_png_base64, not both")),
        };
        let request = KeyframeRequest {
            id: j.keyframe_id,
            frame: f,
            pose: j.pose.domain(),
            convention: j.pose_convention.map(Into::into).unwrap_or_default(),
            depth_png,
            depth_scale: j.depth_scale,
            external_landmarks: j
                .external_landmarks
                .iter()
                .map(|o| ExternalObservation {
                    x: o.x,
                    y: o.y,
                    landmark_id: o.landmark_id,
                    point: [o.point.x, o.point.y, o.point.z],
                })
                .collect(),
        };
        let (added, times) = a.service.add_keyframe(&map, request)?;
        a.metrics.stages(&times);
        Ok(wire::KeyframeAck {
            keyframe_id: added.keyframe,
            new_landmarks: added.new_landmarks,
            observations: added.observations,
            map_version: added.version,
            external_rejected: added.external.rejected,
            external_unassociated: added.external.unassociated,
        })
    })
    .await?;
    Ok(Json(out))
}

/// Removes a keyframe; its observations leave the index (rpc Maps.RemoveKeyframe).
#[utoipa::path(delete, path = "/v1/maps/{map_id}/keyframes/{keyframe_id}", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office"),
           ("keyframe_id" = u64, Path, description = "The keyframe", example = 1)),
    responses((status = 200, description = "The map after the removal", body = wire::MapInfo), ApiErrors))]
pub async fn remove_keyframe(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath((id, keyframe)): ApiPath<(String, String)>,
) -> ApiResult<Json<wire::MapInfo>> {
    let keyframe: u64 = keyframe
        .parse()
        .map_err(|_| invalid("keyframe_id", format!("'{keyframe}' is not a keyframe id (a whole number)")))?;
    let s = call(&app, authorized, MapId(id), move |a, map| a.service.remove_keyframe(&map, keyframe)).await?;
    Ok(Json(s.into()))
}

/// Merges another map into this one (rpc Maps.MergeMaps): without a transform, the server estimates it from
/// the source keyframes it localises here. One durable write; the source is not changed.
#[utoipa::path(post, path = "/v1/maps/{map_id}/merge", tag = "maps",
    params(("map_id" = String, Path, description = "The target map", example = "office")),
    request_body(content((wire::MergeMapsRequest = "application/json", example = examples::merge_maps))),
    responses((status = 200, description = "What the merge did", body = wire::MergeMapsResponse), ApiErrors))]
pub async fn merge_maps(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<wire::MergeMapsResponse>> {
    media_type(&headers, JSON_ONLY)?;
    let limit = app.settings.server.max_request_bytes;
    let body = bytes_within(req, limit, too_large(limit)).await?;
    let j: wire::MergeMapsRequest = json_body(&body)?;
    let o = call(&app, authorized, MapId(id), move |a, map| {
        a.service.merge_maps(&map, &j.source_map_id, j.transform.map(Into::into))
    })
    .await?;
    Ok(Json(wire::MergeMapsResponse {
        target: o.target.into(),
        transform: o.transform.into(),
        transform_estimated: o.estimated,
        source_keyframes: o.source_keyframes,
        keyframes_localised: o.localised,
        transform_inliers: o.inliers,
        keyframe_id_offset: o.keyframe_id_offset,
        landmarks_fused: o.landmarks_fused,
        landmarks_added: o.landmarks_added,
    }))
}

/// The map as one versioned, checksummed file (rpc Maps.ExportMap).
#[utoipa::path(get, path = "/v1/maps/{map_id}/export", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    responses((status = 200, description = "The map file", content((wire::Binary = "application/octet-stream"))),
        ApiErrors))]
pub async fn export_map(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
) -> ApiResult<Response> {
    let name = id.clone();
    let bytes = call(&app, authorized, MapId(id), |a, map| a.service.export_map(&map)).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{name}.scone-map\"")),
        ],
        bytes,
    )
        .into_response())
}

/// A file from ExportMap under a new id (rpc Maps.ImportMap). Idempotent: the same content again into the map
/// it made is 201 with that map.
#[utoipa::path(post, path = "/v1/maps/{map_id}/import", tag = "maps",
    params(("map_id" = String, Path, description = "The new map's id", example = "office-copy")),
    request_body(content((wire::Binary = "application/octet-stream"))),
    responses((status = 201, description = "The imported map", body = wire::MapInfo), ApiErrors))]
pub async fn import_map(
    State(app): State<Arc<App>>,
    Extension(authorized): Extension<Authorized>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<wire::MapInfo>)> {
    media_type(&headers, MAP_FILE)?;
    let limit = app.settings.server.max_map_bytes;
    let refusal = ApiError::Service(ServiceError::TooLarge { what: "the map file".into(), limit });
    let bytes = bytes_within(req, limit, refusal).await?;
    let s = call(&app, authorized, NoMap, move |a, ()| a.service.import_map(&id, &bytes)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}
