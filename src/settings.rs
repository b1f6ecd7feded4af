//! One typed settings struct for the server, loaded in layers: built-in defaults, then a TOML file
//! (`--config` or `SCONE_CONFIG`), then environment variables `SCONE_<SECTION>__<KEY>` (e.g.
//! `SCONE_SERVER__HTTP_ADDR=0.0.0.0:8080`), then command-line flags. Validated once at start; the sub-structs
//! are handed to the parts that use them. [`Settings::redacted`] is what gets logged (no key material).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use figment::providers::{Env, Format, Serialized, Toml};
use figment::Figment;
use serde::{Deserialize, Serialize};

use crate::describe::decode::ImageLimitSettings;
use crate::describe::embedding::EmbedderSettings;
use crate::describe::features::{ExtractorSettings, KeypointLimitSettings};
use crate::map::store::StoreSettings;
use crate::pose::RansacSettings;

/// Listeners and request lifetime.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerSettings {
    pub grpc_addr: SocketAddr,
    pub http_addr: SocketAddr,
    /// A request is answered DEADLINE_EXCEEDED / 504 after this long (queueing included).
    pub request_timeout_ms: u64,
    /// On SIGTERM, in-flight requests get this long to finish before the servers stop.
    pub shutdown_grace_ms: u64,
    /// Largest gRPC message or HTTP body, bytes.
    pub max_request_bytes: usize,
    /// Largest map file accepted by ImportMap, bytes.
    pub max_map_bytes: usize,
    /// Open connections per listener; beyond that new clients wait in the backlog until one closes.
    pub max_connections: usize,
    /// A new connection must deliver its first request head (HTTP/2: its preface) within this long; an
    /// HTTP/1.1 keep-alive request head must be complete within this long of its first byte.
    pub header_read_timeout_ms: u64,
    /// An HTTP request body must be complete within this long of its head (408 otherwise). gRPC: a call
    /// must be answered within this plus `request_timeout_ms`.
    pub body_read_timeout_ms: u64,
    /// A connection without a request in flight for this long is closed (also: one whose client stopped
    /// reading for this long); on gRPC, also the longest gap between the messages of a client stream.
    pub idle_timeout_ms: u64,
    /// TCP keepalive idle time on accepted sockets (0: off).
    pub tcp_keepalive_ms: u64,
    /// HTTP/2 PING interval on gRPC connections (0: off) and how long to wait for the answer.
    pub grpc_keepalive_interval_ms: u64,
    pub grpc_keepalive_timeout_ms: u64,
    /// Concurrent HTTP/2 streams (calls) per connection.
    pub max_concurrent_streams: u32,
    /// Origins (`scheme://host[:port]`) whose browser pages may write (non-GET/HEAD) and get CORS answers;
    /// `"*"` allows every origin. Empty: the HTTP listener's own origins (`http://127.0.0.1:PORT`,
    /// `http://localhost:PORT` on loopback). Requests without an `Origin` header are not affected.
    pub allowed_origins: Vec<String>,
}

impl Default for ServerSettings {
    fn default() -> Self {
        Self {
            grpc_addr: "127.0.0.1:50051".parse().expect("valid"),
            http_addr: "127.0.0.1:8080".parse().expect("valid"),
            request_timeout_ms: 10_000,
            shutdown_grace_ms: 20_000,
            max_request_bytes: 32 << 20,
            max_map_bytes: 1 << 30,
            max_connections: 1024,
            header_read_timeout_ms: 10_000,
            body_read_timeout_ms: 60_000,
            idle_timeout_ms: 60_000,
            tcp_keepalive_ms: 60_000,
            grpc_keepalive_interval_ms: 30_000,
            grpc_keepalive_timeout_ms: 10_000,
            max_concurrent_streams: 100,
            allowed_origins: Vec::new(),
        }
    }
}

