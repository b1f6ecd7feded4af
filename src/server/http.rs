//! HTTP/JSON transport (axum): every RPC under `/v1/...`, plus `/healthz`, `/readyz`, `/metrics` and
//! `/openapi.json`.
//!
//! Frames come in three forms: a raw image body (`Content-Type: image/jpeg` or `image/png`, intrinsics in the
//! query string), `multipart/form-data` with a JSON part named `request` and file parts (`image`, `image1`,
//! `image2`, `depth`), or `application/json` with base64 images or precomputed keypoints.

use std::future::Future;
use std::sync::Arc;
use std::time::Instant;

use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, FromRequest, MatchedPath, Multipart, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use axum::serve::ListenerExt;
use axum::{Json, Router};
use base64::Engine;
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;

use super::App;
use crate::decode::read_header;
use crate::features::Keypoint;
use crate::map::builder::ExternalObservation;
use crate::map::localize::Prior;
use crate::map::store::MapSummary;
use crate::scene::Camera;
use crate::service::{
    pose_from_parts, quaternion_xyzw, ErrorKind, FrameInput, FrameSource, KeyframeRequest, KeypointsInput, PairOptions,
    ServiceError,
};
use crate::settings::Access;

/// The OpenAPI description of this transport.
pub const OPENAPI: &str = include_str!("openapi.json");

/// A service error on its way out: the one mapping to HTTP statuses.
pub struct ApiError(pub ServiceError);

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self(e)
    }
}

fn code_name(kind: ErrorKind) -> &'static str {
    match kind {
        ErrorKind::InvalidArgument => "INVALID_ARGUMENT",
        ErrorKind::NotFound => "NOT_FOUND",
        ErrorKind::AlreadyExists => "ALREADY_EXISTS",
        ErrorKind::FailedPrecondition => "FAILED_PRECONDITION",
        ErrorKind::Unavailable => "UNAVAILABLE",
        ErrorKind::ResourceExhausted => "RESOURCE_EXHAUSTED",
        ErrorKind::PayloadTooLarge => "PAYLOAD_TOO_LARGE",
        ErrorKind::DeadlineExceeded => "DEADLINE_EXCEEDED",
        ErrorKind::Unauthenticated => "UNAUTHENTICATED",
        ErrorKind::PermissionDenied => "PERMISSION_DENIED",
        ErrorKind::Internal => "INTERNAL",
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let kind = self.0.kind();
        let status = match kind {
            ErrorKind::InvalidArgument => StatusCode::BAD_REQUEST,
            ErrorKind::NotFound => StatusCode::NOT_FOUND,
            ErrorKind::AlreadyExists => StatusCode::CONFLICT,
            ErrorKind::FailedPrecondition => StatusCode::CONFLICT,
            ErrorKind::Unavailable => StatusCode::SERVICE_UNAVAILABLE,
            ErrorKind::ResourceExhausted => StatusCode::TOO_MANY_REQUESTS,
            ErrorKind::PayloadTooLarge => StatusCode::PAYLOAD_TOO_LARGE,
            ErrorKind::DeadlineExceeded => StatusCode::GATEWAY_TIMEOUT,
            ErrorKind::Unauthenticated => StatusCode::UNAUTHORIZED,
            ErrorKind::PermissionDenied => StatusCode::FORBIDDEN,
            ErrorKind::Internal => StatusCode::INTERNAL_SERVER_ERROR,
        };
        let body = serde_json::json!({"error": {"code": code_name(kind), "message": self.0.client_message()}});
        let mut resp = (status, Json(body)).into_response();
        if let Some(s) = self.0.retry_after_s() {
            resp.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        resp
    }
}

type ApiResult<T> = Result<T, ApiError>;

fn invalid(field: &str, reason: impl Into<String>) -> ApiError {
    ApiError(ServiceError::invalid(field, reason))
}

fn api_key(headers: &HeaderMap) -> Option<String> {
    let get = |name: &str| headers.get(name).and_then(|v| v.to_str().ok());
    super::auth::key_from_headers(get("x-api-key"), get("authorization")).map(str::to_string)
}

async fn call<R, F>(app: &Arc<App>, headers: &HeaderMap, access: Access, op: &str, f: F) -> ApiResult<R>
where
    R: Send + 'static,
    F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
{
    app.call(api_key(headers).as_deref(), access, op, f).await.map_err(|e| {
        app.log_error(op, &e);
        ApiError(e)
    })
}

