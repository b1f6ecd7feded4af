//! The multipart layouts and binary bodies, for the OpenAPI document (`body::read_body` reads them).

use utoipa::ToSchema;

/// Raw bytes: an image (PNG or JPEG), a picture the service drew (PNG), or a map file.
#[derive(ToSchema)]
#[schema(value_type = String, format = Binary)]
#[allow(dead_code)] // Documentation of a binary body; the bytes are read and sent as they are.
pub struct Binary(Vec<u8>);

/// A one-frame request as `multipart/form-data`: the JSON fields in a part named `request`, the image as a
/// file part.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct FrameForm {
    /// The request's JSON fields (as the `application/json` body), optional when the image is all.
    request: Option<String>,
    /// PNG or JPEG.
    #[schema(value_type = Option<String>, format = Binary)]
    image: Option<Vec<u8>>,
}

/// A MatchPair request as `multipart/form-data`.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct PairForm {
    /// The request's JSON fields (as the `application/json` body: intrinsics of each frame, ratio, ...).
    request: Option<String>,
    /// Frame 1's image (the part may also be named `image`).
    #[schema(value_type = Option<String>, format = Binary)]
    image1: Option<Vec<u8>>,
    /// Frame 2's image.
    #[schema(value_type = Option<String>, format = Binary)]
    image2: Option<Vec<u8>>,
}

/// An AddKeyframe request as `multipart/form-data`.
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct KeyframeForm {
    /// The request's JSON fields (keyframe_id, pose, intrinsics, ...).
    request: String,
    /// PNG or JPEG.
    #[schema(value_type = Option<String>, format = Binary)]
    image: Option<Vec<u8>>,
    /// 16-bit PNG depth aligned with the image.
    #[schema(value_type = Option<String>, format = Binary)]
    depth: Option<Vec<u8>>,
}

/// A LocalizeTrack request as `multipart/form-data`: the JSON in `request`, each frame's image as the part
/// `trackN` (N its position in `frames`, 0-9).
#[derive(ToSchema)]
#[allow(dead_code)] // Documentation of the multipart layout that `body::read_body` reads.
pub struct TrackForm {
    /// The request's JSON fields (frames with their poses and intrinsics, estimate_scale, ...).
    request: String,
    /// Frame 0's image (PNG or JPEG); likewise `track1` .. `track9`.
    #[schema(value_type = Option<String>, format = Binary)]
    track0: Option<Vec<u8>>,
    /// Frame 1's image.
    #[schema(value_type = Option<String>, format = Binary)]
    track1: Option<Vec<u8>>,
}
