//! What every request handler holds: the service, the CPU pool, the keys, the metrics and the settings, and
//! the one way a request reaches the service ([`App::call`]): with the key checked, the request's map is
//! looked up once (loaded if it must be) and handed to the work, which runs on the CPU pool under the
//! request deadline.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cpu_pool::{CpuPool, PoolError, PoolStats};
use crate::server::auth::{self, Authorized};
use crate::server::metrics;
use crate::server::operation::Operation;
use crate::service::{Holdings, Map, Service, ServiceError};
use crate::settings::Settings;

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

impl metrics::Source for App {
    fn holdings(&self) -> Holdings {
        self.service.holdings()
    }

    fn pool(&self) -> &PoolStats {
        self.pool.stats()
    }
}

/// What a request works on, found before its work is queued: nothing in particular ([`NoMap`]), or one map
/// ([`MapId`]), looked up once per request and handed to the work.
pub trait Subject: Send + 'static {
    /// What the work is given.
    type Held: Send + 'static;

    /// Finds it (a map may be loaded or checked for freshness: see [`App::map`]).
    fn find(self, app: &Arc<App>) -> impl std::future::Future<Output = Result<Self::Held, ServiceError>> + Send;
}

/// A request on no map (Describe, MatchPair, ListMaps, CreateMap, ...).
pub struct NoMap;

impl Subject for NoMap {
    type Held = ();

    async fn find(self, _app: &Arc<App>) -> Result<(), ServiceError> {
        Ok(())
    }
}

/// A request on one map.
pub struct MapId(pub String);

impl Subject for MapId {
    type Held = Arc<Map>;

    async fn find(self, app: &Arc<App>) -> Result<Arc<Map>, ServiceError> {
        app.map(&self.0).await
    }
}

impl App {
    /// Checks `key` for `operation` ([`auth::Keys::authorize`]). The transports call this before they read a
    /// request's body.
    pub fn authorize(&self, key: Option<&str>, operation: Operation) -> Result<Authorized, ServiceError> {
        self.keys.authorize(key, operation)
    }

    /// The one way a request reaches the service: finds what it works on (`subject`: its map, once), then
    /// runs `f` with it on the CPU pool under the request deadline. The key was checked (`authorized`).
    pub async fn call<S, R, F>(self: &Arc<Self>, authorized: Authorized, subject: S, f: F) -> Result<R, ServiceError>
    where
        S: Subject,
        R: Send + 'static,
        F: FnOnce(&App, S::Held) -> Result<R, ServiceError> + Send + 'static,
    {
        let operation = authorized.operation().name();
        let held = subject.find(self).await?;
        let timeout = self.settings.server.request_timeout_ms;
        let deadline = Instant::now() + Duration::from_millis(timeout);
        let app = Arc::clone(self);
        match self.pool.run(deadline, move || f(&app, held)).await {
            Ok(r) => r,
            Err(PoolError::Full(_)) => {
                self.hold_refusal().await;
                Err(ServiceError::Overloaded { queued: self.pool.stats().queued.load(Ordering::Relaxed) })
            }
            Err(PoolError::Expired) => {
                let write = authorized.operation().access() == crate::settings::Access::Write;
                Err(ServiceError::DeadlineExceeded { ms: timeout, write })
            }
            Err(PoolError::Closed) => Err(ServiceError::ShuttingDown),
            Err(PoolError::Panicked) => Err(ServiceError::Internal(format!("{operation} panicked"))),
        }
    }

    /// Map `id`, looked up once for a request: an unknown map is refused before any CPU work. When a lookup
    /// may block (maps loaded on demand, or a freshness check against object storage) it runs on tokio's
    /// blocking threads, so a load never holds a CPU worker that requests for loaded maps need, and cold maps
    /// load two at a time (`map_loads`).
    pub async fn map(self: &Arc<Self>, id: &str) -> Result<Arc<Map>, ServiceError> {
        let service = &self.service;
        if !service.lookup_may_block() {
            return service.map(id);
        }
        let _loading = match service.is_loaded(id) {
            true => None,
            false => Some(self.map_loads.acquire().await.map_err(|_| ServiceError::ShuttingDown)?),
        };
        let (app, id) = (Arc::clone(self), id.to_string());
        tokio::task::spawn_blocking(move || app.service.map(&id))
            .await
            .map_err(|_| ServiceError::Internal("loading the map panicked".into()))?
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
    /// must free space) at error level, object storage that did not answer at warning level (with the object
    /// and its answer, which the client is not told); the client's own mistakes at debug.
    pub fn log_error(&self, operation: &str, e: &ServiceError) {
        use crate::error::MapError::{NoBucket, StorageUnavailable};
        use crate::service::ErrorKind::{InsufficientStorage, Internal};
        if matches!(e.kind(), Internal | InsufficientStorage) {
            tracing::error!(operation, error = %e, "request failed");
        } else if matches!(e, ServiceError::Map(StorageUnavailable { .. } | NoBucket { .. })) {
            tracing::warn!(operation, error = %e, "map storage unavailable");
        } else {
            tracing::debug!(operation, error = %e, "request refused");
        }
    }
}
