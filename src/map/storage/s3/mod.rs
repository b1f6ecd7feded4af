//! Maps in object storage (the S3 API, through the `object_store` crate): immutable objects plus one manifest
//! per map that is replaced only by conditional writes.
//!
//! Object storage has no append and no fsync, so the local log's design does not carry over. Layout under
//! `<prefix>/maps/<id>/`:
//!
//! * `manifest.json`: `{format_version, map_uid, writer, snapshot: {object, version}, segments: [..],
//!   next_seq, stats, index}`. The one mutable object: what it names is the map. `stats` (the map's counts,
//!   for listings by replicas that have not loaded it) and `index` (the dump of the snapshot's HNSW graph)
//!   are optional: manifests written before them still read.
//! * `snapshots/<version:020>-<nonce:016x>.bin`: the whole map in the snapshot/export format
//!   ([`encode_snapshot`](crate::map::storage::snapshot::encode_snapshot)), written once.
//! * `segments/<seq:020>-<nonce:016x>.rec`: one record each, with the local log's framing and CRC
//!   ([`encode_segment`](crate::map::storage::format::encode_segment)), written once.
//! * `index/<version:020>-<nonce:016x>/{index.hnsw.graph, index.hnsw.data, index.json}`: the index dump of
//!   a snapshot, written once, named by the manifest with that snapshot.
//!
//! Every new object is written with `If-None-Match: *` (`PutMode::Create`) under a name with a random nonce,
//! so no object is ever overwritten, not even by a writer that lost its claim or by a retry of a failed write.
//!
//! **A write** (append): PUT the segment (create-only), then PUT the manifest with the segment appended,
//! conditional on the manifest's ETag as this writer last read or wrote it (`If-Match`, `PutMode::Update`).
//! The write is acknowledged only after the manifest PUT succeeded. If the condition fails, someone else
//! replaced the manifest since: this writer's copy is stale, it gets [`MapError::WriterConflict`] naming the
//! other writer, deletes its own segment, and refuses every later write (it is fenced). Nothing it wrote is
//! referenced, so the map as stored is unchanged. If the manifest PUT fails for another reason (network),
//! the manifest is read back to learn the outcome: ours (the write happened; the response was lost), the
//! previous one (it did not; the error is returned and a retry is safe), or unknown (fenced).
//!
//! **One writer per map.** The conditional write makes concurrent writers safe (one wins, the others are
//! fenced, nothing is lost or overwritten), not useful: the deployment routes each map id to one replica
//! (ring hash in Envoy, `docs/object-storage.md`), which is the map's single writer. When the routing moves
//! (pods added or removed), the new writer's copy may be older than the old writer's last write: its first
//! write then fails the same way, and the store reloads the map
//! ([`MapStore`](crate::map::store::MapStore) on [`MapError::WriterConflict`]), so the client's retry
//! succeeds on fresh data. Between writes, a replica's reads come from the copy it loaded, checked against
//! the stored map at most every `store.cache.freshness_ms` ([`MapJournal::refresh`]: a GET of the manifest
//! with `If-None-Match`; appended segments are applied, a rewritten map is loaded again).
//!
//! **Crash between the two PUTs**: the segment exists but no manifest names it (an orphan). Loading reads only
//! what the manifest names, so the orphan is ignored; the write was never acknowledged. Compaction deletes
//! orphans whose sequence number the new snapshot covers (no valid manifest can ever name them).
//!
//! **Compaction**: PUT a new snapshot (create-only), conditional manifest PUT pointing at it with an empty
//! segment list, then best-effort deletion of the replaced snapshot and segments. Only the replica that wrote
//! records compacts, and only when there is something to fold: shutting down a replica that merely loaded a
//! map neither rewrites it nor fences its writer.
//!
//! **Loading** reads the manifest, the snapshot and the segments in order and verifies every checksum and
//! sequence number; a problem is [`MapError::Corrupt`] naming the object (`s3://bucket/key`), and the store
//! holds that map back while the others serve.
//!
//! **Index dump**: the HNSW graph is dumped to a local cache directory (`<cache_dir>/<id>/`) and, at
//! compaction, uploaded with the snapshot; a replica without a matching local dump (new pod, emptied cache)
//! downloads it instead of rebuilding the graph from the map data (11-18 s per 100k observations here), and inserts
//! the observations of the segments after it. A download that fails is a rebuild, not an error. A marker
//! with the manifest's `map_uid` keeps a dump of an earlier map of the same id from being used.
//!
//! **Threads**: `object_store` is async. The backend owns a small tokio runtime (one worker, for the HTTP
//! client's I/O) and `block_on`s it from the store's synchronous methods. Those run on blocking threads (the
//! CPU pool, `spawn_blocking`), never on an async worker thread: there, tokio panics with "Cannot start a
//! runtime from within a runtime", which is the intended guard against stalling the servers' I/O.
//!
//! **Tested against** moto's server mode (`tests/it/object_store.rs`): an S3 *emulator*, which honours
//! `If-Match` and `If-None-Match: *` on PUT (moto 5.2.5). Real S3 has supported both since 2024; an
//! S3-compatible service must support them too (the backend refuses to write without them).

