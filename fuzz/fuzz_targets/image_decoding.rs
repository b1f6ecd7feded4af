//! Arbitrary bytes as an uploaded image: the header parser that enforces the limits before decoding, then
//! OpenCV's decoders behind it (small limits, so each input decodes quickly). Nothing may panic or crash;
//! every refusal must be the client's error.
#![no_main]

use libfuzzer_sys::fuzz_target;
use scone::describe::decode::{decode_grey, read_header, ImageLimitSettings};
use scone::service::{ErrorKind, ServiceError};

fuzz_target!(|data: &[u8]| {
    let _ = read_header(data);
    let limits = ImageLimitSettings { max_bytes: 1 << 20, max_width: 256, max_height: 256, max_pixels: 65_536 };
    match decode_grey(data, &limits) {
        Ok(img) => assert!(img.width() <= 256 && img.height() <= 256),
        Err(e) => assert_eq!(ServiceError::from(e).kind(), ErrorKind::InvalidArgument, "{data:?}"),
    }
});
