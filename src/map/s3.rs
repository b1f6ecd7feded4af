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
//!   ([`encode_snapshot`]), written once.
//! * `segments/<seq:020>-<nonce:016x>.rec`: one record each, with the local log's framing and CRC
//!   ([`encode_segment`]), written once.
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

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use futures_util::{StreamExt, TryStreamExt};
use object_store::aws::{AmazonS3Builder, S3ConditionalPut};
use object_store::path::Path as ObjectPath;
use object_store::{
    GetOptions, ObjectMeta, ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload, UpdateVersion,
};
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::format::{
    decode_segment, decode_snapshot, encode_segment, encode_snapshot, io_err, io_error, readable_version, write_atomic,
    FORMAT_VERSION, OLDEST_FORMAT_VERSION,
};
use crate::map::index::{install_dump, read_dump, DumpBytes, DUMP_MANIFEST};
use crate::map::journal::{Freshness, LoadReport, MapBackend, MapJournal, OperationStats};
use crate::map::model::{validate_map_id, MapData, MapStats, Record};

/// Largest manifest accepted when reading (a guard against a hostile or broken object).
const MAX_MANIFEST_BYTES: u64 = 16 << 20;
/// Segments fetched at once when loading a map.
const PARALLEL_GETS: usize = 16;
const MANIFEST: &str = "manifest.json";
const CACHE_MARKER: &str = "map.json";
/// The objects of an index dump ([`EmbeddingIndex::dump`](crate::map::index::EmbeddingIndex::dump)) under
/// `index/<version>-<nonce>/`: the graph file, the data file and the manifest (which names the base the files
/// take in a local directory). The manifest goes last on upload and is compared first on download.
const INDEX_FILES: [&str; 3] = ["index.hnsw.graph", "index.hnsw.data", "index.json"];

/// Settings of the S3 backend.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct S3Config {
    pub bucket: String,
    /// Key prefix inside the bucket; maps live under `<prefix>/maps/<id>/`.
    #[serde(default)]
    pub prefix: String,
    /// Region; when absent, `AWS_REGION` / `AWS_DEFAULT_REGION`, else `us-east-1`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<String>,
    /// Endpoint URL of an S3-compatible service (path-style requests); AWS when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub endpoint: Option<String>,
    /// Permit a plain-HTTP endpoint (tests, a service inside the cluster network).
    #[serde(default)]
    pub allow_http: bool,
    /// Local cache of index dumps, one sub-directory per map; `store.data_dir/cache` when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_dir: Option<PathBuf>,
}

/// Where the S3 credentials come from.
#[derive(Clone)]
pub enum S3Credentials {
    /// The standard AWS environment variables (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
    /// `AWS_SESSION_TOKEN`, web identity, container credentials, ...), as the AWS SDKs read them.
    FromEnv,
    /// Given keys (tests against an emulator).
    Static { access_key_id: String, secret_access_key: String },
}

impl std::fmt::Debug for S3Credentials {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::FromEnv => f.write_str("FromEnv"),
            Self::Static { .. } => f.write_str("Static([redacted])"),
        }
    }
}

/// The map's manifest: the one object that changes, only by conditional PUTs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Manifest {
    format_version: u32,
    /// Random, fixed when the map is created: tells this map from an earlier one with the same id.
    map_uid: String,
    /// The writer that wrote this manifest (host, process, random).
    writer: String,
    snapshot: SnapshotRef,
    /// Segment objects (relative to the map's prefix) holding versions `snapshot.version + 1 ..`, in order.
    segments: Vec<String>,
    next_seq: u64,
    /// The map's counts at `next_seq - 1`, so replicas list maps they have not loaded (absent in manifests
    /// written before they were recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stats: Option<MapStats>,
    /// The HNSW index dump of the snapshot, uploaded with it (absent while the map is below the exact-search
    /// threshold, or written before dumps were uploaded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    index: Option<IndexRef>,
}

/// An index dump in the bucket: the directory (relative to the map's prefix) holding [`INDEX_FILES`], and
/// the map version it was dumped at.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct IndexRef {
    dir: String,
    version: u64,
}

