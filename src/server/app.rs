//! What every request handler holds: the service, the CPU pool, the keys, the metrics and the settings, and
//! the one way a request reaches the service ([`App::call`], [`App::call_map`]): the key is checked, the map
//! is loaded if it must be (lazy mode), and the work runs on the CPU pool under the request deadline.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cpu_pool::{CpuPool, PoolError};
use crate::server::auth::{self, Authorized};
use crate::server::metrics;
use crate::service::{Service, ServiceError};
use crate::settings::{Access, Settings};

/// Everything a request handler needs.
pub struct App {
    pub service: Service,
    pub pool: CpuPool,
    pub keys: auth::Keys,
    pub metrics: metrics::Metrics,
    pub settings: Settings,
    pub(crate) shutting_down: AtomicBool,
    /// Maps loaded at once (lazy mode): a burst of requests for cold maps loads them two at a time instead of
    /// all together past the cache's budget.
    pub(crate) map_loads: tokio::sync::Semaphore,
}

impl App {
    /// Checks `key` for `access` ([`auth::Keys::authorize`]): what [`App::call`] and [`App::call_map`] need.
    pub fn authorize(&self, key: Option<&str>, access: Access, operation: &str) -> Result<Authorized, ServiceError> {
        self.keys.authorize(key, access, operation)
    }

    /// Runs `f` on the CPU pool under the request deadline (the key was checked: `_authorized`).
    pub async fn call<R, F>(self: &Arc<Self>, _authorized: Authorized, operation: &str, f: F) -> Result<R, ServiceError>
    where
        R: Send + 'static,
        F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
    {
        self.run_on_pool(operation, f).await
    }

    /// Runs `f` on the CPU pool under the request deadline.
    async fn run_on_pool<R, F>(self: &Arc<Self>, operation: &str, f: F) -> Result<R, ServiceError>
    where
        R: Send + 'static,
        F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
    {
        let timeout = self.settings.server.request_timeout_ms;
        let deadline = Instant::now() + Duration::from_millis(timeout);
        let app = Arc::clone(self);
        match self.pool.run(deadline, move || f(&app)).await {
            Ok(r) => r,
            Err(PoolError::Full(_)) => {
                self.hold_refusal().await;
                Err(ServiceError::Overloaded { queued: self.pool.stats().queued.load(Ordering::Relaxed) })
            }
            Err(PoolError::Expired) => Err(ServiceError::DeadlineExceeded { ms: timeout }),
            Err(PoolError::Closed) => Err(ServiceError::ShuttingDown),
            Err(PoolError::Panicked) => Err(ServiceError::Internal(format!("{operation} panicked"))),
        }
    }

    /// [`App::call`] for a request on one map: first, when maps are loaded on demand, the map is loaded (or
    /// checked for freshness) on tokio's blocking threads, so a load never holds a CPU worker that requests
    /// for loaded maps need; an unknown map is refused before any CPU work.
    pub async fn call_map<R, F>(
        self: &Arc<Self>,
        _authorized: Authorized,
        operation: &str,
        map: &str,
        f: F,
    ) -> Result<R, ServiceError>
    where
        R: Send + 'static,
        F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
    {
        // The map, held until the request is done so that it cannot be evicted in between.
        let mut _held = None;
        if let Some(cold) = self.service.map_to_prepare(map) {
            let _loading = match cold {
                false => None,
                true => Some(self.map_loads.acquire().await.map_err(|_| ServiceError::ShuttingDown)?),
            };
            let (app, id) = (Arc::clone(self), map.to_string());
            _held = Some(
                tokio::task::spawn_blocking(move || app.service.prepare(&id))
                    .await
                    .map_err(|_| ServiceError::Internal(format!("{operation}: loading the map panicked")))??,
            );
        }
        self.run_on_pool(operation, f).await
    }

    /// [`App::call_map`] for a request on `map`, [`App::call`] without one.
    pub async fn call_on<R, F>(
        self: &Arc<Self>,
        authorized: Authorized,
        operation: &str,
        map: Option<&str>,
        f: F,
    ) -> Result<R, ServiceError>
    where
        R: Send + 'static,
        F: FnOnce(&App) -> Result<R, ServiceError> + Send + 'static,
    {
        match map {
            Some(map) => self.call_map(authorized, operation, map, f).await,
            None => self.call(authorized, operation, f).await,
        }
    }

    /// Refuses with [`ServiceError::Overloaded`] when every slot of the CPU pool is taken. The transports
    /// call this before they read a body that the pool would refuse anyway; it reserves nothing.
    pub fn check_room(&self) -> Result<(), ServiceError> {
        self.pool
            .check_room()
            .map_err(|_| ServiceError::Overloaded { queued: self.pool.stats().queued.load(Ordering::Relaxed) })
    }

    /// Waits `workers.refusal_hold_ms` before a refusal for a full pool is sent: a client that retries at
    /// once is held to one attempt per hold, so refusals cannot take the core from the pool.
    pub async fn hold_refusal(&self) {
        let ms = self.settings.workers.refusal_hold_ms;
        if ms > 0 {
            tokio::time::sleep(Duration::from_millis(ms)).await;
        }
    }

    /// Ready to serve maps: loaded, not shutting down.
    pub fn is_ready(&self) -> bool {
        self.service.is_ready() && !self.shutting_down.load(Ordering::Relaxed)
    }

    /// Logs errors that are ours (clients get a generic message for those) and a full data volume (the operator
    /// must free space) at error level; the client's own mistakes at debug.
    pub fn log_error(&self, operation: &str, e: &ServiceError) {
        use crate::service::ErrorKind::{InsufficientStorage, Internal};
        if matches!(e.kind(), Internal | InsufficientStorage) {
            tracing::error!(operation, error = %e, "request failed");
        } else {
            tracing::debug!(operation, error = %e, "request refused");
        }
    }
}
