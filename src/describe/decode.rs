//! Image decoding with limits checked before anything large is allocated.
//!
//! Every image reaching the service is hostile until proven otherwise: the byte length is checked first,
//! then the format and the dimensions are read from the container header (PNG `IHDR`, JPEG `SOFn`) without
//! decoding, and only an image within [`ImageLimitSettings`] is handed to OpenCV's decoder. A decoder failure or a
//! result whose size disagrees with the header is reported as a corrupt image.

use opencv::core::{Mat, Vector};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use serde::{Deserialize, Serialize};

use crate::error::FeatureError;

/// Limits applied to every encoded image before decoding.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImageLimitSettings {
    /// Largest accepted encoded size in bytes.
    pub max_bytes: usize,
    /// Largest accepted width in pixels.
    pub max_width: u32,
    /// Largest accepted height in pixels.
    pub max_height: u32,
    /// Largest accepted width x height.
    pub max_pixels: u64,
}

impl ImageLimitSettings {
    /// Width, height and width x height against the limits; `names` say what each is in the error (an
    /// image's header, or a client's keypoint set).
    pub fn check_dimensions(&self, width: u32, height: u32, names: [&'static str; 3]) -> Result<(), FeatureError> {
        let checks = [
            (names[0], width as u64, self.max_width as u64),
            (names[1], height as u64, self.max_height as u64),
            (names[2], width as u64 * height as u64, self.max_pixels),
        ];
        for (what, value, max) in checks {
            if value > max {
                return Err(FeatureError::ImageTooLarge { what, value, max });
            }
        }
        Ok(())
    }
}

impl Default for ImageLimitSettings {
    fn default() -> Self {
        Self { max_bytes: 16 << 20, max_width: 4096, max_height: 4096, max_pixels: 12_000_000 }
    }
}

/// Encoded formats the service accepts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    Png,
    Jpeg,
}

/// Format and size read from an encoded image's header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ImageHeader {
    pub format: ImageFormat,
    pub width: u32,
    pub height: u32,
}

/// A decoded 8-bit single-channel image.
#[derive(Debug)]
pub struct GreyImage {
    mat: Mat,
}

impl GreyImage {
    /// Wraps an 8-bit single-channel OpenCV matrix.
    pub fn from_mat(mat: Mat) -> Result<Self, FeatureError> {
        if mat.typ() != opencv::core::CV_8UC1 || mat.empty() {
            return Err(FeatureError::CorruptImage { reason: "expected a non-empty 8-bit grey image".into() });
        }
        Ok(Self { mat })
    }

    /// The underlying matrix.
    pub fn mat(&self) -> &Mat {
        &self.mat
    }

    pub fn width(&self) -> u32 {
        self.mat.cols() as u32
    }

    pub fn height(&self) -> u32 {
        self.mat.rows() as u32
    }
}

/// Reads format and dimensions from a PNG or JPEG header without decoding pixels.
pub fn read_header(bytes: &[u8]) -> Result<ImageHeader, FeatureError> {
    if bytes.is_empty() {
        return Err(FeatureError::EmptyImage);
    }
    const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    if bytes.starts_with(&PNG_SIGNATURE) {
        // Signature, then the first chunk must be IHDR: length (4) "IHDR" (4) width (4) height (4).
        if bytes.len() < 24 || &bytes[12..16] != b"IHDR" {
            return Err(FeatureError::CorruptImage { reason: "PNG without an IHDR header".into() });
        }
        let width = u32::from_be_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]);
        let height = u32::from_be_bytes([bytes[20], bytes[21], bytes[22], bytes[23]]);
        return Ok(ImageHeader { format: ImageFormat::Png, width, height });
    }
    if bytes.starts_with(&[0xff, 0xd8]) {
        return jpeg_header(bytes);
    }
    Err(FeatureError::UnsupportedFormat)
}

/// Walks the JPEG marker segments up to the first start-of-frame marker.
fn jpeg_header(bytes: &[u8]) -> Result<ImageHeader, FeatureError> {
    let corrupt = |reason: &str| FeatureError::CorruptImage { reason: reason.to_string() };
    let mut pos = 2;
    loop {
        // Markers may be preceded by any number of 0xff fill bytes.
        while pos < bytes.len() && bytes[pos] == 0xff {
            pos += 1;
        }
        let marker = *bytes.get(pos).ok_or_else(|| corrupt("JPEG ends before a frame header"))?;
        pos += 1;
        match marker {
            // Standalone markers without a length field.
            0x01 | 0xd0..=0xd7 => continue,
            0xd9 | 0xda => return Err(corrupt("JPEG without a frame header before its scan")),
            _ => {}
        }
        if pos + 2 > bytes.len() {
            return Err(corrupt("JPEG segment length truncated"));
        }
        let len = u16::from_be_bytes([bytes[pos], bytes[pos + 1]]) as usize;
        if len < 2 {
            return Err(corrupt("JPEG segment length below 2"));
        }
        // SOF0..SOF15 except DHT (c4), JPG (c8) and DAC (cc) carry precision, height, width.
        let is_sof = matches!(marker, 0xc0..=0xcf) && !matches!(marker, 0xc4 | 0xc8 | 0xcc);
        if is_sof {
            if pos + 7 > bytes.len() {
                return Err(corrupt("JPEG frame header truncated"));
            }
            let height = u16::from_be_bytes([bytes[pos + 3], bytes[pos + 4]]) as u32;
            let width = u16::from_be_bytes([bytes[pos + 5], bytes[pos + 6]]) as u32;
            return Ok(ImageHeader { format: ImageFormat::Jpeg, width, height });
        }
        pos += len;
    }
}

