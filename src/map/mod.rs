//! Maps: keyframes, landmarks and their SConE observations, stored durably (snapshot + write-ahead log) with
//! a nearest-neighbour index per map.
//!
//! - [`model`]: keyframes, landmarks, observations, and the records that change them;
//! - [`storage`]: snapshot + checksummed write-ahead log of one map;
//! - [`backend`]: where maps are stored, behind one trait: the local directory or [`object_storage`];
//! - [`object_storage`]: maps in an S3-API bucket (immutable objects, a manifest replaced conditionally);
//! - [`index`]: exact / HNSW nearest-neighbour search over observation embeddings;
//! - [`builder`]: which landmarks a posed keyframe observes or creates (depth or triangulation);
//! - [`localize`]: 2D-3D matching and PnP against a map;
//! - [`store`]: the registry of maps that commands (and the service) write and query through.

pub mod backend;
pub mod builder;
pub mod index;
pub mod localize;
pub mod model;
pub mod object_storage;
pub mod storage;
pub mod store;
#[cfg(test)]
mod tests;
