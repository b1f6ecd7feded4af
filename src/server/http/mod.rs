//! HTTP/JSON transport (axum): every RPC under `/v1/...`, plus `/healthz`, `/readyz`, `/metrics`,
//! `/openapi.json` and the console under `/ui`.
//!
//! Frames come in three forms: a raw image body (`Content-Type: image/jpeg` or `image/png`, intrinsics in the
//! query string), `multipart/form-data` with a JSON part named `request` and file parts (`image`, `image1`,
//! `image2`, `depth`), or `application/json` with base64 images or precomputed keypoints.
//!
//! Rooms: [`wire`] (every JSON body, typed), [`body`] (reading bodies, frames, extractors), [`error`] (the
//! one error-to-status mapping), the handlers by resource ([`frames`], [`maps`], [`ops`], [`ui`]), and here
//! the router, the middleware (admission, origins, metrics) and the server loop. The OpenAPI document
//! ([`openapi`]) is generated from the handlers' annotations and the wire types by utoipa, from the same
//! route lists the router is built from, so the two cannot drift apart.

use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::{DefaultBodyLimit, MatchedPath, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use tokio::sync::watch;
use tower::ServiceExt;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::connections::{DeadlineBody, GuardedBody, Listener};
use super::metrics::CountedBody;
use super::App;
use crate::service::ServiceError;
use crate::settings::Access;

pub mod body;
pub mod error;
pub mod frames;
pub mod maps;
pub mod ops;
pub mod ui;
pub mod wire;

pub use error::{ApiError, ApiResult};

/// What the document says about the whole API.
#[derive(OpenApi)]
#[openapi(
    info(
        title = "scone",
        version = "1",
        description = "SConE image matching and relocalisation. The `/v1` endpoints mirror the RPCs of \
            `proto/scone/v1/scone.proto`, plus two for people looking at the service (a map's contents, and \
            the pictures of MatchPair and Localize with `render=png`). Authenticate with the `x-api-key` header (or `Authorization: Bearer`) \
            when keys are configured: a read key for reads, a write key for anything that changes a map. Poses \
            are camera-to-world, quaternions (x, y, z, w), OpenCV camera axes. Browser pages may write \
            (anything but GET and HEAD) only from an allowed origin (`server.allowed_origins`; default the \
            listener's own): a request whose Origin header is another origin is 403, and CORS preflights \
            (OPTIONS) are answered by the same policy. Every error body, a wrong route or method included, is \
            `{\"error\": {\"code\", \"message\"}}`."
    ),
    modifiers(&Security),
    security((), ("api_key" = []), ("bearer" = [])),
    components(schemas(error::ErrorBody, error::ErrorDetail)),
    tags(
        (name = "matching", description = "Describe and match frames"),
        (name = "maps", description = "Maps: create, fill, localise against, export, import"),
        (name = "operations", description = "Health, readiness, metrics, this document"),
        (name = "console", description = "The web console (HTML, JavaScript, CSS)"),
    )
)]
struct ApiDoc;

/// The API-key security schemes (a header, or a bearer token).
struct Security;

impl utoipa::Modify for Security {
    fn modify(&self, doc: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{ApiKey, ApiKeyValue, HttpAuthScheme, HttpBuilder, SecurityScheme};
        let c = doc.components.get_or_insert_with(Default::default);
        c.add_security_scheme("api_key", SecurityScheme::ApiKey(ApiKey::Header(ApiKeyValue::new("x-api-key"))));
        c.add_security_scheme(
            "bearer",
            SecurityScheme::Http(HttpBuilder::new().scheme(HttpAuthScheme::Bearer).build()),
        );
    }
}

/// The routes that run on the CPU pool (held to admission before their bodies are read).
fn pool_routes(map_limit: usize) -> OpenApiRouter<Arc<App>> {
    let (schemas, paths, import) = routes!(maps::import_map);
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(frames::describe))
        .routes(routes!(frames::match_pair))
        .routes(routes!(maps::create_map, maps::list_maps))
        .routes(routes!(maps::get_map, maps::delete_map))
        .routes(routes!(maps::map_contents))
        .routes(routes!(maps::add_keyframe))
        .routes(routes!(maps::remove_keyframe))
        .routes(routes!(frames::localize))
        .routes(routes!(maps::export_map))
        .routes((schemas, paths, import.layer(DefaultBodyLimit::max(map_limit))))
}

/// The routes that do not touch the pool: operations and the console.
fn plain_routes() -> OpenApiRouter<Arc<App>> {
    OpenApiRouter::new()
        .routes(routes!(ops::healthz))
        .routes(routes!(ops::readyz))
        .routes(routes!(ops::metrics))
        .routes(routes!(ops::openapi))
        .routes(routes!(ui::console))
        .routes(routes!(ui::asset))
}