/// API keys. With no key configured the service only starts on loopback addresses, unless
/// `allow_anonymous` is set explicitly.
#[derive(Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuthSettings {
    /// Keys that may read and write.
    pub write_keys: Vec<String>,
    /// Keys that may only read (describe, match, localise, get, list, export).
    pub read_keys: Vec<String>,
    /// A file of lines `write <key>` or `read <key>` (`#` starts a comment), e.g. a mounted secret.
    pub keys_file: Option<PathBuf>,
    /// Serve without keys on non-loopback addresses (behind a proxy that authenticates).
    pub allow_anonymous: bool,
}

impl std::fmt::Debug for AuthSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AuthSettings")
            .field("write_keys", &format_args!("[{} redacted]", self.write_keys.len()))
            .field("read_keys", &format_args!("[{} redacted]", self.read_keys.len()))
            .field("keys_file", &self.keys_file)
            .field("allow_anonymous", &self.allow_anonymous)
            .finish()
    }
}

/// Limits on client input.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LimitSettings {
    pub image: ImageLimitSettings,
    pub keypoints: KeypointLimitSettings,
}

/// The CPU pool every request's work runs on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorkerSettings {
    /// Threads doing CPU work (one request each at a time).
    pub threads: usize,
    /// Requests that may wait for a thread; beyond that, RESOURCE_EXHAUSTED / 429.
    pub queue: usize,
    /// How long a refusal for a full pool is held before it is sent (0: at once). A client that ignores
    /// `Retry-After` and retries at once is slowed to one attempt per this long, so a storm of them cannot
    /// take the core from the pool; the hold costs a timer, no CPU.
    pub refusal_hold_ms: u64,
}

impl Default for WorkerSettings {
    fn default() -> Self {
        Self { threads: 2, queue: 8, refusal_hold_ms: 250 }
    }
}

/// Everything the server is configured with.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Settings {
    pub server: ServerSettings,
    pub auth: AuthSettings,
    pub limits: LimitSettings,
    pub workers: WorkerSettings,
    pub model: EmbedderSettings,
    /// Detection and description: the extraction the model declares
    /// ([`crate::describe::embedding::Embedder::extraction`]), with each field given here (`[extractor]`,
    /// `SCONE_EXTRACTOR__*`) over it; an extraction other than the model's is served with a warning.
    pub extractor: ExtractorOverrides,
    pub store: StoreSettings,
    /// MatchPair's essential-matrix search (`[relative_pose]`: threshold_px, confidence, max_iters, essential,
    /// duplicate_px). The defaults favour accuracy; a smaller `max_iters` bounds the time a hard pair can take.
    pub relative_pose: RansacSettings,
}

/// `[extractor]`: the fields of [`ExtractorSettings`] that are set, each over the model's declared extraction.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ExtractorOverrides {
    pub fast_threshold: Option<i32>,
    pub max_keypoints: Option<usize>,
    pub levels: Option<u32>,
    pub scale_factor: Option<f64>,
    pub grid_cell: Option<u32>,
}

impl ExtractorOverrides {
    /// `base` with every field set here replaced.
    pub fn over(&self, base: ExtractorSettings) -> ExtractorSettings {
        ExtractorSettings {
            fast_threshold: self.fast_threshold.unwrap_or(base.fast_threshold),
            max_keypoints: self.max_keypoints.unwrap_or(base.max_keypoints),
            levels: self.levels.unwrap_or(base.levels),
            scale_factor: self.scale_factor.unwrap_or(base.scale_factor),
            grid_cell: self.grid_cell.unwrap_or(base.grid_cell),
        }
    }
}

/// Flags that override everything else.
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    pub grpc_addr: Option<SocketAddr>,
    pub http_addr: Option<SocketAddr>,
    pub data_dir: Option<PathBuf>,
    pub model: Option<PathBuf>,
}

/// A setting that cannot be used, with the reason.
#[derive(Debug, thiserror::Error)]
pub enum SettingsError {
    #[error("configuration: {0}")]
    Load(String),
    #[error("configuration: {field}: {reason}")]
    Invalid { field: &'static str, reason: String },
    #[error("{path}: {source}")]
    KeysFile { path: PathBuf, source: std::io::Error },
    #[error("{path}:{line}: expected `write <key>` or `read <key>`")]
    KeysLine { path: PathBuf, line: usize },
}

impl Settings {
    /// Defaults -> file -> environment (`SCONE_<SECTION>__<KEY>`) -> flags, then validation.
    pub fn load(file: Option<&Path>, overrides: &Overrides) -> Result<Self, SettingsError> {
        Self::load_from(
            file,
            overrides,
            Env::prefixed("SCONE_").split("__").filter(|k| k.as_str().contains("__") || k.as_str().contains('.')),
        )
    }

