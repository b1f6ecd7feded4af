//! Reading request bodies (media types, size and time limits, multipart parts) and turning their JSON into the
//! service's frames; the query-string and path extractors, refused in the JSON envelope.

use axum::body::Bytes;
use axum::extract::{FromRequest, FromRequestParts, Multipart, Path, Query, Request};
use axum::http::request::Parts;
use axum::http::{header, HeaderMap, StatusCode, Uri};
use base64::Engine;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::error::{invalid, ApiError, ApiResult};
use super::wire::{Frame, Intrinsics};
use crate::camera::Camera;
use crate::describe::decode::read_header;
use crate::service::{Distortion, FrameInput, FrameSource, KeypointsInput, ServiceError};

/// What a request body carried.
#[derive(Default)]
pub struct Body {
    pub json: Option<Bytes>,
    pub image: Option<Bytes>,
    pub image2: Option<Bytes>,
    pub depth: Option<Bytes>,
    /// A track's images by position (parts `track0` .. `track9`).
    pub track: std::collections::BTreeMap<usize, Bytes>,
}

/// The body types each route takes (also in `openapi.json`); anything else is 415.
pub const FRAME_BODIES: &[&str] =
    &["image/jpeg", "image/png", "application/octet-stream", "application/json", "multipart/form-data"];
pub const JSON_OR_MULTIPART: &[&str] = &["application/json", "multipart/form-data"];
pub const JSON_ONLY: &[&str] = &["application/json"];
pub const MAP_FILE: &[&str] = &["application/octet-stream"];

pub fn too_large(limit: usize) -> ApiError {
    ApiError::Service(ServiceError::TooLarge { what: "the request body".into(), limit })
}

/// Why reading a body failed: too long, too slow, or the client's stream broke.
pub fn body_error(e: &(dyn std::error::Error + 'static), too_large: ApiError) -> ApiError {
    if let Some(ms) = crate::server::connections::body_timed_out(e) {
        return ApiError::BodyTimeout { ms };
    }
    let mut cur = Some(e);
    while let Some(err) = cur {
        if err.is::<http_body_util::LengthLimitError>() {
            return too_large;
        }
        cur = err.source();
    }
    invalid("body", "the request body could not be read")
}

/// The media type of the request body, if the route takes it. A request without `Content-Type` passes only
/// when it has no body.
pub fn media_type(headers: &HeaderMap, accepted: &'static [&'static str]) -> ApiResult<String> {
    // A compressed body would be read as the image or JSON it is not: refused (images are compressed
    // already, and a decompressed body could outgrow the limits its compressed size passed).
    if let Some(encoding) = headers.get(header::CONTENT_ENCODING) {
        let encoding = encoding.to_str().unwrap_or("(not text)").trim().to_ascii_lowercase();
        if encoding != "identity" {
            return Err(ApiError::UnsupportedEncoding { got: encoding });
        }
    }
    let raw = headers.get(header::CONTENT_TYPE).map(|v| v.to_str().unwrap_or("(not text)"));
    let mime = raw.map(|ct| ct.split(';').next().unwrap_or("").trim().to_ascii_lowercase()).unwrap_or_default();
    if accepted.contains(&mime.as_str()) {
        return Ok(mime);
    }
    let empty = match headers.get(header::CONTENT_LENGTH) {
        Some(n) => n.as_bytes() == b"0",
        None => !headers.contains_key(header::TRANSFER_ENCODING),
    };
    if raw.is_none() && empty {
        return Ok(String::new());
    }
    Err(ApiError::UnsupportedMediaType { got: raw.unwrap_or("").to_string(), accepted })
}

/// The whole body, at most `limit` bytes. A body that declares more is refused from its `Content-Length`
/// alone, before any of it is read (the connection is then closed rather than drained).
pub async fn bytes_within(req: Request, limit: usize, too_large: ApiError) -> ApiResult<Bytes> {
    if declares_more(req.headers(), limit) {
        return Err(too_large);
    }
    axum::body::to_bytes(req.into_body(), limit).await.map_err(|e| body_error(&e, too_large))
}

fn declares_more(headers: &HeaderMap, limit: usize) -> bool {
    let declared = headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    declared.is_some_and(|n| n > limit as u64)
}

