//! Maps: keyframes, landmarks and their SConE observations, stored durably with a nearest-neighbour index per
//! map.
//!
//! Who imports whom, top to bottom (each module imports only from those after it; `tools/check_imports.py`
//! checks it): [`store`] (the registry commands and the service go through) -> [`cache`] (which maps are in
//! memory, and how fresh) / [`merge`] / [`builder`] -> [`localize`] -> [`index`] (which reads and writes its
//! dumps through [`storage::format`]) -> [`storage`] (where maps are kept: the backends, their traits and their
//! bytes) -> [`model`] -> [`payload`] ->
//! [`encoding`].
//!
//! - [`store`]: create, list, delete, write keyframes, localise, export and import;
//! - [`cache`]: the loaded maps: eager or lazy loading, eviction within a memory budget, freshness checks;
//! - [`storage`]: the traits ([`storage::backend`]), the local directory ([`storage::local`]), object storage
//!   ([`storage::s3`]), the shared byte formats ([`storage::format`]) and `[store.backend]`;
//! - [`model`]: keyframes, landmarks, observations, the records that change them, map ids;
//! - [`payload`]: a keyframe's keypoints, descriptors and embeddings, in memory until a snapshot holds them,
//!   then read from its file on demand;
//! - [`encoding`]: the encodings of stored bodies (postcard; bincode 1, read only, for formats 1 to 3);
//! - [`index`]: exact / HNSW nearest-neighbour search over observation embeddings, and its dump;
//! - [`builder`]: which landmarks a posed keyframe observes or creates (depth or triangulation);
//! - [`localize`]: 2D-3D matching and PnP against a map;
//! - [`merge`]: one map merged into another (the transform between them estimated from localised keyframes).

pub mod builder;
pub mod cache;
pub mod encoding;
pub mod index;
pub mod localize;
pub mod merge;
pub mod model;
pub mod payload;
pub mod storage;
pub mod store;
#[cfg(test)]
mod tests;