impl Manifest {
    /// Whether this manifest names the object (or index directory) `relative` to the map's prefix.
    fn names(&self, relative: &str) -> bool {
        self.snapshot.object == relative
            || self.segments.iter().any(|s| s == relative)
            || self.index.as_ref().is_some_and(|ix| ix.dir == relative || relative.starts_with(&format!("{}/", ix.dir)))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct SnapshotRef {
    object: String,
    version: u64,
}

/// Sequence number or version encoded at the start of an object's file name (`<n:020>-<nonce>.<ext>`).
fn number_of(name: &str) -> Option<u64> {
    let file = name.rsplit('/').next()?;
    file.get(..20)?.parse().ok()
}

fn nonce() -> String {
    format!("{:016x}", rand::random::<u64>())
}

/// The kinds of call made to the object store, as `/metrics` labels them.
#[derive(Debug, Clone, Copy)]
enum Op {
    Get,
    Put,
    Head,
    List,
    Delete,
}

const OPS: [(Op, &str); 5] =
    [(Op::Get, "get"), (Op::Put, "put"), (Op::Head, "head"), (Op::List, "list"), (Op::Delete, "delete")];

/// Calls, failures and time per [`Op`] since start. Answers that are outcomes of the protocol (not found,
/// not modified, a failed condition, already exists) are calls, not failures.
#[derive(Default)]
struct OpCounters {
    calls: [AtomicU64; 5],
    errors: [AtomicU64; 5],
    nanos: [AtomicU64; 5],
}

/// State shared by the backend and its journals: the object store and the runtime that drives it.
struct Shared {
    store: Arc<dyn ObjectStore>,
    /// `s3://bucket` (or another scheme), to name objects in messages.
    url: String,
    /// `<prefix>/maps`
    root: ObjectPath,
    cache_root: PathBuf,
    compact_every: usize,
    /// This process's writer id, recorded in every manifest it writes.
    writer: String,
    ops: OpCounters,
    runtime: Option<tokio::runtime::Runtime>,
}

impl Drop for Shared {
    fn drop(&mut self) {
        // Dropping a runtime blocks, which tokio forbids inside an async context (the store may be dropped on
        // an async thread at shutdown); nothing is in flight once the last user is gone.
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl Shared {
    /// Runs `f` to completion on the backend's runtime. Panics (tokio's own message) on an async worker.
    fn block_on<F: Future>(&self, f: F) -> F::Output {
        self.runtime.as_ref().expect("the runtime lives until drop").block_on(f)
    }

    fn map_prefix(&self, id: &str) -> ObjectPath {
        self.root.clone().join(id)
    }

    fn object(&self, id: &str, relative: &str) -> ObjectPath {
        let mut p = self.map_prefix(id);
        for part in relative.split('/') {
            p = p.join(part);
        }
        p
    }

    /// `s3://bucket/key`, for errors and logs.
    fn name(&self, path: &ObjectPath) -> PathBuf {
        PathBuf::from(format!("{}/{}", self.url, path))
    }

    fn io(&self, path: &ObjectPath, e: object_store::Error) -> MapError {
        MapError::Io { path: self.name(path), source: std::io::Error::other(e) }
    }

    fn corrupt(&self, path: &ObjectPath, reason: impl Into<String>) -> MapError {
        MapError::Corrupt { path: self.name(path), reason: reason.into() }
    }

    fn cache_dir(&self, id: &str) -> PathBuf {
        self.cache_root.join(id)
    }

    /// Awaits one call to the object store, counting it under `op`.
    async fn timed<T>(
        &self,
        op: Op,
        call: impl Future<Output = Result<T, object_store::Error>>,
    ) -> Result<T, object_store::Error> {
        let t = Instant::now();
        let r = call.await;
        let i = op as usize;
        self.ops.calls[i].fetch_add(1, Ordering::Relaxed);
        self.ops.nanos[i].fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        if let Err(e) = &r {
            use object_store::Error as E;
            if !matches!(
                e,
                E::NotFound { .. } | E::NotModified { .. } | E::Precondition { .. } | E::AlreadyExists { .. }
            ) {
                self.ops.errors[i].fetch_add(1, Ordering::Relaxed);
            }
        }
        r
    }

    async fn get(&self, path: &ObjectPath) -> Result<(Vec<u8>, UpdateVersion), object_store::Error> {
        self.get_with(path, GetOptions::default()).await
    }

    async fn get_with(
        &self,
        path: &ObjectPath,
        options: GetOptions,
    ) -> Result<(Vec<u8>, UpdateVersion), object_store::Error> {
        self.timed(Op::Get, async {
            let r = self.store.get_opts(path, options).await?;
            let version = UpdateVersion { e_tag: r.meta.e_tag.clone(), version: r.meta.version.clone() };
            Ok((r.bytes().await?.to_vec(), version))
        })
        .await
    }

    /// A GET conditional on the object's ETag no longer being `known`: `None` when it still is.
    async fn get_changed(
        &self,
        path: &ObjectPath,
        known: String,
    ) -> Result<Option<(Vec<u8>, UpdateVersion)>, object_store::Error> {
        match self.get_with(path, GetOptions { if_none_match: Some(known), ..Default::default() }).await {
            Ok(got) => Ok(Some(got)),
            Err(object_store::Error::NotModified { .. }) => Ok(None),
            Err(e) => Err(e),
        }
    }

    async fn put(
        &self,
        path: &ObjectPath,
        bytes: Vec<u8>,
        mode: PutMode,
    ) -> Result<UpdateVersion, object_store::Error> {
        // Fault injection for the durability tests (fail point `s3-put`, argument: part of the key).
        if crate::map::format::injected("s3-put", Path::new(path.as_ref())) {
            let source = Box::new(std::io::Error::other(format!("injected fault: PUT {path} failed")));
            return Err(object_store::Error::Generic { store: "S3", source });
        }
        let r = self.timed(Op::Put, self.store.put_opts(path, PutPayload::from(bytes), PutOptions::from(mode))).await?;
        Ok(UpdateVersion { e_tag: r.e_tag, version: r.version })
    }

    async fn head(&self, path: &ObjectPath) -> Result<ObjectMeta, object_store::Error> {
        self.timed(Op::Head, self.store.head(path)).await
    }

    /// Every object under `prefix`.
    async fn list_under(&self, prefix: &ObjectPath) -> Result<Vec<ObjectPath>, object_store::Error> {
        self.timed(Op::List, self.store.list(Some(prefix)).map_ok(|o| o.location).try_collect::<Vec<_>>()).await
    }

    async fn delete_one(&self, path: &ObjectPath) -> Result<(), object_store::Error> {
        self.timed(Op::Delete, self.store.delete(path)).await
    }

    /// Deletes objects, logging (not failing on) what could not be deleted.
    async fn delete_quietly(&self, paths: Vec<ObjectPath>) {
        if paths.is_empty() {
            return;
        }
        let t = Instant::now();
        let n = paths.len() as u64;
        let results: Vec<_> =
            self.store.delete_stream(futures_util::stream::iter(paths.into_iter().map(Ok)).boxed()).collect().await;
        let i = Op::Delete as usize;
        self.ops.calls[i].fetch_add(n, Ordering::Relaxed);
        self.ops.nanos[i].fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
        for r in results {
            match r {
                Ok(_) | Err(object_store::Error::NotFound { .. }) => {}
                Err(e) => {
                    self.ops.errors[i].fetch_add(1, Ordering::Relaxed);
                    tracing::warn!(error = %e, "could not delete a replaced object; it stays as garbage")
                }
            }
        }
    }

    /// Reads and checks a manifest (`None` when there is none).
    async fn read_manifest(&self, id: &str) -> Result<Option<(Manifest, Vec<u8>, UpdateVersion)>, MapError> {
        let path = self.object(id, MANIFEST);
        let meta = match self.head(&path).await {
            Ok(m) => m,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.io(&path, e)),
        };
        if meta.size > MAX_MANIFEST_BYTES {
            return Err(self.corrupt(&path, format!("manifest of {} bytes", meta.size)));
        }
        let (bytes, version) = match self.get(&path).await {
            Ok(r) => r,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.io(&path, e)),
        };
        let manifest = self.parse_manifest(id, &bytes)?;
        Ok(Some((manifest, bytes, version)))
    }

    fn parse_manifest(&self, id: &str, bytes: &[u8]) -> Result<Manifest, MapError> {
        let path = self.object(id, MANIFEST);
        let m: Manifest =
            serde_json::from_slice(bytes).map_err(|e| self.corrupt(&path, format!("cannot parse: {e}")))?;
        if !readable_version(m.format_version) {
            return Err(self.corrupt(
                &path,
                format!(
                    "manifest format version {}, this build reads {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}",
                    m.format_version
                ),
            ));
        }
        let named = |name: &str, dir: &str| {
            name.strip_prefix(dir).is_some_and(|f| !f.contains('/')) && ObjectPath::parse(name).is_ok()
        };
        if !named(&m.snapshot.object, "snapshots/") || number_of(&m.snapshot.object) != Some(m.snapshot.version) {
            return Err(self.corrupt(&path, format!("bad snapshot reference '{}'", m.snapshot.object)));
        }
        for (i, s) in m.segments.iter().enumerate() {
            if !named(s, "segments/") || number_of(s) != Some(m.snapshot.version + 1 + i as u64) {
                return Err(self.corrupt(&path, format!("segment {i} '{s}' is out of sequence")));
            }
        }
        if let Some(ix) = &m.index {
            let dir_ok = ix.dir.strip_prefix("index/").is_some_and(|d| !d.is_empty() && !d.contains('/'));
            if !dir_ok || number_of(&ix.dir) != Some(ix.version) || ObjectPath::parse(&ix.dir).is_err() {
                return Err(self.corrupt(&path, format!("bad index reference '{}'", ix.dir)));
            }
        }
        if m.next_seq != m.snapshot.version + 1 + m.segments.len() as u64 {
            return Err(self.corrupt(&path, format!("next_seq {} does not follow the segments", m.next_seq)));
        }
        Ok(m)
    }

    /// The objects a manifest names (relative to the map's prefix), fetched [`PARALLEL_GETS`] at a time, in
    /// order; a missing one is corruption (the manifest names it).
    fn fetch_all(&self, id: &str, names: &[String]) -> Result<Vec<(ObjectPath, Vec<u8>)>, MapError> {
        let paths: Vec<ObjectPath> = names.iter().map(|name| self.object(id, name)).collect();
        self.block_on(
            futures_util::stream::iter(paths.into_iter().map(|p| async move {
                match self.get(&p).await {
                    Ok((bytes, _)) => Ok((p, bytes)),
                    Err(object_store::Error::NotFound { .. }) => {
                        Err(self.corrupt(&p, "named by the manifest but missing"))
                    }
                    Err(e) => Err(self.io(&p, e)),
                }
            }))
            .buffered(PARALLEL_GETS)
            .try_collect(),
        )
    }

    /// Puts the index dump the manifest names into the map's cache directory, unless the dump there is that
    /// one already (same `index.json`, which holds the files' checksums). The files are written atomically,
    /// `index.json` last ([`install_dump`]); the index loader checks the dump against the map, so one that
    /// does not match is rebuilt.
    async fn fetch_index(&self, id: &str, index: &IndexRef, cache_dir: &Path) -> Result<(), MapError> {
        let remote = |file: &str| self.object(id, &format!("{}/{file}", index.dir));
        let manifest_path = remote(INDEX_FILES[2]);
        let (manifest, _) = self.get(&manifest_path).await.map_err(|e| self.io(&manifest_path, e))?;
        if std::fs::read(cache_dir.join(DUMP_MANIFEST)).ok().as_deref() == Some(manifest.as_slice()) {
            return Ok(());
        }
        let mut files = Vec::with_capacity(2);
        for file in &INDEX_FILES[..2] {
            let path = remote(file);
            files.push(self.get(&path).await.map_err(|e| self.io(&path, e))?.0);
        }
        let data = files.pop().expect("two files");
        let graph = files.pop().expect("two files");
        install_dump(cache_dir, &DumpBytes { manifest, graph, data })
    }

    /// Uploads the index dump in `cache_dir` (when there is one) under a new `index/<version>-<nonce>/`, the
    /// manifest last.
    async fn upload_index(&self, id: &str, version: u64, cache_dir: &Path) -> Result<Option<IndexRef>, MapError> {
        let Some(dump) = read_dump(cache_dir) else {
            return Ok(None);
        };
        let dir = format!("index/{version:020}-{}", nonce());
        for (file, bytes) in INDEX_FILES.into_iter().zip([dump.graph, dump.data, dump.manifest]) {
            let path = self.object(id, &format!("{dir}/{file}"));
            self.put(&path, bytes, PutMode::Create).await.map_err(|e| self.io(&path, e))?;
        }
        Ok(Some(IndexRef { dir, version }))
    }

    /// Makes the cache directory of a map belong to this incarnation of it (`map_uid`), emptying it otherwise.
    fn claim_cache(&self, id: &str, map_uid: &str) -> Result<PathBuf, MapError> {
        let dir = self.cache_dir(id);
        let io = |source| io_error(&dir, source);
        let marker = dir.join(CACHE_MARKER);
        let current = std::fs::read(&marker).ok();
        if current.as_deref() != Some(map_uid.as_bytes()) {
            if dir.exists() {
                std::fs::remove_dir_all(&dir).map_err(io)?;
            }
            std::fs::create_dir_all(&dir).map_err(io)?;
            write_atomic(&marker, map_uid.as_bytes())?;
        }
        Ok(dir)
    }
}

/// Maps in an object store (an S3 bucket in production, [`object_store::memory::InMemory`] in unit tests).
pub struct ObjectStorageBackend {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for ObjectStorageBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectStorageBackend").field("location", &self.location()).finish()
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
        config: &S3Config,
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
            .with_allow_http(config.allow_http);
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
            }),
        })
    }

    /// This process's writer id (recorded in the manifests it writes).
    pub fn writer(&self) -> &str {
        &self.shared.writer
    }
}