mod client;
mod journal;
mod manifest;

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;

use futures_util::StreamExt;
use object_store::aws::{AmazonS3Builder, S3ConditionalPut};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, PutMode};

use crate::error::MapError;
use crate::map::model::{validate_map_id, MapData, MapStats};
use crate::map::payload::{FetchSection, PayloadFile, Span};
use crate::map::storage::backend::{EarlyIndex, LoadReport, MapBackend, MapJournal, OperationStats};
use crate::map::storage::format::{decode_segment, io_err, FORMAT_VERSION};
use crate::map::storage::snapshot::{
    decode_snapshot, encode_snapshot_spans, map_from_core, split_layout, stored_payloads, SplitLayout,
};

use client::{OpCounters, Shared, OPS};
pub use client::{S3Credentials, S3Settings};
use journal::ObjectJournal;
use manifest::{nonce, number_of, Manifest, SnapshotRef, MANIFEST, PARALLEL_GETS};

/// Maps in an object store (an S3 bucket in production, [`object_store::memory::InMemory`] in unit tests).
pub struct ObjectStorageBackend {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for ObjectStorageBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectStorageBackend").field("location", &self.location()).finish()
    }
}

/// The object store's own retries of a failed call: a few, within about 2 s, so that storage that is down
/// is answered UNAVAILABLE (retry later) within the request deadline (`server.request_timeout_ms`, 10 s by
/// default) instead of holding a CPU worker for minutes (object_store's default: 10 retries within 3 minutes).
fn retries() -> object_store::RetryConfig {
    object_store::RetryConfig {
        backoff: object_store::BackoffConfig {
            init_backoff: std::time::Duration::from_millis(100),
            max_backoff: std::time::Duration::from_secs(1),
            base: 2.0,
        },
        max_retries: 3,
        retry_timeout: std::time::Duration::from_secs(4),
    }
}

fn writer_id() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "host".into());
    format!("{host}-{}-{:08x}", std::process::id(), rand::random::<u32>())
}

impl ObjectStorageBackend {
    /// An S3 bucket (conditional PUTs by ETag), credentials as `credentials` says.
    pub fn s3(
        config: &S3Settings,
        cache_root: &Path,
        compact_every: usize,
        credentials: S3Credentials,
    ) -> Result<Self, MapError> {
        let mut builder = match credentials {
            S3Credentials::FromEnv => AmazonS3Builder::from_env(),
            S3Credentials::Static { access_key_id, secret_access_key } => {
                AmazonS3Builder::new().with_access_key_id(access_key_id).with_secret_access_key(secret_access_key)
            }
        };
        builder = builder
            .with_bucket_name(&config.bucket)
            .with_conditional_put(S3ConditionalPut::ETagMatch)
            .with_allow_http(config.allow_http)
            .with_retry(retries());
        if let Some(r) = &config.region {
            builder = builder.with_region(r);
        }
        if let Some(e) = &config.endpoint {
            builder = builder.with_endpoint(e);
        }
        let store = builder.build().map_err(|e| MapError::InvalidInput {
            field: "store.backend".into(),
            reason: format!("cannot configure S3: {e}"),
        })?;
        Self::new(Arc::new(store), &format!("s3://{}", config.bucket), &config.prefix, cache_root, compact_every)
    }

