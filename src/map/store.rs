//! The registry of maps: create, list, get, delete, write keyframes, localise, export and import.
//!
//! Concurrency: the registry is a `RwLock<HashMap<id, Arc<Map>>>` held only to look up or insert an `Arc`;
//! work on a map happens after the registry lock is released, so maps never wait for each other. Inside a
//! map, one `Mutex` serialises writers (plan, log with fsync, apply) and a `RwLock` guards the state: queries
//! take it shared; a writer takes it exclusively only to apply a planned record and update the index. None
//! of these locks is held across an `.await` (callers run this code on blocking worker threads).
//!
//! **Which maps are in memory** (`[store.cache]`). Eager (the default with a local directory): start-up
//! loads every stored map. Lazy (the default with object storage, where several replicas share one bucket):
//! a map is loaded on its first request and kept while the loaded maps fit `memory_budget_mb` (estimated per
//! map, [`MapData::memory_bytes`]); beyond it the least recently used map that no request is using is
//! evicted, and loaded again when asked for. Existence is the backend's, not the cache's: create, import,
//! delete and listings ask the backend, so a map another replica created or deleted is seen at this
//! replica's next request for it. The server loads a map before it queues the request's CPU work
//! ([`MapStore::prepare`]), so a load never holds a CPU worker that queries of loaded maps need.
//!
//! **Freshness**: a request for a loaded map whose copy was last checked more than `freshness_ms` ago first
//! asks the backend whether the stored map moved on ([`MapJournal::refresh`]: a conditional GET of the
//! manifest), then applies the records another replica appended, or loads the map again when it was
//! rewritten. So a read reflects every write acknowledged by any replica more than `freshness_ms` (plus one
//! manifest round trip) before it. One request per map checks at a time; the others meanwhile serve the
//! copy as it is. When a check fails (the bucket unreachable) the copy is served and checked again after
//! the interval.
//!
//! A map that fails to load (corruption) is held back with its reason and reported as unavailable, and the
//! others serve; in lazy mode its load is tried again after `freshness_ms`.
//!
//! Storage goes through a [`MapBackend`] chosen by `store.backend`: the local directory (default) or object
//! storage ([`crate::map::s3`]). Its calls block (fsync, HTTP round trips), like the rest of
//! this module: call it from blocking threads only.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use parking_lot::{Mutex, RwLock};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::MapError;
use crate::features::Features;
use crate::map::builder::{plan, BuildParams, ExternalCounts, KeyframeInput};
use crate::map::format::{decode_export, encode_export, write_atomic};
use crate::map::index::{install_dump, read_dump, EmbeddingIndex, IndexParams};
use crate::map::journal::{Freshness, LoadReport, MapBackend, MapJournal, OperationStats};
use crate::map::local::LocalBackend;
use crate::map::localize::{localize, Localization, LocalizeParams, Prior};
use crate::map::model::{validate_map_id, MapData, MapMeta, MapStats, Record};
use crate::map::s3::{ObjectStorageBackend, S3Config, S3Credentials};

/// Settings of the map store.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StoreConfig {
    /// Local directory: the maps themselves with the local backend (`maps/<id>/`), the cache of index
    /// dumps with object storage (`cache/<id>/`, unless `backend.cache_dir` says otherwise).
    pub data_dir: PathBuf,
    /// Log records between snapshots.
    pub compact_every: usize,
    pub index: IndexParams,
    pub build: BuildParams,
    pub localize: LocalizeParams,
    /// Where maps are stored: `kind = "local"` (default) or `kind = "s3"`.
    pub backend: BackendConfig,
    /// Which maps are kept in memory, and how fresh a replica's copy is.
    pub cache: CacheConfig,
}

/// The cache of loaded maps (`[store.cache]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CacheConfig {
    /// Load maps on first request and evict the least recently used beyond the budget (`true`), or load
    /// every map at start and keep them all (`false`). Absent: lazy with object storage, eager with a local
    /// directory.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lazy: Option<bool>,
    /// Memory the loaded maps may take, in MiB (estimated; 0: no limit). Lazy mode only. The default suits a
    /// pod with 4 GiB: the rest is the model, the CPU pool's images and the allocator's slack.
    pub memory_budget_mb: u64,
    /// A loaded map is checked against the stored one when its last check is older than this (ms); 0 checks
    /// on every request. The staleness bound readers see.
    pub freshness_ms: u64,
}

impl Default for CacheConfig {
    fn default() -> Self {
        Self { lazy: None, memory_budget_mb: 2048, freshness_ms: 2000 }
    }
}

impl CacheConfig {
    /// Whether maps are loaded on demand with this backend.
    pub fn is_lazy(&self, backend: &BackendConfig) -> bool {
        self.lazy.unwrap_or(matches!(backend, BackendConfig::S3(_)))
    }
}

/// Counts of the map cache since start, for `/metrics`.
#[derive(Debug, Default)]
pub struct CacheStats {
    /// Requests that found their map loaded...
    pub hits: AtomicU64,
    /// ...and that had to load it (lazy mode).
    pub misses: AtomicU64,
    /// Maps loaded, and the time spent loading them (ns).
    pub loads: AtomicU64,
    pub load_nanos: AtomicU64,
    pub evictions: AtomicU64,
    /// Freshness checks, and those that found the stored map changed (applied or reloaded).
    pub checks: AtomicU64,
    pub changed: AtomicU64,
    pub check_errors: AtomicU64,
    /// Map loads that cut bytes off the end of a log (a record torn by a crash, or a damaged file).
    pub logs_cut: AtomicU64,
}

