//! How an HTTP handler reaches the service: the API key from the headers, then [`App::call`] /
//! [`App::call_map`], with the error logged and wrapped for the one error-to-status mapping. The gRPC
//! transport's twins carry the same names ([`crate::server::grpc`]).

use std::sync::Arc;

use axum::http::HeaderMap;

use crate::server::app::App;
use crate::server::auth::{self, Authorized};
use crate::server::http::error::{ApiError, ApiResult};
use crate::service::ServiceError;
use crate::settings::Access;

pub fn api_key(headers: &HeaderMap) -> Option<String> {
    let get = |name: &str| headers.get(name).and_then(|v| v.to_str().ok());
    auth::key_from_headers(get("x-api-key"), get("authorization")).map(str::to_string)
}

/// Checks the request's key for `access`, answering the refusal in the JSON envelope.
pub fn authorize(app: &App, headers: &HeaderMap, access: Access, op: &str) -> ApiResult<Authorized> {
    app.authorize(api_key(headers).as_deref(), access, op).map_err(|e| failed(app, op, e))
}

fn failed(app: &App, op: &str, e: ServiceError) -> ApiError {
    app.log_error(op, &e);
    ApiError::Service(e)
}

/// Checks the key, then runs `f` on the CPU pool ([`App::call`]).
pub async fn call<R, F>(app: &Arc<App>, headers: &HeaderMap, access: Access, op: &str, f: F) -> ApiResult<R>
where
    R: Send + 'static,
    F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
{
    let authorized = authorize(app, headers, access, op)?;
    call_authorized(app, authorized, op, None, f).await
}

/// Checks the key, then runs `f` for a request on map `map` ([`App::call_map`]).
pub async fn call_map<R, F>(
    app: &Arc<App>,
    headers: &HeaderMap,
    access: Access,
    op: &str,
    map: &str,
    f: F,
) -> ApiResult<R>
where
    R: Send + 'static,
    F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
{
    let authorized = authorize(app, headers, access, op)?;
    call_authorized(app, authorized, op, Some(map), f).await
}

/// [`call`] (or [`call_map`] with `map`) for a handler that checked the key before it read the body.
pub async fn call_authorized<R, F>(
    app: &Arc<App>,
    authorized: Authorized,
    op: &str,
    map: Option<&str>,
    f: F,
) -> ApiResult<R>
where
    R: Send + 'static,
    F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
{
    app.call_on(authorized, op, map, f).await.map_err(|e| failed(app, op, e))
}
