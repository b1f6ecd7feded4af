use std::path::PathBuf;

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

pub use crate::test_dir::temp_dir;
