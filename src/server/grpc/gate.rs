//! The gate in front of the `scone.v1` services ([`GateLayer`]).

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Instant;

use super::convert::to_status;
use crate::server::app::App;
use crate::server::auth;
use crate::server::metrics::CountedBody;
use crate::server::operation::Operation;

/// The gate of the `scone.v1` services, before a call's message is read or decoded: a call is refused with
/// RESOURCE_EXHAUSTED (and `retry-after`, after [`App::hold_refusal`]) when the CPU pool has no free slot, then
/// with UNAUTHENTICATED or PERMISSION_DENIED when its key does not allow its operation ([`Operation`]); a call
/// that passes carries the proof ([`auth::Authorized`]) to its method. Counts the bytes of the messages it lets
/// through.
#[derive(Clone)]
pub struct GateLayer {
    app: Arc<App>,
    body_bytes: prometheus_client::metrics::counter::Counter,
}

impl GateLayer {
    pub fn new(app: Arc<App>) -> Self {
        let body_bytes = app.metrics.body_bytes("grpc");
        Self { app, body_bytes }
    }
}

impl<S> tower::Layer<S> for GateLayer {
    type Service = Gate<S>;

    fn layer(&self, inner: S) -> Gate<S> {
        Gate { inner, layer: self.clone() }
    }
}

/// See [`GateLayer`].
#[derive(Clone)]
pub struct Gate<S> {
    inner: S,
    layer: GateLayer,
}

const POOL_SERVICES: &str = "/scone.v1.";

impl<S> tower::Service<axum::http::Request<tonic::body::Body>> for Gate<S>
where
    S: tower::Service<axum::http::Request<tonic::body::Body>, Response = axum::http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = axum::http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, S::Error>> + Send + 'static>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: axum::http::Request<tonic::body::Body>) -> Self::Future {
        let path = req.uri().path();
        if path.starts_with(POOL_SERVICES) {
            let (app, t) = (Arc::clone(&self.layer.app), Instant::now());
            let method = path.rsplit('/').next().unwrap_or(path).to_string();
            let refusal = match app.check_room() {
                Err(e) => Some((e, true)),
                // An unknown method passes: tonic answers UNIMPLEMENTED.
                Ok(()) => Operation::from_grpc_path(path).and_then(|operation| {
                    match app.authorize(auth::request_key(req.headers()).as_deref(), operation) {
                        Ok(authorized) => {
                            req.extensions_mut().insert(authorized);
                            None
                        }
                        Err(e) => Some((e, false)),
                    }
                }),
            };
            if let Some((e, overloaded)) = refusal {
                app.log_error(&method, &e);
                // The request, and with it the unread message, is dropped here.
                drop(req);
                return Box::pin(async move {
                    if overloaded {
                        app.hold_refusal().await;
                    }
                    let status = to_status(&e);
                    let code = format!("{:?}", status.code());
                    app.metrics.request("grpc", &method, &code, t.elapsed().as_secs_f64());
                    Ok(status.into_http())
                });
            }
        }
        let bytes = self.layer.body_bytes.clone();
        let req = req.map(|b| tonic::body::Body::new(CountedBody::new(b, bytes)));
        Box::pin(self.inner.call(req))
    }
}