pub async fn read_body(req: Request, limit: usize, accepted: &'static [&'static str]) -> ApiResult<Body> {
    let mime = media_type(req.headers(), accepted)?;
    if mime == "multipart/form-data" {
        if declares_more(req.headers(), limit) {
            return Err(too_large(limit));
        }
        let mut mp = Multipart::from_request(req, &()).await.map_err(|e| invalid("body", e.body_text()))?;
        let mut body = Body::default();
        while let Some(field) = mp.next_field().await.map_err(|e| multipart_error(e, limit))? {
            let name = field.name().unwrap_or("").to_string();
            let track = name.strip_prefix("track").and_then(|n| n.parse::<usize>().ok()).filter(|&n| n < 10);
            let slot = match (name.as_str(), track) {
                ("request", _) => &mut body.json,
                ("image" | "image1", _) => &mut body.image,
                ("image2", _) => &mut body.image2,
                ("depth", _) => &mut body.depth,
                (_, Some(n)) => {
                    if body.track.contains_key(&n) {
                        return Err(invalid("body", format!("multipart part '{name}' is given more than once")));
                    }
                    let bytes = field.bytes().await.map_err(|e| multipart_error(e, limit))?;
                    body.track.insert(n, bytes);
                    continue;
                }
                (other, None) => {
                    return Err(invalid(
                        "body",
                        format!(
                            "unknown multipart part '{other}': use request, image, image1, image2, depth, track0-track9"
                        ),
                    ))
                }
            };
            if slot.is_some() {
                let same =
                    if name.starts_with("image") && name != "image2" { " (image and image1 are one part)" } else { "" };
                return Err(invalid("body", format!("multipart part '{name}' is given more than once{same}")));
            }
            *slot = Some(field.bytes().await.map_err(|e| multipart_error(e, limit))?);
        }
        return Ok(body);
    }
    let bytes = bytes_within(req, limit, too_large(limit)).await?;
    match mime.as_str() {
        "application/json" => Ok(Body { json: Some(bytes), ..Default::default() }),
        "image/jpeg" | "image/png" | "application/octet-stream" => {
            Ok(Body { image: Some(bytes), ..Default::default() })
        }
        _ if bytes.is_empty() => Ok(Body::default()),
        _ => Err(ApiError::UnsupportedMediaType { got: mime, accepted }),
    }
}

pub fn multipart_error(e: axum::extract::multipart::MultipartError, limit: usize) -> ApiError {
    if let Some(ms) = crate::server::connections::body_timed_out(&e) {
        ApiError::BodyTimeout { ms }
    } else if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        too_large(limit)
    } else {
        invalid("body", e.body_text())
    }
}

/// The request's JSON as `T`, or `T::default()` without one ([`json_body`]).
pub fn parse_json<T: DeserializeOwned + Serialize + Default>(bytes: &Option<Bytes>) -> Result<T, ServiceError> {
    match bytes {
        None => Ok(T::default()),
        Some(b) => json_body(b),
    }
}

/// A JSON request body as `T`. A JSON array where `T` has an object is refused, naming the field: serde reads
/// a struct from an array by position, so `["office"]` would otherwise create the map `office`, and a pose
/// sent as `[qx, qy, qz, qw, tx, ty, tz]` would be read in the wrong order without a word.
pub fn json_body<T: DeserializeOwned + Serialize>(bytes: &[u8]) -> Result<T, ServiceError> {
    let bad = |e: serde_json::Error| ServiceError::invalid("request JSON", e.to_string());
    let typed: T = serde_json::from_slice(bytes).map_err(bad)?;
    let shape: Shape = serde_json::from_slice(bytes).map_err(bad)?;
    // The typed value is only written out (a copy of its strings) when the body holds an array at all.
    if shape.has_array() {
        let expected = serde_json::to_value(&typed).map_err(bad)?;
        if let Some(path) = shape.array_for_object(&expected, "") {
            let field = if path.is_empty() { "request JSON".to_string() } else { path };
            return Err(ServiceError::invalid(field, "must be a JSON object, not an array"));
        }
    }
    Ok(typed)
}

/// The structure of a JSON document without its strings and numbers (so big base64 fields are not copied).
enum Shape {
    Object(Vec<(String, Shape)>),
    Array(Vec<Shape>),
    Scalar,
}

impl Shape {
    fn has_array(&self) -> bool {
        match self {
            Shape::Array(_) => true,
            Shape::Object(fields) => fields.iter().any(|(_, v)| v.has_array()),
            Shape::Scalar => false,
        }
    }

