//! What both gRPC services hold, and the one way a method reaches the service ([`GrpcApi::call`]).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tonic::{Code, Request, Status, Streaming};

use super::convert::to_status;
use crate::server::app::{App, Subject};
use crate::server::auth::Authorized;
use crate::service::ServiceError;

/// Both gRPC services over one [`App`].
#[derive(Clone)]
pub struct GrpcApi {
    pub(super) app: Arc<App>,
}

impl GrpcApi {
    /// The one way a method reaches the service: with the key its [`super::GateLayer`] checked (before the message
    /// was read), finds what the request works on (its map, once) and runs `f` on the CPU pool
    /// ([`App::call`]); the outcome is counted, logged and mapped to a status.
    pub(super) async fn call<S, R, F>(&self, authorized: Authorized, subject: S, f: F) -> Result<R, Status>
    where
        S: Subject,
        R: Send + 'static,
        F: FnOnce(&App, S::Held) -> Result<R, ServiceError> + Send + 'static,
    {
        let t = Instant::now();
        let r = self.app.call(authorized, subject, f).await;
        let route = authorized.operation().name();
        let code = match &r {
            Ok(_) => Code::Ok,
            Err(e) => to_status(e).code(),
        };
        self.app.metrics.request("grpc", route, &format!("{code:?}"), t.elapsed().as_secs_f64());
        r.map_err(|e| {
            self.app.log_error(route, &e);
            to_status(&e)
        })
    }
}

/// The proof that [`super::GateLayer`] checked the call's key (a request extension).
pub(super) fn authorized<T>(req: &Request<T>) -> Result<Authorized, Status> {
    req.extensions().get::<Authorized>().copied().ok_or_else(|| {
        to_status(&ServiceError::Internal("a scone.v1 call reached its method without a key check".into()))
    })
}

impl GrpcApi {
    /// The next message of a client stream, or DEADLINE_EXCEEDED when none came within
    /// `server.idle_timeout_ms` (a stream left open without messages would hold its connection).
    pub(super) async fn next_message<T>(&self, inbound: &mut Streaming<T>) -> Result<Option<T>, Status> {
        let ms = self.app.settings.server.idle_timeout_ms;
        match tokio::time::timeout(Duration::from_millis(ms), inbound.message()).await {
            Ok(r) => r,
            Err(_) => Err(to_status(&ServiceError::DeadlineExceeded { ms, write: false })),
        }
    }
}
