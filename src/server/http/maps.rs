//! Handlers of the map routes: create, list, get, delete, contents, keyframes, export and import. (Localize,
//! a frame route under a map, is in [`super::frames`].)

use std::sync::Arc;

use axum::extract::{Query, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::body::{
    base64, bytes_within, frame_input, json_body, media_type, read_body, too_large, ApiPath, JSON_ONLY,
    JSON_OR_MULTIPART, MAP_FILE,
};
use super::error::{invalid, ApiError, ApiErrors, ApiResult};
use super::wire::{self, examples};
use crate::decode::TUM_DEPTH_SCALE;
use crate::server::app::App;
use crate::server::http::plumbing::{authorize, call, call_authorized, call_map};
use crate::service::{ExternalObservation, KeyframeRequest, PoseConvention, ServiceError, DEFAULT_CONTENTS_LANDMARKS};
use crate::settings::Access;

/// A new, empty map (rpc Maps.CreateMap).
#[utoipa::path(post, path = "/v1/maps", tag = "maps",
    request_body(content((wire::CreateMapRequest = "application/json", example = examples::create_map))),
    responses((status = 201, description = "The new map", body = wire::MapInfo), ApiErrors))]
pub async fn create_map(
    State(app): State<Arc<App>>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<wire::MapInfo>)> {
    media_type(&headers, JSON_ONLY)?;
    let limit = app.settings.server.max_request_bytes;
    let body = bytes_within(req, limit, too_large(limit)).await?;
    let j: wire::CreateMapRequest = json_body(&body)?;
    let s = call(&app, &headers, Access::Write, "CreateMap", move |a| a.service.create_map(&j.map_id)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}

/// The maps (with object storage every stored one) and those held back, with the reason (rpc Maps.ListMaps).
#[utoipa::path(get, path = "/v1/maps", tag = "maps",
    responses((status = 200, description = "Every map", body = wire::MapList), ApiErrors))]
pub async fn list_maps(State(app): State<Arc<App>>, headers: HeaderMap) -> ApiResult<Json<wire::MapList>> {
    let (maps, held) = call(&app, &headers, Access::Read, "ListMaps", |a| a.service.list_maps()).await?;
    Ok(Json(wire::MapList {
        maps: maps.into_iter().map(Into::into).collect(),
        held_back: held.into_iter().map(|(map_id, reason)| wire::HeldBack { map_id, reason }).collect(),
    }))
}

/// One map's statistics (rpc Maps.GetMap).
#[utoipa::path(get, path = "/v1/maps/{map_id}", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    responses((status = 200, description = "The map", body = wire::MapInfo), ApiErrors))]
pub async fn get_map(
    State(app): State<Arc<App>>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<Json<wire::MapInfo>> {
    let s = call_map(&app, &headers, Access::Read, "GetMap", &id.clone(), move |a| a.service.get_map(&id)).await?;
    Ok(Json(s.into()))
}

/// Deletes a map and everything stored for it (rpc Maps.DeleteMap).
#[utoipa::path(delete, path = "/v1/maps/{map_id}", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office")),
    responses((status = 204, description = "Deleted"), ApiErrors))]
pub async fn delete_map(
    State(app): State<Arc<App>>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<StatusCode> {
    call(&app, &headers, Access::Write, "DeleteMap", move |a| a.service.delete_map(&id)).await?;
    Ok(StatusCode::NO_CONTENT)
}

/// A map's contents for viewers: keyframe poses and intrinsics, and its landmarks (an even subsample of at
/// most `max_landmarks`). The console draws its 3D view from this.
#[utoipa::path(get, path = "/v1/maps/{map_id}/contents", tag = "maps",
    params(("map_id" = String, Path, description = "The map", example = "office"), wire::ContentsQuery),
    responses((status = 200, description = "Keyframes and landmarks", body = wire::MapContents), ApiErrors))]
pub async fn map_contents(
    State(app): State<Arc<App>>,
    ApiPath(id): ApiPath<String>,
    query: Result<Query<wire::ContentsQuery>, axum::extract::rejection::QueryRejection>,
    headers: HeaderMap,
) -> ApiResult<Json<wire::MapContents>> {
    let Query(q) = query.map_err(|e| invalid("query string", e.body_text()))?;
    let max = q.max_landmarks.unwrap_or(DEFAULT_CONTENTS_LANDMARKS);
    let convention: PoseConvention = q.pose_convention.map(Into::into).unwrap_or_default();
    let out = call_map(&app, &headers, Access::Read, "MapContents", &id.clone(), move |a| {
        let c = a.service.map_contents(&id, max)?;
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
    ApiPath(map_id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<wire::KeyframeAck>> {
    // Authenticate before reading a possibly large body.
    let authorized = authorize(&app, &headers, Access::Write, "AddKeyframe")?;
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    let out = call_authorized(&app, authorized, "AddKeyframe", Some(&map_id.clone()), move |a| {
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
            depth_scale: j.depth_scale.unwrap_or(TUM_DEPTH_SCALE),
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
        let (added, times) = a.service.add_keyframe(&map_id, request)?;
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
    ApiPath((id, keyframe)): ApiPath<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Json<wire::MapInfo>> {
    let keyframe: u64 = keyframe
        .parse()
        .map_err(|_| invalid("keyframe_id", format!("'{keyframe}' is not a keyframe id (a whole number)")))?;
    let s = call_map(&app, &headers, Access::Write, "RemoveKeyframe", &id.clone(), move |a| {
        a.service.remove_keyframe(&id, keyframe)
    })
    .await?;
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
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<wire::MergeMapsResponse>> {
    media_type(&headers, JSON_ONLY)?;
    let limit = app.settings.server.max_request_bytes;
    let body = bytes_within(req, limit, too_large(limit)).await?;
    let j: wire::MergeMapsRequest = json_body(&body)?;
    let o = call_map(&app, &headers, Access::Write, "MergeMaps", &id.clone(), move |a| {
        a.service.merge_maps(&id, &j.source_map_id, j.transform.map(Into::into))
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
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let name = id.clone();
    let bytes =
        call_map(&app, &headers, Access::Read, "ExportMap", &id.clone(), move |a| a.service.export_map(&id)).await?;
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
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<wire::MapInfo>)> {
    let authorized = authorize(&app, &headers, Access::Write, "ImportMap")?;
    media_type(&headers, MAP_FILE)?;
    let limit = app.settings.server.max_map_bytes;
    let refusal = ApiError::Service(ServiceError::TooLarge { what: "the map file".into(), limit });
    let bytes = bytes_within(req, limit, refusal).await?;
    let s = call_authorized(&app, authorized, "ImportMap", None, move |a| a.service.import_map(&id, &bytes)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}
