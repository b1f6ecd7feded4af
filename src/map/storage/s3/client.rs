//! The object-store client of the S3 backend: settings and credentials, the calls it makes (counted per
//! operation for `/metrics`), reading manifests and segments, and moving index dumps between the bucket and
//! the local cache.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use futures_util::{StreamExt, TryStreamExt};
use object_store::path::Path as ObjectPath;
use object_store::{
    GetOptions, ObjectMeta, ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload, UpdateVersion,
};
use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::storage::format::{install_dump, read_dump, DumpBytes, DUMP_MANIFEST};
use crate::map::storage::format::{io_error, readable_version, write_atomic, FORMAT_VERSION, OLDEST_FORMAT_VERSION};
use crate::map::storage::s3::manifest::{
    nonce, number_of, IndexRef, Manifest, CACHE_MARKER, INDEX_FILES, MANIFEST, MAX_MANIFEST_BYTES, PARALLEL_GETS,
    SNAPSHOT_COPY,
};

/// Settings of the S3 backend.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct S3Settings {
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

/// The kinds of call made to the object store, as `/metrics` labels them.
#[derive(Debug, Clone, Copy)]
pub(super) enum Op {
    Get,
    Put,
    Head,
    List,
    Delete,
}

pub(super) const OPS: [(Op, &str); 5] =
    [(Op::Get, "get"), (Op::Put, "put"), (Op::Head, "head"), (Op::List, "list"), (Op::Delete, "delete")];

/// Calls, failures and time per [`Op`] since start. Answers that are outcomes of the protocol (not found,
/// not modified, a failed condition, already exists) are calls, not failures.
#[derive(Default)]
pub(super) struct OpCounters {
    pub(super) calls: [AtomicU64; 5],
    pub(super) errors: [AtomicU64; 5],
    pub(super) nanos: [AtomicU64; 5],
}

/// State shared by the backend and its journals: the object store and the runtime that drives it.
pub(super) struct Shared {
    pub(super) store: Arc<dyn ObjectStore>,
    /// `s3://bucket` (or another scheme), to name objects in messages.
    pub(super) url: String,
    /// `<prefix>/maps`
    pub(super) root: ObjectPath,
    pub(super) cache_root: PathBuf,
    pub(super) compact_every: usize,
    /// This process's writer id, recorded in every manifest it writes.
    pub(super) writer: String,
    pub(super) ops: OpCounters,
    pub(super) runtime: Option<tokio::runtime::Runtime>,
    /// One lock per cache directory that index dumps are fetched into ([`Shared::fetch_index`]).
    pub(super) fetching: std::sync::Mutex<std::collections::HashMap<PathBuf, Arc<tokio::sync::Mutex<()>>>>,
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
    pub(super) fn block_on<F: Future>(&self, f: F) -> F::Output {
        self.runtime.as_ref().expect("the runtime lives until drop").block_on(f)
    }

    pub(super) fn map_prefix(&self, id: &str) -> ObjectPath {
        self.root.clone().join(id)
    }

    pub(super) fn object(&self, id: &str, relative: &str) -> ObjectPath {
        let mut p = self.map_prefix(id);
        for part in relative.split('/') {
            p = p.join(part);
        }
        p
    }

    /// `s3://bucket/key`, for errors and logs.
    pub(super) fn name(&self, path: &ObjectPath) -> PathBuf {
        PathBuf::from(format!("{}/{}", self.url, path))
    }

    /// What a failed call on `path` means for a client: the bucket is missing (named), or the storage did
    /// not complete the call and a retry can succeed. The object and the storage's answer go to the log.
    pub(super) fn io(&self, path: &ObjectPath, e: object_store::Error) -> MapError {
        let detail = format!("{}: {e}", self.name(path).display());
        // S3 answers a call on a bucket that does not exist with the error code NoSuchBucket, which
        // object_store keeps in its message.
        if detail.contains("NoSuchBucket") {
            let bucket = self.url.split_once("://").map_or(self.url.as_str(), |(_, b)| b).to_string();
            return MapError::NoBucket { bucket };
        }
        MapError::StorageUnavailable { detail }
    }

    pub(super) fn corrupt(&self, path: &ObjectPath, reason: impl Into<String>) -> MapError {
        MapError::Corrupt { path: self.name(path), reason: reason.into() }
    }

    /// A failed call on an object the manifest names: one that is missing is corruption, as a damaged one is.
    pub(super) fn named_error(&self, path: &ObjectPath, e: object_store::Error) -> MapError {
        match e {
            object_store::Error::NotFound { .. } => self.corrupt(path, "named by the manifest but missing"),
            e => self.io(path, e),
        }
    }

    pub(super) fn cache_dir(&self, id: &str) -> PathBuf {
        self.cache_root.join(id)
    }

