//! The manifest of a map in object storage (the one object that changes, only by conditional PUTs), what it
//! names, and the names of the objects it names.

use serde::{Deserialize, Serialize};

use crate::map::model::MapStats;

/// Largest manifest accepted when reading (a guard against a hostile or broken object).
pub(super) const MAX_MANIFEST_BYTES: u64 = 16 << 20;
/// Segments fetched at once when loading a map.
pub(super) const PARALLEL_GETS: usize = 16;
pub(super) const MANIFEST: &str = "manifest.json";
pub(super) const CACHE_MARKER: &str = "map.json";
/// Prefix of the local copy of the current snapshot in a map's cache directory.
pub(super) const SNAPSHOT_COPY: &str = "snapshot-";
/// The objects of an index dump ([`EmbeddingIndex::dump`](crate::map::index::EmbeddingIndex::dump)) under
/// `index/<version>-<nonce>/`: the graph file, the data file and the manifest (which names the base the files
/// take in a local directory). The manifest goes last on upload and is compared first on download.
pub(super) const INDEX_FILES: [&str; 3] = ["index.hnsw.graph", "index.hnsw.data", "index.json"];

/// The map's manifest: the one object that changes, only by conditional PUTs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct Manifest {
    pub(super) format_version: u32,
    /// Random, fixed when the map is created: tells this map from an earlier one with the same id.
    pub(super) map_uid: String,
    /// The writer that wrote this manifest (host, process, random).
    pub(super) writer: String,
    pub(super) snapshot: SnapshotRef,
    /// Segment objects (relative to the map's prefix) holding versions `snapshot.version + 1 ..`, in order.
    pub(super) segments: Vec<String>,
    pub(super) next_seq: u64,
    /// The map's counts at `next_seq - 1`, so replicas list maps they have not loaded (absent in manifests
    /// written before they were recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) stats: Option<MapStats>,
    /// The HNSW index dump of the snapshot, uploaded with it (absent while the map is below the exact-search
    /// threshold, or written before dumps were uploaded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) index: Option<IndexRef>,
}

/// An index dump in the bucket: the directory (relative to the map's prefix) holding [`INDEX_FILES`], and
/// the map version it was dumped at.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct IndexRef {
    pub(super) dir: String,
    pub(super) version: u64,
}

impl Manifest {
    /// Whether this manifest names the object (or index directory) `relative` to the map's prefix.
    pub(super) fn names(&self, relative: &str) -> bool {
        self.snapshot.object == relative
            || self.segments.iter().any(|s| s == relative)
            || self.index.as_ref().is_some_and(|ix| ix.dir == relative || relative.starts_with(&format!("{}/", ix.dir)))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(super) struct SnapshotRef {
    pub(super) object: String,
    pub(super) version: u64,
}

/// Sequence number or version encoded at the start of an object's file name (`<n:020>-<nonce>.<ext>`).
pub(super) fn number_of(name: &str) -> Option<u64> {
    let file = name.rsplit('/').next()?;
    file.get(..20)?.parse().ok()
}

pub(super) fn nonce() -> String {
    format!("{:016x}", rand::random::<u64>())
}
