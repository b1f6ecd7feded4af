//! HTTP/JSON transport (axum): every RPC under `/v1/...`, plus `/healthz`, `/readyz`, `/metrics` and
//! `/openapi.json`.
//!
//! Frames come in three forms: a raw image body (`Content-Type: image/jpeg` or `image/png`, intrinsics in the
//! query string), `multipart/form-data` with a JSON part named `request` and file parts (`image`, `image1`,
//! `image2`, `depth`), or `application/json` with base64 images or precomputed keypoints.

use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{
    DefaultBodyLimit, FromRequest, FromRequestParts, MatchedPath, Multipart, Path, Query, Request, State,
};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post};
use axum::{Json, Router};
use base64::Engine;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use serde::{Deserialize, Serialize};
use tokio::sync::watch;
use tower::ServiceExt;

use super::connections::{DeadlineBody, GuardedBody, Listener};
use super::metrics::CountedBody;
use super::App;
use crate::camera::{quaternion_xyzw, Camera, Pose};
use crate::decode::{read_header, TUM_DEPTH_SCALE};
use crate::features::Keypoint;
use crate::map::builder::ExternalObservation;
use crate::map::localize::Prior;
use crate::map::store::MapSummary;
use crate::matching::DEFAULT_RATIO;
use crate::service::{ErrorKind, FrameInput, FrameSource, KeyframeRequest, KeypointsInput, PairOptions, ServiceError};
use crate::settings::Access;

/// The OpenAPI description of this transport.
pub const OPENAPI: &str = include_str!("openapi.json");

/// Errors of the HTTP layer: the service's own, and the transport's (media types, origins, routing, slow
/// bodies). Its [`IntoResponse`] is the one mapping to HTTP statuses; every error body is the JSON envelope
/// `{"error": {"code", "message"}}`.
#[derive(Debug)]
pub enum ApiError {
    Service(ServiceError),
    /// The route does not take this body's `Content-Type` (415).
    UnsupportedMediaType {
        got: String,
        accepted: &'static [&'static str],
    },
    /// A write (or a CORS preflight) from a browser page of another origin (403).
    ForeignOrigin {
        origin: String,
    },
    /// The request body did not arrive within `server.body_read_timeout_ms` (408).
    BodyTimeout {
        ms: u64,
    },
    NoRoute {
        path: String,
    },
    MethodNotAllowed {
        method: String,
        path: String,
    },
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        Self::Service(e)
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