impl Default for StoreConfig {
    fn default() -> Self {
        Self {
            data_dir: PathBuf::from("data"),
            compact_every: 200,
            index: IndexParams::default(),
            build: BuildParams::default(),
            localize: LocalizeParams::default(),
            backend: BackendConfig::default(),
            cache: CacheConfig::default(),
        }
    }
}

/// What the model that embeds queries and keyframes is.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    pub model_id: String,
    pub k: usize,
    pub dim: usize,
}

/// Statistics of a map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapSummary {
    pub id: String,
    pub model_id: String,
    pub keyframes: usize,
    pub landmarks: usize,
    pub observations: usize,
    pub live_observations: usize,
    pub version: u64,
    pub approximate_index: bool,
    /// Whether this server holds the map in memory (lazy mode lists stored maps it has not loaded).
    pub loaded: bool,
    /// What loading the map found that a client should know: the log ended inside a record and its bytes
    /// were cut off ([`LoadReport::truncated_bytes`]). After a crash that is the one write in flight, never
    /// acknowledged; a longer loss means damage to the file.
    pub load_note: Option<String>,
}

/// A map's contents for viewers (see [`MapStore::contents`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MapContents {
    pub version: u64,
    /// (keyframe id, camera-to-world pose, intrinsics), by id.
    pub keyframes: Vec<(u64, crate::camera::Pose, Camera)>,
    /// (landmark id, position, observations), an even subsample by id.
    pub landmarks: Vec<(u64, [f64; 3], usize)>,
    pub landmarks_total: usize,
}

/// What a keyframe write added.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct KeyframeAdded {
    pub keyframe: u64,
    pub new_landmarks: usize,
    pub observations: usize,
    pub version: u64,
    /// What became of the keyframe's external landmarks (all zero without them).
    pub external: ExternalCounts,
}

struct MapState {
    data: MapData,
    index: EmbeddingIndex,
}

/// What to do with a loaded map after a freshness check.
enum Next {
    Keep,
    Reload,
    Gone,
}

/// One loaded map.
pub struct Map {
    id: String,
    state: RwLock<MapState>,
    log: Mutex<Box<dyn MapJournal>>,
    /// The store's request counter at the map's last request, for eviction (a counter, not a clock: two
    /// requests in one millisecond still have an order).
    last_used: AtomicU64,
    /// The store's clock (ms since it opened) at the map's last freshness check.
    checked: AtomicU64,
    /// Estimated memory of the map and its index ([`MapData::memory_bytes`]).
    bytes: AtomicU64,
    /// [`MapSummary::load_note`].
    load_note: Option<String>,
}

impl Map {
    fn new(id: &str, data: MapData, index: EmbeddingIndex, log: Box<dyn MapJournal>, now: u64) -> Self {
        let bytes = data.memory_bytes() as u64;
        Self {
            id: id.to_string(),
            state: RwLock::new(MapState { data, index }),
            log: Mutex::new(log),
            last_used: AtomicU64::new(0),
            checked: AtomicU64::new(now),
            bytes: AtomicU64::new(bytes),
            load_note: None,
        }
    }

    fn summary(&self) -> MapSummary {
        let s = self.state.read();
        MapSummary {
            id: self.id.clone(),
            model_id: s.data.meta.model_id.clone(),
            keyframes: s.data.keyframes.len(),
            landmarks: s.data.landmarks.len(),
            observations: s.data.observations.len(),
            live_observations: s.data.live_observations(),
            version: s.data.version,
            approximate_index: s.index.is_approximate(),
            loaded: true,
            load_note: self.load_note.clone(),
        }
    }

    /// Runs `f` on the map's data under the shared lock.
    pub fn read<R>(&self, f: impl FnOnce(&MapData, &EmbeddingIndex) -> R) -> R {
        let s = self.state.read();
        f(&s.data, &s.index)
    }
}

/// Why a map is held back, as clients are told it (ListMaps, UNAVAILABLE): the stored file by its name and
/// what is wrong with it, never the server's paths or the internals of a failure (those go to the log).
fn held_back_reason(e: &MapError) -> String {
    let file = |path: &Path| {
        path.file_name().map_or_else(|| "a stored file".to_string(), |n| n.to_string_lossy().into_owned())
    };
    match e {
        MapError::Corrupt { path, reason } => format!("{} is corrupt: {reason}", file(path)),
        MapError::Io { path, source } => format!("{} cannot be read ({})", file(path), source.kind()),
        MapError::StorageFull { path } => format!("{} cannot be written: the data volume is full", file(path)),
        MapError::ModelMismatch { .. }
        | MapError::Unavailable { .. }
        | MapError::WriterConflict { .. }
        | MapError::InvalidInput { .. }
        | MapError::InvalidMapId { .. } => e.to_string(),
        MapError::UnknownMap { .. }
        | MapError::MapExists { .. }
        | MapError::UnknownKeyframe { .. }
        | MapError::KeyframeExists { .. }
        | MapError::Feature(_)
        | MapError::Embedding(_)
        | MapError::Pose(_) => "it could not be loaded; the server log has the details".to_string(),
    }
}

