//! scone: image matching and relocalisation with the SConE constellation descriptor
//! (Trzcinski et al., "SConE: Siamese Constellation Embedding Descriptor for Image Matching").
//!
//! Layout (the core modules never import a transport; only [`server`] knows tonic and axum):
//!
//! - [`decode`]: encoded image bytes -> grey image, with size limits checked before decoding.
//! - [`features`]: FAST on an image pyramid with grid bucketing, FREAK descriptors; validation of keypoints
//!   supplied by clients. The single extraction path for the service, evaluation and training export.
//! - [`constellation`]: each keypoint's k nearest keypoints with relative geometry in its own frame.
//! - [`matching`]: nearest-neighbour matching with ratio test (and mutual check).
//! - [`scene`]: scenes on disk in the TUM RGB-D layout (frames, poses, intrinsics, depth).
//! - [`colmap`]: maps made by an external SfM: COLMAP text models, imported through the map store.
//! - [`export`]: a scene's features and constellations as `.npz` for training.
//!
//! - [`map`]: maps of landmarks with their SConE observations, durable storage, the ANN index, relocalisation.
//! - [`service`]: the operations the API offers, in domain types; [`workers`]: the bounded CPU pool.
//! - [`settings`]: the server's typed, layered configuration; [`server`]: the gRPC and HTTP transports.
//!
//! Path of an image: bytes -> [`decode::decode_grey`] -> [`features::extract`] -> [`constellation::build`]
//! -> (the embedding network) -> matching and pose estimation.

pub mod camera;
pub mod constellation;
pub mod decode;
pub mod embedding;
pub mod error;
pub mod features;
pub mod map;
pub mod matching;
pub mod offline;
pub mod pipeline;
pub mod pose;
pub mod server;
pub mod service;
pub mod settings;
#[cfg(test)]
pub(crate) mod test_dir;
pub mod workers;

pub use error::{EmbeddingError, FeatureError, ImportError, MapError, PoseError, SceneError};