    /// Any object store with conditional PUTs; `url` names it in messages, maps go under `<prefix>/maps/`.
    pub fn new(
        store: Arc<dyn ObjectStore>,
        url: &str,
        prefix: &str,
        cache_root: &Path,
        compact_every: usize,
    ) -> Result<Self, MapError> {
        let prefix = ObjectPath::parse(prefix)
            .map_err(|e| MapError::InvalidInput { field: "store.backend.prefix".into(), reason: e.to_string() })?;
        std::fs::create_dir_all(cache_root).map_err(io_err(cache_root))?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("scone-objects")
            .enable_all()
            .build()
            .map_err(|source| MapError::Io { path: PathBuf::from(url), source })?;
        Ok(Self {
            shared: Arc::new(Shared {
                store,
                url: url.trim_end_matches('/').to_string(),
                root: prefix.join("maps"),
                cache_root: cache_root.to_path_buf(),
                compact_every,
                writer: writer_id(),
                ops: OpCounters::default(),
                runtime: Some(runtime),
                fetching: Default::default(),
            }),
        })
    }

    /// This process's writer id (recorded in the manifests it writes).
    pub fn writer(&self) -> &str {
        &self.shared.writer
    }

    /// The snapshot object `path` (`object` in the manifest) as a map, its keyframes' payloads read from a
    /// copy in `cache_dir`. Formats 3 and 4 (the payloads read in the snapshot's own encoding): the header and the core by ranged GETs, so the map is ready once its
    /// core is; the payload section is still to arrive in the file returned with it
    /// ([`PayloadFile::arriving`]: a read of a payload before it is there fetches it or waits for it). Older
    /// formats: the whole object, its copy written in the current format.
    fn open_snapshot(
        &self,
        path: &ObjectPath,
        object: &str,
        cache_dir: &Path,
    ) -> Result<(MapData, Option<Arc<PayloadFile>>), MapError> {
        let s = &self.shared;
        let fetch_error = |e| s.named_error(path, e);
        let size = s.block_on(s.head(path)).map_err(fetch_error)?.size;
        let first = match size.min(SplitLayout::HEADER_LEN) {
            0 => Vec::new(),
            n => s.block_on(s.get_range(path, 0..n)).map_err(fetch_error)?,
        };
        let name = s.name(path);
        let Some(layout) = split_layout(&first, size, &name)? else {
            return Ok((self.open_whole_snapshot(path, object, cache_dir)?, None));
        };
        let core = s.block_on(s.get_range(path, layout.core())).map_err(fetch_error)?;
        let (copy, handle) = s.copy_snapshot(cache_dir, object, size, &[(0, &first), (layout.core().start, &core)])?;
        let mut arriving = None;
        let data = map_from_core(&layout, &core, &name, |spans| {
            let fetch = fetch_section(Arc::clone(s), path.clone(), layout, spans, handle, copy.clone());
            let file =
                PayloadFile::arriving(&copy, layout.section().start, layout.section_len, layout.encoding(), fetch)?;
            arriving = Some(Arc::clone(&file));
            Ok(file)
        })?;
        Ok((data, arriving))
    }

    /// A format-1/2 snapshot object: fetched and decoded whole, its copy in `cache_dir` written in the current
    /// format (the payloads leave memory). The bucket's objects are left to the writer, whose next compaction
    /// rewrites them (a replica that rewrote them would fence it).
    fn open_whole_snapshot(&self, path: &ObjectPath, object: &str, cache_dir: &Path) -> Result<MapData, MapError> {
        let s = &self.shared;
        let (bytes, _) = s.block_on(s.get(path)).map_err(|e| s.named_error(path, e))?;
        let mut data = decode_snapshot(&bytes, &s.name(path))?;
        drop(bytes);
        let encoded = encode_snapshot_spans(&data)?;
        let copy = s.keep_snapshot(cache_dir, object, &encoded.bytes)?;
        data.store_payloads(&stored_payloads(&copy, &encoded, data.version)?);
        Ok(data)
    }
}