    /// The path of the first array that stands where `expected` (the typed value written out) has an object.
    fn array_for_object(&self, expected: &serde_json::Value, path: &str) -> Option<String> {
        use serde_json::Value;
        match (self, expected) {
            (Shape::Array(_), Value::Object(_)) => Some(path.to_string()),
            (Shape::Object(fields), Value::Object(map)) => fields.iter().find_map(|(k, v)| {
                let sub = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                map.get(k).and_then(|e| v.array_for_object(e, &sub))
            }),
            (Shape::Array(items), Value::Array(values)) => items
                .iter()
                .zip(values)
                .enumerate()
                .find_map(|(i, (v, e))| v.array_for_object(e, &format!("{path}[{i}]"))),
            _ => None,
        }
    }
}

impl<'de> serde::Deserialize<'de> for Shape {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = Shape;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("JSON")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(self, mut a: A) -> Result<Shape, A::Error> {
                let mut fields = Vec::new();
                while let Some((k, v)) = a.next_entry::<String, Shape>()? {
                    fields.push((k, v));
                }
                Ok(Shape::Object(fields))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut a: A) -> Result<Shape, A::Error> {
                let mut items = Vec::new();
                while let Some(v) = a.next_element::<Shape>()? {
                    items.push(v);
                }
                Ok(Shape::Array(items))
            }
            fn visit_bool<E>(self, _: bool) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
            fn visit_i64<E>(self, _: i64) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
            fn visit_u64<E>(self, _: u64) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
            fn visit_f64<E>(self, _: f64) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
            fn visit_str<E>(self, _: &str) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
            fn visit_unit<E>(self) -> Result<Shape, E> {
                Ok(Shape::Scalar)
            }
        }
        d.deserialize_any(V)
    }
}

pub fn base64(field: &str, s: &str) -> Result<Vec<u8>, ServiceError> {
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map_err(|e| ServiceError::invalid(field, format!("is not valid base64: {e}")))
}

/// The intrinsics of a frame given in several places (`frame.intrinsics`, a top-level `intrinsics`, the
/// query string): one of them, or several that agree. A size given in one and left out in another agrees.
pub fn agreed_intrinsics(given: &[(&str, Option<Intrinsics>)]) -> Result<Option<Intrinsics>, ServiceError> {
    let mut chosen: Option<(&str, Intrinsics)> = None;
    for (name, i) in given {
        let (name, Some(i)) = (*name, i.clone()) else { continue };
        let Some((first, c)) = chosen else {
            chosen = Some((name, i));
            continue;
        };
        let same_size = |a: Option<u32>, b: Option<u32>| a.is_none() || b.is_none() || a == b;
        let agree = (c.fx, c.fy, c.cx, c.cy) == (i.fx, i.fy, i.cx, i.cy)
            && (c.distortion_model.unwrap_or_default(), &c.distortion)
                == (i.distortion_model.unwrap_or_default(), &i.distortion)
            && same_size(c.width, i.width)
            && same_size(c.height, i.height);
        if !agree {
            return Err(ServiceError::invalid(
                format!("{first} and {name}"),
                "give the intrinsics once, or the same values in both",
            ));
        }
        chosen = Some((first, Intrinsics { width: c.width.or(i.width), height: c.height.or(i.height), ..c }));
    }
    Ok(chosen.map(|(_, i)| i))
}

