//! Which maps are in memory, and how fresh they are: the cache of loaded maps that the
//! [`MapStore`](crate::map::store::MapStore) looks every map up in.
//!
//! Concurrency: the registry is a `RwLock<HashMap<id, Arc<Map>>>` held only to look up or insert an `Arc`;
//! work on a map happens after the registry lock is released, so maps never wait for each other. Inside a
//! map, one `Mutex` serialises writers (its journal) and a `RwLock` guards the state: queries take it shared;
//! a writer takes it exclusively only to apply a planned record and update the index. None of these locks is
//! held across an `.await` (callers run this code on blocking worker threads).
//!
//! **Which maps are in memory** (`[store.cache]`). Eager (the default with a local directory): start-up
//! loads every stored map. Lazy (the default with object storage, where several replicas share one bucket):
//! a map is loaded on its first request and kept while the loaded maps fit `memory_budget_mb` (estimated per
//! map: its data, [`MapData::memory_bytes`], and its index's graph); beyond it the least recently used map
//! that no request is using is evicted, and loaded again when asked for. Existence is the backend's, not the
//! cache's: the store asks the backend on create, import, delete and listings, so a map another replica
//! created or deleted is seen at this replica's next request for it. The server loads a map before it queues
//! the request's CPU work ([`crate::server::app::App::map`]), so a load never holds a CPU worker that queries
//! of loaded maps need.
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
//! The cache does not know where maps come from: the store hands it a [`Load`] (open from the backend, then
//! load or build the index) for the maps it must load.

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use parking_lot::{Mutex, RwLock};
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::index::EmbeddingIndex;
use crate::map::model::{validate_map_id, MapData, Record};
use crate::map::storage::backend::{Freshness, LoadReport, MapJournal};
use crate::map::storage::BackendSettings;

/// How the cache loads a map it does not hold (the store's backend and index build).
pub type Load<'a> = &'a dyn Fn(&str) -> Result<(Map, LoadReport), MapError>;

/// The cache of loaded maps (`[store.cache]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CacheSettings {
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

impl Default for CacheSettings {
    fn default() -> Self {
        Self { lazy: None, memory_budget_mb: 2048, freshness_ms: 2000 }
    }
}