    fn load_from(file: Option<&Path>, overrides: &Overrides, env: Env) -> Result<Self, SettingsError> {
        let mut fig = Figment::from(Serialized::defaults(Settings::default()));
        if let Some(f) = file {
            if !f.is_file() {
                return Err(SettingsError::Load(format!("{}: no such file", f.display())));
            }
            fig = fig.merge(Toml::file(f));
        }
        fig = fig.merge(env);
        let mut s: Settings = fig.extract().map_err(|e| SettingsError::Load(e.to_string()))?;
        if let Some(a) = overrides.grpc_addr {
            s.server.grpc_addr = a;
        }
        if let Some(a) = overrides.http_addr {
            s.server.http_addr = a;
        }
        if let Some(d) = &overrides.data_dir {
            s.store.data_dir = d.clone();
        }
        if let Some(m) = &overrides.model {
            s.model.model = m.clone();
        }
        s.validate()?;
        Ok(s)
    }

    /// Checks that need no I/O beyond the keys file.
    pub fn validate(&self) -> Result<(), SettingsError> {
        let bad = |field, reason: &str| Err(SettingsError::Invalid { field, reason: reason.to_string() });
        if self.server.grpc_addr == self.server.http_addr && self.server.grpc_addr.port() != 0 {
            return bad("server.grpc_addr", "must differ from server.http_addr");
        }
        if self.server.request_timeout_ms == 0 {
            return bad("server.request_timeout_ms", "must be positive");
        }
        if self.server.max_request_bytes < 1024 {
            return bad("server.max_request_bytes", "must be at least 1024");
        }
        if self.server.max_connections == 0 || self.server.max_connections > 1 << 20 {
            return bad("server.max_connections", "must be in 1..=1048576");
        }
        for (field, ms) in [
            ("server.header_read_timeout_ms", self.server.header_read_timeout_ms),
            ("server.body_read_timeout_ms", self.server.body_read_timeout_ms),
            ("server.idle_timeout_ms", self.server.idle_timeout_ms),
            ("server.grpc_keepalive_timeout_ms", self.server.grpc_keepalive_timeout_ms),
        ] {
            if ms == 0 {
                return bad(field, "must be positive");
            }
        }
        if self.server.max_concurrent_streams == 0 {
            return bad("server.max_concurrent_streams", "must be positive");
        }
        for origin in &self.server.allowed_origins {
            check_origin(origin).map_err(|reason| SettingsError::Invalid {
                field: "server.allowed_origins",
                reason: format!("'{origin}' {reason}"),
            })?;
        }
        if self.workers.threads == 0 || self.workers.threads > 256 {
            return bad("workers.threads", "must be in 1..=256");
        }
        if self.workers.refusal_hold_ms > 1_000 {
            return bad("workers.refusal_hold_ms", "must be at most 1000 (Retry-After is 1 s)");
        }
        if self.model.sessions == 0 || self.model.intra_threads == 0 {
            return bad("model", "sessions and intra_threads must be positive");
        }
        if self.limits.keypoints.max_keypoints == 0 {
            return bad("limits.keypoints.max_keypoints", "must be positive");
        }
        if self.limits.image.max_bytes > self.server.max_request_bytes {
            return bad("limits.image.max_bytes", "must not exceed server.max_request_bytes");
        }
        self.extractor
            .over(ExtractorSettings::default())
            .validate()
            .map_err(|e| SettingsError::Invalid { field: "extractor", reason: e.to_string() })?;
        self.relative_pose.validate().map_err(|reason| SettingsError::Invalid { field: "relative_pose", reason })?;
        self.store.backend.validate().map_err(|reason| SettingsError::Invalid { field: "store.backend", reason })?;
        self.store.build.validate().map_err(|reason| SettingsError::Invalid { field: "store.build", reason })?;
        self.store.localize.validate().map_err(|reason| SettingsError::Invalid { field: "store.localize", reason })?;
        let keys = self.keys()?;
        let loopback = self.server.grpc_addr.ip().is_loopback() && self.server.http_addr.ip().is_loopback();
        if keys.is_empty() && !loopback && !self.auth.allow_anonymous {
            return bad(
                "auth",
                "no API key is configured and the service would listen beyond loopback: set auth.keys_file (or \
                 auth.write_keys), or auth.allow_anonymous = true behind an authenticating proxy",
            );
        }
        Ok(())
    }

