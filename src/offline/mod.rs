//! Offline tooling: what the `scone` commands use besides serving, and what the service never calls. A reader
//! of the service can skip this whole directory.
//!
//! - [`scene`]: scenes on disk in the TUM RGB-D layout (frames, poses, intrinsics, depth);
//! - [`colmap`]: maps made by an external SfM: COLMAP text models, imported through the map store
//!   (`scone map import-colmap`);
//! - [`training_features`]: a scene's features and constellations as `.npz` for training (`scone features`);
//! - [`eval`]: the evaluation protocol on real scenes: pair matching with relative pose, relocalisation
//!   (`scone eval pairs`, `scone eval reloc`);
//! - [`progress`]: a progress bar on a terminal, log lines otherwise, for the long jobs above.

pub mod colmap;
pub mod eval;
pub mod progress;
pub mod scene;
pub mod training_features;
