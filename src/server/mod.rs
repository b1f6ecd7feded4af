//! The transports: gRPC ([`grpc`], tonic) and HTTP/JSON ([`http`], axum) over one [`Service`].
//!
//! Path of a request: from its head alone, the transport first refuses it when the CPU pool has no free slot
//! ([`App::check_room`], so overload costs a request head), then checks its key for its [`operation`]
//! ([`auth`]), so a client without a key cannot make the server read a body. Then it reads the body, converts
//! the wire format to the service's domain types, and hands a closure to [`App::call`], which looks the
//! request's map up once and runs the closure with it on the bounded CPU pool
//! ([`crate::cpu_pool::CpuPool`]) under the request deadline; the result or the
//! [`ServiceError`](crate::service::ServiceError) is converted back, each transport with exactly one error
//! mapping.
//!
//! Life cycle ([`start`]): settings are validated and the model is loaded (a model that breaks the contract
//! stops the start here), both listeners bind, health reports NOT_SERVING while the maps load on a blocking
//! thread, then SERVING. On shutdown health flips to NOT_SERVING first, both servers stop accepting and
//! finish in-flight requests within `server.shutdown_grace_ms`, the pool drains, and every map is flushed.

pub mod app;
pub mod auth;
pub mod connections;
pub mod grpc;
pub mod http;
pub mod metrics;
pub mod operation;
pub mod proto;

pub use app::App;

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::cpu_pool::CpuPool;
use crate::describe::embedding::Embedder;
use crate::describe::pipeline::Describer;
use crate::service::Service;
use crate::settings::Settings;

/// A started server.
pub struct Running {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    pub app: Arc<App>,
    stop: watch::Sender<bool>,
    done: JoinHandle<anyhow::Result<()>>,
}

