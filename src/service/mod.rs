//! The operations the service offers, in domain types: one function per RPC. A gRPC method and its HTTP twin
//! both validate their wire format, build these inputs, call the same function here and map the one
//! [`ServiceError`] through [`ServiceError::kind`]. Nothing here knows about tonic, axum or HTTP.
//!
//! Every function is synchronous and CPU-bound (OpenCV, ONNX Runtime, index search, fsync): transports call
//! them on the bounded [`crate::cpu_pool::CpuPool`], never on async worker threads.
//!
//! Maps load after the listeners are up (health says NOT_SERVING meanwhile), so the store is attached once it
//! is ready; map operations before that answer [`ServiceError::NotReady`].
//!
//! Rooms: `core.rs` (the service, its store, the lookup of a request's map), `frame.rs` (a frame's source and
//! intrinsics checked and described: Describe), `pair.rs`
//! (MatchPair), `localize.rs` (Localize), `track.rs` (LocalizeTrack), `maps.rs` (the map operations),
//! `error.rs` (what a client is told, and its class).
//! Operations on one map take the map itself: the transport looks it up once per request ([`Service::map`]).

mod core;
mod error;
mod frame;
mod localize;
mod maps;
mod pair;
mod track;

pub use crate::camera::{Distortion, DistortionModel, PoseConvention, Similarity};
// What the transports need of the map layer, so that they import only this module.
pub use crate::map::builder::ExternalObservation;
pub use crate::map::localize::Prior;
pub use crate::map::store::{Map, MapSummary};
pub use crate::pose::{TrackScale, TrackerError};
pub use core::{Holdings, Service};
pub use error::{ErrorKind, ServiceError};
pub use frame::{Description, FrameInput, FrameSource, KeypointsInput};
pub use localize::LocalizeOutcome;
pub use maps::{KeyframeRequest, MapListing, MergeOutcome, DEFAULT_CONTENTS_LANDMARKS, MAX_CONTENTS_LANDMARKS};
pub use pair::{PairOptions, PairOutcome};
pub use track::{TrackFrameInput, TrackFrameOutcome, TrackOutcome, TrackRequest, TRACK_FRAMES};