    /// Awaits one call to the object store, counting it under `op`.
    pub(super) async fn timed<T>(
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

    pub(super) async fn get(&self, path: &ObjectPath) -> Result<(Vec<u8>, UpdateVersion), object_store::Error> {
        self.get_with(path, GetOptions::default()).await
    }

    pub(super) async fn get_with(
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

    /// Bytes `range` of an object (a ranged GET).
    pub(super) async fn get_range(
        &self,
        path: &ObjectPath,
        range: std::ops::Range<u64>,
    ) -> Result<Vec<u8>, object_store::Error> {
        let options = GetOptions { range: Some(range.into()), ..Default::default() };
        Ok(self.get_with(path, options).await?.0)
    }

    /// Bytes `range` of an object written into `file` from byte `at` as they arrive (a ranged GET that never
    /// holds the range in memory; `copy` names the file in errors): how many bytes came.
    pub(super) async fn get_range_into(
        &self,
        path: &ObjectPath,
        range: std::ops::Range<u64>,
        file: &std::fs::File,
        at: u64,
        copy: &Path,
    ) -> Result<u64, MapError> {
        use std::os::unix::fs::FileExt;
        let options = GetOptions { range: Some(range.into()), ..Default::default() };
        let (mut written, mut failed_write) = (0u64, None);
        let got = self
            .timed(Op::Get, async {
                let mut stream = self.store.get_opts(path, options).await?.into_stream();
                while let Some(chunk) = stream.next().await {
                    let chunk = chunk?;
                    if let Err(e) = file.write_all_at(&chunk, at + written) {
                        failed_write = Some(e);
                        break;
                    }
                    written += chunk.len() as u64;
                }
                Ok(())
            })
            .await;
        got.map_err(|e| self.io(path, e))?;
        match failed_write {
            Some(e) => Err(io_error(copy, e)),
            None => Ok(written),
        }
    }

    /// A GET conditional on the object's ETag no longer being `known`: `None` when it still is.
    pub(super) async fn get_changed(
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

    /// PUTs `bytes` as a new object at `path`, a name no other write uses (it carries a nonce). An object
    /// already there is this write's own, from an attempt whose answer was lost and that the client retried:
    /// the write stands when the stored bytes are `bytes`.
    pub(super) async fn put_new(&self, path: &ObjectPath, bytes: Vec<u8>) -> Result<(), object_store::Error> {
        match self.put(path, bytes.clone(), PutMode::Create).await {
            Ok(_) => Ok(()),
            Err(e @ object_store::Error::AlreadyExists { .. }) => match self.get(path).await {
                Ok((stored, _)) if stored == bytes => {
                    tracing::info!(object = %path, "a PUT whose answer was lost had been applied; kept");
                    Ok(())
                }
                _ => Err(e),
            },
            Err(e) => Err(e),
        }
    }

    pub(super) async fn put(
        &self,
        path: &ObjectPath,
        bytes: Vec<u8>,
        mode: PutMode,
    ) -> Result<UpdateVersion, object_store::Error> {
        // Fault injection for the durability tests (fail point `s3-put`, argument: part of the key).
        if crate::map::storage::format::injected("s3-put", Path::new(path.as_ref())) {
            let source = Box::new(std::io::Error::other(format!("injected fault: PUT {path} failed")));
            return Err(object_store::Error::Generic { store: "S3", source });
        }
        let r = self.timed(Op::Put, self.store.put_opts(path, PutPayload::from(bytes), PutOptions::from(mode))).await?;
        Ok(UpdateVersion { e_tag: r.e_tag, version: r.version })
    }

    pub(super) async fn head(&self, path: &ObjectPath) -> Result<ObjectMeta, object_store::Error> {
        self.timed(Op::Head, self.store.head(path)).await
    }

    /// Every object under `prefix`.
    pub(super) async fn list_under(&self, prefix: &ObjectPath) -> Result<Vec<ObjectPath>, object_store::Error> {
        self.timed(Op::List, self.store.list(Some(prefix)).map_ok(|o| o.location).try_collect::<Vec<_>>()).await
    }

    pub(super) async fn delete_one(&self, path: &ObjectPath) -> Result<(), object_store::Error> {
        self.timed(Op::Delete, self.store.delete(path)).await
    }

    /// Deletes objects, logging (not failing on) what could not be deleted.
    pub(super) async fn delete_quietly(&self, paths: Vec<ObjectPath>) {
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
    pub(super) async fn read_manifest(&self, id: &str) -> Result<Option<(Manifest, Vec<u8>, UpdateVersion)>, MapError> {
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

    pub(super) fn parse_manifest(&self, id: &str, bytes: &[u8]) -> Result<Manifest, MapError> {
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
    pub(super) fn fetch_all(&self, id: &str, names: &[String]) -> Result<Vec<(ObjectPath, Vec<u8>)>, MapError> {
        let paths: Vec<ObjectPath> = names.iter().map(|name| self.object(id, name)).collect();
        self.block_on(
            futures_util::stream::iter(paths.into_iter().map(|p| async move {
                match self.get(&p).await {
                    Ok((bytes, _)) => Ok((p, bytes)),
                    Err(e) => Err(self.named_error(&p, e)),
                }
            }))
            .buffered(PARALLEL_GETS)
            .try_collect(),
        )
    }

    /// Puts the index dump the manifest names into the map's cache directory, unless the dump there is that
    /// one already (same `index.json`, which holds the files' checksums). The files are written atomically,
    /// `index.json` last ([`install_dump`]); the index loader checks the dump against the map, so one that
    /// does not match is rebuilt. The two files are fetched at once, and one fetch into a directory waits for
    /// another in flight there (a load fetches the dump beside its open, and the open after it).
    pub(super) async fn fetch_index(&self, id: &str, index: &IndexRef, cache_dir: &Path) -> Result<(), MapError> {
        let lock = Arc::clone(
            self.fetching
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .entry(cache_dir.into())
                .or_default(),
        );
        let _one_at_a_time = lock.lock().await;
        let remote = |file: &str| self.object(id, &format!("{}/{file}", index.dir));
        let manifest_path = remote(INDEX_FILES[2]);
        let (manifest, _) = self.get(&manifest_path).await.map_err(|e| self.io(&manifest_path, e))?;
        if std::fs::read(cache_dir.join(DUMP_MANIFEST)).ok().as_deref() == Some(manifest.as_slice()) {
            return Ok(());
        }
        let fetch = |file: &str| {
            let path = remote(file);
            async move { self.get(&path).await.map(|r| r.0).map_err(|e| self.io(&path, e)) }
        };
        let (graph, data) = futures_util::try_join!(fetch(INDEX_FILES[0]), fetch(INDEX_FILES[1]))?;
        install_dump(cache_dir, &DumpBytes { manifest, graph, data })
    }

    /// Uploads the index dump in `cache_dir` (when there is one) under a new `index/<version>-<nonce>/`, the
    /// manifest last.
    pub(super) async fn upload_index(
        &self,
        id: &str,
        version: u64,
        cache_dir: &Path,
    ) -> Result<Option<IndexRef>, MapError> {
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

    /// A snapshot object copied into the map's cache directory, as `snapshot-<the object's file name>`: the
    /// file the loaded map reads its keyframes' payloads from ([`crate::map::payload`]). Not fsync'd: only
    /// this process reads it, and each load writes it anew. The other copies there are removed (a map that
    /// still reads one keeps it open, so its reads go on).
    pub(super) fn keep_snapshot(&self, cache_dir: &Path, object: &str, bytes: &[u8]) -> Result<PathBuf, MapError> {
        Ok(self.copy_snapshot(cache_dir, object, bytes.len() as u64, &[(0, bytes)])?.0)
    }

    /// [`Shared::keep_snapshot`] of a snapshot of `size` bytes of which only `parts` (offset, bytes) are here
    /// yet: the file has its size, and the rest is written later through the handle returned with its path.
    pub(super) fn copy_snapshot(
        &self,
        cache_dir: &Path,
        object: &str,
        size: u64,
        parts: &[(u64, &[u8])],
    ) -> Result<(PathBuf, std::fs::File), MapError> {
        use std::os::unix::fs::FileExt;
        let file = object.rsplit('/').next().unwrap_or(object);
        let path = cache_dir.join(format!("{SNAPSHOT_COPY}{file}"));
        let tmp = path.with_extension("tmp");
        let written =
            std::fs::File::options().read(true).write(true).create(true).truncate(true).open(&tmp).and_then(|f| {
                f.set_len(size)?;
                for (offset, bytes) in parts {
                    f.write_all_at(bytes, *offset)?;
                }
                std::fs::rename(&tmp, &path)?;
                Ok(f)
            });
        let handle = match written {
            Ok(f) => f,
            Err(e) => {
                let _ = std::fs::remove_file(&tmp);
                return Err(io_error(&path, e));
            }
        };
        for entry in std::fs::read_dir(cache_dir).map_err(|e| io_error(cache_dir, e))?.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with(SNAPSHOT_COPY) && entry.path() != path {
                let _ = std::fs::remove_file(entry.path());
            }
        }
        Ok((path, handle))
    }

    /// Makes the cache directory of a map belong to this incarnation of it (`map_uid`), emptying it otherwise.
    pub(super) fn claim_cache(&self, id: &str, map_uid: &str) -> Result<PathBuf, MapError> {
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