/// A frame from its JSON description and/or a binary image part. `outer`: intrinsics given outside the
/// frame (name, value), which must agree with the frame's own.
pub fn frame_input(
    json: Option<Frame>,
    image: Option<Bytes>,
    outer: &[(&str, Option<Intrinsics>)],
    field: &str,
) -> Result<FrameInput, ServiceError> {
    let json = json.unwrap_or_default();
    let own = format!("{field}.intrinsics");
    let mut given = vec![(own.as_str(), json.intrinsics)];
    given.extend_from_slice(outer);
    let intrinsics = agreed_intrinsics(&given)?;
    let (source, size) = match (image, json.image_base64, json.keypoints) {
        (Some(bytes), None, None) => {
            let size = read_header(&bytes).ok().map(|h| (h.width, h.height));
            (FrameSource::Image(bytes.to_vec()), size)
        }
        (None, Some(b64), None) => {
            let bytes = base64(&format!("{field}.image_base64"), &b64)?;
            let size = read_header(&bytes).ok().map(|h| (h.width, h.height));
            (FrameSource::Image(bytes), size)
        }
        (None, None, Some(k)) => {
            let descriptors = base64(&format!("{field}.keypoints.descriptors_base64"), &k.descriptors_base64)?;
            let context = match &k.context_base64 {
                Some(c) => base64(&format!("{field}.keypoints.context_base64"), c)?,
                None => Vec::new(),
            };
            let keypoints = k.keypoints.iter().map(Into::into).collect();
            let size = Some((k.width, k.height));
            (
                FrameSource::Keypoints(KeypointsInput {
                    width: k.width,
                    height: k.height,
                    keypoints,
                    descriptors,
                    model_id: k.model_id,
                    context,
                }),
                size,
            )
        }
        (None, None, None) => return Err(ServiceError::invalid(field, "needs an image or keypoints")),
        _ => return Err(ServiceError::invalid(field, "give exactly one of an image or keypoints")),
    };
    let distortion = match &intrinsics {
        Some(i) => i.lens().map_err(|e| ServiceError::invalid(format!("{own}.distortion"), e.to_string()))?,
        None => Distortion::None,
    };
    let camera = intrinsics.map(|i| {
        let (w, h) = size.unwrap_or((0, 0));
        Camera { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy, width: i.width.unwrap_or(w), height: i.height.unwrap_or(h) }
    });
    Ok(FrameInput { source, camera, distortion })
}

/// Intrinsics in the query string, for a raw image body (`?fx=&fy=&cx=&cy=&width=&height=`, and
/// `distortion_model=&distortion=k1,k2,...`).
#[derive(Debug, Default, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
pub struct IntrinsicsQuery {
    /// Focal length x, pixels.
    fx: Option<f64>,
    /// Focal length y, pixels (defaults to fx).
    fy: Option<f64>,
    /// Principal point x, pixels.
    cx: Option<f64>,
    /// Principal point y, pixels.
    cy: Option<f64>,
    /// Image width (defaults to the image's).
    width: Option<u32>,
    /// Image height (defaults to the image's).
    height: Option<u32>,
    /// Lens model: `none`, `radial_tangential` or `fisheye`.
    distortion_model: Option<String>,
    /// The model's coefficients, comma-separated, OpenCV's order.
    distortion: Option<String>,
}

impl IntrinsicsQuery {
    /// The intrinsics among a query string's pairs ([`query_pairs`]).
    pub fn parse(pairs: &[(String, String)]) -> Result<Self, ServiceError> {
        let mut q = Self::default();
        for (key, value) in pairs {
            fn set<T: std::str::FromStr>(
                slot: &mut Option<T>,
                key: &str,
                value: &str,
                what: &str,
            ) -> Result<(), ServiceError> {
                if slot.is_some() {
                    return Err(ServiceError::invalid(key, "is given more than once"));
                }
                let v =
                    value.trim().parse().map_err(|_| ServiceError::invalid(key, format!("'{value}' is not {what}")))?;
                *slot = Some(v);
                Ok(())
            }
            let number = "a number";
            let pixels = "a whole number of pixels";
            match key.as_str() {
                "fx" => set(&mut q.fx, key, value, number)?,
                "fy" => set(&mut q.fy, key, value, number)?,
                "cx" => set(&mut q.cx, key, value, number)?,
                "cy" => set(&mut q.cy, key, value, number)?,
                "width" => set(&mut q.width, key, value, pixels)?,
                "height" => set(&mut q.height, key, value, pixels)?,
                "distortion_model" => set(&mut q.distortion_model, key, value, "a model name")?,
                "distortion" => set(&mut q.distortion, key, value, "a list")?,
                _ => {}
            }
        }
        Ok(q)
    }