impl MapBackend for ObjectStorageBackend {
    fn location(&self) -> String {
        format!("{}/{}", self.shared.url, self.shared.root)
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
        s.block_on(s.put(&snapshot_path, encode_snapshot(data)?, PutMode::Create))
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
        Ok(Box::new(ObjectJournal {
            shared: Arc::clone(s),
            id: id.to_string(),
            manifest,
            version,
            cache_dir,
            fenced: None,
            wrote: false,
        }))
    }

    fn open(&self, id: &str) -> Result<(MapData, Box<dyn MapJournal>, LoadReport), MapError> {
        let s = &self.shared;
        let Some((manifest, _, version)) = s.block_on(s.read_manifest(id))? else {
            return Err(MapError::UnknownMap { map: id.to_string() });
        };
        let snapshot_path = s.object(id, &manifest.snapshot.object);
        let (bytes, _) = s.block_on(s.get(&snapshot_path)).map_err(|e| match e {
            object_store::Error::NotFound { .. } => s.corrupt(&snapshot_path, "named by the manifest but missing"),
            e => s.io(&snapshot_path, e),
        })?;
        let mut data = decode_snapshot(&bytes, &s.name(&snapshot_path))?;
        drop(bytes);
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
            data.apply(&record);
            report.replayed += 1;
        }
        let cache_dir = s.claim_cache(id, &manifest.map_uid)?;
        if let Some(index) = &manifest.index {
            if let Err(e) = s.block_on(s.fetch_index(id, index, &cache_dir)) {
                tracing::warn!(map = %id, error = %e, "cannot download the index dump; it is rebuilt");
            }
        }
        let journal = ObjectJournal {
            shared: Arc::clone(s),
            id: id.to_string(),
            manifest,
            version,
            cache_dir,
            fenced: None,
            wrote: false,
        };
        Ok((data, Box::new(journal), report))
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

/// How a conditional manifest PUT ended.
enum Outcome {
    Written(UpdateVersion),
    /// Someone else's manifest is there (or none: the map was deleted): its writer, and the manifest when it
    /// could be read (it may name what this writer just wrote: another replica that followed this writer's
    /// manifest, whose PUT answer was lost, and appended on top of it).
    Conflict(String, Option<Manifest>),
    /// The stored manifest could not be read back: as a conflict, but nothing written may be deleted.
    Unknown(String),
    /// The PUT failed and the manifest is still the previous one: nothing changed.
    NotWritten(MapError),
}

/// The writer of one map in object storage.
struct ObjectJournal {
    shared: Arc<Shared>,
    id: String,
    /// The manifest as this writer last read or wrote it...
    manifest: Manifest,
    /// ...and its ETag/version, the condition of the next manifest PUT.
    version: UpdateVersion,
    cache_dir: PathBuf,
    /// Set once this writer lost the map (or cannot tell whether it did): the other writer, named in the
    /// [`MapError::WriterConflict`] every later write fails with.
    fenced: Option<String>,
    /// Whether this journal wrote a record: a replica that only loaded the map does not compact it.
    wrote: bool,
}

impl std::fmt::Debug for ObjectJournal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObjectJournal")
            .field("map", &self.id)
            .field("manifest", &self.manifest)
            .field("fenced", &self.fenced)
            .finish()
    }
}