/// All maps of a backend.
pub struct MapStore {
    config: StoreConfig,
    backend: Arc<dyn MapBackend>,
    model: ModelInfo,
    /// The loaded maps (all of them in eager mode, a cache in lazy mode).
    maps: RwLock<HashMap<String, Arc<Map>>>,
    /// Maps that failed to load: the reason, and when (the store's clock, ms).
    held_back: RwLock<HashMap<String, (String, u64)>>,
    /// Serialises create, delete and import (changes to the set of maps).
    admin: Mutex<()>,
    lazy: bool,
    /// One lock per map being loaded, so concurrent requests for it wait for one load.
    loading: Mutex<HashMap<String, Arc<Mutex<()>>>>,
    cache_stats: CacheStats,
    opened: Instant,
    /// Requests for maps so far (the order of [`Map::last_used`]).
    requests: AtomicU64,
}

fn now_ms() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0)
}

impl MapStore {
    /// Opens the backend `config.backend` describes and loads every map with its index.
    pub fn open(config: StoreConfig, model: ModelInfo) -> Result<Self, MapError> {
        let backend = open_backend(&config.backend, &config.data_dir, config.compact_every)?;
        Self::open_with_backend(config, model, backend)
    }

    /// Loads every map of `backend` (`config.backend` is not consulted).
    pub fn open_with_backend(
        config: StoreConfig,
        model: ModelInfo,
        backend: Arc<dyn MapBackend>,
    ) -> Result<Self, MapError> {
        let lazy = config.cache.is_lazy(&config.backend);
        let store = Self {
            config,
            backend,
            model,
            maps: RwLock::new(HashMap::new()),
            held_back: RwLock::new(HashMap::new()),
            admin: Mutex::new(()),
            lazy,
            loading: Mutex::new(HashMap::new()),
            cache_stats: CacheStats::default(),
            opened: Instant::now(),
            requests: AtomicU64::new(0),
        };
        if lazy {
            tracing::info!(location = %store.backend.location(), budget_mb = store.config.cache.memory_budget_mb,
                "maps are loaded on first request");
            return Ok(store);
        }
        tracing::info!(location = %store.backend.location(), "loading maps");
        for name in store.backend.list()? {
            match store.load_map(&name) {
                Ok((map, report)) => {
                    tracing::info!(map = %name, replayed = report.replayed, truncated = report.truncated_bytes, "map loaded");
                    store.maps.write().insert(name, Arc::new(map));
                }
                Err(e) => {
                    tracing::error!(map = %name, error = %e, "map held back");
                    store.held_back.write().insert(name, (held_back_reason(&e), 0));
                }
            }
        }
        Ok(store)
    }

    /// Milliseconds since the store opened (the clock of eviction and freshness).
    fn now(&self) -> u64 {
        self.opened.elapsed().as_millis() as u64
    }

    fn load_map(&self, id: &str) -> Result<(Map, LoadReport), MapError> {
        let t = Instant::now();
        let (data, log, report) = self.backend.open(id)?;
        let index = EmbeddingIndex::load_or_build(self.config.index, log.index_dir(), &data);
        self.cache_stats.loads.fetch_add(1, Ordering::Relaxed);
        self.cache_stats.load_nanos.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        let mut map = Map::new(id, data, index, log, self.now());
        if report.truncated_bytes > 0 {
            self.cache_stats.logs_cut.fetch_add(1, Ordering::Relaxed);
            map.load_note = Some(format!(
                "the log ended inside a record: its last {} bytes were cut off at load. After a crash this is the \
                 one write in flight, which was never acknowledged; otherwise the file was damaged and \
                 acknowledged writes may be missing",
                report.truncated_bytes
            ));
        }
        Ok((map, report))
    }

    /// Marks `map` as the most recently used.
    fn touch(&self, map: &Map) {
        map.last_used.store(self.requests.fetch_add(1, Ordering::Relaxed) + 1, Ordering::Relaxed);
    }

    /// Whether maps are loaded on demand (and evicted).
    pub fn is_lazy(&self) -> bool {
        self.lazy
    }

    pub fn cache_stats(&self) -> &CacheStats {
        &self.cache_stats
    }

    /// Calls made to the storage service (object storage), per operation.
    pub fn operation_stats(&self) -> Vec<OperationStats> {
        self.backend.operation_stats()
    }

    /// Loads `id` if it is not loaded and checks its freshness: what [`MapStore::get`] does first, for the
    /// server to run before it queues the request's CPU work. Holding the map keeps it from being evicted.
    pub fn prepare(&self, id: &str) -> Result<Arc<Map>, MapError> {
        self.get(id)
    }

    /// Whether `id` is in memory now.
    pub fn is_loaded(&self, id: &str) -> bool {
        self.maps.read().contains_key(id)
    }

    pub fn model(&self) -> &ModelInfo {
        &self.model
    }

    /// The map, or why it cannot be used.
    pub fn get(&self, id: &str) -> Result<Arc<Map>, MapError> {
        validate_map_id(id)?;
        let cached = self.maps.read().get(id).cloned();
        if let Some(map) = cached {
            self.touch(&map);
            self.cache_stats.hits.fetch_add(1, Ordering::Relaxed);
            return self.fresh(map);
        }
        if self.lazy {
            return self.load_into_cache(id);
        }
        if let Some((reason, _)) = self.held_back.read().get(id) {
            return Err(MapError::Unavailable { map: id.to_string(), reason: reason.clone() });
        }
        Err(MapError::UnknownMap { map: id.to_string() })
    }