impl CacheSettings {
    /// Whether maps are loaded on demand with this backend.
    pub fn is_lazy(&self, backend: &BackendSettings) -> bool {
        self.lazy.unwrap_or(matches!(backend, BackendSettings::S3(_)))
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

pub(crate) struct MapState {
    pub(crate) data: MapData,
    pub(crate) index: EmbeddingIndex,
}

impl MapState {
    /// Estimated memory of the map's data and its index, for the cache's budget.
    pub(crate) fn memory_bytes(&self) -> u64 {
        (self.data.memory_bytes() + self.index.memory_bytes(self.data.meta.dim)) as u64
    }
}

/// What to do with a loaded map after a freshness check.
enum Next {
    Keep,
    Reload,
    Gone,
}

/// One loaded map.
pub struct Map {
    pub(crate) id: String,
    pub(crate) state: RwLock<MapState>,
    pub(crate) journal: Mutex<Box<dyn MapJournal>>,
    /// The store's request counter at the map's last request, for eviction (a counter, not a clock: two
    /// requests in one millisecond still have an order).
    pub(crate) last_used: AtomicU64,
    /// The store's clock (ms since it opened) at the map's last freshness check.
    pub(crate) checked: AtomicU64,
    /// Estimated memory of the map and its index ([`MapState::memory_bytes`]).
    pub(crate) bytes: AtomicU64,
    /// [`MapSummary::load_note`].
    pub(crate) load_note: Option<String>,
}

impl Map {
    pub(crate) fn new(id: &str, data: MapData, index: EmbeddingIndex, journal: Box<dyn MapJournal>, now: u64) -> Self {
        let state = MapState { data, index };
        let bytes = state.memory_bytes();
        Self {
            id: id.to_string(),
            state: RwLock::new(state),
            journal: Mutex::new(journal),
            last_used: AtomicU64::new(0),
            checked: AtomicU64::new(now),
            bytes: AtomicU64::new(bytes),
            load_note: None,
        }
    }

    pub fn summary(&self) -> MapSummary {
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
pub(crate) fn held_back_reason(e: &MapError) -> String {
    let file = |path: &Path| {
        path.file_name().map_or_else(|| "a stored file".to_string(), |n| n.to_string_lossy().into_owned())
    };
    match e {
        MapError::Corrupt { path, reason } => format!("{} is corrupt: {reason}", file(path)),
        MapError::Io { path, source } => format!("{} cannot be read ({})", file(path), source.kind()),
        MapError::StorageFull { path } => format!("{} cannot be written: the data volume is full", file(path)),
        MapError::ModelMismatch { .. }
        | MapError::Unavailable { .. }
        | MapError::NoBucket { .. }
        | MapError::WriterConflict { .. }
        | MapError::InvalidInput { .. }
        | MapError::InvalidMapId { .. } => e.to_string(),
        MapError::UnknownMap { .. }
        | MapError::MapExists { .. }
        | MapError::UnknownKeyframe { .. }
        | MapError::KeyframeExists { .. }
        | MapError::StorageUnavailable { .. }
        | MapError::Feature(_)
        | MapError::Embedding(_)
        | MapError::Pose(_) => "it could not be loaded; the server log has the details".to_string(),
    }
}

/// The loaded maps (all of them in eager mode, a cache in lazy mode), those held back, and the cache's clock.
pub struct MapCache {
    config: CacheSettings,
    lazy: bool,
    maps: RwLock<HashMap<String, Arc<Map>>>,
    /// Maps that failed to load: the reason, and when (the cache's clock, ms).
    held_back: RwLock<HashMap<String, (String, u64)>>,
    /// One lock per map being loaded, so concurrent requests for it wait for one load.
    loading: Mutex<HashMap<String, Arc<Mutex<()>>>>,
    stats: CacheStats,
    opened: Instant,
    /// Requests for maps so far (the order of [`Map::last_used`]).
    requests: AtomicU64,
}

impl MapCache {
    pub fn new(config: CacheSettings, lazy: bool) -> Self {
        Self {
            config,
            lazy,
            maps: RwLock::new(HashMap::new()),
            held_back: RwLock::new(HashMap::new()),
            loading: Mutex::new(HashMap::new()),
            stats: CacheStats::default(),
            opened: Instant::now(),
            requests: AtomicU64::new(0),
        }
    }

    /// Whether maps are loaded on demand (and evicted).
    pub fn is_lazy(&self) -> bool {
        self.lazy
    }

    pub fn stats(&self) -> &CacheStats {
        &self.stats
    }

    /// Whether `id` is in memory now.
    pub fn is_loaded(&self, id: &str) -> bool {
        self.maps.read().contains_key(id)
    }

    /// The map if it is in memory (no load, no freshness check).
    pub fn loaded_map(&self, id: &str) -> Option<Arc<Map>> {
        self.maps.read().get(id).cloned()
    }

    /// Every map in memory.
    pub fn loaded_maps(&self) -> Vec<Arc<Map>> {
        self.maps.read().values().cloned().collect()
    }

    /// Puts a map just created, imported or loaded at start into memory (lazy mode: then evicts beyond the
    /// budget).
    pub fn insert(&self, map: Arc<Map>) {
        self.touch(&map);
        let id = map.id.clone();
        self.held_back.write().remove(&id);
        self.maps.write().insert(id.clone(), map);
        if self.lazy {
            self.evict_beyond_budget(&id);
        }
    }

    /// Takes a map out of memory and off the held-back list (not out of the backend); whether it was in either.
    pub fn remove(&self, id: &str) -> bool {
        self.maps.write().remove(id).is_some() | self.held_back.write().remove(id).is_some()
    }

    /// Records that `id` failed to load, with the reason clients are told.
    pub fn hold_back(&self, id: &str, e: &MapError) {
        self.held_back.write().insert(id.to_string(), (held_back_reason(e), self.now()));
    }

    /// Whether `id` is held back.
    pub fn is_held_back(&self, id: &str) -> bool {
        self.held_back.read().contains_key(id)
    }

    /// Ids of maps that failed to load, with the reason.
    pub fn held_back(&self) -> Vec<(String, String)> {
        let mut v: Vec<_> = self.held_back.read().iter().map(|(k, (reason, _))| (k.clone(), reason.clone())).collect();
        v.sort();
        v
    }

    /// Estimated memory of the maps in memory.
    pub fn loaded_bytes(&self) -> u64 {
        self.maps.read().values().map(|m| m.bytes.load(Ordering::Relaxed)).sum()
    }

    /// Milliseconds since the store opened (the clock of eviction and freshness).
    pub fn now(&self) -> u64 {
        self.opened.elapsed().as_millis() as u64
    }

    /// Marks `map` as the most recently used.
    pub fn touch(&self, map: &Map) {
        map.last_used.store(self.requests.fetch_add(1, Ordering::Relaxed) + 1, Ordering::Relaxed);
    }

    /// The map, or why it cannot be used.
    pub fn get(&self, id: &str, load: Load) -> Result<Arc<Map>, MapError> {
        validate_map_id(id)?;
        let cached = self.maps.read().get(id).cloned();
        if let Some(map) = cached {
            self.touch(&map);
            self.stats.hits.fetch_add(1, Ordering::Relaxed);
            return self.fresh(map, load);
        }
        if self.lazy {
            return self.load_into_cache(id, load);
        }
        if let Some((reason, _)) = self.held_back.read().get(id) {
            return Err(MapError::Unavailable { map: id.to_string(), reason: reason.clone() });
        }
        Err(MapError::UnknownMap { map: id.to_string() })
    }

    /// `map`, checked against the stored map when its last check is older than `freshness_ms`.
    fn fresh(&self, map: Arc<Map>, load: Load) -> Result<Arc<Map>, MapError> {
        let now = self.now();
        let last = map.checked.load(Ordering::Relaxed);
        if now.saturating_sub(last) < self.config.freshness_ms {
            return Ok(map);
        }
        // One check per map at a time; a writer holding the journal makes the copy current (or learns that it
        // is not) with its own write.
        if map.checked.compare_exchange(last, now, Ordering::AcqRel, Ordering::Relaxed).is_err() {
            return Ok(map);
        }
        let next = match map.journal.try_lock() {
            None => {
                // A writer holds the journal: its write makes the copy current or fails on a stale one. The
                // check is owed: the next request makes it.
                map.checked.store(last, Ordering::Relaxed);
                Next::Keep
            }
            Some(mut log) => {
                self.stats.checks.fetch_add(1, Ordering::Relaxed);
                match log.refresh() {
                    Ok(Freshness::Current) => Next::Keep,
                    Ok(Freshness::Appended(records)) => self.apply_others(&map, &records),
                    Ok(Freshness::Replaced) => Next::Reload,
                    Ok(Freshness::Gone) => Next::Gone,
                    Err(e) => {
                        self.stats.check_errors.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!(map = %map.id, error = %e, "cannot check the map's freshness; serving the copy");
                        Next::Keep
                    }
                }
            }
        };
        match next {
            Next::Keep => Ok(map),
            Next::Reload => {
                self.stats.changed.fetch_add(1, Ordering::Relaxed);
                self.reload(&map, load)
            }
            Next::Gone => {
                self.stats.changed.fetch_add(1, Ordering::Relaxed);
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
        self.stats.changed.fetch_add(1, Ordering::Relaxed);
        let mut s = map.state.write();
        for record in records {
            if let Err(reason) = s.data.check(record) {
                // Part of the batch may be applied: the reload replaces this copy (or holds the map back).
                tracing::error!(map = %map.id, %reason, "another writer's record does not apply; reloading");
                return Next::Reload;
            }
            if let Err(e) = s.data.apply(record) {
                tracing::error!(map = %map.id, error = %e, "another writer's record does not apply; reloading");
                return Next::Reload;
            }
        }
        let MapState { data, index } = &mut *s;
        if records.iter().any(|r| matches!(r, Record::Reembed { .. })) {
            // Every embedding changed (another server re-embedded the map): the graph holds the old ones.
            index.reset();
        }
        index.sync(data);
        let version = data.version;
        map.bytes.store(s.memory_bytes(), Ordering::Relaxed);
        tracing::debug!(map = %map.id, records = records.len(), version, "applied other writes");
        Next::Keep
    }

    /// Loads `stale` again and puts the new copy in its place (unless the registry moved on meanwhile).
    fn reload(&self, stale: &Arc<Map>, load: Load) -> Result<Arc<Map>, MapError> {
        self.reload_stale(stale, load);
        self.maps.read().get(&stale.id).cloned().ok_or_else(|| MapError::UnknownMap { map: stale.id.clone() })
    }

    /// Lazy mode: loads a map that is not in memory (one load per map at a time), then evicts beyond the budget.
    fn load_into_cache(&self, id: &str, load: Load) -> Result<Arc<Map>, MapError> {
        let gate = Arc::clone(self.loading.lock().entry(id.to_string()).or_default());
        let loaded = {
            let _loading = gate.lock();
            self.load_gated(id, load)
        };
        let mut loading = self.loading.lock();
        if loading.get(id).is_some_and(|g| Arc::ptr_eq(g, &gate)) && Arc::strong_count(&gate) == 2 {
            loading.remove(id);
        }
        loaded
    }

    fn load_gated(&self, id: &str, load: Load) -> Result<Arc<Map>, MapError> {
        if let Some(map) = self.maps.read().get(id).cloned() {
            // Loaded by the request this one waited for.
            self.stats.hits.fetch_add(1, Ordering::Relaxed);
            return Ok(map);
        }
        let now = self.now();
        if let Some((reason, at)) = self.held_back.read().get(id) {
            if now.saturating_sub(*at) < self.config.freshness_ms {
                return Err(MapError::Unavailable { map: id.to_string(), reason: reason.clone() });
            }
        }
        self.stats.misses.fetch_add(1, Ordering::Relaxed);
        // A load that read the manifest just before another server compacted finds the old objects gone
        // ("named by the manifest but missing"): once more, from the new manifest.
        let loaded = match load(id) {
            Err(MapError::Corrupt { .. }) => load(id),
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
            Err(e @ (MapError::StorageUnavailable { .. } | MapError::NoBucket { .. })) => {
                tracing::warn!(map = %id, error = %e, "cannot load the map");
                Err(e)
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
    pub fn evict_beyond_budget(&self, keep: &str) {
        let budget = self.config.memory_budget_mb << 20;
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
                self.stats.evictions.fetch_add(1, Ordering::Relaxed);
                tracing::info!(map = %victim, bytes = m.bytes.load(Ordering::Relaxed), total, budget, "map evicted");
            }
        }
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
    pub fn reload_stale(&self, stale: &Map, load: Load) {
        let id = stale.id.as_str();
        let still_registered =
            |maps: &HashMap<String, Arc<Map>>| maps.get(id).is_some_and(|m| std::ptr::eq(Arc::as_ptr(m), stale));
        let gate = Arc::clone(self.loading.lock().entry(id.to_string()).or_default());
        let _reloading = gate.lock();
        if !still_registered(&self.maps.read()) {
            return;
        }
        match load(id) {
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
}