fn service_status(kind: ErrorKind) -> StatusCode {
    match kind {
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
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let (status, code, message, retry_after) = match self {
            Self::Service(e) => {
                let kind = e.kind();
                (service_status(kind), code_name(kind), e.client_message(), e.retry_after_s())
            }
            Self::UnsupportedMediaType { got, accepted } => (
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "UNSUPPORTED_MEDIA_TYPE",
                format!(
                    "content-type {} is not accepted here: send {}",
                    if got.is_empty() { "(none)".to_string() } else { format!("'{got}'") },
                    accepted.join(", ")
                ),
                None,
            ),
            Self::ForeignOrigin { origin } => (
                StatusCode::FORBIDDEN,
                "PERMISSION_DENIED",
                format!("origin '{origin}' is not allowed to call this API (server.allowed_origins)"),
                None,
            ),
            Self::BodyTimeout { ms } => (
                StatusCode::REQUEST_TIMEOUT,
                "DEADLINE_EXCEEDED",
                format!("the request body did not arrive within {ms} ms"),
                None,
            ),
            Self::NoRoute { path } => (StatusCode::NOT_FOUND, "NOT_FOUND", format!("no route {path}"), None),
            Self::MethodNotAllowed { method, path } => {
                (StatusCode::METHOD_NOT_ALLOWED, "METHOD_NOT_ALLOWED", format!("{path} does not take {method}"), None)
            }
        };
        let body = serde_json::json!({"error": {"code": code, "message": message}});
        let mut resp = (status, Json(body)).into_response();
        if let Some(s) = retry_after {
            resp.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        resp
    }
}

type ApiResult<T> = Result<T, ApiError>;

fn invalid(field: &str, reason: impl Into<String>) -> ApiError {
    ApiError::Service(ServiceError::invalid(field, reason))
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
        ApiError::Service(e)
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

/// The body types each route takes (also in `openapi.json`); anything else is 415.
const FRAME_BODIES: &[&str] =
    &["image/jpeg", "image/png", "application/octet-stream", "application/json", "multipart/form-data"];
const JSON_OR_MULTIPART: &[&str] = &["application/json", "multipart/form-data"];
const JSON_ONLY: &[&str] = &["application/json"];
const MAP_FILE: &[&str] = &["application/octet-stream"];

fn too_large(limit: usize) -> ApiError {
    ApiError::Service(ServiceError::TooLarge { what: "the request body".into(), limit })
}

/// Why reading a body failed: too long, too slow, or the client's stream broke.
fn body_error(e: &(dyn std::error::Error + 'static), too_large: ApiError) -> ApiError {
    if let Some(ms) = super::connections::body_timed_out(e) {
        return ApiError::BodyTimeout { ms };
    }
    let mut cur = Some(e);
    while let Some(err) = cur {
        if err.is::<http_body_util::LengthLimitError>() {
            return too_large;
        }
        cur = err.source();
    }
    invalid("body", "the request body could not be read")
}

/// The media type of the request body, if the route takes it. A request without `Content-Type` passes only
/// when it has no body.
fn media_type(headers: &HeaderMap, accepted: &'static [&'static str]) -> ApiResult<String> {
    let raw = headers.get(header::CONTENT_TYPE).map(|v| v.to_str().unwrap_or("(not text)"));
    let mime = raw.map(|ct| ct.split(';').next().unwrap_or("").trim().to_ascii_lowercase()).unwrap_or_default();
    if accepted.contains(&mime.as_str()) {
        return Ok(mime);
    }
    let empty = match headers.get(header::CONTENT_LENGTH) {
        Some(n) => n.as_bytes() == b"0",
        None => !headers.contains_key(header::TRANSFER_ENCODING),
    };
    if raw.is_none() && empty {
        return Ok(String::new());
    }
    Err(ApiError::UnsupportedMediaType { got: raw.unwrap_or("").to_string(), accepted })
}

async fn read_body(req: Request, limit: usize, accepted: &'static [&'static str]) -> ApiResult<Body> {
    let mime = media_type(req.headers(), accepted)?;
    if mime == "multipart/form-data" {
        let mut mp = Multipart::from_request(req, &()).await.map_err(|e| invalid("body", e.body_text()))?;
        let mut body = Body::default();
        while let Some(field) = mp.next_field().await.map_err(|e| multipart_error(e, limit))? {
            let name = field.name().unwrap_or("").to_string();
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
            if slot.is_some() {
                let same =
                    if name.starts_with("image") && name != "image2" { " (image and image1 are one part)" } else { "" };
                return Err(invalid("body", format!("multipart part '{name}' is given more than once{same}")));
            }
            *slot = Some(field.bytes().await.map_err(|e| multipart_error(e, limit))?);
        }
        return Ok(body);
    }
    let bytes = axum::body::to_bytes(req.into_body(), limit).await.map_err(|e| body_error(&e, too_large(limit)))?;
    match mime.as_str() {
        "application/json" => Ok(Body { json: Some(bytes), ..Default::default() }),
        "image/jpeg" | "image/png" | "application/octet-stream" => {
            Ok(Body { image: Some(bytes), ..Default::default() })
        }
        _ if bytes.is_empty() => Ok(Body::default()),
        _ => Err(ApiError::UnsupportedMediaType { got: mime, accepted }),
    }
}

fn multipart_error(e: axum::extract::multipart::MultipartError, limit: usize) -> ApiError {
    if let Some(ms) = super::connections::body_timed_out(&e) {
        ApiError::BodyTimeout { ms }
    } else if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        too_large(limit)
    } else {
        invalid("body", e.body_text())
    }
}

fn parse_json<T: serde::de::DeserializeOwned + Default>(bytes: &Option<Bytes>) -> Result<T, ServiceError> {
    match bytes {
        None => Ok(T::default()),
        Some(b) => serde_json::from_slice(b).map_err(|e| ServiceError::invalid("request JSON", e.to_string())),
    }
}