    /// `map`, checked against the stored map when its last check is older than `freshness_ms`.
    fn fresh(&self, map: Arc<Map>) -> Result<Arc<Map>, MapError> {
        let now = self.now();
        let last = map.checked.load(Ordering::Relaxed);
        if now.saturating_sub(last) < self.config.cache.freshness_ms {
            return Ok(map);
        }
        // One check per map at a time; a writer holding the journal makes the copy current (or learns that it
        // is not) with its own write.
        if map.checked.compare_exchange(last, now, Ordering::AcqRel, Ordering::Relaxed).is_err() {
            return Ok(map);
        }
        let next = match map.log.try_lock() {
            None => {
                // A writer holds the journal: its write makes the copy current or fails on a stale one. The
                // check is owed: the next request makes it.
                map.checked.store(last, Ordering::Relaxed);
                Next::Keep
            }
            Some(mut log) => {
                self.cache_stats.checks.fetch_add(1, Ordering::Relaxed);
                match log.refresh() {
                    Ok(Freshness::Current) => Next::Keep,
                    Ok(Freshness::Appended(records)) => self.apply_others(&map, &records),
                    Ok(Freshness::Replaced) => Next::Reload,
                    Ok(Freshness::Gone) => Next::Gone,
                    Err(e) => {
                        self.cache_stats.check_errors.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(map = %map.id, error = %e, "cannot check the map's freshness; serving the copy");
                        Next::Keep
                    }
                }
            }
        };
        match next {
            Next::Keep => Ok(map),
            Next::Reload => {
                self.cache_stats.changed.fetch_add(1, Ordering::Relaxed);
                self.reload(&map)
            }
            Next::Gone => {
                self.cache_stats.changed.fetch_add(1, Ordering::Relaxed);
                let mut maps = self.maps.write();
                if maps.get(&map.id).is_some_and(|m| Arc::ptr_eq(m, &map)) {
                    tracing::info!(map = %map.id, "deleted through another server; dropped");
                    maps.remove(&map.id);
                }
                Err(MapError::UnknownMap { map: map.id.clone() })
            }
        }
    }

    /// Applies records another server appended (the caller holds the map's journal); a record that does not
    /// apply means this copy went wrong somewhere: load the map again.
    fn apply_others(&self, map: &Map, records: &[Record]) -> Next {
        self.cache_stats.changed.fetch_add(1, Ordering::Relaxed);
        let mut s = map.state.write();
        for record in records {
            if let Err(reason) = s.data.check(record) {
                // Part of the batch may be applied: the reload replaces this copy (or holds the map back).
                tracing::error!(map = %map.id, %reason, "another writer's record does not apply; reloading");
                return Next::Reload;
            }
            s.data.apply(record);
        }
        let MapState { data, index } = &mut *s;
        if records.iter().any(|r| matches!(r, Record::Reembed { .. })) {
            // Every embedding changed (another server re-embedded the map): the graph holds the old ones.
            index.reset();
        }
        index.sync(data);
        map.bytes.store(data.memory_bytes() as u64, Ordering::Relaxed);
        tracing::debug!(map = %map.id, records = records.len(), version = data.version, "applied other writes");
        Next::Keep
    }

    /// Loads `stale` again and puts the new copy in its place (unless the registry moved on meanwhile).
    fn reload(&self, stale: &Arc<Map>) -> Result<Arc<Map>, MapError> {
        self.reload_stale(stale);
        self.maps.read().get(&stale.id).cloned().ok_or_else(|| MapError::UnknownMap { map: stale.id.clone() })
    }

    /// Lazy mode: loads a map that is not in memory (one load per map at a time), then evicts beyond the budget.
    fn load_into_cache(&self, id: &str) -> Result<Arc<Map>, MapError> {
        let gate = Arc::clone(self.loading.lock().entry(id.to_string()).or_default());
        let loaded = {
            let _loading = gate.lock();
            self.load_gated(id)
        };
        let mut loading = self.loading.lock();
        if loading.get(id).is_some_and(|g| Arc::ptr_eq(g, &gate)) && Arc::strong_count(&gate) == 2 {
            loading.remove(id);
        }
        loaded
    }

    fn load_gated(&self, id: &str) -> Result<Arc<Map>, MapError> {
        if let Some(map) = self.maps.read().get(id).cloned() {
            // Loaded by the request this one waited for.
            self.cache_stats.hits.fetch_add(1, Ordering::Relaxed);
            return Ok(map);
        }
        let now = self.now();
        if let Some((reason, at)) = self.held_back.read().get(id) {
            if now.saturating_sub(*at) < self.config.cache.freshness_ms {
                return Err(MapError::Unavailable { map: id.to_string(), reason: reason.clone() });
            }
        }
        self.cache_stats.misses.fetch_add(1, Ordering::Relaxed);
        // A load that read the manifest just before another server compacted finds the old objects gone
        // ("named by the manifest but missing"): once more, from the new manifest.
        let loaded = match self.load_map(id) {
            Err(MapError::Corrupt { .. }) => self.load_map(id),
            r => r,
        };
        match loaded {
            Ok((map, report)) => {
                let map = Arc::new(map);
                self.touch(&map);
                tracing::info!(map = %id, replayed = report.replayed, bytes = map.bytes.load(Ordering::Relaxed),
                    from_dump = map.state.read().index.loaded_from_dump(), "map loaded on request");
                self.held_back.write().remove(id);
                self.maps.write().insert(id.to_string(), Arc::clone(&map));
                self.evict_beyond_budget(id);
                Ok(map)
            }
            Err(e @ MapError::UnknownMap { .. }) => {
                self.held_back.write().remove(id);
                Err(e)
            }
            Err(e @ MapError::Io { .. }) => {
                // Storage unreachable: this request fails; the next one tries again (nothing is held back).
                tracing::warn!(map = %id, error = %e, "cannot load the map");
                Err(MapError::Unavailable { map: id.to_string(), reason: held_back_reason(&e) })
            }
            Err(e) => {
                tracing::error!(map = %id, error = %e, "map held back");
                let reason = held_back_reason(&e);
                self.held_back.write().insert(id.to_string(), (reason.clone(), now));
                Err(MapError::Unavailable { map: id.to_string(), reason })
            }
        }
    }