    /// The intrinsics the query string gives (`None` when it names none of them); what it leaves out is 0, as
    /// in a JSON body.
    pub fn intrinsics(&self) -> Result<Option<Intrinsics>, ServiceError> {
        // A size alone is not intrinsics (it is the image's anyway): as before lenses, it is then left out.
        let any = [self.fx, self.fy, self.cx, self.cy].iter().any(Option::is_some)
            || self.distortion_model.is_some()
            || self.distortion.is_some();
        if !any {
            return Ok(None);
        }
        let distortion_model = match self.distortion_model.as_deref().map(str::trim) {
            None => None,
            Some(name) => Some(serde_json::from_value(serde_json::Value::String(name.to_string())).map_err(|_| {
                ServiceError::invalid("distortion_model", format!("'{name}' is not none, radial_tangential or fisheye"))
            })?),
        };
        let distortion = match self.distortion.as_deref().map(str::trim).filter(|s| !s.is_empty()) {
            None => Vec::new(),
            Some(list) => list
                .split(',')
                .map(|v| {
                    v.trim()
                        .parse::<f64>()
                        .map_err(|_| ServiceError::invalid("distortion", format!("'{v}' is not a number")))
                })
                .collect::<Result<_, _>>()?,
        };
        Ok(Some(Intrinsics {
            fx: self.fx.unwrap_or(0.0),
            fy: self.fy.unwrap_or(0.0),
            cx: self.cx.unwrap_or(0.0),
            cy: self.cy.unwrap_or(0.0),
            width: self.width,
            height: self.height,
            distortion_model,
            distortion,
        }))
    }
}

/// axum's `Path`, refused in the JSON envelope.
pub struct ApiPath<T>(pub T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned + Send> FromRequestParts<S> for ApiPath<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        match Path::<T>::from_request_parts(parts, state).await {
            Ok(Path(t)) => Ok(Self(t)),
            Err(e) => {
                tracing::debug!("path rejected: {}", e.body_text());
                Err(invalid("URL path", "cannot be decoded (bad percent-encoding or UTF-8)"))
            }
        }
    }
}

/// Whether the client asked for a picture instead of JSON: `?render=png`, or an `Accept` header that names
/// `image/png` and not `application/json` (`?render=json` forces JSON).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Render(pub bool);

impl<S: Send + Sync> FromRequestParts<S> for Render {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Self, ApiError> {
        let accept = parts.headers.get(header::ACCEPT).and_then(|v| v.to_str().ok());
        Ok(Self(wants_picture(&query_pairs(&parts.uri)?, accept)?))
    }
}

/// The pairs of a request's query string, refused as the client's error when it cannot be decoded.
pub fn query_pairs(uri: &Uri) -> Result<Vec<(String, String)>, ServiceError> {
    let Query(pairs) = Query::<Vec<(String, String)>>::try_from_uri(uri)
        .map_err(|e| ServiceError::invalid("query string", e.body_text()))?;
    Ok(pairs)
}

/// Whether the client asked for a picture instead of JSON ([`Render`]).
pub fn wants_picture(pairs: &[(String, String)], accept: Option<&str>) -> Result<bool, ServiceError> {
    let mut asked = pairs.iter().filter(|(k, _)| k == "render").map(|(_, v)| v.as_str());
    match (asked.next(), asked.next()) {
        (Some(_), Some(_)) => return Err(ServiceError::invalid("render", "is given more than once")),
        (Some("png"), None) => return Ok(true),
        (Some("json"), None) => return Ok(false),
        (Some(other), None) => return Err(ServiceError::invalid("render", format!("'{other}' is not png or json"))),
        (None, _) => {}
    }
    let types: Vec<String> = accept
        .unwrap_or("")
        .split(',')
        .map(|t| t.split(';').next().unwrap_or("").trim().to_ascii_lowercase())
        .collect();
    Ok(types.iter().any(|t| t == "image/png") && !types.iter().any(|t| t == "application/json"))
}

#[cfg(test)]
mod tests {
    use super::super::wire::{DescribeRequest, Keypoint, KeypointSet, LocalizeRequest, MatchRequest};
    use super::*;
    use crate::describe::features::{from_precomputed, KeypointLimitSettings};
    use crate::service::ErrorKind;
    use proptest::prelude::*;

    fn keypoints_body(kps: &[(f32, f32, f32, f32, i32)], descriptor_bytes: usize, w: u32, h: u32) -> Frame {
        Frame {
            keypoints: Some(KeypointSet {
                width: w,
                height: h,
                keypoints: kps
                    .iter()
                    .map(|&(x, y, size, angle, octave)| Keypoint { x, y, size, angle, response: 1.0, octave })
                    .collect(),
                descriptors_base64: base64::engine::general_purpose::STANDARD.encode(vec![0x5a; descriptor_bytes]),
                model_id: None,
                context_base64: None,
            }),
            ..Default::default()
        }
    }