/// The OpenAPI document of every route of [`router`].
pub fn openapi() -> utoipa::openapi::OpenApi {
    pool_routes(0).merge(plain_routes()).into_openapi()
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

/// [`call`] for a request on map `map` ([`App::call_map`]).
async fn call_map<R, F>(app: &Arc<App>, headers: &HeaderMap, access: Access, op: &str, map: &str, f: F) -> ApiResult<R>
where
    R: Send + 'static,
    F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
{
    app.call_map(api_key(headers).as_deref(), access, op, map, f).await.map_err(|e| {
        app.log_error(op, &e);
        ApiError::Service(e)
    })
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
    /// Whether a page served by this server (its Origin is `http(s)://` + the request's Host) may write.
    same_host: bool,
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
        Self { any, allowed, same_host: false }
    }

    /// Also lets pages of this server's own host write (the console, when it is reached under a name or address
    /// that is not in the list). Only with API keys on: without keys, a page whose name was rebound to this
    /// server's address (DNS rebinding) would pass this check, so the explicit list is all that holds.
    pub fn with_same_host(mut self, on: bool) -> Self {
        self.same_host = on;
        self
    }

    /// Whether `origin` is the page of the host the request was sent to.
    fn is_same_host(&self, origin: &str, host: Option<&str>) -> bool {
        self.same_host
            && host.is_some_and(|h| {
                let o = origin.to_ascii_lowercase();
                let h = h.trim().to_ascii_lowercase();
                o == format!("http://{h}") || o == format!("https://{h}")
            })
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
    let host =
        req.headers().get(header::HOST).and_then(|v| v.to_str().ok()).or(req.uri().authority().map(|a| a.as_str()));
    let allowed = origin.as_deref().is_some_and(|o| policy.allows(o) || policy.is_same_host(o, host));
    let cors = |resp: &mut Response, origin: &str| {
        let h = resp.headers_mut();
        if let Ok(v) = HeaderValue::from_str(origin) {
            h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, v);
        }
        h.insert(header::ACCESS_CONTROL_EXPOSE_HEADERS, HeaderValue::from_static("x-scone-matches, x-scone-inliers"));
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
    let (router, _) = pool_routes(map_limit)
        .route_layer(middleware::from_fn_with_state(Arc::clone(&app), admission))
        .merge(plain_routes())
        .route_layer(middleware::from_fn_with_state(Arc::clone(&app), observe))
        .split_for_parts();
    router
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
    let origins =
        OriginPolicy::new(&server.allowed_origins, listener.local_addr()?).with_same_host(!app.keys.is_empty());
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

    #[test]
    fn the_default_origins_are_the_listeners_own() {
        let p = OriginPolicy::new(&[], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("http://127.0.0.1:8080") && p.allows("http://localhost:8080"));
        assert!(!p.allows("http://127.0.0.1:8081") && !p.allows("https://evil.example") && !p.allows("null"));
        let p = OriginPolicy::new(&["https://App.example.com/".into()], "127.0.0.1:8080".parse().unwrap());
        assert!(p.allows("https://app.example.com") && !p.allows("http://127.0.0.1:8080"));
        assert!(OriginPolicy::new(&["*".into()], "0.0.0.0:80".parse().unwrap()).allows("https://any.where"));
        // The server's own host: only with keys on (a rebound name must not pass a keyless server).
        let open = OriginPolicy::new(&[], "0.0.0.0:8080".parse().unwrap());
        assert!(!open.is_same_host("http://maps.example:8080", Some("maps.example:8080")));
        let keyed = open.with_same_host(true);
        assert!(keyed.is_same_host("http://maps.example:8080", Some("maps.example:8080")));
        assert!(keyed.is_same_host("https://Maps.Example", Some("maps.example")));
        assert!(!keyed.is_same_host("http://evil.example", Some("maps.example:8080")));
        assert!(!keyed.is_same_host("http://maps.example:8080", None));
    }

    /// The document's operations are exactly the expected list, and the router's routes are all added through
    /// utoipa's `routes!` (so none can be missing from the document). That each documented operation is
    /// served is checked against the running server by `clients/python/tests/test_http_api.py`.
    #[test]
    fn every_documented_operation_is_routed_and_every_route_documented() {
        let doc = openapi();
        let mut operations = Vec::new();
        for (path, item) in &doc.paths.paths {
            let methods = [
                ("GET", item.get.is_some()),
                ("POST", item.post.is_some()),
                ("PUT", item.put.is_some()),
                ("DELETE", item.delete.is_some()),
                ("PATCH", item.patch.is_some()),
            ];
            for (m, present) in methods {
                if present {
                    operations.push(format!("{m} {path}"));
                }
            }
        }
        operations.sort();
        let expected = [
            "DELETE /v1/maps/{map_id}",
            "DELETE /v1/maps/{map_id}/keyframes/{keyframe_id}",
            "GET /healthz",
            "GET /metrics",
            "GET /openapi.json",
            "GET /readyz",
            "GET /ui",
            "GET /ui/{file}",
            "GET /v1/maps",
            "GET /v1/maps/{map_id}",
            "GET /v1/maps/{map_id}/contents",
            "GET /v1/maps/{map_id}/export",
            "POST /v1/describe",
            "POST /v1/maps",
            "POST /v1/maps/{map_id}/import",
            "POST /v1/maps/{map_id}/keyframes",
            "POST /v1/maps/{map_id}/localize",
            "POST /v1/match",
        ];
        assert_eq!(operations, expected);
        // No route of the HTTP transport bypasses the document: axum's plain `.route(` is not used here.
        for (name, src) in [
            ("mod.rs", include_str!("mod.rs")),
            ("frames.rs", include_str!("frames.rs")),
            ("maps.rs", include_str!("maps.rs")),
            ("ops.rs", include_str!("ops.rs")),
            ("ui.rs", include_str!("ui.rs")),
        ] {
            let plain = [".route(", ".nest(", ".route_service(", ".nest_service("];
            let code = src.split("#[cfg(test)]").next().unwrap_or(src);
            let code: String =
                code.lines().filter(|l| !l.trim_start().starts_with("//")).collect::<Vec<_>>().join("\n");
            for p in plain {
                assert!(!code.contains(&format!("{p}\"")), "{name} adds a route with {p} outside the document");
            }
        }
    }
}
