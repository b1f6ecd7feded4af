//! Scratch directories for tests, shared by the unit tests and (through `#[path]`) the integration tests.

use std::path::Path;

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

/// A [`TestDir`] named `scone-{name}-...`.
pub fn temp_dir(name: &str) -> TestDir {
    TestDir(tempfile::Builder::new().prefix(&format!("scone-{name}-")).tempdir().unwrap())
}