    /// Evicts the least recently used maps that no request holds until the loaded maps fit the budget
    /// (`keep`, the map just loaded, stays even when it alone is over it).
    fn evict_beyond_budget(&self, keep: &str) {
        let budget = self.config.cache.memory_budget_mb << 20;
        if budget == 0 {
            return;
        }
        let mut maps = self.maps.write();
        loop {
            let total: u64 = maps.values().map(|m| m.bytes.load(Ordering::Relaxed)).sum();
            if total <= budget {
                return;
            }
            // A map some request holds (an `Arc` besides the registry's) is in use: evicting it could put a
            // second copy beside it, and two writers on one local log.
            let victim = maps
                .iter()
                .filter(|(id, m)| id.as_str() != keep && Arc::strong_count(m) == 1)
                .min_by_key(|(_, m)| m.last_used.load(Ordering::Relaxed))
                .map(|(id, _)| id.clone());
            let Some(victim) = victim else { return };
            if let Some(m) = maps.remove(&victim) {
                self.cache_stats.evictions.fetch_add(1, Ordering::Relaxed);
                tracing::info!(map = %victim, bytes = m.bytes.load(Ordering::Relaxed), total, budget, "map evicted");
            }
        }
    }

    fn check_model(&self, map: &Map) -> Result<(), MapError> {
        let model_id = map.state.read().data.meta.model_id.clone();
        if model_id != self.model.model_id {
            return Err(MapError::ModelMismatch {
                map: map.id.clone(),
                map_model: model_id,
                model: self.model.model_id.clone(),
            });
        }
        Ok(())
    }

