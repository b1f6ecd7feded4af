//! The service itself: the description path, the limits on client input and the map store, attached once
//! the maps are open; the lookup of a request's map; counts for metrics; the flush at shutdown.

use std::sync::{Arc, OnceLock};

use serde::Serialize;

use super::error::ServiceError;
use crate::describe::decode::ImageLimitSettings;
use crate::describe::features::{ExtractorSettings, KeypointLimitSettings};
use crate::describe::pipeline::Describer;
use crate::error::{EmbeddingError, MapError};
use crate::map::store::{Map, MapStore, ModelInfo, StoreSettings};
use crate::matching::SconeMatcher;
use crate::pose::RansacSettings;

/// Counts of what the service holds, for metrics.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Holdings {
    pub maps: usize,
    pub held_back: usize,
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    /// Estimated memory of the loaded maps.
    pub loaded_bytes: u64,
    /// The map cache's counts since start, by event (hit, miss, load, eviction, check, change, check_error,
    /// log_cut).
    pub cache_events: Vec<(&'static str, u64)>,
    pub cache_load_seconds: f64,
    /// Calls to the storage service (object storage) since start.
    pub storage: Vec<crate::map::storage::backend::OperationStats>,
}

/// The service's core: the description path, the map store and the limits on client input.
pub struct Service {
    pub(super) describer: Describer,
    pub(super) keypoint_limits: KeypointLimitSettings,
    pub(super) ransac: RansacSettings,
    /// MatchPair's matcher when the request names none: the model's declared one.
    pub(super) default_matcher: SconeMatcher,
    store: OnceLock<Arc<MapStore>>,
}

impl Service {
    /// `ransac`: MatchPair's essential-matrix search (`Settings::relative_pose`).
    /// Fails when the model declares a matcher that does not exist.
    pub fn new(
        describer: Describer,
        keypoint_limits: KeypointLimitSettings,
        ransac: RansacSettings,
    ) -> Result<Self, ServiceError> {
        let e = &describer.embedder;
        let default_matcher = SconeMatcher::declared(e.declared_matcher()).map_err(|reason| {
            ServiceError::Embedding(EmbeddingError::Contract { path: e.path().to_path_buf(), reason })
        })?;
        Ok(Self { describer, keypoint_limits, ransac, default_matcher, store: OnceLock::new() })
    }

    /// The extraction every image is described with (the model's declaration, `[extractor]` over it): what a
    /// client that sends keypoint sets must extract with.
    pub fn extraction(&self) -> &ExtractorSettings {
        &self.describer.extractor
    }

    /// MatchPair's matcher when a request names none (the model's declaration, `scale-aware` without one).
    pub fn default_matcher(&self) -> SconeMatcher {
        self.default_matcher
    }

    /// Makes maps available (once, after they loaded).
    pub fn attach_store(&self, store: Arc<MapStore>) {
        let _ = self.store.set(store);
    }

    /// Opens the maps `config` describes, for the model this service embeds with, and makes them available.
    /// Blocks: in eager mode every map is loaded here.
    pub fn open_store(&self, config: StoreSettings) -> Result<(), MapError> {
        let e = &self.describer.embedder;
        let info = ModelInfo { model_id: e.model_id().to_string(), k: e.k(), dim: e.dim() };
        self.attach_store(Arc::new(MapStore::open(config, info)?));
        Ok(())
    }

    pub fn store(&self) -> Result<&Arc<MapStore>, ServiceError> {
        self.store.get().ok_or(ServiceError::NotReady)
    }

    /// Map `id` for one request: the operations on a map take what this returns. With maps loaded on demand
    /// it may load the map or check its freshness ([`Service::lookup_may_block`]); holding it keeps it from
    /// being evicted until the request is done.
    pub fn map(&self, id: &str) -> Result<Arc<Map>, ServiceError> {
        Ok(self.store()?.get(id)?)
    }

    /// Whether [`Service::map`] may block on storage (a load, a freshness check against object storage), so
    /// that async callers run it on blocking threads; false before the maps are open (it answers at once).
    pub fn lookup_may_block(&self) -> bool {
        self.store.get().is_some_and(|s| s.lookup_may_block())
    }

    /// Whether map `id` is in memory now.
    pub fn is_loaded(&self, id: &str) -> bool {
        self.store.get().is_some_and(|s| s.is_loaded(id))
    }

    pub fn is_ready(&self) -> bool {
        self.store.get().is_some()
    }

    pub fn model_id(&self) -> &str {
        self.describer.embedder.model_id()
    }

    pub fn dim(&self) -> usize {
        self.describer.embedder.dim()
    }

    pub fn image_limits(&self) -> &ImageLimitSettings {
        &self.describer.limits
    }

    /// Counts for metrics (cheap: summaries only).
    pub fn holdings(&self) -> Holdings {
        let Some(store) = self.store.get() else { return Holdings::default() };
        let maps = store.loaded();
        let c = store.cache_stats();
        let n = |a: &std::sync::atomic::AtomicU64| a.load(std::sync::atomic::Ordering::Relaxed);
        Holdings {
            maps: maps.len(),
            held_back: store.held_back().len(),
            keyframes: maps.iter().map(|m| m.keyframes).sum(),
            landmarks: maps.iter().map(|m| m.landmarks).sum(),
            observations: maps.iter().map(|m| m.live_observations).sum(),
            loaded_bytes: store.loaded_bytes(),
            cache_events: vec![
                ("hit", n(&c.hits)),
                ("miss", n(&c.misses)),
                ("load", n(&c.loads)),
                ("eviction", n(&c.evictions)),
                ("check", n(&c.checks)),
                ("change", n(&c.changed)),
                ("check_error", n(&c.check_errors)),
                ("log_cut", n(&c.logs_cut)),
            ],
            cache_load_seconds: n(&c.load_nanos) as f64 * 1e-9,
            storage: store.operation_stats(),
        }
    }

    /// Snapshots every map and dumps its index; returns the maps that could not be (their acknowledged writes
    /// are in their logs), with the error.
    pub fn flush(&self) -> Vec<(String, MapError)> {
        self.store.get().map(|s| s.flush()).unwrap_or_default()
    }
}
