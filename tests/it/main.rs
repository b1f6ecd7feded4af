//! Integration tests, one binary. Tests that read the real scenes in `../shared/data` (or `$SCONE_DATA`)
//! skip when the data is absent, except under `CI=true`, where missing data is a failure.

mod colmap;
mod common;
mod console;
mod conventions;
mod durability;
mod embedding;
mod eval_cli;
mod full_disk;
mod hostile;
mod input_bounds;
mod keys;
mod lenses;
mod merge;
mod object_store;
mod pipeline;
mod raw;
mod replicas;
mod restarts;
mod ring;
mod service;
mod storage_faults;
#[path = "../../src/test_dir.rs"]
mod test_dir;
mod track;
mod upgrade;