    pub fn create(&self, id: &str) -> Result<MapSummary, MapError> {
        validate_map_id(id)?;
        let _admin = self.admin.lock();
        if self.backend.exists(id)? {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        // Lazy mode: what the backend does not hold is gone (deleted through another server), whatever the
        // cache says. Eager mode: this server is the only one, and its registry is the truth.
        if self.lazy {
            self.forget(id);
        } else if self.maps.read().contains_key(id) || self.held_back.read().contains_key(id) {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        let data = MapData::new(MapMeta {
            id: id.to_string(),
            model_id: self.model.model_id.clone(),
            k: self.model.k,
            dim: self.model.dim,
            created_unix_ms: now_ms(),
        });
        let log = self.backend.create(id, &data)?;
        let index = EmbeddingIndex::new(self.config.index);
        let map = Arc::new(Map::new(id, data, index, log, self.now()));
        self.touch(&map);
        self.maps.write().insert(id.to_string(), Arc::clone(&map));
        if self.lazy {
            self.evict_beyond_budget(id);
        }
        Ok(map.summary())
    }

    /// Drops a map from memory and from the held-back list (not from the backend).
    fn forget(&self, id: &str) {
        self.maps.write().remove(id);
        self.held_back.write().remove(id);
    }

    /// Every map: the loaded ones (eager mode), or every stored map (lazy mode), the counts of those not
    /// loaded as the backend records them. A stored map without recorded counts is loaded to tell; one
    /// that fails to load is left out (it is in [`MapStore::held_back`]).
    pub fn list(&self) -> Result<Vec<MapSummary>, MapError> {
        if !self.lazy {
            return Ok(self.loaded());
        }
        let mut out = Vec::new();
        for (id, stats) in self.backend.list_stats()? {
            let cached = self.maps.read().get(&id).cloned();
            match (cached, stats) {
                (Some(map), _) => out.push(map.summary()),
                (None, Some(stats)) => out.push(self.stored_summary(&id, &stats)),
                (None, None) => match self.get(&id) {
                    Ok(map) => out.push(map.summary()),
                    Err(e) => tracing::warn!(map = %id, error = %e, "left out of the listing"),
                },
            }
        }
        Ok(out)
    }

    /// Estimated memory of the maps in memory.
    pub fn loaded_bytes(&self) -> u64 {
        self.maps.read().values().map(|m| m.bytes.load(Ordering::Relaxed)).sum()
    }

    /// The maps in memory, by id (cheap: for metrics).
    pub fn loaded(&self) -> Vec<MapSummary> {
        let maps: Vec<Arc<Map>> = self.maps.read().values().cloned().collect();
        let mut out: Vec<MapSummary> = maps.iter().map(|m| m.summary()).collect();
        out.sort_by(|a, b| a.id.cmp(&b.id));
        out
    }

    fn stored_summary(&self, id: &str, stats: &MapStats) -> MapSummary {
        MapSummary {
            id: id.to_string(),
            model_id: stats.model_id.clone(),
            keyframes: stats.keyframes,
            landmarks: stats.landmarks,
            observations: stats.observations,
            live_observations: stats.live_observations,
            version: stats.version,
            approximate_index: stats.observations >= self.config.index.exact_below,
            loaded: false,
            load_note: None,
        }
    }

    /// Ids of maps that failed to load, with the reason.
    pub fn held_back(&self) -> Vec<(String, String)> {
        let mut v: Vec<_> = self.held_back.read().iter().map(|(k, (reason, _))| (k.clone(), reason.clone())).collect();
        v.sort();
        v
    }

    pub fn summary(&self, id: &str) -> Result<MapSummary, MapError> {
        Ok(self.get(id)?.summary())
    }

    /// Keyframe poses and intrinsics, and at most `max_landmarks` landmarks (every n-th by id, so the
    /// subsample covers the whole map), read under the map's shared lock.
    pub fn contents(&self, id: &str, max_landmarks: usize) -> Result<MapContents, MapError> {
        Ok(self.get(id)?.read(|data, _| {
            let total = data.landmarks.len();
            let step = total.div_ceil(max_landmarks.max(1)).max(1);
            MapContents {
                version: data.version,
                keyframes: data.keyframes.values().map(|k| (k.id, k.pose, k.camera)).collect(),
                landmarks: data
                    .landmarks
                    .iter()
                    .step_by(step)
                    .take(max_landmarks)
                    .map(|(id, l)| (*id, l.point, l.observations.len()))
                    .collect(),
                landmarks_total: total,
            }
        }))
    }

    /// Deletes a map: out of the registry first, then out of the backend.
    pub fn delete(&self, id: &str) -> Result<(), MapError> {
        validate_map_id(id)?;
        let _admin = self.admin.lock();
        let known = self.maps.write().remove(id).is_some() | self.held_back.write().remove(id).is_some();
        // Lazy mode: the map may be stored without being loaded here; a cached copy of a map deleted
        // elsewhere is not a map.
        let known = if self.lazy { self.backend.exists(id)? } else { known };
        if !known {
            return Err(MapError::UnknownMap { map: id.to_string() });
        }
        self.backend.delete(id)
    }

    /// Adds a keyframe; returns after the record is durable and applied.
    pub fn add_keyframe(&self, id: &str, input: &KeyframeInput) -> Result<KeyframeAdded, MapError> {
        let map = self.get(id)?;
        self.check_model(&map)?;
        let mut log = map.log.lock();
        let planned = {
            let s = map.state.read();
            let p = plan(&s.data, input, &self.config.build)?;
            s.data.check(&p.record).map_err(|reason| MapError::InvalidInput { field: "keyframe".into(), reason })?;
            p
        };
        let (Record::AddKeyframe { new_landmarks, observations, .. }
        | Record::AddExternalKeyframe { new_landmarks, observations, .. }) = &planned.record
        else {
            unreachable!("planned a keyframe")
        };
        let (new, obs) = (new_landmarks.len(), observations.len());
        let version = self.commit(&map, log.as_mut(), planned.record)?;
        Ok(KeyframeAdded {
            keyframe: input.id,
            new_landmarks: new,
            observations: obs,
            version,
            external: planned.external,
        })
    }

    pub fn remove_keyframe(&self, id: &str, keyframe: u64) -> Result<u64, MapError> {
        let map = self.get(id)?;
        let mut log = map.log.lock();
        let record = Record::RemoveKeyframe { id: keyframe };
        if map.state.read().data.check(&record).is_err() {
            return Err(MapError::UnknownKeyframe { map: id.to_string(), keyframe });
        }
        self.commit(&map, log.as_mut(), record)
    }

    /// Re-embeds every keyframe of a map with the current model (from the stored keypoints and FREAK
    /// descriptors), so a map made by an earlier model can be queried again. `embed` computes a keyframe's
    /// embeddings; the record replaces them all at once and the index is rebuilt.
    pub fn reembed(
        &self,
        id: &str,
        embed: &dyn Fn(&crate::map::model::Keyframe) -> Result<Vec<f32>, MapError>,
    ) -> Result<MapSummary, MapError> {
        let map = self.get(id)?;
        let mut log = map.log.lock();
        let keyframes = {
            let s = map.state.read();
            let mut out = Vec::with_capacity(s.data.keyframes.len());
            for kf in s.data.keyframes.values() {
                if kf.descriptors.is_empty() && !kf.keypoints.is_empty() {
                    return Err(MapError::InvalidInput {
                        field: "map".into(),
                        reason: format!("keyframe {} has no FREAK descriptors to re-embed", kf.id),
                    });
                }
                out.push((kf.id, embed(kf)?));
            }
            out
        };
        let record =
            Record::Reembed { model_id: self.model.model_id.clone(), k: self.model.k, dim: self.model.dim, keyframes };
        map.state
            .read()
            .data
            .check(&record)
            .map_err(|reason| MapError::InvalidInput { field: "re-embedding".into(), reason })?;
        map.state.write().index.reset();
        self.commit(&map, log.as_mut(), record)?;
        Ok(map.summary())
    }

    /// Log (fsync) then apply; compacts and dumps the index when the log is long. Returns the new version.
    fn commit(&self, map: &Map, log: &mut dyn MapJournal, record: Record) -> Result<u64, MapError> {
        let (seq, after) = {
            let s = map.state.read();
            (s.data.version + 1, s.data.stats_after(&record))
        };
        if let Err(e) = log.append(seq, &record, &after) {
            if matches!(e, MapError::WriterConflict { .. }) {
                self.reload_stale(map);
            }
            return Err(e);
        }
        let mut s = map.state.write();
        s.data.apply(&record);
        {
            let MapState { data, index } = &mut *s;
            index.sync(data);
            map.bytes.store(data.memory_bytes() as u64, Ordering::Relaxed);
        }
        map.checked.store(self.now(), Ordering::Relaxed);
        let version = s.data.version;
        if log.wants_compaction() {
            // Queries may read on while the snapshot (and the index dump) is written and uploaded. The record
            // is durable and applied: a failed dump or compaction is logged, not this write's error (the log
            // keeps the records, and the next write tries again).
            let s = parking_lot::RwLockWriteGuard::downgrade(s);
            if let Err(e) = s.index.dump(log.index_dir(), &s.data).and_then(|()| log.compact(&s.data)) {
                tracing::error!(map = %map.id, error = %e, "compaction failed; the records stay in the log");
            }
        }
        Ok(version)
    }

    /// Localises a query against a map.
    pub fn localize(
        &self,
        id: &str,
        features: &Features,
        embeddings: &[f32],
        camera: &Camera,
        prior: Option<&Prior>,
    ) -> Result<Localization, MapError> {
        let map = self.get(id)?;
        self.check_model(&map)?;
        map.read(|data, index| localize(data, index, features, embeddings, camera, prior, &self.config.localize))
    }

    /// The whole map in the versioned, checksummed export format, with its index dump when it has an HNSW
    /// graph ([`encode_export`]: an import then answers exactly as this map). The dump is written into the
    /// map's index directory first (as a compaction would); if that fails the export goes without it.
    pub fn export(&self, id: &str) -> Result<Vec<u8>, MapError> {
        let map = self.get(id)?;
        let log = map.log.lock();
        let s = map.state.read();
        let dump = if s.index.is_approximate() {
            match s.index.dump(log.index_dir(), &s.data) {
                Ok(()) => read_dump(log.index_dir()),
                Err(e) => {
                    tracing::warn!(map = %id, error = %e, "export without the index dump: an import rebuilds it");
                    None
                }
            }
        } else {
            None
        };
        encode_export(&s.data, dump.as_ref())
    }

    /// Imports an exported map under `id` (refused if it was embedded by another model).
    ///
    /// Idempotent for identical content: when `id` is a loaded map whose data equals the file's (under that
    /// id), the import already happened (e.g. the server died after the write but before the answer) and the
    /// map is returned as it is. Any other map under `id`, held-back or stored ones included, is
    /// [`MapError::MapExists`].
    pub fn import(&self, id: &str, bytes: &[u8]) -> Result<MapSummary, MapError> {
        validate_map_id(id)?;
        let (mut data, dump) = decode_export(bytes, Path::new("import"))?;
        if data.meta.model_id != self.model.model_id {
            return Err(MapError::ModelMismatch {
                map: id.to_string(),
                map_model: data.meta.model_id,
                model: self.model.model_id.clone(),
            });
        }
        data.meta.id = id.to_string();
        let _admin = self.admin.lock();
        let existing = match self.lazy {
            // The stored map (loaded to compare), if there is one.
            true => match self.get(id) {
                Ok(map) => Some(map),
                Err(MapError::UnknownMap { .. }) => None,
                // Stored but held back (corrupt): the id is taken. Unreachable storage stays an error.
                Err(MapError::Unavailable { .. }) if self.held_back.read().contains_key(id) => {
                    return Err(MapError::MapExists { map: id.to_string() })
                }
                Err(e) => return Err(e),
            },
            false => self.maps.read().get(id).cloned(),
        };
        if let Some(map) = existing {
            if map.read(|held, _| *held == data) {
                return Ok(map.summary());
            }
            return Err(MapError::MapExists { map: id.to_string() });
        }
        if (!self.lazy && self.held_back.read().contains_key(id)) || self.backend.exists(id)? {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        let log = self.backend.create(id, &data)?;
        let installed = dump.map(|d| install_dump(log.index_dir(), &d));
        if let Some(Err(e)) = &installed {
            tracing::warn!(map = %id, error = %e, "cannot install the exported index dump; it is rebuilt");
        }
        // The loader checks the dump against the map, and builds the graph itself when it does not match.
        let index = EmbeddingIndex::load_or_build(self.config.index, log.index_dir(), &data);
        let map = Arc::new(Map::new(id, data, index, log, self.now()));
        self.touch(&map);
        self.maps.write().insert(id.to_string(), Arc::clone(&map));
        if self.lazy {
            self.evict_beyond_budget(id);
        }
        Ok(map.summary())
    }

    /// After another writer replaced a map in object storage ([`MapError::WriterConflict`]), this copy is
    /// stale and its journal refuses writes: load the map again and swap it into the registry, unless the
    /// registry moved on meanwhile (deleted, already reloaded). The failed write is not retried here (it was
    /// planned against stale data); the client's retry is planned against the fresh copy. Queries in flight
    /// finish on the old copy.
    ///
    /// One load per map at a time (the loading gate): a request that finds the map reloaded meanwhile does
    /// not load it again. A reload that fails takes the stale copy out (held back with the reason), so no
    /// request is answered from a copy known to be wrong.
    fn reload_stale(&self, stale: &Map) {
        let id = stale.id.as_str();
        let still_registered =
            |maps: &HashMap<String, Arc<Map>>| maps.get(id).is_some_and(|m| std::ptr::eq(Arc::as_ptr(m), stale));
        let gate = Arc::clone(self.loading.lock().entry(id.to_string()).or_default());
        let _reloading = gate.lock();
        if !still_registered(&self.maps.read()) {
            return;
        }
        match self.load_map(id) {
            Ok((map, report)) => {
                let mut maps = self.maps.write();
                if still_registered(&maps) {
                    tracing::info!(map = %id, replayed = report.replayed, "reloaded after another writer's write");
                    let map = Arc::new(map);
                    self.touch(&map);
                    maps.insert(id.to_string(), map);
                }
            }
            Err(MapError::UnknownMap { .. }) => {
                let mut maps = self.maps.write();
                if still_registered(&maps) {
                    tracing::warn!(map = %id, "deleted by another writer; dropped");
                    maps.remove(id);
                }
            }
            Err(e) => {
                tracing::error!(map = %id, error = %e, "cannot reload a stale copy; held back");
                let mut maps = self.maps.write();
                if still_registered(&maps) {
                    maps.remove(id);
                    self.held_back.write().insert(id.to_string(), (held_back_reason(&e), self.now()));
                }
            }
        }
    }

    /// Snapshots every map and dumps its index (at shutdown, so the next start loads instead of rebuilding).
    /// A map another writer took over (object storage) is left to that writer. Every map is tried; those that
    /// could not be flushed (a full volume, say) are returned with the error: their acknowledged writes are
    /// in their logs, so the next start replays them (and rebuilds an index it has no dump of).
    pub fn flush(&self) -> Vec<(String, MapError)> {
        let maps: Vec<Arc<Map>> = self.maps.read().values().cloned().collect();
        let mut failed = Vec::new();
        for map in maps {
            let mut log = map.log.lock();
            let s = map.state.read();
            let dumped = s.index.dump(log.index_dir(), &s.data);
            match dumped.and_then(|()| log.compact(&s.data)) {
                Ok(()) => {}
                Err(e @ MapError::WriterConflict { .. }) => {
                    tracing::warn!(map = %map.id, error = %e, "not flushed");
                }
                Err(e) => {
                    tracing::error!(map = %map.id, error = %e,
                        "not flushed: its acknowledged writes are in its log and are replayed at the next start");
                    failed.push((map.id.clone(), e));
                }
            }
        }
        failed
    }

    /// Writes an export file atomically.
    pub fn export_to_file(&self, id: &str, path: &Path) -> Result<(), MapError> {
        write_atomic(path, &self.export(id)?)
    }
}

/// Which backend stores the maps (`[store.backend]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum BackendConfig {
    /// `store.data_dir/maps/<id>/`: snapshot + fsync'd write-ahead log, index dump beside them. (A struct
    /// variant, so that S3 keys under `kind = "local"`, e.g. a forgotten `kind = "s3"`, are refused.)
    Local {},
    /// An S3-API bucket. Credentials come from the standard AWS environment variables
    /// (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, ...), never from this file.
    S3(S3Config),
}

impl Default for BackendConfig {
    fn default() -> Self {
        Self::Local {}
    }
}

impl BackendConfig {
    /// Checks that need no I/O.
    pub fn validate(&self) -> Result<(), String> {
        match self {
            BackendConfig::Local {} => Ok(()),
            BackendConfig::S3(s3) => {
                if s3.bucket.trim().is_empty() {
                    return Err("bucket must not be empty".into());
                }
                if object_store::path::Path::parse(&s3.prefix).is_err() {
                    return Err(format!("prefix '{}' is not a valid object key prefix", s3.prefix));
                }
                if let Some(e) = &s3.endpoint {
                    if e.starts_with("http://") && !s3.allow_http {
                        return Err(format!("endpoint {e} is plain HTTP: set allow_http = true to permit it"));
                    }
                    if !e.starts_with("http://") && !e.starts_with("https://") {
                        return Err(format!("endpoint {e} must start with http:// or https://"));
                    }
                }
                Ok(())
            }
        }
    }
}

/// The backend `config` describes; `data_dir` roots the local layout and the default cache.
pub fn open_backend(
    config: &BackendConfig,
    data_dir: &Path,
    compact_every: usize,
) -> Result<Arc<dyn MapBackend>, MapError> {
    match config {
        BackendConfig::Local {} => Ok(Arc::new(LocalBackend::new(data_dir, compact_every)?)),
        BackendConfig::S3(s3) => {
            config.validate().map_err(|reason| MapError::InvalidInput { field: "store.backend".into(), reason })?;
            let cache = s3.cache_dir.clone().unwrap_or_else(|| data_dir.join("cache"));
            Ok(Arc::new(ObjectStorageBackend::s3(s3, &cache, compact_every, S3Credentials::FromEnv)?))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_backend_setting_defaults_to_local_and_reads_s3_tables() {
        let c: BackendConfig = serde_json::from_str(r#"{"kind":"local"}"#).unwrap();
        assert_eq!(c, BackendConfig::Local {});
        let c: BackendConfig = serde_json::from_str(
            r#"{"kind":"s3","bucket":"maps","endpoint":"http://127.0.0.1:9000","allow_http":true}"#,
        )
        .unwrap();
        let BackendConfig::S3(s3) = &c else { panic!("{c:?}") };
        assert_eq!((s3.bucket.as_str(), s3.prefix.as_str(), s3.region.as_deref()), ("maps", "", None));
        c.validate().unwrap();
        let e = serde_json::from_str::<BackendConfig>(r#"{"kind":"s3","bucket":"m","secret_key":"x"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("secret_key"), "{e}");
        let e = serde_json::from_str::<BackendConfig>(r#"{"kind":"local","bucket":"m"}"#).unwrap_err().to_string();
        assert!(e.contains("bucket"), "{e}");
        let plain = BackendConfig::S3(S3Config {
            bucket: "m".into(),
            prefix: String::new(),
            region: None,
            endpoint: Some("http://minio:9000".into()),
            allow_http: false,
            cache_dir: None,
        });
        assert!(plain.validate().unwrap_err().contains("allow_http"));
    }
}
