//! Where maps are stored, behind one trait, so the [`MapStore`](crate::map::store::MapStore) does not care:
//!
//! * [`MapBackend`]: the collection of maps (list, exists, create, open, delete);
//! * [`MapJournal`]: the single writer of one open map (append a record durably, compact), plus the local
//!   directory that holds the map's HNSW index dump.
//!
//! Two implementations, chosen by [`BackendConfig`] (`[store.backend]`, `kind = "local"` by default):
//!
//! * [`LocalBackend`]: `data_dir/maps/<id>/`, the snapshot + fsync'd log of [`MapLog`] (unchanged), with
//!   the index dump beside them;
//! * [`ObjectStorageBackend`] (`kind = "s3"`): immutable objects plus a manifest replaced by conditional
//!   writes in an S3-API bucket, the index dump in a local cache directory. See [`crate::map::object_storage`]
//!   for the protocol.
//!
//! Both are synchronous: the store calls them on blocking threads (the CPU pool, `spawn_blocking`), never on
//! async worker threads.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::model::{MapData, Record};
use crate::map::object_storage::{ObjectStorageBackend, S3Credentials};
use crate::map::storage::{sync_dir, LoadReport, MapLog};
use crate::map::store::validate_map_id;

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
}

/// The writer of one open map. Calls are serialised by the caller (the map's writer lock).
pub trait MapJournal: Send + std::fmt::Debug {
    /// Makes the record that takes the map to version `seq` durable; returns only once it is.
    fn append(&mut self, seq: u64, record: &Record) -> Result<(), MapError>;

    /// Whether enough records accumulated to fold them into a snapshot.
    fn wants_compaction(&self) -> bool;

    /// Replaces the stored snapshot with `data` and drops the records it covers.
    fn compact(&mut self, data: &MapData) -> Result<(), MapError>;

    /// Local directory for the map's index dump.
    fn index_dir(&self) -> &Path;
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

/// Maps in `data_dir/maps/<id>/`, each a [`MapLog`].
#[derive(Debug)]
pub struct LocalBackend {
    root: PathBuf,
    compact_every: usize,
}

impl LocalBackend {
    /// Creates `data_dir/maps` if needed.
    pub fn new(data_dir: &Path, compact_every: usize) -> Result<Self, MapError> {
        let root = data_dir.join("maps");
        std::fs::create_dir_all(&root).map_err(|source| MapError::Io { path: root.clone(), source })?;
        Ok(Self { root, compact_every })
    }

    fn dir(&self, id: &str) -> PathBuf {
        self.root.join(id)
    }
}

impl MapJournal for MapLog {
    fn append(&mut self, seq: u64, record: &Record) -> Result<(), MapError> {
        MapLog::append(self, seq, record)
    }

    fn wants_compaction(&self) -> bool {
        MapLog::wants_compaction(self)
    }

    fn compact(&mut self, data: &MapData) -> Result<(), MapError> {
        MapLog::compact(self, data)
    }

    fn index_dir(&self) -> &Path {
        self.dir()
    }
}

impl MapBackend for LocalBackend {
    fn location(&self) -> String {
        self.root.display().to_string()
    }

    fn list(&self) -> Result<Vec<String>, MapError> {
        let io = |source| MapError::Io { path: self.root.clone(), source };
        let mut ids = Vec::new();
        for entry in std::fs::read_dir(&self.root).map_err(io)? {
            let entry = entry.map_err(io)?;
            let name = entry.file_name().to_string_lossy().into_owned();
            // Skips the `.deleted-*` directories of an interrupted delete, among others.
            if entry.path().is_dir() && validate_map_id(&name).is_ok() {
                ids.push(name);
            }
        }
        ids.sort();
        Ok(ids)
    }

    fn exists(&self, id: &str) -> Result<bool, MapError> {
        Ok(self.dir(id).exists())
    }

    fn create(&self, id: &str, data: &MapData) -> Result<Box<dyn MapJournal>, MapError> {
        if self.dir(id).exists() {
            return Err(MapError::MapExists { map: id.to_string() });
        }
        Ok(Box::new(MapLog::create(&self.dir(id), data, self.compact_every)?))
    }

    fn open(&self, id: &str) -> Result<(MapData, Box<dyn MapJournal>, LoadReport), MapError> {
        let (data, log, report) = MapLog::open(&self.dir(id), self.compact_every)?;
        Ok((data, Box::new(log), report))
    }

    /// Renames the directory away (atomic), then removes it.
    fn delete(&self, id: &str) -> Result<(), MapError> {
        let dir = self.dir(id);
        let millis = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_millis() as u64)
            .unwrap_or(0);
        let trash = self.root.join(format!(".deleted-{id}-{millis}"));
        std::fs::rename(&dir, &trash).map_err(|source| MapError::Io { path: dir.clone(), source })?;
        sync_dir(&self.root)?;
        std::fs::remove_dir_all(&trash).map_err(|source| MapError::Io { path: trash, source })
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