/// What fetches a format-3 snapshot's payload section (`layout`) from the object at `path` into its copy
/// (`file`, at `copy`) as it arrives, then checks every payload's span and CRC (`spans`) there.
fn fetch_section(
    s: Arc<Shared>,
    path: ObjectPath,
    layout: SplitLayout,
    spans: Vec<Span>,
    file: std::fs::File,
    copy: PathBuf,
) -> FetchSection {
    Box::new(move || {
        use std::os::unix::fs::FileExt;
        let section = layout.section();
        let got = s.block_on(s.get_range_into(&path, section.clone(), &file, section.start, &copy))?;
        if got != layout.section_len {
            let reason = format!("payload section of {got} bytes, the header says {}", layout.section_len);
            return Err(s.corrupt(&path, reason));
        }
        let mut bytes = Vec::new();
        for span in &spans {
            let at = section.start + span.offset;
            let checked = span.offset.checked_add(span.len).filter(|&end| end <= layout.section_len).is_some() && {
                bytes.resize(span.len as usize, 0);
                file.read_exact_at(&mut bytes, at).map_err(io_err(&copy))?;
                crc32fast::hash(&bytes) == span.crc
            };
            if !checked {
                return Err(s.corrupt(&path, format!("payload at byte {at}: bad span or checksum")));
            }
        }
        Ok(())
    })
}

impl MapBackend for ObjectStorageBackend {
    fn location(&self) -> String {
        format!("{}/{}", self.shared.url, self.shared.root)
    }

    fn is_remote(&self) -> bool {
        true
    }

    /// Maps are the prefixes with a manifest (a prefix without one is a create or delete that did not finish).
    fn list(&self) -> Result<Vec<String>, MapError> {
        let s = &self.shared;
        let objects = s.block_on(s.list_under(&s.root)).map_err(|e| s.io(&s.root, e))?;
        let depth = s.root.parts().count();
        let mut ids: Vec<String> = objects
            .iter()
            .filter_map(|o| {
                let parts: Vec<_> = o.parts().skip(depth).collect();
                match parts.as_slice() {
                    [id, file] if file.as_ref() == MANIFEST && validate_map_id(id.as_ref()).is_ok() => {
                        Some(id.as_ref().to_string())
                    }
                    _ => None,
                }
            })
            .collect();
        ids.sort();
        ids.dedup();
        Ok(ids)
    }

    fn exists(&self, id: &str) -> Result<bool, MapError> {
        let s = &self.shared;
        let path = s.object(id, MANIFEST);
        match s.block_on(s.head(&path)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(s.io(&path, e)),
        }
    }

    /// Snapshot first, then the manifest with create-only semantics: of two creators, one gets MapExists.
    fn create(&self, id: &str, data: &MapData) -> Result<Box<dyn MapJournal>, MapError> {
        let s = &self.shared;
        let snapshot = format!("snapshots/{:020}-{}.bin", data.version, nonce());
        let snapshot_path = s.object(id, &snapshot);
        let encoded = encode_snapshot_spans(data)?;
        s.block_on(s.put(&snapshot_path, encoded.bytes.clone(), PutMode::Create))
            .map_err(|e| s.io(&snapshot_path, e))?;
        let manifest = Manifest {
            format_version: FORMAT_VERSION,
            map_uid: format!("{:016x}{:016x}", rand::random::<u64>(), rand::random::<u64>()),
            writer: s.writer.clone(),
            snapshot: SnapshotRef { object: snapshot, version: data.version },
            segments: Vec::new(),
            next_seq: data.version + 1,
            stats: Some(data.stats()),
            index: None,
        };
        let bytes = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
        let manifest_path = s.object(id, MANIFEST);
        let version = match s.block_on(s.put(&manifest_path, bytes, PutMode::Create)) {
            Ok(v) => v,
            Err(e) => {
                s.block_on(s.delete_quietly(vec![snapshot_path]));
                return Err(match e {
                    object_store::Error::AlreadyExists { .. } => MapError::MapExists { map: id.to_string() },
                    e => s.io(&manifest_path, e),
                });
            }
        };
        let cache_dir = s.claim_cache(id, &manifest.map_uid)?;
        let copy = s.keep_snapshot(&cache_dir, &manifest.snapshot.object, &encoded.bytes)?;
        let mut journal = ObjectJournal::new(s, id, manifest, version, cache_dir);
        journal.stored = Some(stored_payloads(&copy, &encoded, data.version)?);
        Ok(Box::new(journal))
    }

