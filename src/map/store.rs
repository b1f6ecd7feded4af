//! The registry of maps: create, list, get, delete, write keyframes, localise, export and import.
//!
//! Every map is looked up in the [`MapCache`] (which maps are in memory, and how fresh: `[store.cache]`);
//! existence is the backend's, not the cache's: create, import, delete and listings ask the backend, so a map
//! another replica created or deleted is seen at this replica's next request for it. A write plans its record
//! against the map, makes it durable through the map's journal (append + fsync, or a conditional manifest
//! PUT), then applies it; every few records the map is compacted into a snapshot with its index dump.
//!
//! Storage goes through a [`MapBackend`] chosen by `store.backend`: the local directory (default) or object
//! storage ([`crate::map::storage::s3`]). Its calls block (fsync, HTTP round trips), like the rest of
//! this module: call it from blocking threads only.

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Instant;

use parking_lot::Mutex;
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::describe::features::Features;
use crate::error::MapError;
use crate::map::builder::{plan, BuildSettings, ExternalCounts, KeyframeInput};
pub use crate::map::cache::{CacheSettings, CacheStats, Map, MapSummary};
use crate::map::cache::{MapCache, MapState};
use crate::map::index::{DumpRead, EmbeddingIndex, IndexSettings};
use crate::map::localize::{localize, Localization, LocalizeSettings, Prior};
use crate::map::merge::plan_merge;
pub use crate::map::merge::MergePlan;
use crate::map::model::{validate_map_id, MapData, MapMeta, MapStats, Record};
use crate::map::storage::backend::{EarlyIndex, LoadReport, MapBackend, MapJournal, OperationStats};
use crate::map::storage::format::{install_dump, read_dump, write_atomic};
use crate::map::storage::snapshot::{decode_export, encode_export};
use crate::map::storage::{open_backend, BackendSettings};

/// Settings of the map store.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StoreSettings {
    /// Local directory: the maps themselves with the local backend (`maps/<id>/`), the cache of index
    /// dumps with object storage (`cache/<id>/`, unless `backend.cache_dir` says otherwise).
    pub data_dir: PathBuf,
    /// Log records between snapshots.
    pub compact_every: usize,
    pub index: IndexSettings,
    pub build: BuildSettings,
    pub localize: LocalizeSettings,
    /// Where maps are stored: `kind = "local"` (default) or `kind = "s3"`.
    pub backend: BackendSettings,
    /// Which maps are kept in memory, and how fresh a replica's copy is.
    pub cache: CacheSettings,
}

impl Default for StoreSettings {
    fn default() -> Self {
        Self {
            data_dir: PathBuf::from("data"),
            compact_every: 200,
            index: IndexSettings::default(),
            build: BuildSettings::default(),
            localize: LocalizeSettings::default(),
            backend: BackendSettings::default(),
            cache: CacheSettings::default(),
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

/// All maps of a backend.
pub struct MapStore {
    config: StoreSettings,
    backend: Arc<dyn MapBackend>,
    model: ModelInfo,
    cache: MapCache,
    /// Serialises create, delete and import (changes to the set of maps).
    admin: Mutex<()>,
}

fn now_ms() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0)
}

impl MapStore {
    /// Opens the backend `config.backend` describes and loads every map with its index.
    pub fn open(config: StoreSettings, model: ModelInfo) -> Result<Self, MapError> {
        let backend = open_backend(&config.backend, &config.data_dir, config.compact_every)?;
        Self::open_with_backend(config, model, backend)
    }

    /// Loads every map of `backend` (`config.backend` is not consulted).
    pub fn open_with_backend(
        config: StoreSettings,
        model: ModelInfo,
        backend: Arc<dyn MapBackend>,
    ) -> Result<Self, MapError> {
        let cache = MapCache::new(config.cache.clone(), config.cache.is_lazy(&config.backend));
        let store = Self { config, backend, model, cache, admin: Mutex::new(()) };
        if store.cache.is_lazy() {
            tracing::info!(location = %store.backend.location(), budget_mb = store.config.cache.memory_budget_mb,
                "maps are loaded on first request");
            return Ok(store);
        }
        tracing::info!(location = %store.backend.location(), "loading maps");
        for name in store.backend.list()? {
            match store.load_map(&name) {
                Ok((map, report)) => {
                    tracing::info!(map = %name, replayed = report.replayed, truncated = report.truncated_bytes, "map loaded");
                    store.cache.insert(Arc::new(map));
                }
                Err(e) => {
                    tracing::error!(map = %name, error = %e, "map held back");
                    store.cache.hold_back(&name, &e);
                }
            }
        }
        Ok(store)
    }