// ---------------------------------------------------------------------------------------------------------
// Wire types
// ---------------------------------------------------------------------------------------------------------

#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct IntrinsicsJson {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    /// Defaults to the image's (or the keypoint set's) size.
    width: Option<u32>,
    height: Option<u32>,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct KeypointJson {
    x: f32,
    y: f32,
    size: f32,
    angle: f32,
    #[serde(default)]
    response: f32,
    #[serde(default)]
    octave: i32,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeypointSetJson {
    width: u32,
    height: u32,
    keypoints: Vec<KeypointJson>,
    descriptors_base64: String,
    #[serde(default)]
    model_id: Option<String>,
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct FrameJson {
    #[serde(default)]
    image_base64: Option<String>,
    #[serde(default)]
    keypoints: Option<KeypointSetJson>,
    #[serde(default)]
    intrinsics: Option<IntrinsicsJson>,
}

#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
struct PoseJson {
    tx: f64,
    ty: f64,
    tz: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    qw: f64,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
struct PriorJson {
    x: f64,
    y: f64,
    z: f64,
    radius: f64,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct DescribeJson {
    #[serde(default)]
    frame: Option<FrameJson>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct MatchJson {
    #[serde(default)]
    frame1: Option<FrameJson>,
    #[serde(default)]
    frame2: Option<FrameJson>,
    #[serde(default)]
    ratio: Option<f32>,
    #[serde(default)]
    mutual: bool,
    /// "plain", "union" or "rerank"; absent = the server's default.
    #[serde(default)]
    matcher: Option<crate::matching::SconeMatcher>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct LocalizeJson {
    #[serde(default)]
    frame: Option<FrameJson>,
    #[serde(default)]
    intrinsics: Option<IntrinsicsJson>,
    #[serde(default)]
    prior: Option<PriorJson>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyframeJson {
    keyframe_id: u64,
    pose: PoseJson,
    #[serde(default)]
    frame: Option<FrameJson>,
    #[serde(default)]
    intrinsics: Option<IntrinsicsJson>,
    #[serde(default)]
    depth_png_base64: Option<String>,
    #[serde(default)]
    depth_scale: Option<f64>,
    #[serde(default)]
    external_landmarks: Vec<ExternalObservationJson>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
struct Point3Json {
    x: f64,
    y: f64,
    z: f64,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
struct ExternalObservationJson {
    x: f64,
    y: f64,
    landmark_id: u64,
    point: Point3Json,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CreateMapJson {
    map_id: String,
}

#[derive(Debug, Serialize)]
struct MapInfoJson {
    map_id: String,
    model_id: String,
    keyframes: usize,
    landmarks: usize,
    observations: usize,
    live_observations: usize,
    version: u64,
    approximate_index: bool,
}

impl From<MapSummary> for MapInfoJson {
    fn from(s: MapSummary) -> Self {
        Self {
            map_id: s.id,
            model_id: s.model_id,
            keyframes: s.keyframes,
            landmarks: s.landmarks,
            observations: s.observations,
            live_observations: s.live_observations,
            version: s.version,
            approximate_index: s.approximate_index,
        }
    }
}

// ---------------------------------------------------------------------------------------------------------
// Bodies
// ---------------------------------------------------------------------------------------------------------

/// What a request body carried.
#[derive(Default)]
struct Body {
    json: Option<Bytes>,
    image: Option<Bytes>,
    image2: Option<Bytes>,
    depth: Option<Bytes>,
}

fn too_large(limit: usize) -> ApiError {
    ApiError(ServiceError::TooLarge { what: "the request body".into(), limit })
}

async fn read_body(req: Request, limit: usize) -> ApiResult<Body> {
    let ct = req.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    let mime = ct.split(';').next().unwrap_or("").trim().to_string();
    if mime == "multipart/form-data" {
        let mut mp = Multipart::from_request(req, &()).await.map_err(|e| invalid("body", e.body_text()))?;
        let mut body = Body::default();
        while let Some(field) = mp.next_field().await.map_err(|e| multipart_error(e, limit))? {
            let name = field.name().unwrap_or("").to_string();
            let data = field.bytes().await.map_err(|e| multipart_error(e, limit))?;
            let slot = match name.as_str() {
                "request" => &mut body.json,
                "image" | "image1" => &mut body.image,
                "image2" => &mut body.image2,
                "depth" => &mut body.depth,
                other => {
                    return Err(invalid(
                        "body",
                        format!("unknown multipart part '{other}': use request, image, image1, image2, depth"),
                    ))
                }
            };
            *slot = Some(data);
        }
        return Ok(body);
    }
    let bytes = axum::body::to_bytes(req.into_body(), limit).await.map_err(|_| too_large(limit))?;
    match mime.as_str() {
        "application/json" => Ok(Body { json: Some(bytes), ..Default::default() }),
        "image/jpeg" | "image/png" | "application/octet-stream" => {
            Ok(Body { image: Some(bytes), ..Default::default() })
        }
        "" if bytes.is_empty() => Ok(Body::default()),
        other => Err(invalid(
            "content-type",
            format!("'{other}' is not accepted: send image/jpeg, image/png, application/json or multipart/form-data"),
        )),
    }
}

fn multipart_error(e: axum::extract::multipart::MultipartError, limit: usize) -> ApiError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        too_large(limit)
    } else {
        invalid("body", e.body_text())
    }
}

fn parse_json<T: serde::de::DeserializeOwned + Default>(bytes: &Option<Bytes>) -> ApiResult<T> {
    match bytes {
        None => Ok(T::default()),
        Some(b) => serde_json::from_slice(b).map_err(|e| invalid("request JSON", e.to_string())),
    }
}

fn base64(field: &str, s: &str) -> Result<Vec<u8>, ServiceError> {
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map_err(|e| ServiceError::invalid(field, format!("is not valid base64: {e}")))
}

/// A frame from its JSON description and/or a binary image part.
fn frame(
    json: Option<FrameJson>,
    image: Option<Bytes>,
    intrinsics: Option<IntrinsicsJson>,
    field: &str,
) -> Result<FrameInput, ServiceError> {
    let json = json.unwrap_or_default();
    let intrinsics = intrinsics.or(json.intrinsics);
    let (source, size) = match (image, json.image_base64, json.keypoints) {
        (Some(bytes), None, None) => {
            let size = read_header(&bytes).ok().map(|h| (h.width, h.height));
            (FrameSource::Image(bytes.to_vec()), size)
        }
        (None, Some(b64), None) => {
            let bytes = base64(&format!("{field}.image_base64"), &b64)?;
            let size = read_header(&bytes).ok().map(|h| (h.width, h.height));
            (FrameSource::Image(bytes), size)
        }
        (None, None, Some(k)) => {
            let descriptors = base64(&format!("{field}.keypoints.descriptors_base64"), &k.descriptors_base64)?;
            let keypoints = k
                .keypoints
                .iter()
                .map(|p| Keypoint {
                    x: p.x,
                    y: p.y,
                    size: p.size,
                    angle: p.angle,
                    response: p.response,
                    octave: p.octave,
                })
                .collect();
            let size = Some((k.width, k.height));
            (
                FrameSource::Keypoints(KeypointsInput {
                    width: k.width,
                    height: k.height,
                    keypoints,
                    descriptors,
                    model_id: k.model_id,
                }),
                size,
            )
        }
        (None, None, None) => return Err(ServiceError::invalid(field, "needs an image or keypoints")),
        _ => return Err(ServiceError::invalid(field, "give exactly one of an image or keypoints")),
    };
    let camera = intrinsics.map(|i| {
        let (w, h) = size.unwrap_or((0, 0));
        Camera { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy, width: i.width.unwrap_or(w), height: i.height.unwrap_or(h) }
    });
    Ok(FrameInput { source, camera })
}

#[derive(Debug, Default, Deserialize)]
struct IntrinsicsQuery {
    fx: Option<f64>,
    fy: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    width: Option<u32>,
    height: Option<u32>,
}

impl IntrinsicsQuery {
    fn intrinsics(&self) -> Option<IntrinsicsJson> {
        Some(IntrinsicsJson {
            fx: self.fx?,
            fy: self.fy.or(self.fx)?,
            cx: self.cx?,
            cy: self.cy?,
            width: self.width,
            height: self.height,
        })
    }
}

fn pose_json(p: &nalgebra::Isometry3<f64>) -> PoseJson {
    let q = p.rotation.quaternion();
    let t = p.translation.vector;
    PoseJson { tx: t.x, ty: t.y, tz: t.z, qx: q.i, qy: q.j, qz: q.k, qw: q.w }
}

// ---------------------------------------------------------------------------------------------------------
// Handlers
// ---------------------------------------------------------------------------------------------------------

async fn describe(State(app): State<Arc<App>>, headers: HeaderMap, req: Request) -> ApiResult<Json<serde_json::Value>> {
    let body = read_body(req, app.settings.server.max_request_bytes).await?;
    let out = call(&app, &headers, Access::Read, "Describe", move |a| {
        let j: DescribeJson = parse_json(&body.json).map_err(|e| e.0)?;
        let f = frame(j.frame, body.image, None, "frame")?;
        let d = a.service.describe(f.source)?;
        a.metrics.stages(&d.times);
        let keypoints: Vec<KeypointJson> = d
            .features
            .keypoints
            .iter()
            .map(|k| KeypointJson {
                x: k.x,
                y: k.y,
                size: k.size,
                angle: k.angle,
                response: k.response,
                octave: k.octave,
            })
            .collect();
        Ok(serde_json::json!({
            "width": d.features.width,
            "height": d.features.height,
            "keypoints": keypoints,
            "descriptors_base64": base64::engine::general_purpose::STANDARD.encode(d.features.descriptors.concat()),
            "embeddings": d.embeddings,
            "dim": d.dim,
            "model_id": d.model_id,
        }))
    })
    .await?;
    Ok(Json(out))
}

async fn match_pair(
    State(app): State<Arc<App>>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<serde_json::Value>> {
    let body = read_body(req, app.settings.server.max_request_bytes).await?;
    let out = call(&app, &headers, Access::Read, "MatchPair", move |a| {
        let j: MatchJson = parse_json(&body.json).map_err(|e| e.0)?;
        let f1 = frame(j.frame1, body.image, None, "frame1")?;
        let f2 = frame(j.frame2, body.image2, None, "frame2")?;
        let options =
            PairOptions { ratio: j.ratio.unwrap_or(0.8), mutual: j.mutual, matcher: j.matcher.unwrap_or_default() };
        let o = a.service.match_pair(f1, f2, options)?;
        a.metrics.stages(&o.times);
        let inliers = o.pose.as_ref().map(|p| p.inliers.clone()).unwrap_or_default();
        let matches: Vec<_> = o
            .matches
            .iter()
            .enumerate()
            .map(|(i, m)| {
                serde_json::json!({"index1": m.query, "index2": m.train, "distance": m.distance,
                                   "inlier": inliers.get(i).copied().unwrap_or(false)})
            })
            .collect();
        let pose = o.pose.as_ref().map(|p| {
            let [qx, qy, qz, qw] = quaternion_xyzw(&p.rotation);
            serde_json::json!({"qx": qx, "qy": qy, "qz": qz, "qw": qw,
                               "tx": p.translation.x, "ty": p.translation.y, "tz": p.translation.z})
        });
        Ok(serde_json::json!({
            "matches": matches,
            "pose": pose,
            "inliers": o.pose.as_ref().map_or(0, |p| p.inlier_count),
        }))
    })
    .await?;
    Ok(Json(out))
}

async fn localize(
    State(app): State<Arc<App>>,
    Path(map_id): Path<String>,
    Query(q): Query<IntrinsicsQuery>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<serde_json::Value>> {
    let body = read_body(req, app.settings.server.max_request_bytes).await?;
    let out = call(&app, &headers, Access::Read, "Localize", move |a| {
        let j: LocalizeJson = parse_json(&body.json).map_err(|e| e.0)?;
        let f = frame(j.frame, body.image, j.intrinsics.or(q.intrinsics()), "frame")?;
        let prior = j.prior.map(|p| Prior { position: [p.x, p.y, p.z], radius: p.radius });
        let o = a.service.localize(&map_id, f, prior)?;
        a.metrics.stages(&o.times);
        Ok(serde_json::json!({
            "localized": o.pose.is_some(),
            "pose": o.pose.as_ref().map(|p| pose_json(&p.camera_to_world)),
            "matches": o.matches.len(),
            "inliers": o.pose.as_ref().map_or(0, |p| p.inliers.len()),
            "reprojection_error": o.pose.as_ref().map_or(0.0, |p| p.reprojection_error),
            "confidence": o.confidence,
        }))
    })
    .await?;
    Ok(Json(out))
}

async fn add_keyframe(
    State(app): State<Arc<App>>,
    Path(map_id): Path<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<serde_json::Value>> {
    // Authenticate before reading a possibly large body.
    app.keys.check(api_key(&headers).as_deref(), Access::Write, "AddKeyframe").map_err(ApiError)?;
    let body = read_body(req, app.settings.server.max_request_bytes).await?;
    let out = call(&app, &headers, Access::Write, "AddKeyframe", move |a| {
        let Some(json) = &body.json else {
            return Err(ServiceError::invalid(
                "body",
                "a keyframe needs JSON (keyframe_id, pose, intrinsics): send application/json or a multipart part 'request'",
            ));
        };
        let j: KeyframeJson =
            serde_json::from_slice(json).map_err(|e| ServiceError::invalid("request JSON", e.to_string()))?;
        let f = frame(j.frame, body.image, j.intrinsics, "frame")?;
        let depth_png = match (body.depth, j.depth_png_base64) {
            (Some(d), None) => Some(d.to_vec()),
            (None, Some(b)) => Some(base64("depth_png_base64", &b)?),
            (None, None) => None,
            (Some(_), Some(_)) => return Err(ServiceError::invalid("depth", "give a depth part or depth_png_base64, not both")),
        };
        let p = j.pose;
        let request = KeyframeRequest {
            id: j.keyframe_id,
            frame: f,
            pose: pose_from_parts([p.tx, p.ty, p.tz], [p.qx, p.qy, p.qz, p.qw]),
            depth_png,
            depth_scale: j.depth_scale.unwrap_or(1.0 / 5000.0),
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
        Ok(serde_json::json!({
            "keyframe_id": added.keyframe,
            "new_landmarks": added.new_landmarks,
            "observations": added.observations,
            "map_version": added.version,
            "external_rejected": added.external.rejected,
            "external_unassociated": added.external.unassociated,
        }))
    })
    .await?;
    Ok(Json(out))
}

async fn create_map(
    State(app): State<Arc<App>>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<MapInfoJson>)> {
    let j: CreateMapJson = serde_json::from_slice(&body).map_err(|e| invalid("request JSON", e.to_string()))?;
    let s = call(&app, &headers, Access::Write, "CreateMap", move |a| a.service.create_map(&j.map_id)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}

async fn list_maps(State(app): State<Arc<App>>, headers: HeaderMap) -> ApiResult<Json<serde_json::Value>> {
    let (maps, held) = call(&app, &headers, Access::Read, "ListMaps", |a| a.service.list_maps()).await?;
    let maps: Vec<MapInfoJson> = maps.into_iter().map(Into::into).collect();
    let held: Vec<_> = held.into_iter().map(|(m, r)| serde_json::json!({"map_id": m, "reason": r})).collect();
    Ok(Json(serde_json::json!({"maps": maps, "held_back": held})))
}

async fn get_map(
    State(app): State<Arc<App>>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Json<MapInfoJson>> {
    let s = call(&app, &headers, Access::Read, "GetMap", move |a| a.service.get_map(&id)).await?;
    Ok(Json(s.into()))
}

async fn delete_map(State(app): State<Arc<App>>, Path(id): Path<String>, headers: HeaderMap) -> ApiResult<StatusCode> {
    call(&app, &headers, Access::Write, "DeleteMap", move |a| a.service.delete_map(&id)).await?;
    Ok(StatusCode::NO_CONTENT)
}

async fn remove_keyframe(
    State(app): State<Arc<App>>,
    Path((id, keyframe)): Path<(String, u64)>,
    headers: HeaderMap,
) -> ApiResult<Json<MapInfoJson>> {
    let s = call(&app, &headers, Access::Write, "RemoveKeyframe", move |a| a.service.remove_keyframe(&id, keyframe))
        .await?;
    Ok(Json(s.into()))
}

async fn export_map(State(app): State<Arc<App>>, Path(id): Path<String>, headers: HeaderMap) -> ApiResult<Response> {
    let name = id.clone();
    let bytes = call(&app, &headers, Access::Read, "ExportMap", move |a| a.service.export_map(&id)).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "application/octet-stream".to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{name}.scone-map\"")),
        ],
        bytes,
    )
        .into_response())
}

async fn import_map(
    State(app): State<Arc<App>>,
    Path(id): Path<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<MapInfoJson>)> {
    app.keys.check(api_key(&headers).as_deref(), Access::Write, "ImportMap").map_err(ApiError)?;
    let limit = app.settings.server.max_map_bytes;
    let bytes = axum::body::to_bytes(req.into_body(), limit)
        .await
        .map_err(|_| ApiError(ServiceError::TooLarge { what: "the map file".into(), limit }))?;
    let s = call(&app, &headers, Access::Write, "ImportMap", move |a| a.service.import_map(&id, &bytes)).await?;
    Ok((StatusCode::CREATED, Json(s.into())))
}

async fn healthz() -> &'static str {
    "ok\n"
}

async fn readyz(State(app): State<Arc<App>>) -> (StatusCode, &'static str) {
    if app.is_ready() {
        (StatusCode::OK, "ready\n")
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "not ready: loading maps or shutting down\n")
    }
}

async fn metrics(State(app): State<Arc<App>>) -> impl IntoResponse {
    let text = app.metrics.render(app.service.holdings(), app.pool.stats());
    ([(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")], text)
}

async fn openapi() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI)
}

async fn observe(State(app): State<Arc<App>>, req: Request, next: Next) -> Response {
    let route = req.extensions().get::<MatchedPath>().map(|m| m.as_str().to_string()).unwrap_or_default();
    let t = Instant::now();
    let resp = next.run(req).await;
    app.metrics.request("http", &route, resp.status().as_str(), t.elapsed().as_secs_f64());
    resp
}

/// Every route, as `METHOD path` (the OpenAPI document is checked against this list).
pub const ROUTES: &[&str] = &[
    "GET /healthz",
    "GET /readyz",
    "GET /metrics",
    "GET /openapi.json",
    "POST /v1/describe",
    "POST /v1/match",
    "POST /v1/maps",
    "GET /v1/maps",
    "GET /v1/maps/{map_id}",
    "DELETE /v1/maps/{map_id}",
    "POST /v1/maps/{map_id}/keyframes",
    "DELETE /v1/maps/{map_id}/keyframes/{keyframe_id}",
    "POST /v1/maps/{map_id}/localize",
    "GET /v1/maps/{map_id}/export",
    "POST /v1/maps/{map_id}/import",
];

/// The HTTP API.
pub fn router(app: Arc<App>) -> Router {
    let limit = app.settings.server.max_request_bytes;
    let map_limit = app.settings.server.max_map_bytes;
    Router::new()
        .route("/v1/describe", post(describe))
        .route("/v1/match", post(match_pair))
        .route("/v1/maps", post(create_map).get(list_maps))
        .route("/v1/maps/{map_id}", get(get_map).delete(delete_map))
        .route("/v1/maps/{map_id}/keyframes", post(add_keyframe))
        .route("/v1/maps/{map_id}/keyframes/{keyframe_id}", delete(remove_keyframe))
        .route("/v1/maps/{map_id}/localize", post(localize))
        .route("/v1/maps/{map_id}/export", get(export_map))
        .route("/v1/maps/{map_id}/import", post(import_map).layer(DefaultBodyLimit::max(map_limit)))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi))
        .route_layer(middleware::from_fn_with_state(Arc::clone(&app), observe))
        .layer(DefaultBodyLimit::max(limit))
        .with_state(app)
}

/// Serves HTTP on `listener` until `shutdown` resolves, then lets in-flight requests finish.
pub async fn serve(
    app: Arc<App>,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    // TCP_NODELAY, as on the gRPC port: a response written in more than one piece must not wait for an ACK.
    let listener = listener.tap_io(|tcp| {
        if let Err(e) = tcp.set_nodelay(true) {
            tracing::warn!("TCP_NODELAY on an accepted connection: {e}");
        }
    });
    axum::serve(listener, router(app)).with_graceful_shutdown(shutdown).await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::{from_precomputed, KeypointLimits};
    use proptest::prelude::*;

    fn keypoints_body(kps: &[(f32, f32, f32, f32, i32)], descriptor_bytes: usize, w: u32, h: u32) -> FrameJson {
        FrameJson {
            keypoints: Some(KeypointSetJson {
                width: w,
                height: h,
                keypoints: kps
                    .iter()
                    .map(|&(x, y, size, angle, octave)| KeypointJson { x, y, size, angle, response: 1.0, octave })
                    .collect(),
                descriptors_base64: base64::engine::general_purpose::STANDARD.encode(vec![0x5a; descriptor_bytes]),
                model_id: None,
            }),
            ..Default::default()
        }
    }

    proptest! {
        /// Any keypoint set a client can send decodes to a frame and is then accepted or refused with a
        /// client error; nothing panics and nothing is classified as the server's fault.
        #[test]
        fn client_keypoints_decode_and_validate_without_panics(
            kps in prop::collection::vec(
                (any::<f32>(), any::<f32>(), any::<f32>(), any::<f32>(), any::<i32>()), 0..40),
            extra in -70i64..70,
            w in 0u32..5000,
            h in 0u32..5000,
        ) {
            let bytes = (kps.len() as i64 * 64 + extra).max(0) as usize;
            let f = frame(Some(keypoints_body(&kps, bytes, w, h)), None, None, "frame").unwrap();
            let FrameSource::Keypoints(k) = f.source else { panic!("keypoints expected") };
            match from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &KeypointLimits::default()) {
                Ok(features) => {
                    prop_assert_eq!(features.len(), kps.len());
                    prop_assert_eq!(bytes, kps.len() * 64);
                }
                Err(e) => prop_assert_eq!(ServiceError::from(e).kind(), ErrorKind::InvalidArgument),
            }
        }

        /// Well-formed keypoints inside the image are accepted.
        #[test]
        fn in_range_keypoints_are_accepted(
            kps in prop::collection::vec((40.0f32..600.0, 40.0f32..440.0, 7.0f32..12.0, 0.0f32..359.9, 0i32..3), 1..60),
        ) {
            let f = frame(Some(keypoints_body(&kps, kps.len() * 64, 640, 480)), None, None, "frame").unwrap();
            let FrameSource::Keypoints(k) = f.source else { panic!("keypoints expected") };
            let features = from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &KeypointLimits::default());
            prop_assert!(features.is_ok(), "{:?}", features.err());
        }

        /// Arbitrary bytes as a request's JSON are refused as the client's error, never a panic.
        #[test]
        fn arbitrary_request_json_is_refused_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
            for r in [
                parse_json::<LocalizeJson>(&Some(Bytes::from(bytes.clone()))).err(),
                parse_json::<MatchJson>(&Some(Bytes::from(bytes.clone()))).err(),
                parse_json::<DescribeJson>(&Some(Bytes::from(bytes))).err(),
            ].into_iter().flatten() {
                prop_assert_eq!(r.0.kind(), ErrorKind::InvalidArgument);
            }
        }

        /// Base64 that is not base64, and frames with both or neither source, are refused with the field.
        #[test]
        fn malformed_frames_name_the_field(junk in "[!-*,-.:-<>-@\\[-`{-~]{1,20}") {
            let f = FrameJson { image_base64: Some(junk), ..Default::default() };
            let e = frame(Some(f), None, None, "frame1").unwrap_err();
            prop_assert!(e.to_string().contains("frame1.image_base64"), "{}", e);
            let both = FrameJson { image_base64: Some("aGk=".into()), ..keypoints_body(&[], 0, 1, 1) };
            prop_assert!(frame(Some(both), None, None, "frame").is_err());
        }
    }

    #[test]
    fn openapi_lists_exactly_the_routes() {
        let doc: serde_json::Value = serde_json::from_str(OPENAPI).expect("openapi.json parses");
        let mut documented: Vec<String> = Vec::new();
        for (path, ops) in doc["paths"].as_object().expect("paths") {
            for method in ops.as_object().expect("operations").keys() {
                documented.push(format!("{} {path}", method.to_uppercase()));
            }
        }
        documented.sort();
        let mut routes: Vec<String> = ROUTES.iter().map(|s| s.to_string()).collect();
        routes.sort();
        assert_eq!(documented, routes);
    }
}
