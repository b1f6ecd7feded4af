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
//! The description path, in the order an image takes it:
//! - [`decode`]: encoded image bytes -> grey image, with size limits checked before decoding; depth PNGs;
//! - [`features`]: FAST on an image pyramid with grid bucketing, FREAK descriptors; validation of keypoints
//!   supplied by clients (the client contract);
//! - [`constellation`]: each keypoint's k nearest keypoints with relative geometry in its own frame;
//! - [`context`]: the ring context, the image around each keypoint sampled at fixed places in its frame;
//! - [`embedding`]: the SConE network in ONNX Runtime, checked against its contract when loaded;
//! - [`pipeline`]: the one function chain over the four above ([`pipeline::Describer`]), with stage times.
//!
//! Geometry and matching:
//! - [`camera`]: intrinsics and camera-to-world poses, their checks and quaternion conversions;
//! - [`matching`]: nearest-neighbour matching with the ratio test, and the SConE matchers that add FREAK;
//! - [`nearest`]: brute-force neighbours in both directions (the mutual check), OpenCV's answer to the bit;
//! - [`pose`]: relative pose (essential matrix) and absolute pose (PnP) with OpenCV's RANSAC;
//! - [`render`]: pictures of matches and localisations (PNG) for people debugging the service.
//!
//! Maps and the service:
//! - [`map`]: landmarks with their SConE observations, durable storage (local or S3), the ANN index,
//!   relocalisation;
//! - [`service`]: the operations the API offers, in domain types, with one error type for clients;
//! - [`cpu_pool`]: the bounded CPU pool every request's CPU work runs on;
//! - [`settings`]: the server's typed, layered configuration;
//! - [`server`]: the gRPC and HTTP transports, auth, connection limits, metrics, life cycle;
//! - [`error`]: the error types of the core modules.
//!
//! Offline: [`offline`] (scene reader, COLMAP import, training-feature export, evaluation), with
//! [`progress`] (a bar or log lines) on its long jobs.
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
//! 3. [`pipeline::Describer`] decodes ([`decode::decode_grey`]), extracts FAST + FREAK
//!    ([`features::extract`]), builds constellations ([`constellation::build`]) and embeds them
//!    ([`embedding::Embedder`]), recording each stage's time;
//! 4. [`map::store::MapStore::localize`] searches the map's HNSW index ([`map::index`]) for each embedding's
//!    nearest landmark observations, ratio-tests them into 2D-3D matches and runs PnP
//!    ([`pose::absolute_pose`], in [`map::localize`]);
//! 5. the outcome (pose, matches, inliers, confidence) goes back as JSON, its stage times to `/metrics`;
//!    a [`service::ServiceError`] becomes one HTTP status through the transport's single error mapping.
//!
//! The gRPC `Localize` call ([`server::grpc`]) takes the same path from step 2.

pub mod camera;
pub mod constellation;
pub mod context;
pub mod cpu_pool;
pub mod decode;
pub mod embedding;
pub mod error;
pub mod features;
pub mod map;
pub mod matching;
pub mod nearest;
pub mod offline;
pub mod pipeline;
pub mod pose;
pub mod progress;
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
