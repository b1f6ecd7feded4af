use std::path::{Path, PathBuf};

/// Directory of committed fixtures.
pub fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

/// The shared real-data directory, or `None` when absent outside CI (inside CI a missing directory panics).
pub fn shared_data() -> Option<PathBuf> {
    let dir = std::env::var_os("SCONE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    if dir.join("scenes").is_dir() {
        return Some(dir);
    }
    if std::env::var("CI").as_deref() == Ok("true") {
        panic!("CI=true but the shared data is missing at {}", dir.display());
    }
    eprintln!("skipping: no shared data at {}", dir.display());
    None
}

/// A fresh directory under the system temp dir, removed with everything in it when dropped.
pub struct TestDir(tempfile::TempDir);

impl std::ops::Deref for TestDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for TestDir {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<std::ffi::OsStr> for TestDir {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.0.path().as_os_str()
    }
}

/// A [`TestDir`] named `scone-it-{name}-...`.
pub fn temp_dir(name: &str) -> TestDir {
    TestDir(tempfile::Builder::new().prefix(&format!("scone-it-{name}-")).tempdir().unwrap())
}
