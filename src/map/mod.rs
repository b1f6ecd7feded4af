//! Maps: keyframes, landmarks and their SConE observations, stored durably with a nearest-neighbour index per
//! map.
//!
//! Who imports whom, top to bottom (nothing imports back up): [`store`] -> [`local`] / [`s3`] (the two
//! backends, which implement the traits of [`journal`]) -> [`index`] (the object-storage backend moves its
//! dumps) -> [`format`](mod@format) (the shared bytes) -> [`model`]; beside them [`localize`] and [`builder`],
//! which the store calls and which import only the model and the index.
//!
//! - [`store`]: the registry of maps that commands (and the service) write and query through; it opens the
//!   backend that `[store.backend]` names ([`store::BackendConfig`]);
//! - [`journal`]: what the store needs from storage, as traits: the collection of maps, one map's writer;
//! - [`local`]: maps in a local directory (snapshot + fsync'd write-ahead log);
//! - [`s3`]: maps in an S3-API bucket (immutable objects, a manifest replaced conditionally);
//! - [`format`](mod@format): the byte formats both backends share (snapshot, log records, segments) and their versions;
//! - [`model`]: keyframes, landmarks, observations, the records that change them, map ids;
//! - [`index`]: exact / HNSW nearest-neighbour search over observation embeddings;
//! - [`builder`]: which landmarks a posed keyframe observes or creates (depth or triangulation);
//! - [`localize`]: 2D-3D matching and PnP against a map.

pub mod builder;
#[cfg(test)]
mod cache_tests;
#[cfg(test)]
mod fault_tests;
pub mod format;
pub mod index;
pub mod journal;
pub mod local;
pub mod localize;
pub mod model;
pub mod s3;
pub mod store;
#[cfg(test)]
mod tests;