impl ObjectJournal {
    fn check_fence(&self) -> Result<(), MapError> {
        match &self.fenced {
            None => Ok(()),
            Some(writer) => Err(MapError::WriterConflict { map: self.id.clone(), writer: writer.clone() }),
        }
    }

    /// PUTs `next` as the manifest if it is still the one this writer knows, and finds out what happened when
    /// the answer is not clear.
    fn replace_manifest(&self, next: &Manifest) -> Outcome {
        let s = &self.shared;
        let path = s.object(&self.id, MANIFEST);
        let bytes = serde_json::to_vec_pretty(next).expect("manifest serialises");
        let err = match s.block_on(s.put(&path, bytes.clone(), PutMode::Update(self.version.clone()))) {
            Ok(v) => return Outcome::Written(v),
            Err(e) => e,
        };
        let precondition = matches!(err, object_store::Error::Precondition { .. });
        // Read back: a lost response to a PUT that was applied, a rival's manifest, or the previous one.
        match s.block_on(s.get(&path)) {
            Ok((current, v)) if current == bytes => Outcome::Written(v),
            Ok((_, v)) if !precondition && v.e_tag.is_some() && v.e_tag == self.version.e_tag => {
                Outcome::NotWritten(s.io(&path, err))
            }
            Ok((current, _)) => match serde_json::from_slice::<Manifest>(&current) {
                Ok(m) => Outcome::Conflict(m.writer.clone(), Some(m)),
                Err(_) => Outcome::Conflict("unknown (unreadable manifest)".into(), None),
            },
            Err(object_store::Error::NotFound { .. }) => Outcome::Conflict("none (the map was deleted)".into(), None),
            Err(e) => {
                tracing::error!(map = %self.id, error = %e, put_error = %err, "manifest write outcome unknown");
                // Not knowing what the stored manifest names, nothing of this write may be deleted.
                Outcome::Unknown(format!("unknown (the manifest could not be read back: {e})"))
            }
        }
    }