fn base64(field: &str, s: &str) -> Result<Vec<u8>, ServiceError> {
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map_err(|e| ServiceError::invalid(field, format!("is not valid base64: {e}")))
}

/// The intrinsics of a frame given in several places (`frame.intrinsics`, a top-level `intrinsics`, the
/// query string): one of them, or several that agree. A size given in one and left out in another agrees.
fn agreed_intrinsics(given: &[(&str, Option<IntrinsicsJson>)]) -> Result<Option<IntrinsicsJson>, ServiceError> {
    let mut chosen: Option<(&str, IntrinsicsJson)> = None;
    for &(name, i) in given {
        let Some(i) = i else { continue };
        let Some((first, c)) = chosen else {
            chosen = Some((name, i));
            continue;
        };
        let same_size = |a: Option<u32>, b: Option<u32>| a.is_none() || b.is_none() || a == b;
        let agree = (c.fx, c.fy, c.cx, c.cy) == (i.fx, i.fy, i.cx, i.cy)
            && same_size(c.width, i.width)
            && same_size(c.height, i.height);
        if !agree {
            return Err(ServiceError::invalid(
                format!("{first} and {name}"),
                "give the intrinsics once, or the same values in both",
            ));
        }
        chosen = Some((first, IntrinsicsJson { width: c.width.or(i.width), height: c.height.or(i.height), ..c }));
    }
    Ok(chosen.map(|(_, i)| i))
}