impl Running {
    /// Waits until the maps are loaded (or the server stopped).
    pub async fn wait_ready(&self, timeout: Duration) -> anyhow::Result<()> {
        let t = Instant::now();
        while !self.app.is_ready() {
            anyhow::ensure!(!self.done.is_finished(), "the server stopped while starting");
            anyhow::ensure!(t.elapsed() < timeout, "not ready after {timeout:?}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(())
    }

    /// Asks the server to stop without waiting.
    pub fn request_shutdown(&self) {
        self.app.shutting_down.store(true, Ordering::Relaxed);
        let _ = self.stop.send(true);
    }

    /// Stops the server gracefully and waits for the flush.
    pub async fn shutdown(self) -> anyhow::Result<()> {
        self.request_shutdown();
        self.done.await.context("server task")?
    }

    /// Waits for the server to stop (after [`Running::request_shutdown`] or a failure).
    pub async fn wait(self) -> anyhow::Result<()> {
        self.done.await.context("server task")?
    }
}

const SERVICES: [&str; 3] = ["", "scone.v1.Maps", "scone.v1.Matching"];

async fn set_health(reporter: &tonic_health::server::HealthReporter, serving: bool) {
    let status = if serving { tonic_health::ServingStatus::Serving } else { tonic_health::ServingStatus::NotServing };
    for s in SERVICES {
        reporter.set_service_status(s, status).await;
    }
}

/// Loads the model, binds both listeners and starts serving; maps load in the background.
pub async fn start(settings: Settings) -> anyhow::Result<Running> {
    settings.validate()?;
    let keys = auth::Keys::new(settings.keys()?);
    tracing::info!(settings = %settings.redacted(), api_keys = keys.len(), "starting scone");
    // The pool gives the parallelism; OpenCV's own threads inside each job would only oversubscribe.
    crate::describe::features::set_opencv_threads(1)?;
    let model_cfg = settings.model.clone();
    let embedder = tokio::task::spawn_blocking(move || Embedder::load(&model_cfg)).await??;
    let embedder = Arc::new(embedder);
    tracing::info!(model = %embedder.model_id(), path = %embedder.path().display(), "model loaded");
    let extractor = settings.extractor.over(embedder.extraction());
    if extractor != embedder.extraction() {
        tracing::warn!(
            configured = ?extractor,
            trained_at = ?embedder.extraction(),
            "[extractor] differs from the extraction the model was trained at: its answers will be worse, and \
             clients that send keypoint sets must extract as configured"
        );
    }
    tracing::info!(extractor = ?extractor, "extraction");
    let describer = Describer { extractor, limits: settings.limits.image, embedder: Arc::clone(&embedder) };
    let service = Service::new(describer, settings.limits.keypoints, settings.relative_pose)?;
    let grpc_listener = TcpListener::bind(settings.server.grpc_addr)
        .await
        .with_context(|| format!("binding gRPC to {}", settings.server.grpc_addr))?;
    let http_listener = TcpListener::bind(settings.server.http_addr)
        .await
        .with_context(|| format!("binding HTTP to {}", settings.server.http_addr))?;
    let grpc_addr = grpc_listener.local_addr()?;
    let http_addr = http_listener.local_addr()?;
    let limits = connections::ConnectionLimits::from_settings(&settings.server);
    let grpc_listener = connections::Listener::new(grpc_listener, limits, connections::Protocol::Http2, "grpc");
    let http_listener = connections::Listener::new(http_listener, limits, connections::Protocol::Http1OrHttp2, "http");
    // The metrics read the maps held and the pool's counts from the app at each scrape.
    let app = Arc::new_cyclic(|app: &std::sync::Weak<App>| App {
        service,
        pool: CpuPool::new(settings.workers.threads, settings.workers.queue),
        keys,
        metrics: metrics::Metrics::new(app.clone()),
        settings: settings.clone(),
        shutting_down: AtomicBool::new(false),
        map_loads: tokio::sync::Semaphore::new(2),
    });

    let (reporter, health_service) = tonic_health::server::health_reporter();
    set_health(&reporter, false).await;
    let (stop, stop_rx) = watch::channel(false);

    let grpc_task = tokio::spawn(grpc::serve(Arc::clone(&app), grpc_listener, health_service, signal(stop_rx.clone())));
    let http_task = tokio::spawn(http::serve(Arc::clone(&app), http_listener, signal(stop_rx.clone())));
    tracing::info!(%grpc_addr, %http_addr, "listening (gRPC, HTTP); loading maps");

    // Maps load on a blocking thread while health says NOT_SERVING.
    let loader = {
        let app = Arc::clone(&app);
        let reporter = reporter.clone();
        let store_cfg = settings.store.clone();
        tokio::spawn(async move {
            let t = Instant::now();
            let opener = Arc::clone(&app);
            tokio::task::spawn_blocking(move || opener.service.open_store(store_cfg)).await??;
            if !app.shutting_down.load(Ordering::Relaxed) {
                set_health(&reporter, true).await;
            }
            let h = app.service.holdings();
            tracing::info!(
                maps = h.maps,
                held_back = h.held_back,
                observations = h.observations,
                seconds = t.elapsed().as_secs_f64(),
                "maps loaded; serving"
            );
            anyhow::Ok(())
        })
    };

    let grace = Duration::from_millis(settings.server.shutdown_grace_ms);
    let driver_app = Arc::clone(&app);
    let stopper = stop.clone();
    let done = tokio::spawn(async move {
        let app = driver_app;
        let mut loader = loader;
        let load_failed = tokio::select! {
            _ = signal(stop_rx.clone()) => None,
            r = &mut loader => match r {
                Ok(Ok(())) => { signal(stop_rx.clone()).await; None }
                Ok(Err(e)) => Some(e),
                Err(e) => Some(anyhow::anyhow!("map loader: {e}")),
            },
        };
        if let Some(e) = &load_failed {
            tracing::error!(error = %e, "loading maps failed; stopping");
            let _ = stopper.send(true);
        }
        tracing::info!("shutting down: NOT_SERVING, finishing in-flight requests");
        app.shutting_down.store(true, Ordering::Relaxed);
        set_health(&reporter, false).await;
        let servers = async {
            let (g, h) = tokio::join!(grpc_task, http_task);
            for r in [g, h] {
                match r {
                    Ok(Err(e)) => tracing::error!(error = %e, "server error"),
                    Err(e) => tracing::error!(error = %e, "server task failed"),
                    Ok(Ok(())) => {}
                }
            }
        };
        if tokio::time::timeout(grace, servers).await.is_err() {
            tracing::warn!(
                grace_ms = grace.as_millis() as u64,
                "in-flight requests did not finish within the grace period"
            );
        }
        loader.abort();
        let flush_app = Arc::clone(&app);
        let not_flushed = tokio::task::spawn_blocking(move || {
            flush_app.pool.shutdown();
            flush_app.service.flush()
        })
        .await?;
        if not_flushed.is_empty() {
            tracing::info!("maps flushed; stopped");
        } else {
            // Not a failed shutdown: what was acknowledged is in the logs, and the next start replays it.
            let maps: Vec<&str> = not_flushed.iter().map(|(id, _)| id.as_str()).collect();
            tracing::warn!(
                ?maps,
                "stopped; these maps were not snapshotted (their logs hold every acknowledged write)"
            );
        }
        match load_failed {
            Some(e) => Err(e),
            None => Ok(()),
        }
    });
    Ok(Running { grpc_addr, http_addr, app, stop, done })
}

async fn signal(mut rx: watch::Receiver<bool>) {
    let _ = rx.wait_for(|s| *s).await;
}

/// Runs until SIGINT or SIGTERM, then shuts down gracefully.
pub async fn run(settings: Settings) -> anyhow::Result<()> {
    let running = start(settings).await?;
    println!("scone listening: gRPC {} HTTP http://{}", running.grpc_addr, running.http_addr);
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    let stop = running.stop.clone();
    tokio::spawn(async move {
        tokio::select! {
            _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT"),
            _ = term.recv() => tracing::info!("SIGTERM"),
        }
        let _ = stop.send(true);
    });
    running.wait().await
}