    /// Applies an outcome: success updates the known manifest; anything else cleans up `written` (relative to
    /// the map's prefix) unless the stored manifest names it, and returns the error, fencing the writer on a
    /// conflict.
    fn settle(&mut self, next: Manifest, outcome: Outcome, written: &str) -> Result<(), MapError> {
        let s = Arc::clone(&self.shared);
        let path = s.object(&self.id, written);
        match outcome {
            Outcome::Written(v) => {
                self.manifest = next;
                self.version = v;
                Ok(())
            }
            Outcome::NotWritten(e) => {
                s.block_on(s.delete_quietly(vec![path]));
                Err(e)
            }
            Outcome::Conflict(writer, stored) => {
                if !stored.as_ref().is_some_and(|m| m.names(written)) {
                    s.block_on(s.delete_quietly(vec![path]));
                }
                tracing::error!(map = %self.id, other = %writer, "another writer replaced the manifest: fenced");
                self.fenced = Some(writer.clone());
                Err(MapError::WriterConflict { map: self.id.clone(), writer })
            }
            Outcome::Unknown(writer) => {
                tracing::error!(map = %self.id, other = %writer, "manifest write outcome unknown: fenced");
                self.fenced = Some(writer.clone());
                Err(MapError::WriterConflict { map: self.id.clone(), writer })
            }
        }
    }
}