    /// The map, or why it cannot be used (loaded on demand in lazy mode, checked for freshness). The
    /// operations on one map take what this returns: a request looks its map up once.
    pub fn get(&self, id: &str) -> Result<Arc<Map>, MapError> {
        self.cache.get(id, &|id| self.load_map(id))
    }

    fn load_map(&self, id: &str) -> Result<(Map, LoadReport), MapError> {
        let t = Instant::now();
        let params = self.config.index;
        // Where the dump is known beforehand, a second thread fetches it (object storage) and hnsw_rs reads
        // the graph while the snapshot downloads and decodes (the largest parts of a load); the dump is
        // checked against the map data afterwards. Not for a map held back after a failed load: its next try
        // would read a graph it may not get to use.
        let early = if self.cache.is_held_back(id) { None } else { self.backend.index_before_open(id) };
        let early_dir = early.as_ref().map(|e| e.dir.clone());
        let (opened, early, open_s, graph_s) = match early {
            Some(EarlyIndex { dir, fetch }) => std::thread::scope(|s| {
                let reader = std::thread::Builder::new().name("scone-dump-read".into()).spawn_scoped(s, move || {
                    let t = Instant::now();
                    // A dump that did not arrive is left to the open, which fetches it as it always could.
                    fetch.is_none_or(|f| f()).then(|| (DumpRead::read(&dir, params.points), t.elapsed().as_secs_f64()))
                });
                let opened = self.backend.open(id);
                let open_s = t.elapsed().as_secs_f64();
                // Without a second thread, the index reads its dump after the open, as it always could.
                let read =
                    reader.ok().and_then(|r| r.join().map_err(|_| "reading it panicked".to_string()).transpose());
                let graph_s = read.as_ref().and_then(|r| r.as_ref().ok()).map(|r| r.1);
                (opened, read.map(|r| r.and_then(|r| r.0)), open_s, graph_s)
            }),
            None => (self.backend.open(id), None, t.elapsed().as_secs_f64(), None),
        };
        let (data, log, report) = opened?;
        let data_s = t.elapsed().as_secs_f64();
        let index = match (early, &early_dir) {
            (Some(read), Some(dir)) if dir.as_path() == log.index_dir() => {
                EmbeddingIndex::from_dump(params, dir, &data, read)
            }
            _ => EmbeddingIndex::load_or_build(params, log.index_dir(), &data),
        };
        // Where the time to ready goes: the map data (snapshot and log, `open_s` alone; `data_s` until the
        // graph read beside it, `graph_s` alone, was done too), then what the index took beyond it.
        tracing::info!(map = %id, observations = data.observations.len(), data_s, open_s, graph_s,
            index_s = t.elapsed().as_secs_f64() - data_s, from_dump = index.loaded_from_dump(), "map opened");
        let stats = self.cache.stats();
        stats.loads.fetch_add(1, Ordering::Relaxed);
        stats.load_nanos.fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        let mut map = Map::new(id, data, index, log, self.cache.now());
        if report.truncated_bytes > 0 {
            stats.logs_cut.fetch_add(1, Ordering::Relaxed);
            map.load_note = Some(format!(
                "the log ended inside a record: its last {} bytes were cut off at load. After a crash this is the \
                 one write in flight, which was never acknowledged; otherwise the file was damaged and \
                 acknowledged writes may be missing",
                report.truncated_bytes
            ));
        }
        Ok((map, report))
    }

    /// Whether maps are loaded on demand (and evicted).
    pub fn is_lazy(&self) -> bool {
        self.cache.is_lazy()
    }