/// Checks the encoded size and the header dimensions against `limits`.
pub fn check_limits(bytes: &[u8], limits: &ImageLimitSettings) -> Result<ImageHeader, FeatureError> {
    if bytes.len() > limits.max_bytes {
        return Err(FeatureError::ImageTooLarge {
            what: "encoded bytes",
            value: bytes.len() as u64,
            max: limits.max_bytes as u64,
        });
    }
    let header = read_header(bytes)?;
    if header.width == 0 || header.height == 0 {
        return Err(FeatureError::CorruptImage { reason: "zero width or height in header".into() });
    }
    limits.check_dimensions(header.width, header.height, ["width", "height", "pixels"])?;
    Ok(header)
}

/// Decodes a PNG or JPEG into a grey image, enforcing `limits` before decoding.
///
/// Colour images are converted with OpenCV's BGR-to-grey weights (0.299 R + 0.587 G + 0.114 B), as
/// `imread(..., IMREAD_GRAYSCALE)` does.
pub fn decode_grey(bytes: &[u8], limits: &ImageLimitSettings) -> Result<GreyImage, FeatureError> {
    let header = check_limits(bytes, limits)?;
    let buf = Vector::<u8>::from_slice(bytes);
    let decoded = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_UNCHANGED)
        .map_err(|e| FeatureError::CorruptImage { reason: format!("decoder error: {}", e.message) })?;
    if decoded.empty() {
        return Err(FeatureError::CorruptImage { reason: "the decoder could not read the image".into() });
    }
    if decoded.cols() as u32 != header.width || decoded.rows() as u32 != header.height {
        return Err(FeatureError::CorruptImage {
            reason: format!(
                "decoded size {}x{} differs from header {}x{}",
                decoded.cols(),
                decoded.rows(),
                header.width,
                header.height
            ),
        });
    }
    to_grey_u8(decoded).map(|mat| GreyImage { mat })
}

/// Converts an 8- or 16-bit image with 1, 3 or 4 channels to 8-bit grey.
fn to_grey_u8(mat: Mat) -> Result<Mat, FeatureError> {
    let depth = mat.depth();
    let eight_bit = if depth == opencv::core::CV_8U {
        mat
    } else if depth == opencv::core::CV_16U {
        let mut out = Mat::default();
        mat.convert_to(&mut out, opencv::core::CV_8U, 1.0 / 257.0, 0.0)?;
        out
    } else {
        return Err(FeatureError::UnsupportedFormat);
    };
    let code = match eight_bit.channels() {
        1 => return Ok(eight_bit),
        3 => imgproc::COLOR_BGR2GRAY,
        4 => imgproc::COLOR_BGRA2GRAY,
        _ => return Err(FeatureError::UnsupportedFormat),
    };
    let mut grey = Mat::default();
    imgproc::cvt_color_def(&eight_bit, &mut grey, code)?;
    Ok(grey)
}

/// Raw units per metre of a TUM RGB-D depth image (16-bit PNG; 0 = no reading).
pub const TUM_DEPTH_PER_METRE: f64 = 5000.0;
/// Metres per raw unit of a TUM RGB-D depth image: the default depth scale of every transport and command.
pub const TUM_DEPTH_SCALE: f64 = 1.0 / TUM_DEPTH_PER_METRE;