    /// All configured keys with their access, from the settings and the keys file.
    pub fn keys(&self) -> Result<Vec<(String, Access)>, SettingsError> {
        let mut out: Vec<(String, Access)> = Vec::new();
        out.extend(self.auth.write_keys.iter().map(|k| (k.clone(), Access::Write)));
        out.extend(self.auth.read_keys.iter().map(|k| (k.clone(), Access::Read)));
        if let Some(path) = &self.auth.keys_file {
            let text = std::fs::read_to_string(path)
                .map_err(|source| SettingsError::KeysFile { path: path.clone(), source })?;
            for (i, line) in text.lines().enumerate() {
                let line = line.split('#').next().unwrap_or("").trim();
                if line.is_empty() {
                    continue;
                }
                let mut parts = line.split_whitespace();
                let access = match parts.next() {
                    Some("write") => Access::Write,
                    Some("read") => Access::Read,
                    _ => return Err(SettingsError::KeysLine { path: path.clone(), line: i + 1 }),
                };
                match (parts.next(), parts.next()) {
                    (Some(k), None) => out.push((k.to_string(), access)),
                    _ => return Err(SettingsError::KeysLine { path: path.clone(), line: i + 1 }),
                }
            }
        }
        if let Some((k, _)) = out.iter().find(|(k, _)| k.len() < 16) {
            return Err(SettingsError::Invalid {
                field: "auth",
                reason: format!("API keys need at least 16 characters (one has {})", k.len()),
            });
        }
        Ok(out)
    }

    /// The settings as JSON for the start-up log, with key material removed.
    pub fn redacted(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).unwrap_or_default();
        if let Some(auth) = v.get_mut("auth") {
            auth["write_keys"] = serde_json::json!(format!("[{} redacted]", self.auth.write_keys.len()));
            auth["read_keys"] = serde_json::json!(format!("[{} redacted]", self.auth.read_keys.len()));
        }
        v
    }
}

/// An allowed origin is `*` or `scheme://host[:port]` (http or https, nothing after the authority), as
/// browsers send it in `Origin`.
fn check_origin(origin: &str) -> Result<(), &'static str> {
    if origin == "*" {
        return Ok(());
    }
    let rest = origin
        .strip_prefix("http://")
        .or_else(|| origin.strip_prefix("https://"))
        .ok_or("must start with http:// or https://")?;
    if rest.is_empty() || rest.contains(['/', '?', '#', ' ', '@']) {
        return Err("must be scheme://host[:port], without a path");
    }
    Ok(())
}

/// What a key may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Access {
    Read,
    Write,
}

