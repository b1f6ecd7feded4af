//! What the [`MapStore`](crate::map::store::MapStore) needs from storage, as two traits, so it does not care
//! where maps live:
//!
//! * [`MapBackend`]: the collection of maps (list, exists, create, open, delete);
//! * [`MapJournal`]: the single writer of one open map (append a record durably, compact, check that the copy
//!   is current), plus the local directory that holds the map's HNSW index dump.
//!
//! Two implementations, chosen by [`BackendSettings`](crate::map::storage::BackendSettings) (`[store.backend]`):
//!
//! * [`crate::map::storage::local`] (`kind = "local"`, the default): `data_dir/maps/<id>/`, a snapshot plus an
//!   fsync'd write-ahead log, with the index dump beside them;
//! * [`crate::map::storage::s3`] (`kind = "s3"`): immutable objects plus a manifest replaced by conditional writes in
//!   an S3-API bucket, the index dump in a local cache directory.
//!
//! Both are synchronous: the store calls them on blocking threads (the CPU pool, `spawn_blocking`), never on
//! async worker threads.

use std::path::{Path, PathBuf};

use crate::error::MapError;
use crate::map::model::{MapData, MapStats, Record};
use crate::map::payload::StoredPayloads;

/// Where a map's index dump is to be read before its open ([`MapBackend::index_before_open`]).
pub struct EarlyIndex {
    pub dir: PathBuf,
    /// Brings the dump into `dir` (object storage's download), run before it is read: `false` when it could
    /// not, and the open then fetches it as it always could. `None` where the dump is there already.
    pub fetch: Option<Box<dyn FnOnce() -> bool + Send>>,
}

/// The collection of stored maps.
pub trait MapBackend: Send + Sync {
    /// Where the maps are, for logs (`data/maps`, `s3://bucket/prefix/maps`).
    fn location(&self) -> String;

    /// Ids of the stored maps (only valid ids), sorted.
    fn list(&self) -> Result<Vec<String>, MapError>;

    /// Whether a map with this id is stored.
    fn exists(&self, id: &str) -> Result<bool, MapError>;

    /// Stores a new map holding `data` and returns its writer; [`MapError::MapExists`] if the id is taken.
    fn create(&self, id: &str, data: &MapData) -> Result<Box<dyn MapJournal>, MapError>;

    /// Loads a map (verifying every checksum) and returns it with its writer.
    fn open(&self, id: &str) -> Result<(MapData, Box<dyn MapJournal>, LoadReport), MapError>;

    /// Removes a map and everything stored for it.
    fn delete(&self, id: &str) -> Result<(), MapError>;

    /// Where the map's index dump is before [`MapBackend::open`] (a local map's directory; object storage's
    /// cache directory, with what fetches the dump there): the store then fetches and reads the graph on a
    /// thread of its own while the map data loads and decodes. `None` where the dump comes with the open.
    fn index_before_open(&self, _id: &str) -> Option<EarlyIndex> {
        None
    }

    /// Every stored map with its counts when the backend records them without loading the map (object
    /// storage keeps them in the manifest); `None` where only loading the map tells.
    fn list_stats(&self) -> Result<Vec<(String, Option<MapStats>)>, MapError> {
        Ok(self.list()?.into_iter().map(|id| (id, None)).collect())
    }

    /// Requests made to the storage service, per operation (none for a local directory).
    fn operation_stats(&self) -> Vec<OperationStats> {
        Vec::new()
    }

    /// Whether the maps are behind a network (object storage): a freshness check is then a round trip.
    fn is_remote(&self) -> bool {
        false
    }
}

/// Calls of one kind made to a storage service since start.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct OperationStats {
    pub operation: &'static str,
    pub calls: u64,
    pub errors: u64,
    pub seconds: f64,
}

/// What a freshness check of an open map found ([`MapJournal::refresh`]).
#[derive(Debug)]
pub enum Freshness {
    /// The stored map is the one this copy holds.
    Current,
    /// Another writer appended these records since, in order: apply them (the journal now follows the
    /// stored map again).
    Appended(Vec<Record>),
    /// The stored map was rewritten (another writer compacted it) or is another map under the same id: load
    /// it again.
    Replaced,
    /// The map was deleted.
    Gone,
}

/// The writer of one open map. Calls are serialised by the caller (the map's writer lock).
pub trait MapJournal: Send + std::fmt::Debug {
    /// Makes the record that takes the map to version `seq` durable; returns only once it is. `after` is the
    /// map's counts once the record is applied (object storage records them for listings).
    fn append(&mut self, seq: u64, record: &Record, after: &MapStats) -> Result<(), MapError>;

    /// Whether enough records accumulated to fold them into a snapshot.
    fn wants_compaction(&self) -> bool;

    /// Whether the stored files are of an older format that could not be rewritten when the map was opened (a
    /// full volume): the caller compacts before the next append, and the write fails with the compaction's
    /// error if that fails again.
    fn needs_upgrade(&self) -> bool {
        false
    }

    /// Replaces the stored snapshot with `data` and drops the records it covers. The caller has just dumped
    /// the index of `data` into [`index_dir`](Self::index_dir): object storage uploads that dump with the
    /// snapshot, so a replica that loads the map downloads the graph instead of rebuilding it.
    fn compact(&mut self, data: &MapData) -> Result<(), MapError>;

    /// Local directory for the map's index dump.
    fn index_dir(&self) -> &Path;

    /// Where the snapshot written last (by the create or a compaction) keeps each keyframe's payload, once:
    /// the store points the map's keyframes there ([`MapData::store_payloads`]), and their payloads leave
    /// memory.
    fn take_stored_payloads(&mut self) -> Option<StoredPayloads>;

    /// Whether the stored map moved on from this copy (another replica wrote it). A local directory has one
    /// writer, this process, so it is always current.
    fn refresh(&mut self) -> Result<Freshness, MapError> {
        Ok(Freshness::Current)
    }
}

/// What loading found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LoadReport {
    pub replayed: usize,
    /// Bytes cut off the end of the log (a torn, unacknowledged record).
    pub truncated_bytes: u64,
}
