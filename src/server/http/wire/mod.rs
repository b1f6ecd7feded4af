//! The HTTP API's JSON: every request and response body, typed, with the conversions from the service's
//! domain types. The OpenAPI document's schemas are generated from these structs (their doc comments are the
//! descriptions), so what is documented is what is parsed and sent.
//!
//! Conventions: poses are camera-to-world with quaternions (x, y, z, w) and OpenCV camera axes (x right, y
//! down, z forward); pixels have (0, 0) at the centre of the top-left pixel; binary data in JSON is base64.
//!
//! Rooms: `common.rs` (what several bodies share), `frames.rs` (Describe, MatchPair, Localize,
//! LocalizeTrack), `maps.rs` (the map routes), `forms.rs` (multipart layouts and binary bodies, documented),
//! `examples.rs` (the documented example requests).

mod common;
pub mod examples;
mod forms;
mod frames;
mod maps;

pub use common::*;
pub use forms::*;
pub use frames::*;
pub use maps::*;