impl MapJournal for ObjectJournal {
    fn append(&mut self, seq: u64, record: &Record, after: &MapStats) -> Result<(), MapError> {
        self.check_fence()?;
        if seq != self.manifest.next_seq {
            return Err(MapError::Unavailable {
                map: self.id.clone(),
                reason: format!("write {seq} does not follow the stored version {}", self.manifest.next_seq - 1),
            });
        }
        let s = Arc::clone(&self.shared);
        let name = format!("segments/{seq:020}-{}.rec", nonce());
        let path = s.object(&self.id, &name);
        s.block_on(s.put(&path, encode_segment(seq, record)?, PutMode::Create)).map_err(|e| s.io(&path, e))?;
        let mut next = self.manifest.clone();
        // The manifest names an object of this format from now on (objects carry their own versions).
        next.format_version = FORMAT_VERSION;
        next.writer = s.writer.clone();
        next.segments.push(name.clone());
        next.next_seq += 1;
        next.stats = Some(after.clone());
        let outcome = self.replace_manifest(&next);
        self.settle(next, outcome, &name)?;
        self.wrote = true;
        Ok(())
    }

    fn wants_compaction(&self) -> bool {
        self.shared.compact_every > 0 && self.manifest.segments.len() >= self.shared.compact_every
    }

    fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        self.check_fence()?;
        // Nothing to fold, or not this replica's to fold: the writer compacts, a replica that only loaded the
        // map must not replace its manifest (that would fence the writer).
        if !self.wrote || (self.manifest.segments.is_empty() && self.manifest.snapshot.version == data.version) {
            return Ok(());
        }
        if data.version + 1 != self.manifest.next_seq {
            return Err(MapError::Unavailable {
                map: self.id.clone(),
                reason: format!(
                    "snapshot of version {} does not match the stored {}",
                    data.version,
                    self.manifest.next_seq - 1
                ),
            });
        }
        let s = Arc::clone(&self.shared);
        let name = format!("snapshots/{:020}-{}.bin", data.version, nonce());
        let path = s.object(&self.id, &name);
        s.block_on(s.put(&path, encode_snapshot(data)?, PutMode::Create)).map_err(|e| s.io(&path, e))?;
        // The dump is an optimisation for other replicas: a failed upload leaves the map without one.
        let index = s.block_on(s.upload_index(&self.id, data.version, &self.cache_dir)).unwrap_or_else(|e| {
            tracing::warn!(map = %self.id, error = %e, "cannot upload the index dump; replicas will rebuild it");
            None
        });
        let old = self.manifest.clone();
        let mut next = old.clone();
        next.format_version = FORMAT_VERSION;
        next.writer = s.writer.clone();
        next.snapshot = SnapshotRef { object: name.clone(), version: data.version };
        next.segments.clear();
        next.stats = Some(data.stats());
        next.index = index.clone();
        let outcome = self.replace_manifest(&next);
        if let (Some(ix), Outcome::NotWritten(_) | Outcome::Conflict(_, _)) = (&index, &outcome) {
            let stored_names_it = matches!(&outcome, Outcome::Conflict(_, Some(m)) if m.names(&ix.dir));
            if !stored_names_it {
                let files = INDEX_FILES.iter().map(|f| s.object(&self.id, &format!("{}/{f}", ix.dir))).collect();
                s.block_on(s.delete_quietly(files));
            }
        }
        self.settle(next, outcome, &name)?;
        // The new manifest is in place: the replaced objects, and orphans it covers, are garbage. No valid
        // manifest can name a segment numbered <= data.version or a snapshot older than this one again.
        let prefix = s.map_prefix(&self.id);
        let listed: Vec<ObjectPath> = s.block_on(s.list_under(&prefix)).unwrap_or_else(|e| {
            tracing::warn!(map = %self.id, error = %e, "cannot list objects to collect garbage");
            Vec::new()
        });
        let depth = prefix.parts().count();
        let current = s.object(&self.id, &name);
        let current_index = index.as_ref().map(|ix| ix.dir.trim_start_matches("index/").to_string());
        let mut garbage: Vec<ObjectPath> = listed
            .into_iter()
            .filter(|p| {
                let parts: Vec<_> = p.parts().skip(depth).map(|x| x.as_ref().to_string()).collect();
                match parts.as_slice() {
                    [dir, file] if dir == "segments" => number_of(file).is_some_and(|n| n <= data.version),
                    [dir, file] if dir == "snapshots" => {
                        *p != current && number_of(file).is_some_and(|n| n <= data.version)
                    }
                    [dir, sub, _] if dir == "index" => {
                        current_index.as_deref() != Some(sub.as_str())
                            && number_of(sub).is_some_and(|n| n <= data.version)
                    }
                    _ => false,
                }
            })
            .collect();
        garbage.push(s.object(&self.id, &old.snapshot.object));
        garbage.extend(old.segments.iter().map(|n| s.object(&self.id, n)));
        garbage.sort();
        garbage.dedup();
        s.block_on(s.delete_quietly(garbage));
        Ok(())
    }

    fn index_dir(&self) -> &Path {
        &self.cache_dir
    }

    /// A GET of the manifest conditional on its ETag (`If-None-Match`): not modified, the copy is current;
    /// a manifest that only appended segments to the known one, those records (fetched and checked here,
    /// the journal then follows the new manifest); anything else (a new snapshot, another map under the id),
    /// replaced; no manifest, gone.
    fn refresh(&mut self) -> Result<Freshness, MapError> {
        let s = Arc::clone(&self.shared);
        let path = s.object(&self.id, MANIFEST);
        let fetched = match self.version.e_tag.clone() {
            Some(tag) => s.block_on(s.get_changed(&path, tag)),
            None => s.block_on(s.get(&path)).map(Some),
        };
        let (bytes, version) = match fetched {
            Ok(None) => return Ok(Freshness::Current),
            Ok(Some(got)) => got,
            Err(object_store::Error::NotFound { .. }) => return Ok(Freshness::Gone),
            Err(e) => return Err(s.io(&path, e)),
        };
        let next = s.parse_manifest(&self.id, &bytes)?;
        if next == self.manifest {
            self.version = version;
            return Ok(Freshness::Current);
        }
        let known = &self.manifest;
        if next.map_uid != known.map_uid
            || next.snapshot != known.snapshot
            || !next.segments.starts_with(&known.segments)
        {
            return Ok(Freshness::Replaced);
        }
        let first = known.next_seq;
        let fetched = s.fetch_all(&self.id, &next.segments[known.segments.len()..])?;
        let mut records = Vec::with_capacity(fetched.len());
        for (i, (path, bytes)) in fetched.into_iter().enumerate() {
            let (seq, record) = decode_segment(&bytes, &s.name(&path))?;
            if seq != first + i as u64 {
                return Err(s.corrupt(&path, format!("holds record {seq}, expected {}", first + i as u64)));
            }
            records.push(record);
        }
        self.manifest = next;
        self.version = version;
        self.fenced = None;
        Ok(Freshness::Appended(records))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::model::MapMeta;
    use crate::map::tests::keyframe_record;
    use crate::test_dir::temp_dir;
    use object_store::memory::InMemory;

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
        data.apply(&r);
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
