//! Maps: keyframes, landmarks and their SConE observations, stored durably (snapshot + write-ahead log) with
//! a nearest-neighbour index per map.
//!
//! Status: the data model, durable storage and the index are here; map building from posed keyframes,
//! relocalisation and the map registry follow.

pub mod builder;
pub mod index;
pub mod localize;
pub mod model;
pub mod storage;
pub mod store;
#[cfg(test)]
mod tests;