    fn open(&self, id: &str) -> Result<(MapData, Box<dyn MapJournal>, LoadReport), MapError> {
        let s = &self.shared;
        let Some((manifest, _, version)) = s.block_on(s.read_manifest(id))? else {
            return Err(MapError::UnknownMap { map: id.to_string() });
        };
        let snapshot_path = s.object(id, &manifest.snapshot.object);
        let cache_dir = s.claim_cache(id, &manifest.map_uid)?;
        let (mut data, arriving) = self.open_snapshot(&snapshot_path, &manifest.snapshot.object, &cache_dir)?;
        if data.version != manifest.snapshot.version {
            return Err(s.corrupt(
                &snapshot_path,
                format!("holds version {}, the manifest says {}", data.version, manifest.snapshot.version),
            ));
        }
        let fetched = s.fetch_all(id, &manifest.segments)?;
        let mut report = LoadReport::default();
        for (path, bytes) in fetched {
            let (seq, record) = decode_segment(&bytes, &s.name(&path))?;
            if seq != data.version + 1 || number_of(path.as_ref()) != Some(seq) {
                return Err(s.corrupt(&path, format!("holds record {seq}, expected {}", data.version + 1)));
            }
            data.check(&record).map_err(|reason| s.corrupt(&path, format!("record {seq}: {reason}")))?;
            data.apply(&record)?;
            report.replayed += 1;
        }
        if let Some(index) = &manifest.index {
            if let Err(e) = s.block_on(s.fetch_index(id, index, &cache_dir)) {
                tracing::warn!(map = %id, error = %e, "cannot download the index dump; it is rebuilt");
            }
        }
        if let Some(file) = arriving {
            // The payload section arrives on a thread of its own; without one, the first read of a payload
            // fetches it.
            let map = id.to_string();
            let fetched = std::thread::Builder::new().name("scone-payloads".into()).spawn(move || {
                if let Err(e) = file.arrive() {
                    tracing::warn!(%map, error = %e, "cannot fetch the payload section; a read of a payload tries again");
                }
            });
            drop(fetched);
        }
        Ok((data, Box::new(ObjectJournal::new(s, id, manifest, version, cache_dir)), report))
    }

    /// The manifest first (the map is gone for every reader and writer from then on), then every object under
    /// the map's prefix, then the local cache.
    fn delete(&self, id: &str) -> Result<(), MapError> {
        let s = &self.shared;
        let manifest_path = s.object(id, MANIFEST);
        match s.block_on(s.delete_one(&manifest_path)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
            Err(e) => return Err(s.io(&manifest_path, e)),
        }
        let prefix = s.map_prefix(id);
        let rest = s.block_on(s.list_under(&prefix)).map_err(|e| s.io(&prefix, e))?;
        s.block_on(s.delete_quietly(rest));
        let cache = s.cache_dir(id);
        if cache.exists() {
            std::fs::remove_dir_all(&cache).map_err(io_err(&cache))?;
        }
        Ok(())
    }

    /// The map's cache directory (claimed for the manifest's map now) and the download of the dump its
    /// manifest names (unless it is there already), which the store runs beside the open, so that the
    /// dump's and the snapshot's downloads overlap, and the graph is read while the snapshot decodes. The
    /// open's own fetch of the dump waits for this one and then finds it in place. `None` when the map has
    /// no dump or the manifest cannot be read; a failed download makes the open fetch it as before. Whatever
    /// changes in between (another writer's compaction, the map deleted and made again) is caught where the
    /// graph is checked against the map data, and rebuilt.
    fn index_before_open(&self, id: &str) -> Option<EarlyIndex> {
        let s = &self.shared;
        let (manifest, _, _) = s.block_on(s.read_manifest(id)).ok()??;
        let index = manifest.index?;
        let dir = s.claim_cache(id, &manifest.map_uid).ok()?;
        let (shared, id, cache_dir) = (Arc::clone(s), id.to_string(), dir.clone());
        let fetch = move || match shared.block_on(shared.fetch_index(&id, &index, &cache_dir)) {
            Ok(()) => true,
            Err(e) => {
                tracing::debug!(map = %id, error = %e, "index dump not fetched before the open");
                false
            }
        };
        Some(EarlyIndex { dir, fetch: Some(Box::new(fetch)) })
    }