    pub fn cache_stats(&self) -> &CacheStats {
        self.cache.stats()
    }

    /// Calls made to the storage service (object storage), per operation.
    pub fn operation_stats(&self) -> Vec<OperationStats> {
        self.backend.operation_stats()
    }

    /// Whether [`MapStore::get`] may wait on storage: a load (maps loaded on demand) or a freshness check
    /// against object storage.
    pub fn lookup_may_block(&self) -> bool {
        self.cache.is_lazy() || self.backend.is_remote()
    }

    /// Whether `id` is in memory now.
    pub fn is_loaded(&self, id: &str) -> bool {
        self.cache.is_loaded(id)
    }

    pub fn model(&self) -> &ModelInfo {
        &self.model
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
        if self.cache.is_lazy() {
            self.cache.remove(id);
        } else if self.cache.is_loaded(id) || self.cache.is_held_back(id) {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        let mut data = MapData::new(MapMeta {
            id: id.to_string(),
            model_id: self.model.model_id.clone(),
            k: self.model.k,
            dim: self.model.dim,
            created_unix_ms: now_ms(),
        });
        let mut log = self.backend.create(id, &data)?;
        if let Some(stored) = log.take_stored_payloads() {
            data.store_payloads(&stored);
        }
        let index = EmbeddingIndex::new(self.config.index);
        let map = Arc::new(Map::new(id, data, index, log, self.cache.now()));
        self.cache.insert(Arc::clone(&map));
        Ok(map.summary())
    }

    /// Every map: the loaded ones (eager mode), or every stored map (lazy mode), the counts of those not
    /// loaded as the backend records them. A stored map without recorded counts is loaded to tell; one
    /// that fails to load is left out (it is in [`MapStore::held_back`]).
    pub fn list(&self) -> Result<Vec<MapSummary>, MapError> {
        if !self.cache.is_lazy() {
            return Ok(self.loaded());
        }
        let mut out = Vec::new();
        for (id, stats) in self.backend.list_stats()? {
            let cached = self.cache.loaded_map(&id);
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
        self.cache.loaded_bytes()
    }

    /// The maps in memory, by id (cheap: for metrics).
    pub fn loaded(&self) -> Vec<MapSummary> {
        let maps = self.cache.loaded_maps();
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
        self.cache.held_back()
    }

    /// Map `id`'s statistics (one lookup: for commands and tests; requests hold their map and ask it).
    pub fn summary(&self, id: &str) -> Result<MapSummary, MapError> {
        Ok(self.get(id)?.summary())
    }

    /// Keyframe poses and intrinsics, and at most `max_landmarks` landmarks (every n-th by id, so the
    /// subsample covers the whole map), read under the map's shared lock.
    pub fn contents(&self, map: &Map, max_landmarks: usize) -> MapContents {
        map.read(|data, _| {
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
        })
    }

    /// Deletes a map: out of the registry first, then out of the backend.
    pub fn delete(&self, id: &str) -> Result<(), MapError> {
        validate_map_id(id)?;
        let _admin = self.admin.lock();
        let known = self.cache.remove(id);
        // Lazy mode: the map may be stored without being loaded here; a cached copy of a map deleted
        // elsewhere is not a map.
        let known = if self.cache.is_lazy() { self.backend.exists(id)? } else { known };
        if !known {
            return Err(MapError::UnknownMap { map: id.to_string() });
        }
        self.backend.delete(id)
    }

    /// Adds a keyframe to `map`; returns after the record is durable and applied.
    pub fn add_keyframe(&self, map: &Map, input: &KeyframeInput) -> Result<KeyframeAdded, MapError> {
        self.check_model(map)?;
        let mut log = map.journal.lock();
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
        let version = self.commit(map, log.as_mut(), planned.record)?;
        Ok(KeyframeAdded {
            keyframe: input.id,
            new_landmarks: new,
            observations: obs,
            version,
            external: planned.external,
        })
    }

    /// Removes a keyframe of `map`; returns the map's new version.
    pub fn remove_keyframe(&self, map: &Map, keyframe: u64) -> Result<u64, MapError> {
        let mut log = map.journal.lock();
        let record = Record::RemoveKeyframe { id: keyframe };
        if map.state.read().data.check(&record).is_err() {
            return Err(MapError::UnknownKeyframe { map: map.id.clone(), keyframe });
        }
        self.commit(map, log.as_mut(), record)
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
        let mut log = map.journal.lock();
        let keyframes = {
            let s = map.state.read();
            let mut out = Vec::with_capacity(s.data.keyframes.len());
            for kf in s.data.keyframes.values() {
                let kf = kf.load()?;
                if kf.descriptors.is_empty() && !kf.keypoints.is_empty() {
                    return Err(MapError::InvalidInput {
                        field: "map".into(),
                        reason: format!("keyframe {} has no FREAK descriptors to re-embed", kf.id),
                    });
                }
                out.push((kf.id, embed(&kf)?));
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

    /// Merges map `source` into map `target` (`map::merge`): one durable record on the target; the source is
    /// read, never written. `transform` takes source coordinates to the target's; without it, it is estimated.
    pub fn merge(
        &self,
        into: &Map,
        source: &str,
        transform: Option<nalgebra::Similarity3<f64>>,
    ) -> Result<(MergePlan, MapSummary), MapError> {
        if into.id == source {
            return Err(MapError::InvalidInput {
                field: "source_map_id".into(),
                reason: "a map cannot be merged into itself".into(),
            });
        }
        self.check_model(into)?;
        let from = self.get(source)?;
        self.check_model(&from)?;
        // A copy of the source, so that no lock of the source is held while the target's are: merges in both
        // directions at once cannot wait on each other.
        let source_data = from.read(|data, _| data.clone());
        let mut log = into.journal.lock();
        let plan = into.read(|data, index| plan_merge(data, index, &source_data, transform, &self.config.localize))?;
        self.commit(into, log.as_mut(), plan.record.clone())?;
        drop(log);
        Ok((plan, into.summary()))
    }

    /// Log (fsync) then apply; compacts and dumps the index when the log is long. Returns the new version.
    fn commit(&self, map: &Map, log: &mut dyn MapJournal, record: Record) -> Result<u64, MapError> {
        if log.needs_upgrade() {
            // An older format's files that the open could not rewrite: rewritten now, before the record.
            let upgraded = log.compact(&map.state.read().data);
            upgraded?;
            Self::store_payloads(map, log);
        }
        let (seq, after) = {
            let s = map.state.read();
            (s.data.version + 1, s.data.stats_after(&record))
        };
        if let Err(e) = log.append(seq, &record, &after) {
            if matches!(e, MapError::WriterConflict { .. }) {
                self.cache.reload_stale(map, &|id| self.load_map(id));
            }
            return Err(e);
        }
        let mut s = map.state.write();
        if let Err(e) = s.data.apply(&record) {
            // The record is durable but this copy could not read what it needs (a stored payload): load the
            // map again, which replays the record.
            drop(s);
            tracing::error!(map = %map.id, error = %e, "a logged record does not apply to the loaded copy; reloading");
            self.cache.reload_stale(map, &|id| self.load_map(id));
            return Err(e);
        }
        {
            let MapState { data, index } = &mut *s;
            index.sync(data);
        }
        map.bytes.store(s.memory_bytes(), Ordering::Relaxed);
        map.checked.store(self.cache.now(), Ordering::Relaxed);
        let version = s.data.version;
        // A re-embedding put every payload in memory: a snapshot takes them out again.
        if log.wants_compaction() || matches!(record, Record::Reembed { .. }) {
            // Queries may read on while the snapshot (and the index dump) is written and uploaded. The record
            // is durable and applied: a failed dump or compaction is logged, not this write's error (the log
            // keeps the records, and the next write tries again).
            let s = parking_lot::RwLockWriteGuard::downgrade(s);
            if let Err(e) = s.index.dump(log.index_dir(), &s.data).and_then(|()| log.compact(&s.data)) {
                tracing::error!(map = %map.id, error = %e, "compaction failed; the records stay in the log");
            }
            drop(s);
            Self::store_payloads(map, log);
        }
        Ok(version)
    }

    /// Points `map`'s keyframes at the payloads of the snapshot its journal wrote last, if it wrote one (the
    /// caller holds the journal, so the map is still the version that snapshot holds).
    fn store_payloads(map: &Map, log: &mut dyn MapJournal) {
        if let Some(stored) = log.take_stored_payloads() {
            let mut s = map.state.write();
            s.data.store_payloads(&stored);
            map.bytes.store(s.memory_bytes(), Ordering::Relaxed);
        }
    }

    /// Localises a query against `map`.
    pub fn localize(
        &self,
        map: &Map,
        features: &Features,
        embeddings: &[f32],
        camera: &Camera,
        prior: Option<&Prior>,
    ) -> Result<Localization, MapError> {
        self.check_model(map)?;
        map.read(|data, index| localize(data, index, features, embeddings, camera, prior, &self.config.localize))
    }

    /// How this store localises (`[store.localize]`): the settings a track query shares with single frames.
    pub fn localize_settings(&self) -> &LocalizeSettings {
        &self.config.localize
    }

    /// The whole map in the versioned, checksummed export format, with its index dump when it has an HNSW
    /// graph ([`encode_export`]: an import then answers exactly as this map). The dump is written into the
    /// map's index directory first (as a compaction would); if that fails the export goes without it.
    pub fn export(&self, map: &Map) -> Result<Vec<u8>, MapError> {
        let log = map.journal.lock();
        let s = map.state.read();
        let dump = if s.index.is_approximate() {
            match s.index.dump(log.index_dir(), &s.data) {
                Ok(()) => read_dump(log.index_dir()),
                Err(e) => {
                    tracing::warn!(map = %map.id, error = %e, "export without the index dump: an import rebuilds it");
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
        let existing = match self.cache.is_lazy() {
            // The stored map (loaded to compare), if there is one.
            true => match self.get(id) {
                Ok(map) => Some(map),
                Err(MapError::UnknownMap { .. }) => None,
                // Stored but held back (corrupt): the id is taken. Unreachable storage stays an error.
                Err(MapError::Unavailable { .. }) if self.cache.is_held_back(id) => {
                    return Err(MapError::MapExists { map: id.to_string() })
                }
                Err(e) => return Err(e),
            },
            false => self.cache.loaded_map(id),
        };
        if let Some(map) = existing {
            if map.read(|held, _| *held == data) {
                return Ok(map.summary());
            }
            return Err(MapError::MapExists { map: id.to_string() });
        }
        if (!self.cache.is_lazy() && self.cache.is_held_back(id)) || self.backend.exists(id)? {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        let mut log = self.backend.create(id, &data)?;
        // The imported payloads leave memory for the new map's snapshot.
        if let Some(stored) = log.take_stored_payloads() {
            data.store_payloads(&stored);
        }
        let installed = dump.map(|d| install_dump(log.index_dir(), &d));
        if let Some(Err(e)) = &installed {
            tracing::warn!(map = %id, error = %e, "cannot install the exported index dump; it is rebuilt");
        }
        // The loader checks the dump against the map, and builds the graph itself when it does not match.
        let index = EmbeddingIndex::load_or_build(self.config.index, log.index_dir(), &data);
        let map = Arc::new(Map::new(id, data, index, log, self.cache.now()));
        self.cache.insert(Arc::clone(&map));
        Ok(map.summary())
    }

    /// Snapshots every map and dumps its index (at shutdown, so the next start loads instead of rebuilding).
    /// A map another writer took over (object storage) is left to that writer. Every map is tried; those that
    /// could not be flushed (a full volume, say) are returned with the error: their acknowledged writes are
    /// in their logs, so the next start replays them (and rebuilds an index it has no dump of).
    pub fn flush(&self) -> Vec<(String, MapError)> {
        let maps = self.cache.loaded_maps();
        let mut failed = Vec::new();
        for map in maps {
            let mut log = map.journal.lock();
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
    pub fn export_to_file(&self, map: &Map, path: &Path) -> Result<(), MapError> {
        write_atomic(path, &self.export(map)?)
    }
}