/// Decodes a 16-bit single-channel depth PNG (TUM convention: metres x 5000, 0 = no reading).
pub fn decode_depth_png(bytes: &[u8], limits: &ImageLimitSettings) -> Result<Mat, FeatureError> {
    let header = check_limits(bytes, limits)?;
    if header.format != ImageFormat::Png {
        return Err(FeatureError::CorruptImage { reason: "depth images must be 16-bit PNG".into() });
    }
    let buf = Vector::<u8>::from_slice(bytes);
    let depth = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_ANYDEPTH)
        .map_err(|e| FeatureError::CorruptImage { reason: format!("decoder error: {}", e.message) })?;
    if depth.empty() || depth.typ() != opencv::core::CV_16UC1 {
        return Err(FeatureError::CorruptImage { reason: "depth image is not 16-bit single-channel".into() });
    }
    Ok(depth)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encode(mat: &Mat, ext: &str) -> Vec<u8> {
        let mut buf = Vector::<u8>::new();
        imgcodecs::imencode_def(ext, mat, &mut buf).unwrap();
        buf.to_vec()
    }

    fn gradient(w: i32, h: i32) -> Mat {
        let mut m = Mat::new_rows_cols_with_default(h, w, opencv::core::CV_8UC3, 0.into()).unwrap();
        for y in 0..h {
            for x in 0..w {
                *m.at_2d_mut::<opencv::core::Vec3b>(y, x).unwrap() =
                    opencv::core::Vec3b::from([(x % 256) as u8, (y % 256) as u8, ((x + y) % 256) as u8]);
            }
        }
        m
    }

    #[test]
    fn png_and_jpeg_headers_give_dimensions() {
        let img = gradient(37, 21);
        for (ext, format) in [(".png", ImageFormat::Png), (".jpg", ImageFormat::Jpeg)] {
            let bytes = encode(&img, ext);
            let header = read_header(&bytes).unwrap();
            assert_eq!(header, ImageHeader { format, width: 37, height: 21 });
            let grey = decode_grey(&bytes, &ImageLimitSettings::default()).unwrap();
            assert_eq!((grey.width(), grey.height()), (37, 21));
            assert_eq!(grey.mat().typ(), opencv::core::CV_8UC1);
        }
    }

    #[test]
    fn empty_input_is_rejected() {
        assert!(matches!(decode_grey(&[], &ImageLimitSettings::default()), Err(FeatureError::EmptyImage)));
    }

    #[test]
    fn unknown_format_is_rejected() {
        let err = decode_grey(b"GIF89a this is not supported", &ImageLimitSettings::default()).unwrap_err();
        assert!(matches!(err, FeatureError::UnsupportedFormat), "{err}");
    }

    #[test]
    fn truncated_png_is_corrupt() {
        let bytes = encode(&gradient(64, 64), ".png");
        let err = decode_grey(&bytes[..bytes.len() / 2], &ImageLimitSettings::default()).unwrap_err();
        assert!(matches!(err, FeatureError::CorruptImage { .. }), "{err}");
        let err = decode_grey(&bytes[..20], &ImageLimitSettings::default()).unwrap_err();
        assert!(matches!(err, FeatureError::CorruptImage { .. }), "{err}");
    }

    #[test]
    fn garbage_after_jpeg_magic_is_corrupt() {
        let mut bytes = vec![0xff, 0xd8, 0xff, 0xe0, 0x00, 0x10];
        bytes.extend_from_slice(&[0u8; 14]);
        let err = decode_grey(&bytes, &ImageLimitSettings::default()).unwrap_err();
        assert!(matches!(err, FeatureError::CorruptImage { .. }), "{err}");
    }

    #[test]
    fn corrupted_jpeg_body_is_corrupt() {
        let mut bytes = encode(&gradient(64, 64), ".jpg");
        let n = bytes.len();
        // Keep the headers, destroy the entropy-coded data and the end marker.
        for b in &mut bytes[n / 2..] {
            *b = 0xff;
        }
        match decode_grey(&bytes, &ImageLimitSettings::default()) {
            Err(FeatureError::CorruptImage { .. }) => {}
            // libjpeg may recover a damaged scan with grey filler; the size must still match.
            Ok(img) => assert_eq!((img.width(), img.height()), (64, 64)),
            Err(e) => panic!("unexpected error {e}"),
        }
    }

    #[test]
    fn header_claiming_huge_dimensions_is_refused_before_decoding() {
        // A valid PNG signature and IHDR claiming 100000 x 100000 pixels, with no pixel data at all.
        let mut bytes = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a, 0, 0, 0, 13];
        bytes.extend_from_slice(b"IHDR");
        bytes.extend_from_slice(&100_000u32.to_be_bytes());
        bytes.extend_from_slice(&100_000u32.to_be_bytes());
        bytes.extend_from_slice(&[8, 0, 0, 0, 0, 0, 0, 0, 0]);
        let err = decode_grey(&bytes, &ImageLimitSettings::default()).unwrap_err();
        assert!(matches!(err, FeatureError::ImageTooLarge { what: "width", .. }), "{err}");
    }

    #[test]
    fn pixel_and_byte_limits_apply() {
        let bytes = encode(&gradient(100, 100), ".png");
        let limits = ImageLimitSettings { max_pixels: 9_999, ..ImageLimitSettings::default() };
        let err = decode_grey(&bytes, &limits).unwrap_err();
        assert!(matches!(err, FeatureError::ImageTooLarge { what: "pixels", .. }), "{err}");
        let limits = ImageLimitSettings { max_bytes: bytes.len() - 1, ..ImageLimitSettings::default() };
        let err = decode_grey(&bytes, &limits).unwrap_err();
        assert!(matches!(err, FeatureError::ImageTooLarge { what: "encoded bytes", .. }), "{err}");
        let limits = ImageLimitSettings { max_height: 99, ..ImageLimitSettings::default() };
        let err = decode_grey(&bytes, &limits).unwrap_err();
        assert!(matches!(err, FeatureError::ImageTooLarge { what: "height", .. }), "{err}");
    }
}
