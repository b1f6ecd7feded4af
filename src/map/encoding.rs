//! How stored values become bytes: the encoding of a map file's bodies (log records, object-storage segments,
//! a snapshot's core and its keyframes' payloads), chosen by the format version in the file's header
//! ([`crate::map::storage::format`] lists the versions; the framing, lengths and checksums around the bodies
//! are the same in every format).
//!
//! * Format 4 on: [`postcard`], whose wire format is specified and stable since its 1.0: integers and
//!   lengths as varints, `f32`/`f64` as their little-endian bytes, byte strings in one piece.
//! * Formats 1 to 3: bincode 1's fixed-width layout (little-endian integers, u64 lengths, u32 enum tags),
//!   read so that maps written by earlier builds open and are rewritten in the current format; the service
//!   never writes it ([`encode_bincode1`] is for tests that make maps of those formats). bincode 1.3 is
//!   unmaintained (RUSTSEC-2025-0141) and no maintained crate reads its layout through serde, so it stays a
//!   dependency of this module and of no other.
//!
//! Nothing outside this module names either crate.

use std::io::Read;

use serde::de::DeserializeOwned;
use serde::Serialize;

/// The first format whose bodies are postcard.
pub const FIRST_POSTCARD_FORMAT: u32 = 4;

/// The encoding of a file's bodies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    /// Formats 1 to 3 (read only).
    Bincode1,
    /// Format 4 on.
    Postcard,
}

impl Encoding {
    /// What this build writes.
    pub const CURRENT: Encoding = Encoding::Postcard;

    /// The encoding of the bodies of a file of format `version`.
    pub const fn of_format(version: u32) -> Self {
        if version >= FIRST_POSTCARD_FORMAT {
            Encoding::Postcard
        } else {
            Encoding::Bincode1
        }
    }

    /// Decodes one value that fills `bytes` (postcard refuses bytes after it; bincode 1's layout, as its
    /// writers read it, ignores them).
    pub fn decode<T: DeserializeOwned>(self, bytes: &[u8]) -> Result<T, String> {
        match self {
            Encoding::Postcard => match postcard::take_from_bytes::<T>(bytes) {
                Ok((value, [])) => Ok(value),
                Ok((_, rest)) => Err(format!("{} bytes after the value", rest.len())),
                Err(e) => Err(e.to_string()),
            },
            Encoding::Bincode1 => bincode::deserialize(bytes).map_err(|e| e.to_string()),
        }
    }

    /// Decodes one value from `reader`, which holds `len` bytes, reading no more than it needs (the caller
    /// reads what is left: for its checksum, and to find bytes after the value).
    pub fn decode_from<T: DeserializeOwned, R: Read>(self, reader: &mut R, len: u64) -> Result<T, String> {
        match self {
            Encoding::Postcard => {
                // Scratch for byte strings borrowed from the input; owned values (all this crate decodes)
                // only pass through it, one at a time.
                let mut scratch = vec![0u8; 1 << 16];
                postcard::from_io::<T, _>((reader, &mut scratch)).map(|(value, _)| value).map_err(|e| e.to_string())
            }
            Encoding::Bincode1 => {
                use bincode::Options;
                bincode::DefaultOptions::new()
                    .with_fixint_encoding()
                    .allow_trailing_bytes()
                    .with_limit(len)
                    .deserialize_from(reader)
                    .map_err(|e| e.to_string())
            }
        }
    }
}

/// The bytes of `value` in the current encoding.
pub fn encode<T: Serialize + ?Sized>(value: &T) -> Result<Vec<u8>, String> {
    postcard::to_allocvec(value).map_err(|e| e.to_string())
}

/// The bytes of `value` in bincode 1's layout, as formats 1 to 3 hold it: for tests that make maps of those
/// formats (the unit tests, and the integration tests through [`crate::map::storage::snapshot::encode_snapshot_v3`]
/// and [`crate::map::storage::format::encode_record_bincode1`]). The service never writes them.
pub fn encode_bincode1<T: Serialize + ?Sized>(value: &T) -> Vec<u8> {
    bincode::serialize(value).expect("test values encode")
}
