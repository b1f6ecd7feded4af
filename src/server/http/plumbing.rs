//! How an HTTP handler reaches the service. The router's `authorize` middleware ([`super::router`]) checks
//! the request's key for its operation before anything reads the body and hands the handler the proof
//! ([`Authorized`], a request extension); the handler reads its body, then [`call`] finds the request's map
//! once and runs the work on the CPU pool ([`App::call`]), the error logged and wrapped for the one
//! error-to-status mapping. The gRPC transport's twin is [`crate::server::grpc`]'s `GrpcApi::call`.

use std::sync::Arc;

use crate::server::app::{App, Subject};
use crate::server::auth::Authorized;
use crate::server::http::error::{ApiError, ApiResult};
use crate::service::ServiceError;

/// Logs `e` for `operation` and wraps it for the one error-to-status mapping.
pub fn failed(app: &App, operation: &str, e: ServiceError) -> ApiError {
    app.log_error(operation, &e);
    ApiError::Service(e)
}

/// Runs `f` for a request whose key was checked: with its map when `subject` names one ([`App::call`]).
pub async fn call<S, R, F>(app: &Arc<App>, authorized: Authorized, subject: S, f: F) -> ApiResult<R>
where
    S: Subject,
    R: Send + 'static,
    F: FnOnce(&App, S::Held) -> Result<R, ServiceError> + Send + 'static,
{
    app.call(authorized, subject, f).await.map_err(|e| failed(app, authorized.operation().name(), e))
}