#[cfg(test)]
#[allow(clippy::result_large_err)] // figment::Jail's closures return figment's own large error type
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_loopback_needs_no_key() {
        let s = Settings::default();
        s.validate().unwrap();
        assert!(s.server.grpc_addr.ip().is_loopback());
    }

    #[test]
    fn layers_apply_in_order_file_env_flags() {
        let dir = crate::test_dir::temp_dir("settings");
        let file = dir.join("scone.toml");
        std::fs::write(
            &file,
            "[server]\nrequest_timeout_ms = 1234\nhttp_addr = \"127.0.0.1:9000\"\n[workers]\nqueue = 3\n",
        )
        .unwrap();
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_WORKERS__QUEUE", "5");
            jail.set_env("SCONE_PREFIX", "/not/a/setting");
            let flags = Overrides { http_addr: Some("127.0.0.1:9100".parse().unwrap()), ..Default::default() };
            let s = Settings::load(Some(&file), &flags).map_err(|e| e.to_string())?;
            assert_eq!(s.server.request_timeout_ms, 1234, "file over defaults");
            assert_eq!(s.workers.queue, 5, "environment over file");
            assert_eq!(s.server.http_addr.port(), 9100, "flags over everything");
            Ok(())
        });
    }

    #[test]
    fn the_extractor_is_the_models_with_each_field_given_over_it() {
        let dir = crate::test_dir::temp_dir("settings-extractor");
        assert_eq!(Settings::default().extractor, ExtractorOverrides::default(), "unset: the model's declaration");
        let file = dir.join("scone.toml");
        std::fs::write(&file, "[extractor]\nmax_keypoints = 1000\n").unwrap();
        figment::Jail::expect_with(|jail| {
            let s = Settings::load(Some(&file), &Overrides::default()).map_err(|e| e.to_string())?;
            // Over a model that declares revision 2, only the keypoint budget changes.
            let want = ExtractorSettings { max_keypoints: 1000, ..ExtractorSettings::revision_2() };
            assert_eq!(s.extractor.over(ExtractorSettings::revision_2()), want);
            jail.set_env("SCONE_EXTRACTOR__LEVELS", "5");
            let s = Settings::load(Some(&file), &Overrides::default()).map_err(|e| e.to_string())?;
            let want = ExtractorSettings { levels: 5, max_keypoints: 1000, ..ExtractorSettings::default() };
            assert_eq!(s.extractor.over(ExtractorSettings::default()), want);
            jail.set_env("SCONE_EXTRACTOR__LEVELS", "0");
            let err = Settings::load(None, &Overrides::default()).and_then(|s| s.validate()).unwrap_err().to_string();
            assert!(err.contains("extractor") && err.contains("levels"), "{err}");
            Ok(())
        });
    }

    #[test]
    fn unknown_keys_and_bad_values_are_refused_with_the_field() {
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_WORKERS__THREADZ", "3");
            let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
            assert!(e.contains("threadz"), "{e}");
            Ok(())
        });
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_WORKERS__THREADS", "0");
            let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
            assert!(e.contains("workers.threads"), "{e}");
            Ok(())
        });
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_STORE__LOCALIZE__MAX_QUERY_KEYPOINTS", "400");
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            assert_eq!(s.store.localize.max_query_keypoints, 400);
            jail.set_env("SCONE_STORE__LOCALIZE__MAX_QUERY_KEYPOINTS", "5");
            let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
            assert!(e.contains("store.localize") && e.contains("min_inliers"), "{e}");
            Ok(())
        });
    }

    #[test]
    fn the_relative_pose_search_is_set_by_field_and_checked() {
        figment::Jail::expect_with(|jail| {
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            assert_eq!(s.relative_pose, RansacSettings::default());
            jail.set_env("SCONE_RELATIVE_POSE__MAX_ITERS", "2000");
            jail.set_env("SCONE_RELATIVE_POSE__ESSENTIAL", "ransac");
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            assert_eq!(s.relative_pose.max_iters, 2000);
            assert_eq!(s.relative_pose.essential, crate::pose::EssentialMethod::Ransac);
            assert_eq!(s.relative_pose.confidence, RansacSettings::default().confidence, "unset fields keep defaults");
            Ok(())
        });
        for (var, value, word) in [
            ("SCONE_RELATIVE_POSE__MAX_ITERS", "0", "max_iters"),
            ("SCONE_RELATIVE_POSE__CONFIDENCE", "1.0", "confidence"),
            ("SCONE_RELATIVE_POSE__THRESHOLD_PX", "-1", "threshold_px"),
        ] {
            figment::Jail::expect_with(|jail| {
                jail.set_env(var, value);
                let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
                assert!(e.contains("relative_pose") && e.contains(word), "{e}");
                Ok(())
            });
        }
    }

    #[test]
    fn the_map_backend_is_local_by_default_and_s3_from_the_environment() {
        figment::Jail::expect_with(|_| {
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            assert_eq!(s.store.backend, crate::map::storage::BackendSettings::Local {});
            Ok(())
        });
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_STORE__BACKEND__KIND", "s3");
            jail.set_env("SCONE_STORE__BACKEND__BUCKET", "scone-maps");
            jail.set_env("SCONE_STORE__BACKEND__PREFIX", "prod");
            jail.set_env("SCONE_STORE__BACKEND__ENDPOINT", "http://minio.storage:9000");
            jail.set_env("SCONE_STORE__BACKEND__ALLOW_HTTP", "true");
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            let crate::map::storage::BackendSettings::S3(s3) = &s.store.backend else { panic!("{:?}", s.store) };
            assert_eq!((s3.bucket.as_str(), s3.prefix.as_str(), s3.allow_http), ("scone-maps", "prod", true));
            assert_eq!(s.redacted()["store"]["backend"]["kind"], "s3");
            Ok(())
        });
        // A bucket without `kind = "s3"` is refused rather than silently stored locally.
        figment::Jail::expect_with(|jail| {
            jail.set_env("SCONE_STORE__BACKEND__BUCKET", "scone-maps");
            let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
            assert!(e.contains("bucket"), "{e}");
            Ok(())
        });
    }

    #[test]
    fn public_address_without_keys_is_refused_and_keys_are_not_logged() {
        let mut s = Settings::default();
        s.server.http_addr = "0.0.0.0:8080".parse().unwrap();
        let e = s.validate().unwrap_err().to_string();
        assert!(e.contains("no API key"), "{e}");
        s.auth.write_keys = vec!["0123456789abcdef-secret".into()];
        s.validate().unwrap();
        let logged = format!("{} {:?}", s.redacted(), s);
        assert!(!logged.contains("secret"), "{logged}");
    }

    #[test]
    fn connection_limits_and_origins_are_checked() {
        for (var, value, field) in [
            ("SCONE_SERVER__MAX_CONNECTIONS", "0", "server.max_connections"),
            ("SCONE_SERVER__HEADER_READ_TIMEOUT_MS", "0", "server.header_read_timeout_ms"),
            ("SCONE_SERVER__IDLE_TIMEOUT_MS", "0", "server.idle_timeout_ms"),
            ("SCONE_SERVER__ALLOWED_ORIGINS", "[\"example.com\"]", "server.allowed_origins"),
            ("SCONE_SERVER__ALLOWED_ORIGINS", "[\"https://example.com/app\"]", "server.allowed_origins"),
        ] {
            figment::Jail::expect_with(|jail| {
                jail.set_env(var, value);
                let e = Settings::load(None, &Overrides::default()).unwrap_err().to_string();
                assert!(e.contains(field), "{var}={value}: {e}");
                Ok(())
            });
        }
        figment::Jail::expect_with(|jail| {
            jail.set_env(
                "SCONE_SERVER__ALLOWED_ORIGINS",
                "[\"https://app.example.com\", \"http://localhost:3000\", \"*\"]",
            );
            let s = Settings::load(None, &Overrides::default()).map_err(|e| e.to_string())?;
            assert_eq!(s.server.allowed_origins.len(), 3);
            Ok(())
        });
    }

    #[test]
    fn keys_file_lines_are_parsed_and_bad_lines_named() {
        let dir = crate::test_dir::temp_dir("keys");
        let f = dir.join("keys");
        std::fs::write(&f, "# comment\nwrite aaaaaaaaaaaaaaaa\nread bbbbbbbbbbbbbbbb # phone\n").unwrap();
        let mut s = Settings::default();
        s.auth.keys_file = Some(f.clone());
        let keys = s.keys().unwrap();
        assert_eq!(keys, vec![("aaaaaaaaaaaaaaaa".into(), Access::Write), ("bbbbbbbbbbbbbbbb".into(), Access::Read)]);
        std::fs::write(&f, "admin cccccccccccccccc\n").unwrap();
        assert!(s.keys().unwrap_err().to_string().contains(":1:"));
    }
}