/// A frame from its JSON description and/or a binary image part. `outer`: intrinsics given outside the
/// frame (name, value), which must agree with the frame's own.
fn frame(
    json: Option<FrameJson>,
    image: Option<Bytes>,
    outer: &[(&str, Option<IntrinsicsJson>)],
    field: &str,
) -> Result<FrameInput, ServiceError> {
    let json = json.unwrap_or_default();
    let own = format!("{field}.intrinsics");
    let mut given = vec![(own.as_str(), json.intrinsics)];
    given.extend_from_slice(outer);
    let intrinsics = agreed_intrinsics(&given)?;
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

/// Intrinsics in the query string (`?fx=&fy=&cx=&cy=&width=&height=`; `fy` defaults to `fx`).
#[derive(Debug, Default)]
struct IntrinsicsQuery {
    fx: Option<f64>,
    fy: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    width: Option<u32>,
    height: Option<u32>,
}

impl IntrinsicsQuery {
    fn parse(pairs: Vec<(String, String)>) -> Result<Self, ServiceError> {
        let mut q = Self::default();
        for (key, value) in pairs {
            fn set<T: std::str::FromStr>(
                slot: &mut Option<T>,
                key: &str,
                value: &str,
                what: &str,
            ) -> Result<(), ServiceError> {
                if slot.is_some() {
                    return Err(ServiceError::invalid(key, "is given more than once"));
                }
                let v =
                    value.trim().parse().map_err(|_| ServiceError::invalid(key, format!("'{value}' is not {what}")))?;
                *slot = Some(v);
                Ok(())
            }
            let number = "a number";
            let pixels = "a whole number of pixels";
            match key.as_str() {
                "fx" => set(&mut q.fx, &key, &value, number)?,
                "fy" => set(&mut q.fy, &key, &value, number)?,
                "cx" => set(&mut q.cx, &key, &value, number)?,
                "cy" => set(&mut q.cy, &key, &value, number)?,
                "width" => set(&mut q.width, &key, &value, pixels)?,
                "height" => set(&mut q.height, &key, &value, pixels)?,
                _ => {}
            }
        }
        Ok(q)
    }

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

impl<S: Send + Sync> FromRequestParts<S> for IntrinsicsQuery {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, ApiError> {
        let Query(pairs) = Query::<Vec<(String, String)>>::try_from_uri(&parts.uri)
            .map_err(|e| invalid("query string", e.body_text()))?;
        Ok(Self::parse(pairs)?)
    }
}

/// axum's `Path`, refused in the JSON envelope.
struct ApiPath<T>(T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned + Send> FromRequestParts<S> for ApiPath<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match Path::<T>::from_request_parts(parts, state).await {
            Ok(Path(t)) => Ok(Self(t)),
            Err(e) => {
                tracing::debug!("path rejected: {}", e.body_text());
                Err(invalid("URL path", "cannot be decoded (bad percent-encoding or UTF-8)"))
            }
        }
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
    let body = read_body(req, app.settings.server.max_request_bytes, FRAME_BODIES).await?;
    let out = call(&app, &headers, Access::Read, "Describe", move |a| {
        let j: DescribeJson = parse_json(&body.json)?;
        let f = frame(j.frame, body.image, &[], "frame")?;
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
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    let out = call(&app, &headers, Access::Read, "MatchPair", move |a| {
        let j: MatchJson = parse_json(&body.json)?;
        let f1 = frame(j.frame1, body.image, &[], "frame1")?;
        let f2 = frame(j.frame2, body.image2, &[], "frame2")?;
        let options = PairOptions {
            ratio: j.ratio.unwrap_or(DEFAULT_RATIO),
            mutual: j.mutual,
            matcher: j.matcher.unwrap_or_default(),
        };
        let o = a.service.match_pair(f1, f2, options)?;
        a.metrics.stages(&o.times);
        let matches: Vec<_> = o
            .matches
            .iter()
            .zip(o.inlier_flags())
            .map(|(m, inlier)| {
                serde_json::json!({"index1": m.query, "index2": m.train, "distance": m.distance, "inlier": inlier})
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
            "inliers": o.inlier_count(),
        }))
    })
    .await?;
    Ok(Json(out))
}

async fn localize(
    State(app): State<Arc<App>>,
    ApiPath(map_id): ApiPath<String>,
    q: IntrinsicsQuery,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<serde_json::Value>> {
    let body = read_body(req, app.settings.server.max_request_bytes, FRAME_BODIES).await?;
    let out = call(&app, &headers, Access::Read, "Localize", move |a| {
        let j: LocalizeJson = parse_json(&body.json)?;
        let outer = [("intrinsics", j.intrinsics), ("the query string's intrinsics", q.intrinsics())];
        let f = frame(j.frame, body.image, &outer, "frame")?;
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
    ApiPath(map_id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Json<serde_json::Value>> {
    // Authenticate before reading a possibly large body.
    app.keys.check(api_key(&headers).as_deref(), Access::Write, "AddKeyframe").map_err(ApiError::Service)?;
    let body = read_body(req, app.settings.server.max_request_bytes, JSON_OR_MULTIPART).await?;
    let out = call(&app, &headers, Access::Write, "AddKeyframe", move |a| {
        let Some(json) = &body.json else {
            return Err(ServiceError::invalid(
                "body",
                "a keyframe needs JSON (keyframe_id, pose, intrinsics): send application/json or a multipart part 'request'",
            ));
        };
        let j: KeyframeJson =
            serde_json::from_slice(json).map_err(|e| ServiceError::invalid("request JSON", e.to_string()))?;
        let f = frame(j.frame, body.image, &[("intrinsics", j.intrinsics)], "frame")?;
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
            pose: Pose { translation: [p.tx, p.ty, p.tz], rotation: [p.qx, p.qy, p.qz, p.qw] },
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
    req: Request,
) -> ApiResult<(StatusCode, Json<MapInfoJson>)> {
    media_type(&headers, JSON_ONLY)?;
    let limit = app.settings.server.max_request_bytes;
    let body = axum::body::to_bytes(req.into_body(), limit).await.map_err(|e| body_error(&e, too_large(limit)))?;
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
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<Json<MapInfoJson>> {
    let s = call(&app, &headers, Access::Read, "GetMap", move |a| a.service.get_map(&id)).await?;
    Ok(Json(s.into()))
}

async fn delete_map(
    State(app): State<Arc<App>>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<StatusCode> {
    call(&app, &headers, Access::Write, "DeleteMap", move |a| a.service.delete_map(&id)).await?;
    Ok(StatusCode::NO_CONTENT)
}

async fn remove_keyframe(
    State(app): State<Arc<App>>,
    ApiPath((id, keyframe)): ApiPath<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Json<MapInfoJson>> {
    let keyframe: u64 = keyframe
        .parse()
        .map_err(|_| invalid("keyframe_id", format!("'{keyframe}' is not a keyframe id (a whole number)")))?;
    let s = call(&app, &headers, Access::Write, "RemoveKeyframe", move |a| a.service.remove_keyframe(&id, keyframe))
        .await?;
    Ok(Json(s.into()))
}

async fn export_map(
    State(app): State<Arc<App>>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
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
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<(StatusCode, Json<MapInfoJson>)> {
    app.keys.check(api_key(&headers).as_deref(), Access::Write, "ImportMap").map_err(ApiError::Service)?;
    media_type(&headers, MAP_FILE)?;
    let limit = app.settings.server.max_map_bytes;
    let bytes = axum::body::to_bytes(req.into_body(), limit).await.map_err(|e| {
        body_error(&e, ApiError::Service(ServiceError::TooLarge { what: "the map file".into(), limit }))
    })?;
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

/// A refused HTTP/1.1 request whose unread body is at most this long is read and discarded after the answer,
/// so its connection carries the client's next request; a longer one closes the connection.
const DRAIN_LIMIT: u64 = 1 << 20;

/// Refuses a request for the CPU pool before its body is read when the pool has no free slot
/// ([`App::check_room`]): 429 with `Retry-After`, in the JSON envelope, after [`App::hold_refusal`].
async fn admission(State(app): State<Arc<App>>, req: Request, next: Next) -> Response {
    match app.check_room() {
        Ok(()) => next.run(req).await,
        Err(e) => {
            app.log_error("admission", &e);
            app.hold_refusal().await;
            refuse_unread(req, ApiError::Service(e).into_response())
        }
    }
}

/// `resp` for a request whose body was not read. HTTP/2 resets the request's stream when its body is
/// dropped, which stops the client sending it. HTTP/1.1 cannot stop a body in flight: a remainder of at most
/// [`DRAIN_LIMIT`] is discarded as it arrives (held to the body deadline like any body), a longer or
/// unknown one ends the connection after the answer.
fn refuse_unread(req: Request, mut resp: Response) -> Response {
    let h1 = req.version() < axum::http::Version::HTTP_2;
    let body = req.into_body();
    if !h1 || http_body::Body::is_end_stream(&body) {
        return resp;
    }
    match http_body::Body::size_hint(&body).upper() {
        Some(n) if n <= DRAIN_LIMIT => {
            tokio::spawn(async move {
                let mut body = body;
                while let Some(Ok(_)) = http_body_util::BodyExt::frame(&mut body).await {}
            });
        }
        _ => {
            resp.headers_mut().insert(header::CONNECTION, HeaderValue::from_static("close"));
        }
    }
    resp
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

async fn no_route(uri: Uri) -> ApiError {
    ApiError::NoRoute { path: uri.path().to_string() }
}

async fn method_not_allowed(method: Method, uri: Uri) -> ApiError {
    ApiError::MethodNotAllowed { method: method.to_string(), path: uri.path().to_string() }
}

/// Which browser origins may write and get CORS answers (`server.allowed_origins`).
#[derive(Debug, Clone)]
pub struct OriginPolicy {
    any: bool,
    allowed: Vec<String>,
}

impl OriginPolicy {
    /// `configured` as given, or, when empty, the origins a browser shows for the listener at `addr`.
    pub fn new(configured: &[String], addr: SocketAddr) -> Self {
        let any = configured.iter().any(|o| o == "*");
        let mut allowed: Vec<String> =
            configured.iter().filter(|o| *o != "*").map(|o| o.trim_end_matches('/').to_ascii_lowercase()).collect();
        if configured.is_empty() {
            let port = addr.port();
            let mut hosts = vec![match addr.ip() {
                IpAddr::V4(ip) => ip.to_string(),
                IpAddr::V6(ip) => format!("[{ip}]"),
            }];
            if addr.ip().is_loopback() {
                hosts.push("localhost".into());
            }
            for host in hosts {
                allowed.push(format!("http://{host}:{port}"));
                if port == 80 {
                    allowed.push(format!("http://{host}"));
                }
            }
        }
        Self { any, allowed }
    }

    fn allows(&self, origin: &str) -> bool {
        self.any || self.allowed.iter().any(|a| a.eq_ignore_ascii_case(origin))
    }
}

const CORS_METHODS: &str = "GET, HEAD, POST, DELETE";
const CORS_HEADERS: &str = "content-type, x-api-key, authorization";

/// Browser pages of other origins must not write (a form or a simple `fetch` needs no preflight, so without
/// this any page could create maps on a loopback server without keys): a request with an `Origin` that is
/// not allowed is refused unless it is a GET or HEAD. CORS preflights (OPTIONS) are answered by the same
/// policy, and responses to allowed origins carry `Access-Control-Allow-Origin`.
async fn origin_policy(State(policy): State<Arc<OriginPolicy>>, req: Request, next: Next) -> Response {
    let origin = req.headers().get(header::ORIGIN).map(|v| v.to_str().unwrap_or("(not text)").to_string());
    let allowed = origin.as_deref().is_some_and(|o| policy.allows(o));
    let cors = |resp: &mut Response, origin: &str| {
        let h = resp.headers_mut();
        if let Ok(v) = HeaderValue::from_str(origin) {
            h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, v);
        }
        h.append(header::VARY, HeaderValue::from_static("origin"));
    };
    if req.method() == Method::OPTIONS {
        return match origin {
            Some(o) if allowed => {
                let mut resp = StatusCode::NO_CONTENT.into_response();
                cors(&mut resp, &o);
                let h = resp.headers_mut();
                h.insert(header::ACCESS_CONTROL_ALLOW_METHODS, HeaderValue::from_static(CORS_METHODS));
                h.insert(header::ACCESS_CONTROL_ALLOW_HEADERS, HeaderValue::from_static(CORS_HEADERS));
                h.insert(header::ACCESS_CONTROL_MAX_AGE, HeaderValue::from_static("600"));
                resp
            }
            Some(o) => ApiError::ForeignOrigin { origin: o }.into_response(),
            None => {
                let mut resp = StatusCode::NO_CONTENT.into_response();
                resp.headers_mut().insert(header::ALLOW, HeaderValue::from_static("GET, HEAD, POST, DELETE, OPTIONS"));
                resp
            }
        };
    }
    let write = !matches!(*req.method(), Method::GET | Method::HEAD);
    match origin {
        Some(o) if write && !allowed => ApiError::ForeignOrigin { origin: o }.into_response(),
        Some(o) if allowed => {
            let mut resp = next.run(req).await;
            cors(&mut resp, &o);
            resp
        }
        _ => next.run(req).await,
    }
}

/// The HTTP API; `origins` decides which browser pages may write.
pub fn router(app: Arc<App>, origins: OriginPolicy) -> Router {
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
        // Routes so far run on the CPU pool.
        .route_layer(middleware::from_fn_with_state(Arc::clone(&app), admission))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/openapi.json", get(openapi))
        .route_layer(middleware::from_fn_with_state(Arc::clone(&app), observe))
        .fallback(no_route)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(DefaultBodyLimit::max(limit))
        .layer(middleware::from_fn_with_state(Arc::new(origins), origin_policy))
        .with_state(app)
}

/// Serves HTTP (HTTP/1.1, and HTTP/2 without TLS) on `listener` until `shutdown` resolves, then lets
/// in-flight requests finish. Each connection is held to the limits of [`super::connections`]; each request
/// body to `server.body_read_timeout_ms`.
pub async fn serve(
    app: Arc<App>,
    listener: Listener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let server = &app.settings.server;
    let origins = OriginPolicy::new(&server.allowed_origins, listener.local_addr()?);
    let body_timeout = Duration::from_millis(server.body_read_timeout_ms);
    let keepalive =
        (server.grpc_keepalive_interval_ms > 0).then(|| Duration::from_millis(server.grpc_keepalive_interval_ms));
    let keepalive_timeout = Duration::from_millis(server.grpc_keepalive_timeout_ms);
    let max_streams = server.max_concurrent_streams;
    let router = router(Arc::clone(&app), origins);
    let body_bytes = app.metrics.body_bytes("http");
    // Every connection task holds a receiver; `closed()` resolves once the last one ended.
    let (stop_tx, stop_rx) = watch::channel(false);
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let (conn, _peer) = tokio::select! {
            c = listener.accept() => c,
            _ = &mut shutdown => break,
        };
        let activity = conn.activity();
        let router = router.clone();
        let body_bytes = body_bytes.clone();
        let service = hyper::service::service_fn(move |req: axum::http::Request<hyper::body::Incoming>| {
            let guard = activity.begin();
            let counted = body_bytes.clone();
            let req = req.map(|b| {
                let timed = DeadlineBody::new(axum::body::Body::new(b), body_timeout);
                axum::body::Body::new(CountedBody::new(timed, counted))
            });
            let call = router.clone().oneshot(req);
            async move {
                let resp = call.await?;
                Ok::<_, std::convert::Infallible>(resp.map(|b| axum::body::Body::new(GuardedBody::new(b, Some(guard)))))
            }
        });
        let mut stop = stop_rx.clone();
        tokio::spawn(async move {
            let mut builder = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
            builder
                .http2()
                .timer(TokioTimer::new())
                .keep_alive_interval(keepalive)
                .keep_alive_timeout(keepalive_timeout)
                .max_concurrent_streams(max_streams);
            let conn = builder.serve_connection(TokioIo::new(conn), service);
            let mut conn = std::pin::pin!(conn);
            tokio::select! {
                r = conn.as_mut() => {
                    if let Err(e) = r {
                        tracing::debug!("HTTP connection ended: {e}");
                    }
                    return;
                }
                _ = stop.wait_for(|s| *s) => conn.as_mut().graceful_shutdown(),
            }
            if let Err(e) = conn.await {
                tracing::debug!("HTTP connection ended during shutdown: {e}");
            }
        });
    }
    drop(stop_rx);
    let _ = stop_tx.send(true);
    stop_tx.closed().await;
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
            let f = frame(Some(keypoints_body(&kps, bytes, w, h)), None, &[], "frame").unwrap();
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
            let f = frame(Some(keypoints_body(&kps, kps.len() * 64, 640, 480)), None, &[], "frame").unwrap();
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
                prop_assert_eq!(r.kind(), ErrorKind::InvalidArgument);
            }
        }

        /// Base64 that is not base64, and frames with both or neither source, are refused with the field.
        #[test]
        fn malformed_frames_name_the_field(junk in "[!-*,-.:-<>-@\\[-`{-~]{1,20}") {
            let f = FrameJson { image_base64: Some(junk), ..Default::default() };
            let e = frame(Some(f), None, &[], "frame1").unwrap_err();
            prop_assert!(e.to_string().contains("frame1.image_base64"), "{}", e);
            let both = FrameJson { image_base64: Some("aGk=".into()), ..keypoints_body(&[], 0, 1, 1) };
            prop_assert!(frame(Some(both), None, &[], "frame").is_err());
        }
    }

    #[test]
    fn the_default_origins_are_the_listeners_own() {
        let p = OriginPolicy::new(&[], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("http://127.0.0.1:8080") && p.allows("http://localhost:8080"));
        assert!(!p.allows("http://127.0.0.1:8081") && !p.allows("https://evil.example") && !p.allows("null"));
        let p = OriginPolicy::new(&["https://App.example.com/".into()], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("https://app.example.com") && !p.allows("http://127.0.0.1:8080"));
        assert!(OriginPolicy::new(&["*".into()], "0.0.0.0:80".parse().unwrap()).allows("https://any.where"));
    }

    #[test]
    fn intrinsics_given_twice_must_agree() {
        let a = IntrinsicsJson { fx: 250.0, fy: 250.0, cx: 159.5, cy: 119.5, width: None, height: None };
        let sized = IntrinsicsJson { width: Some(320), height: Some(240), ..a };
        let got = agreed_intrinsics(&[("frame.intrinsics", Some(a)), ("intrinsics", Some(sized))]).unwrap().unwrap();
        assert_eq!((got.width, got.height), (Some(320), Some(240)));
        assert!(agreed_intrinsics(&[("frame.intrinsics", None), ("intrinsics", None)]).unwrap().is_none());
        let other = IntrinsicsJson { cx: 160.0, ..a };
        let e = agreed_intrinsics(&[("frame.intrinsics", Some(a)), ("intrinsics", Some(other))]).unwrap_err();
        assert!(e.to_string().contains("frame.intrinsics and intrinsics"), "{e}");
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
