//! The description path: what turns an image (or a client's keypoints) into the SConE embeddings that are
//! matched and stored. An image is decoded to grey ([`decode`]), FAST finds keypoints on a pyramid and FREAK
//! describes them ([`features`]), each keypoint gets its context, either the ring context sampled from the
//! image around it ([`ring_context`], what the shipped model reads) or its constellation of nearest keypoints
//! ([`constellation`], the paper's), and the network embeds the lot ([`embedding`]). [`pipeline`] runs these
//! stages in that order, with stage times; the service, the commands and the evaluation all go through it.
//!
//! Who imports whom, top to bottom (each module imports only from those after it; `tools/check_imports.py`
//! checks it): [`pipeline`] -> [`embedding`] -> [`constellation`] -> [`features`] (which samples the ring
//! context of the keypoints it finds) -> [`ring_context`] -> [`decode`].
//!
//! - [`decode`]: encoded image bytes -> grey image, with size limits checked before decoding; depth PNGs;
//! - [`features`]: FAST on an image pyramid with grid bucketing, FREAK descriptors; validation of keypoints
//!   supplied by clients (the client contract);
//! - [`ring_context`]: the ring context, the image around each keypoint sampled at fixed places in its frame;
//! - [`constellation`]: each keypoint's k nearest keypoints with relative geometry in its own frame;
//! - [`embedding`]: the SConE network in ONNX Runtime, checked against its contract when loaded;
//! - [`pipeline`]: the one function chain over the stages above ([`pipeline::Describer`]).

pub mod constellation;
pub mod decode;
pub mod embedding;
pub mod features;
pub mod pipeline;
pub mod ring_context;
