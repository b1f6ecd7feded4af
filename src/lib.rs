//! scone: image matching and relocalisation with the SConE constellation descriptor
//! (Trzcinski et al., "SConE: Siamese Constellation Embedding Descriptor for Image Matching").
//!
//! # Modules
//!
//! The core never imports a transport: no module outside [`server`] imports it or names tonic, axum, hyper,
//! http, tower or prost, and none outside [`offline`] (what the service never calls) imports it.
//! `tools/check_imports.py` checks both, with the layering of the module table in `docs/architecture.md`
//! ("Where things are").
//!
//! Layers, bottom first (each imports only from those before it):
//! - [`error`]: the error types of the core modules;
//! - [`cpu_pool`]: the bounded CPU pool every request's CPU work runs on;
//! - [`camera`]: intrinsics and camera-to-world poses, their checks and quaternion conversions;
//! - [`describe`]: the description path, in the order an image takes it: decode -> FAST + FREAK features ->
//!   the ring context or the constellation of each keypoint -> SConE embedding, and the pipeline that runs
//!   them ([`describe::pipeline::Describer`], with stage times);
//! - [`matching`]: nearest-neighbour matching with the ratio test, and the SConE matchers that add FREAK; its
//!   brute-force neighbours in both directions in [`matching::nearest`];
//! - [`pose`]: relative pose (essential matrix) and absolute pose (PnP) with OpenCV's RANSAC;
//! - [`render`]: pictures of matches and localisations (PNG) for people debugging the service;
//! - [`map`]: landmarks with their SConE observations, durable storage (local or S3), the ANN index,
//!   relocalisation;
//! - [`settings`]: the server's typed, layered configuration;
//! - [`service`]: the operations the API offers, in domain types, with one error type for clients;
//! - [`server`]: the gRPC and HTTP transports, auth, connection limits, metrics, life cycle;
//! - [`offline`]: what the service never calls: scene reader, COLMAP import, training-feature export,
//!   evaluation, and a progress bar (or log lines) on their long jobs.
//!
//! # One request, end to end
//!
//! `POST /v1/maps/office/localize` with a JPEG and intrinsics:
//!
//! 1. [`server::http`] refuses it at once if the CPU pool has no free slot, and checks the read key from the
//!    request head ([`server::auth`], [`server::operation`]) before it reads the body (size and time limits);
//! 2. the map is looked up once ([`server::app::App::call`]; an unknown map is refused here) and a closure
//!    runs with it on the [`cpu_pool::CpuPool`] under the request deadline: it parses the request into a
//!    [`service::FrameInput`] and calls [`service::Service::localize`], which checks the image header and the
//!    intrinsics ([`camera::validate_camera`]) before any decoding;
//! 3. [`describe::pipeline::Describer`] decodes ([`describe::decode::decode_grey`]), extracts FAST + FREAK
//!    ([`describe::features::extract`]), samples ring contexts ([`describe::ring_context`]) or builds
//!    constellations ([`describe::constellation::build`]) and embeds them ([`describe::embedding::Embedder`]),
//!    recording each stage's time;
//! 4. [`map::store::MapStore::localize`] searches the map's HNSW index ([`map::index`]) for each embedding's
//!    nearest landmark observations, ratio-tests them into 2D-3D matches and runs PnP
//!    ([`pose::absolute_pose`], in [`map::localize`]);
//! 5. the outcome (pose, matches, inliers, confidence) goes back as JSON, its stage times to `/metrics`;
//!    a [`service::ServiceError`] becomes one HTTP status through the transport's single error mapping.
//!
//! The gRPC `Localize` call ([`server::grpc`]) takes the same path from step 2.

pub mod camera;
pub mod cpu_pool;
pub mod describe;
pub mod error;
pub mod map;
pub mod matching;
pub mod offline;
pub mod pose;
pub mod render;
pub mod server;
pub mod service;
pub mod settings;
#[cfg(test)]
pub(crate) mod test_dir;

/// Rust's allocations go through mimalloc in every binary that links this crate (the service, the CLI, the
/// benches and tests alike). A map's HNSW graph is millions of small allocations, one per link: a reload of
/// the 728k bench map's graph took 0.46x glibc's time under it, in less memory
/// (`docs/history/benchmarks-log.md`, "mimalloc"). onnxruntime and OpenCV allocate through their own C++
/// runtimes, untouched by this. Not in fuzzing builds
/// (`cfg(fuzzing)`, set by cargo-fuzz), where AddressSanitizer must see every allocation.
#[cfg(not(fuzzing))]
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

pub use error::{EmbeddingError, FeatureError, ImportError, MapError, PoseError, SceneError};