    /// The ids, then every manifest (in parallel) for the counts it records. A manifest that cannot be read
    /// or has no counts gives `None`: the store loads that map to tell (and holds it back if it is corrupt).
    fn list_stats(&self) -> Result<Vec<(String, Option<MapStats>)>, MapError> {
        let s = &self.shared;
        let ids = self.list()?;
        Ok(s.block_on(
            futures_util::stream::iter(ids.into_iter().map(|id| async move {
                let stats = match s.read_manifest(&id).await {
                    Ok(m) => m.and_then(|(m, _, _)| m.stats),
                    Err(e) => {
                        tracing::warn!(map = %id, error = %e, "cannot read the manifest for the listing");
                        None
                    }
                };
                (id, stats)
            }))
            .buffered(PARALLEL_GETS)
            .collect::<Vec<_>>(),
        ))
    }

    fn operation_stats(&self) -> Vec<OperationStats> {
        let ops = &self.shared.ops;
        OPS.iter()
            .map(|&(op, name)| {
                let i = op as usize;
                OperationStats {
                    operation: name,
                    calls: ops.calls[i].load(Ordering::Relaxed),
                    errors: ops.errors[i].load(Ordering::Relaxed),
                    seconds: ops.nanos[i].load(Ordering::Relaxed) as f64 * 1e-9,
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::model::MapMeta;
    use crate::map::model::Record;
    use crate::map::storage::format::encode_segment;
    use crate::map::tests::keyframe_record;
    use crate::test_dir::temp_dir;
    use futures_util::TryStreamExt;
    use object_store::memory::InMemory;
    use object_store::ObjectStoreExt;

    fn backend(store: &Arc<InMemory>, cache: &Path, compact_every: usize) -> ObjectStorageBackend {
        let store: Arc<dyn ObjectStore> = Arc::clone(store) as Arc<dyn ObjectStore>;
        ObjectStorageBackend::new(store, "memory://", "test/prefix", cache, compact_every).unwrap()
    }

    fn empty(id: &str) -> MapData {
        MapData::new(MapMeta { id: id.into(), model_id: "sha256:test".into(), k: 20, dim: 8, created_unix_ms: 1 })
    }

    fn write(j: &mut dyn MapJournal, data: &mut MapData, r: Record) -> Result<(), MapError> {
        data.check(&r).unwrap();
        j.append(data.version + 1, &r, &data.stats_after(&r))?;
        data.apply(&r).unwrap();
        Ok(())
    }

    fn keys(store: &InMemory, under: &str) -> Vec<String> {
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let mut v: Vec<String> = rt
            .block_on(
                store.list(Some(&ObjectPath::from(under))).map_ok(|o| o.location.to_string()).try_collect::<Vec<_>>(),
            )
            .unwrap();
        v.sort();
        v
    }

    #[test]
    fn writes_reload_equal_and_compaction_collects_garbage() {
        let mem = Arc::new(InMemory::new());
        let cache = temp_dir("objects-cache");
        let b = backend(&mem, &cache, 3);
        let mut data = empty("m");
        let mut j = b.create("m", &data).unwrap();
        for i in 0..4u64 {
            write(j.as_mut(), &mut data, keyframe_record(i, 5, i * 10, 8, i)).unwrap();
        }
        assert!(j.wants_compaction());
        assert_eq!(b.list().unwrap(), vec!["m".to_string()]);
        let (loaded, _, report) = b.open("m").unwrap();
        assert_eq!((loaded == data, report.replayed), (true, 4));
        j.compact(&data).unwrap();
        let objects = keys(&mem, "test/prefix/maps/m");
        assert_eq!(objects.len(), 2, "only the manifest and the new snapshot stay: {objects:?}");
        write(j.as_mut(), &mut data, keyframe_record(9, 5, 90, 8, 9)).unwrap();
        let (loaded, _, report) = b.open("m").unwrap();
        assert_eq!((loaded == data, report.replayed), (true, 1));
        assert!(j.index_dir().starts_with(&cache));
        // A second create of the same id is refused and leaves the map as it was.
        assert!(matches!(b.create("m", &empty("m")), Err(MapError::MapExists { .. })));
        assert_eq!(b.open("m").unwrap().0, data);
        b.delete("m").unwrap();
        assert!(b.list().unwrap().is_empty() && keys(&mem, "test/prefix").is_empty());
        assert!(!b.exists("m").unwrap());
    }

    #[test]
    fn a_second_writer_is_fenced_and_changes_nothing() {
        let mem = Arc::new(InMemory::new());
        let cache = temp_dir("objects-fence");
        let (a, b) = (backend(&mem, &cache.join("a"), 0), backend(&mem, &cache.join("b"), 0));
        let mut data_a = empty("m");
        drop(a.create("m", &data_a).unwrap());
        let (mut data_b, mut jb, _) = b.open("m").unwrap();
        let (_, mut ja, _) = a.open("m").unwrap();
        write(ja.as_mut(), &mut data_a, keyframe_record(1, 4, 0, 8, 1)).unwrap();
        let before = keys(&mem, "test/prefix");
        let e = write(jb.as_mut(), &mut data_b, keyframe_record(2, 4, 0, 8, 2)).unwrap_err();
        match &e {
            MapError::WriterConflict { map, writer } => assert_eq!((map.as_str(), writer.as_str()), ("m", a.writer())),
            other => panic!("{other}"),
        }
        assert_eq!(keys(&mem, "test/prefix"), before, "the fenced writer left no object behind");
        assert!(matches!(
            jb.append(1, &keyframe_record(3, 4, 0, 8, 3), &MapStats::default()),
            Err(MapError::WriterConflict { .. })
        ));
        assert!(matches!(jb.compact(&data_b), Err(MapError::WriterConflict { .. })));
        assert_eq!(a.open("m").unwrap().0, data_a);
    }

    #[test]
    fn an_orphan_segment_is_ignored_and_a_bad_one_names_the_object() {
        let mem = Arc::new(InMemory::new());
        let cache = temp_dir("objects-orphan");
        let b = backend(&mem, &cache, 0);
        let mut data = empty("m");
        let mut j = b.create("m", &data).unwrap();
        write(j.as_mut(), &mut data, keyframe_record(1, 4, 0, 8, 1)).unwrap();
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        // A crash between the segment PUT and the manifest PUT leaves this behind.
        let orphan = ObjectPath::from("test/prefix/maps/m/segments/00000000000000000002-00000000000000ff.rec");
        let bytes = encode_segment(2, &keyframe_record(2, 4, 4, 8, 2)).unwrap();
        rt.block_on(mem.put(&orphan, bytes.into())).unwrap();
        assert_eq!(b.open("m").unwrap().0, data);
        write(j.as_mut(), &mut data, keyframe_record(3, 4, 8, 8, 3)).unwrap();
        assert_eq!(b.open("m").unwrap().0, data);
        // Damage the first named segment.
        let seg = keys(&mem, "test/prefix/maps/m/segments")
            .into_iter()
            .find(|k| k.contains("00000000000000000001-"))
            .unwrap();
        let path = ObjectPath::from(seg.as_str());
        let mut bytes = rt.block_on(async { mem.get(&path).await.unwrap().bytes().await.unwrap() }).to_vec();
        let last = bytes.len() - 1;
        bytes[last] ^= 0xff;
        rt.block_on(mem.put(&path, bytes.into())).unwrap();
        let e = b.open("m").unwrap_err().to_string();
        assert!(e.contains(&seg) && e.contains("checksum"), "{e}");
    }

    /// The store's methods run on `spawn_blocking` threads in the server: `block_on` works there.
    #[test]
    fn the_backend_can_be_called_from_spawn_blocking() {
        let mem = Arc::new(InMemory::new());
        let cache = temp_dir("objects-blocking");
        let b = Arc::new(backend(&mem, &cache, 0));
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).build().unwrap();
        let b2 = Arc::clone(&b);
        let listed = rt.block_on(async move { tokio::task::spawn_blocking(move || b2.list()).await.unwrap() });
        assert!(listed.unwrap().is_empty());
        // Dropping the backend inside an async context must not panic either.
        rt.block_on(async move { drop(b) });
    }

    #[test]
    #[should_panic(expected = "Cannot start a runtime from within a runtime")]
    fn calling_the_backend_on_an_async_worker_panics() {
        let mem = Arc::new(InMemory::new());
        let cache = temp_dir("objects-async");
        let b = backend(&mem, &cache, 0);
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        rt.block_on(async move {
            let _ = b.list();
        });
    }
}
