//! Where maps are stored, under one roof: what the store needs from storage ([`backend`]: the collection of
//! maps and one map's journal, as traits), the two implementations ([`local`]: a directory with a snapshot and
//! an fsync'd write-ahead log; [`s3`]: immutable objects and a conditionally replaced manifest in an S3-API
//! bucket), the bytes both write ([`format`](mod@format)), and the choice between them (`[store.backend]`,
//! [`BackendSettings`], [`open_backend`]).
//!
//! Who imports whom, top to bottom (each module imports only from those after it; `tools/check_imports.py`
//! checks it): this file -> [`local`] / [`s3`] -> [`backend`] / [`snapshot`] -> [`format`](mod@format). Outside this
//! directory, storage imports only [`crate::map::model`] and [`crate::map::payload`] of the map (the order in
//! [`crate::map`]).

pub mod backend;
pub mod format;
pub mod local;
pub mod s3;
pub mod snapshot;

use std::path::Path;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::error::MapError;
use crate::map::storage::backend::MapBackend;
use crate::map::storage::local::LocalBackend;
use crate::map::storage::s3::{ObjectStorageBackend, S3Credentials, S3Settings};

/// Which backend stores the maps (`[store.backend]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum BackendSettings {
    /// `store.data_dir/maps/<id>/`: snapshot + fsync'd write-ahead log, index dump beside them. (A struct
    /// variant, so that S3 keys under `kind = "local"`, e.g. a forgotten `kind = "s3"`, are refused.)
    Local {},
    /// An S3-API bucket. Credentials come from the standard AWS environment variables
    /// (`AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, ...), never from this file.
    S3(S3Settings),
}

impl Default for BackendSettings {
    fn default() -> Self {
        Self::Local {}
    }
}

impl BackendSettings {
    /// Checks that need no I/O.
    pub fn validate(&self) -> Result<(), String> {
        match self {
            BackendSettings::Local {} => Ok(()),
            BackendSettings::S3(s3) => {
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
    config: &BackendSettings,
    data_dir: &Path,
    compact_every: usize,
) -> Result<Arc<dyn MapBackend>, MapError> {
    match config {
        BackendSettings::Local {} => Ok(Arc::new(LocalBackend::new(data_dir, compact_every)?)),
        BackendSettings::S3(s3) => {
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
        let c: BackendSettings = serde_json::from_str(r#"{"kind":"local"}"#).unwrap();
        assert_eq!(c, BackendSettings::Local {});
        let c: BackendSettings = serde_json::from_str(
            r#"{"kind":"s3","bucket":"maps","endpoint":"http://127.0.0.1:9000","allow_http":true}"#,
        )
        .unwrap();
        let BackendSettings::S3(s3) = &c else { panic!("{c:?}") };
        assert_eq!((s3.bucket.as_str(), s3.prefix.as_str(), s3.region.as_deref()), ("maps", "", None));
        c.validate().unwrap();
        let e = serde_json::from_str::<BackendSettings>(r#"{"kind":"s3","bucket":"m","secret_key":"x"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("secret_key"), "{e}");
        let e = serde_json::from_str::<BackendSettings>(r#"{"kind":"local","bucket":"m"}"#).unwrap_err().to_string();
        assert!(e.contains("bucket"), "{e}");
        let plain = BackendSettings::S3(S3Settings {
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
