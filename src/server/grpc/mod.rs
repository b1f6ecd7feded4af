//! gRPC transport (tonic): `scone.v1.Maps`, `scone.v1.Matching`, `grpc.health.v1` and server reflection.
//!
//! Every `scone.v1` method runs on the CPU pool. Before a call's message is read or decoded ([`GateLayer`]) it
//! is answered RESOURCE_EXHAUSTED when the pool has no free slot, so a storm of clients that do not back off
//! costs a request head each (HTTP/2 resets the stream, which stops the client sending the rest of the
//! message), and UNAUTHENTICATED or PERMISSION_DENIED when its key does not allow it, so a client without a
//! key cannot make the server read a large message.
//!
//! Rooms: `convert.rs` (the wire and the domain both ways, the one error-to-status mapping), `api.rs` (what
//! the services hold, and the one way a method reaches the service), `gate.rs` (room and key, before a
//! message is read), `maps.rs` and `matching.rs` (the two services); here, the server.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

mod api;
mod convert;
mod gate;
mod maps;
mod matching;

pub use api::GrpcApi;
pub use convert::{frame_input, to_status};
pub use gate::{Gate, GateLayer};

use super::connections::{CountRequestsLayer, Listener};
use crate::server::app::App;
use crate::server::proto;

/// Serves gRPC on `listener` until `shutdown` resolves, then lets in-flight calls finish. Connections are
/// held to the limits of [`super::connections`]; HTTP/2 pings find dead peers, streams per connection are
/// capped, and a call must be answered within `body_read_timeout_ms + request_timeout_ms`.
pub async fn serve<H>(
    app: Arc<App>,
    listener: Listener,
    health: tonic_health::pb::health_server::HealthServer<H>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()>
where
    H: tonic_health::pb::health_server::Health,
{
    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    // v1 and v1alpha: grpcurl and older tools still ask for v1alpha.
    let reflection_v1 = reflection().build_v1()?;
    let reflection_v1alpha = reflection().build_v1alpha()?;
    let server = &app.settings.server;
    let max = server.max_request_bytes;
    let call_timeout = Duration::from_millis(server.body_read_timeout_ms + server.request_timeout_ms);
    let keepalive =
        (server.grpc_keepalive_interval_ms > 0).then(|| Duration::from_millis(server.grpc_keepalive_interval_ms));
    let keepalive_timeout = Duration::from_millis(server.grpc_keepalive_timeout_ms);
    let max_streams = server.max_concurrent_streams;
    let api = GrpcApi { app: Arc::clone(&app) };
    let incoming = futures_util::stream::unfold(listener, |listener| async move {
        let (conn, _peer) = listener.accept().await;
        Some((Ok::<_, std::io::Error>(conn), listener))
    });
    tonic::transport::Server::builder()
        .timeout(call_timeout)
        .http2_keepalive_interval(keepalive)
        .http2_keepalive_timeout(Some(keepalive_timeout))
        .max_concurrent_streams(max_streams)
        .layer(CountRequestsLayer)
        .layer(GateLayer::new(Arc::clone(&app)))
        .add_service(health)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(
            proto::maps_server::MapsServer::new(api.clone())
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
        )
        .add_service(
            proto::matching_server::MatchingServer::new(api)
                .max_decoding_message_size(max)
                .max_encoding_message_size(max),
        )
        // TCP_NODELAY is set by the listener.
        .serve_with_incoming_shutdown(incoming, shutdown)
        .await?;
    Ok(())
}