    proptest! {
        /// Any keypoint set a client can send decodes to a frame and is then accepted or refused with a
        /// client error; nothing panics and nothing is classified as the server's fault.
        #[test]
        fn client_keypoints_decode_and_validate_without_panics(
            kps in prop::collection::vec(
                (any::<f32>(), any::<f32>(), any::<f32>(), any::<f32>(), any::<i32>()), 0..40),
            extra in -70i64..70,
            w in 0u32..5000,
            h in 0u32..5000,
        ) {
            let bytes = (kps.len() as i64 * 64 + extra).max(0) as usize;
            let f = frame_input(Some(keypoints_body(&kps, bytes, w, h)), None, &[], "frame").unwrap();
            let FrameSource::Keypoints(k) = f.source else { panic!("keypoints expected") };
            match from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &KeypointLimitSettings::default()) {
                Ok(features) => {
                    prop_assert_eq!(features.len(), kps.len());
                    prop_assert_eq!(bytes, kps.len() * 64);
                }
                Err(e) => prop_assert_eq!(ServiceError::from(e).kind(), ErrorKind::InvalidArgument),
            }
        }

        /// Well-formed keypoints inside the image are accepted.
        #[test]
        fn in_range_keypoints_are_accepted(
            kps in prop::collection::vec((40.0f32..600.0, 40.0f32..440.0, 7.0f32..12.0, 0.0f32..359.9, 0i32..3), 1..60),
        ) {
            let f = frame_input(Some(keypoints_body(&kps, kps.len() * 64, 640, 480)), None, &[], "frame").unwrap();
            let FrameSource::Keypoints(k) = f.source else { panic!("keypoints expected") };
            let features = from_precomputed(k.width, k.height, k.keypoints, &k.descriptors, &KeypointLimitSettings::default());
            prop_assert!(features.is_ok(), "{:?}", features.err());
        }

        /// Arbitrary bytes as a request's JSON are refused as the client's error, never a panic.
        #[test]
        fn arbitrary_request_json_is_refused_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
            for r in [
                parse_json::<LocalizeRequest>(&Some(Bytes::from(bytes.clone()))).err(),
                parse_json::<MatchRequest>(&Some(Bytes::from(bytes.clone()))).err(),
                parse_json::<DescribeRequest>(&Some(Bytes::from(bytes))).err(),
            ].into_iter().flatten() {
                prop_assert_eq!(r.kind(), ErrorKind::InvalidArgument);
            }
        }

        /// Base64 that is not base64, and frames with both or neither source, are refused with the field.
        #[test]
        fn malformed_frames_name_the_field(junk in "[!-*,-.:-<>-@\\[-`{-~]{1,20}") {
            let f = Frame { image_base64: Some(junk), ..Default::default() };
            let e = frame_input(Some(f), None, &[], "frame1").unwrap_err();
            prop_assert!(e.to_string().contains("frame1.image_base64"), "{}", e);
            let both = Frame { image_base64: Some("aGk=".into()), ..keypoints_body(&[], 0, 1, 1) };
            prop_assert!(frame_input(Some(both), None, &[], "frame").is_err());
        }
    }

    #[test]
    fn intrinsics_given_twice_must_agree() {
        let a = Intrinsics {
            fx: 250.0,
            fy: 250.0,
            cx: 159.5,
            cy: 119.5,
            width: None,
            height: None,
            distortion_model: None,
            distortion: Vec::new(),
        };
        let sized = Intrinsics { width: Some(320), height: Some(240), ..a.clone() };
        let got =
            agreed_intrinsics(&[("frame.intrinsics", Some(a.clone())), ("intrinsics", Some(sized))]).unwrap().unwrap();
        assert_eq!((got.width, got.height), (Some(320), Some(240)));
        assert!(agreed_intrinsics(&[("frame.intrinsics", None), ("intrinsics", None)]).unwrap().is_none());
        let other = Intrinsics { cx: 160.0, ..a.clone() };
        let e = agreed_intrinsics(&[("frame.intrinsics", Some(a.clone())), ("intrinsics", Some(other))]).unwrap_err();
        assert!(e.to_string().contains("frame.intrinsics and intrinsics"), "{e}");
        let lens = Intrinsics {
            distortion_model: Some(super::super::wire::DistortionModel::Fisheye),
            distortion: vec![0.1, 0.0, 0.0, 0.0],
            ..a.clone()
        };
        assert!(agreed_intrinsics(&[("frame.intrinsics", Some(a)), ("intrinsics", Some(lens))]).is_err());
    }
}
