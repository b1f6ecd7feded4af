//! FAST keypoints on an image pyramid, spread over the image by grid bucketing, described by FREAK.
//!
//! This is the one feature-extraction path of the project: the service, the evaluation commands and the
//! training-data export all call [`extract`], so the network is trained on exactly what it sees in production.
//!
//! Detection runs OpenCV's FAST (9/16, non-max suppression) on every level of a pyramid built by resizing the
//! grey image by `scale_factor^-l`. A keypoint found on level `l` at `(x_l, y_l)` is mapped to full resolution
//! as `x = (x_l + 0.5) * W / W_l - 0.5` (likewise `y`) and gets `size = 7 * scale_factor^l` (FAST's 7-pixel
//! circle at that level), `octave = l`. FREAK then samples its pattern on the full-resolution image at that
//! size, so it describes the same physical patch whatever the level. With `levels = 1` and bucketing off this
//! is the single-scale FAST + FREAK of the paper and of OpenCV's own pipeline.
//!
//! Budget: `max_keypoints` is split over levels in proportion to their area. Within a level, keypoints are
//! bucketed into square cells of `grid_cell` pixels (level coordinates) and taken round-robin: every cell's
//! strongest first (strongest of those first), then every cell's second, and so on, which spreads keypoints
//! over the image while preferring strong corners. Keypoints whose FREAK pattern would leave the image are
//! dropped before budgeting so they do not take places; FREAK's own border check drops any remaining ones.
//!
//! Descriptors: 512 bits packed into 64 bytes, bit `i` of the descriptor in byte `i / 8`, bit `i % 8`
//! (least significant first), as OpenCV stores them; `numpy.unpackbits(..., bitorder="little")` unpacks them.
//!
//! Every rounding, precision and order of this module is written out in the client contract of
//! `proto/scone/v1/scone.proto` (above `message KeypointSet`); `clients/python` reproduces it bit for bit.
//! A change here that alters any keypoint or descriptor must change that text and its revision.

use std::time::Instant;

use opencv::core::{KeyPoint, Mat, Size, Vector};
use opencv::features2d::{FastFeatureDetector, FastFeatureDetector_DetectorType};
use opencv::prelude::*;
use opencv::{imgproc, xfeatures2d};
use serde::{Deserialize, Serialize};

use crate::describe::decode::GreyImage;
use crate::describe::ring_context::{self, Context, KeypointFrame, RingSampler, SAMPLES};
use crate::error::FeatureError;

/// Bytes in one FREAK descriptor (512 bits).
pub const DESCRIPTOR_BYTES: usize = 64;
/// FAST's circle diameter in pixels: the size of a keypoint detected at full resolution.
pub const FAST_SIZE: f32 = 7.0;
/// FREAK's pattern scale (OpenCV's default); with `FAST_SIZE` it sets the pattern radius at each size.
const FREAK_PATTERN_SCALE: f32 = 22.0;
/// FREAK's octave count (OpenCV's default).
const FREAK_OCTAVES: i32 = 4;

/// Settings of detection and description. Defaults suit a 640x480 image: they are the client contract's
/// revision 3 (the extraction E1, which the embedded model declares); [`ExtractorSettings::revision_2`] is what
/// models before it were trained at.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ExtractorSettings {
    /// FAST intensity threshold.
    pub fast_threshold: i32,
    /// Keypoints kept at most (before FREAK's own border check).
    pub max_keypoints: usize,
    /// Pyramid levels (1 = single-scale FAST as in the paper).
    pub levels: u32,
    /// Downscale factor between consecutive levels.
    pub scale_factor: f64,
    /// Grid cell side in pixels for bucketing; 0 keeps the strongest keypoints with no spreading.
    pub grid_cell: u32,
}

impl Default for ExtractorSettings {
    fn default() -> Self {
        Self { fast_threshold: 20, max_keypoints: 2000, levels: 8, scale_factor: 1.2, grid_cell: 32 }
    }
}

impl ExtractorSettings {
    /// The client contract's revision 2: 6 levels and 1,500 keypoints, the extraction of every model made before
    /// models declared theirs (`scone-freak-k20`).
    pub fn revision_2() -> Self {
        Self { max_keypoints: 1500, levels: 6, ..Self::default() }
    }

    /// Single-scale FAST, strongest `max_keypoints`, no bucketing: the paper's and OpenCV's pipeline.
    pub fn single_scale(fast_threshold: i32, max_keypoints: usize) -> Self {
        Self { fast_threshold, max_keypoints, levels: 1, scale_factor: 1.2, grid_cell: 0 }
    }

    /// Checks ranges; called before any extraction.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let bad = |field, reason: &str| Err(FeatureError::InvalidConfig { field, reason: reason.into() });
        if !(1..=254).contains(&self.fast_threshold) {
            return bad("fast_threshold", "must be in 1..=254");
        }
        if self.max_keypoints == 0 || self.max_keypoints > 100_000 {
            return bad("max_keypoints", "must be in 1..=100000");
        }
        if !(1..=16).contains(&self.levels) {
            return bad("levels", "must be in 1..=16");
        }
        if !(self.scale_factor > 1.0 && self.scale_factor <= 2.0) {
            return bad("scale_factor", "must be in (1, 2]");
        }
        if self.grid_cell > 1024 {
            return bad("grid_cell", "must be at most 1024 (0 = off)");
        }
        Ok(())
    }
}

/// A keypoint in full-resolution pixel coordinates, with OpenCV's conventions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Keypoint {
    /// Column, pixels (0 = centre of the first pixel).
    pub x: f32,
    /// Row, pixels.
    pub y: f32,
    /// Diameter of the described region, pixels.
    pub size: f32,
    /// Orientation in degrees, [0, 360), measured from +x towards +y (image axes, y down).
    pub angle: f32,
    /// Detector response (FAST score).
    pub response: f32,
    /// Pyramid level the keypoint was found on.
    pub octave: i32,
}

impl Keypoint {
    /// From OpenCV's keypoint (angle normalised to [0, 360)).
    pub fn from_cv(kp: &KeyPoint) -> Self {
        let p = kp.pt();
        // FREAK reports atan2 in degrees, (-180, 180]; normalise to [0, 360) like client input.
        let angle = kp.angle().rem_euclid(360.0);
        Self { x: p.x, y: p.y, size: kp.size(), angle, response: kp.response(), octave: kp.octave() }
    }

    /// To OpenCV's keypoint (class id -1).
    pub fn to_cv(self) -> opencv::Result<KeyPoint> {
        KeyPoint::new_coords(self.x, self.y, self.size, self.angle, self.response, self.octave, -1)
    }
}

/// Keypoints of one image with their FREAK descriptors (row `i` describes keypoint `i`), and their ring
/// contexts when the model reads them ([`crate::describe::ring_context`]; empty otherwise).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Features {
    pub width: u32,
    pub height: u32,
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Vec<[u8; DESCRIPTOR_BYTES]>,
    pub context: Vec<Context>,
}

impl Features {
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Keypoint positions `(x, y)` in pixels, in keypoint order.
    pub fn points(&self) -> Vec<(f32, f32)> {
        self.keypoints.iter().map(|k| (k.x, k.y)).collect()
    }

    /// Samples each keypoint's ring context ([`crate::describe::ring_context`]) on `image`, the image they were detected on.
    pub fn sample_context(&mut self, image: &GreyImage) -> Result<(), FeatureError> {
        self.context = ring_context::sample(image, &self.frames())?;
        Ok(())
    }

    /// Samples each keypoint's ring context from its image's integral (`sampler`), for a caller that samples
    /// one image's keypoints in parts; `two_threads` as in [`RingSampler::sample`].
    pub fn sample_context_from(&mut self, sampler: &RingSampler, two_threads: bool) {
        self.context = sampler.sample(&self.frames(), two_threads);
    }

    fn frames(&self) -> Vec<KeypointFrame> {
        self.keypoints.iter().map(|k| KeypointFrame { x: k.x, y: k.y, size: k.size, angle: k.angle }).collect()
    }

    /// Splits the set in two at keypoint `at`: this one keeps the keypoints before it (with their descriptors
    /// and contexts), the one returned holds the rest.
    pub fn split_off(&mut self, at: usize) -> Features {
        Features {
            width: self.width,
            height: self.height,
            keypoints: self.keypoints.split_off(at),
            descriptors: self.descriptors.split_off(at),
            context: if self.context.len() > at { self.context.split_off(at) } else { Vec::new() },
        }
    }

    /// Appends `other`'s keypoints, descriptors and contexts (of the same image) after this set's.
    pub fn append(&mut self, other: Features) {
        self.keypoints.extend(other.keypoints);
        self.descriptors.extend(other.descriptors);
        self.context.extend(other.context);
    }

    /// Descriptors as an OpenCV matrix [N, 64] of u8, for OpenCV's matchers.
    pub fn descriptor_mat(&self) -> Result<Mat, FeatureError> {
        bits_mat(self.descriptors.as_flattened())
    }
}

/// FREAK descriptors laid end to end (`DESCRIPTOR_BYTES` each) as an OpenCV matrix, one row per descriptor
/// (empty when there are none).
pub fn bits_mat(flat: &[u8]) -> Result<Mat, FeatureError> {
    if flat.is_empty() {
        return Ok(Mat::default());
    }
    let rows = (flat.len() / DESCRIPTOR_BYTES) as i32;
    let mat = Mat::new_rows_cols_with_data(rows, DESCRIPTOR_BYTES as i32, &flat[..rows as usize * DESCRIPTOR_BYTES])?;
    Ok(mat.try_clone()?)
}

/// Limits on client-supplied keypoints.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KeypointLimitSettings {
    pub max_keypoints: usize,
    /// Largest accepted keypoint size in pixels.
    pub max_size: f32,
}

impl Default for KeypointLimitSettings {
    fn default() -> Self {
        Self { max_keypoints: 10_000, max_size: 1024.0 }
    }
}

/// Radius in pixels that FREAK's pattern needs around a keypoint of `size` (its border check, conservatively).
fn freak_border(size: f32) -> f32 {
    FREAK_PATTERN_SCALE * size / FAST_SIZE + 2.0
}

/// Detects and describes keypoints on a grey image.
pub fn extract(image: &GreyImage, config: &ExtractorSettings) -> Result<Features, FeatureError> {
    config.validate()?;
    let mut candidates = detect(image, config)?;
    describe(image, &mut candidates)
}

/// A caller's record of where a stage's time went: called with the stage's name (`pyramid`, `fast`, `grid`,
/// `freak`, `freak_output`) and its wall time, once or more per call (the pyramid's stages once per level).
pub type StageSink<'a> = &'a mut dyn FnMut(&'static str, std::time::Duration);

/// FAST on every pyramid level, border-filtered and budgeted; keypoints in full-resolution coordinates.
pub fn detect(image: &GreyImage, config: &ExtractorSettings) -> Result<Vector<KeyPoint>, FeatureError> {
    detect_staged(image, config, &mut |_, _| {})
}

/// [`detect`], telling `stage` the time of each level's resize (`pyramid`), FAST (`fast`) and the border
/// filter with the grid budget (`grid`): the per-stage accounting of the `stages` bench.
pub fn detect_staged(
    image: &GreyImage,
    config: &ExtractorSettings,
    stage: StageSink,
) -> Result<Vector<KeyPoint>, FeatureError> {
    let full = image.mat();
    let (w, h) = (full.cols(), full.rows());
    let level_weights: Vec<f64> = (0..config.levels).map(|l| config.scale_factor.powi(-2 * l as i32)).collect();
    let weight_sum: f64 = level_weights.iter().sum();
    let mut detector =
        FastFeatureDetector::create(config.fast_threshold, true, FastFeatureDetector_DetectorType::TYPE_9_16)?;
    let mut selected = Vector::<KeyPoint>::new();
    let mut level_img = Mat::default();
    let mut remaining = config.max_keypoints;
    for (level, weight) in level_weights.iter().enumerate() {
        let scale = config.scale_factor.powi(level as i32);
        let lw = (w as f64 / scale).round() as i32;
        let lh = (h as f64 / scale).round() as i32;
        let size = FAST_SIZE * scale as f32;
        let border = freak_border(size);
        if lw < 16 || lh < 16 || 2.0 * border >= w.min(h) as f32 {
            break;
        }
        let t = Instant::now();
        let img: &Mat = if level == 0 {
            full
        } else {
            imgproc::resize(full, &mut level_img, Size::new(lw, lh), 0.0, 0.0, imgproc::INTER_LINEAR)?;
            &level_img
        };
        stage("pyramid", t.elapsed());
        let t = Instant::now();
        let mut raw = Vector::<KeyPoint>::new();
        detector.detect(img, &mut raw, &Mat::default())?;
        stage("fast", t.elapsed());
        let t = Instant::now();
        let sx = w as f32 / lw as f32;
        let sy = h as f32 / lh as f32;
        let mut level_kps: Vec<(KeyPoint, f32, f32)> = Vec::with_capacity(raw.len());
        for kp in raw.iter() {
            let p = kp.pt();
            let x = (p.x + 0.5) * sx - 0.5;
            let y = (p.y + 0.5) * sy - 0.5;
            if x < border || y < border || x >= w as f32 - border || y >= h as f32 - border {
                continue;
            }
            let full_kp = KeyPoint::new_coords(x, y, size, -1.0, kp.response(), level as i32, -1)?;
            level_kps.push((full_kp, p.x, p.y));
        }
        let budget = if level + 1 == level_weights.len() {
            remaining
        } else {
            ((config.max_keypoints as f64 * weight / weight_sum).round() as usize).min(remaining)
        };
        let kept = select_spread(level_kps, budget, config.grid_cell);
        remaining -= kept.len();
        for kp in kept {
            selected.push(kp);
        }
        stage("grid", t.elapsed());
    }
    Ok(selected)
}

/// Keeps at most `budget` keypoints: round-robin over grid cells by response rank, or strongest-first
/// when `cell == 0`. Ties are broken by position so the result is deterministic.
fn select_spread(mut kps: Vec<(KeyPoint, f32, f32)>, budget: usize, cell: u32) -> Vec<KeyPoint> {
    let stronger = |a: &(KeyPoint, f32, f32), b: &(KeyPoint, f32, f32)| {
        b.0.response().total_cmp(&a.0.response()).then(a.2.total_cmp(&b.2)).then(a.1.total_cmp(&b.1))
    };
    if cell == 0 || kps.len() <= budget {
        kps.sort_by(stronger);
        return kps.into_iter().take(budget).map(|k| k.0).collect();
    }
    let c = cell as f32;
    let cell_of = |k: &(KeyPoint, f32, f32)| ((k.2 / c) as u32, (k.1 / c) as u32);
    kps.sort_by(|a, b| cell_of(a).cmp(&cell_of(b)).then_with(|| stronger(a, b)));
    let mut ranked: Vec<(u32, (KeyPoint, f32, f32))> = Vec::with_capacity(kps.len());
    let mut rank = 0u32;
    let mut prev = None;
    for k in kps {
        let c = cell_of(&k);
        rank = if prev == Some(c) { rank + 1 } else { 0 };
        prev = Some(c);
        ranked.push((rank, k));
    }
    ranked.sort_by(|a, b| a.0.cmp(&b.0).then_with(|| stronger(&a.1, &b.1)));
    ranked.into_iter().take(budget).map(|(_, k)| k.0).collect()
}

thread_local! {
    /// One FREAK per thread: OpenCV builds its sampling-pattern lookup table (64 scales x 256 orientations)
    /// on first use, which costs more than describing an image, so the instance is kept.
    static FREAK: std::cell::RefCell<Option<opencv::core::Ptr<xfeatures2d::FREAK>>> =
        const { std::cell::RefCell::new(None) };
}

/// Runs FREAK on `keypoints` (it assigns orientation and drops keypoints whose pattern leaves the image).
pub fn describe(image: &GreyImage, keypoints: &mut Vector<KeyPoint>) -> Result<Features, FeatureError> {
    describe_staged(image, keypoints, &mut |_, _| {})
}

/// [`describe`], telling `stage` the time of OpenCV's FREAK (`freak`) and of copying its output into
/// [`Features`] (`freak_output`).
pub fn describe_staged(
    image: &GreyImage,
    keypoints: &mut Vector<KeyPoint>,
    stage: StageSink,
) -> Result<Features, FeatureError> {
    let t = Instant::now();
    let mut desc = Mat::default();
    FREAK.with(|cell| -> Result<(), FeatureError> {
        let mut slot = cell.borrow_mut();
        let freak = match slot.as_mut() {
            Some(f) => f,
            None => {
                slot.insert(xfeatures2d::FREAK::create(true, true, FREAK_PATTERN_SCALE, FREAK_OCTAVES, &Vector::new())?)
            }
        };
        freak.compute(image.mat(), keypoints, &mut desc)?;
        Ok(())
    })?;
    stage("freak", t.elapsed());
    let t = Instant::now();
    let n = keypoints.len();
    if n > 0 && (desc.rows() as usize != n || desc.cols() as usize != DESCRIPTOR_BYTES) {
        return Err(FeatureError::OpenCv(opencv::Error::new(
            opencv::core::StsError,
            format!("FREAK returned {}x{} descriptors for {n} keypoints", desc.rows(), desc.cols()),
        )));
    }
    let mut descriptors = Vec::with_capacity(n);
    for i in 0..n {
        let row = desc.at_row::<u8>(i as i32)?;
        let mut d = [0u8; DESCRIPTOR_BYTES];
        d.copy_from_slice(row);
        descriptors.push(d);
    }
    let keypoints = keypoints.iter().map(|k| Keypoint::from_cv(&k)).collect();
    stage("freak_output", t.elapsed());
    Ok(Features { width: image.width(), height: image.height(), keypoints, descriptors, context: Vec::new() })
}

/// Validates keypoints and descriptors supplied by a client (computed with the same contract on a device)
/// and returns them as [`Features`]. Nothing is re-detected; the caller gets a precise error for the first
/// violation found.
pub fn from_precomputed(
    width: u32,
    height: u32,
    keypoints: Vec<Keypoint>,
    descriptors: &[u8],
    limits: &KeypointLimitSettings,
) -> Result<Features, FeatureError> {
    if width == 0 || height == 0 {
        return Err(FeatureError::InvalidKeypoint {
            index: 0,
            field: "image size",
            reason: format!("{width}x{height} must be positive"),
        });
    }
    if keypoints.len() > limits.max_keypoints {
        return Err(FeatureError::TooManyKeypoints { count: keypoints.len(), max: limits.max_keypoints });
    }
    if descriptors.len() != keypoints.len() * DESCRIPTOR_BYTES {
        return Err(FeatureError::InvalidDescriptors {
            reason: format!(
                "expected {} bytes ({} keypoints x {DESCRIPTOR_BYTES}), got {}",
                keypoints.len() * DESCRIPTOR_BYTES,
                keypoints.len(),
                descriptors.len()
            ),
        });
    }
    let mut out = Vec::with_capacity(keypoints.len());
    for (index, mut k) in keypoints.into_iter().enumerate() {
        let bad = |field, reason: String| FeatureError::InvalidKeypoint { index, field, reason };
        for (field, v) in [("x", k.x), ("y", k.y), ("size", k.size), ("angle", k.angle), ("response", k.response)] {
            if !v.is_finite() {
                return Err(bad(field, format!("is not finite ({v})")));
            }
        }
        if k.x < 0.0 || k.x > (width - 1) as f32 {
            return Err(bad("x", format!("{} is outside [0, {}]", k.x, width - 1)));
        }
        if k.y < 0.0 || k.y > (height - 1) as f32 {
            return Err(bad("y", format!("{} is outside [0, {}]", k.y, height - 1)));
        }
        if k.size <= 0.0 || k.size > limits.max_size {
            return Err(bad("size", format!("{} is outside (0, {}]", k.size, limits.max_size)));
        }
        if !(-360.0..=360.0).contains(&k.angle) {
            return Err(bad("angle", format!("{} degrees is outside [-360, 360]", k.angle)));
        }
        if !(0..=31).contains(&k.octave) {
            return Err(bad("octave", format!("{} is outside 0..=31", k.octave)));
        }
        k.angle = k.angle.rem_euclid(360.0);
        out.push(k);
    }
    let descriptors = descriptors
        .chunks_exact(DESCRIPTOR_BYTES)
        .map(|c| {
            let mut d = [0u8; DESCRIPTOR_BYTES];
            d.copy_from_slice(c);
            d
        })
        .collect();
    Ok(Features { width, height, keypoints: out, descriptors, context: Vec::new() })
}

/// Attaches the ring contexts a client computed ([`crate::describe::ring_context`], `SAMPLES` bytes per keypoint in
/// keypoint order) to its validated keypoints.
pub fn with_context(mut features: Features, context: &[u8]) -> Result<Features, FeatureError> {
    if context.len() != features.len() * SAMPLES {
        return Err(FeatureError::InvalidContext {
            reason: format!(
                "expected {} bytes ({} keypoints x {SAMPLES}), got {}",
                features.len() * SAMPLES,
                features.len(),
                context.len()
            ),
        });
    }
    features.context = context
        .chunks_exact(SAMPLES)
        .map(|c| {
            let mut out = [0u8; SAMPLES];
            out.copy_from_slice(c);
            out
        })
        .collect();
    Ok(features)
}

/// Re-describes client keypoints on an image (used to check a client's extraction against the server's).
pub fn describe_keypoints(image: &GreyImage, keypoints: &[Keypoint]) -> Result<Features, FeatureError> {
    let mut cv = Vector::<KeyPoint>::with_capacity(keypoints.len());
    for k in keypoints {
        cv.push(k.to_cv()?);
    }
    describe(image, &mut cv)
}

/// Sets the size of OpenCV's internal thread pool (0 = OpenCV's default, all cores).
///
/// The service parallelises across requests on its own bounded pool, so it runs OpenCV single-threaded by
/// default: two layers of pools on two cores would only contend.
pub fn set_opencv_threads(threads: usize) -> Result<(), FeatureError> {
    opencv::core::set_num_threads(if threads == 0 { -1 } else { threads as i32 })?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32, response: f32) -> (KeyPoint, f32, f32) {
        (KeyPoint::new_coords(x, y, 7.0, -1.0, response, 0, -1).unwrap(), x, y)
    }

    #[test]
    fn strongest_first_without_grid() {
        let kps = vec![kp(1.0, 1.0, 5.0), kp(2.0, 2.0, 9.0), kp(3.0, 3.0, 7.0)];
        let out = select_spread(kps, 2, 0);
        assert_eq!(out.iter().map(|k| k.response()).collect::<Vec<_>>(), vec![9.0, 7.0]);
    }

    #[test]
    fn grid_spreads_before_taking_second_best() {
        // Cell (0,0) has three strong corners, cell (0,1) one weak one: the weak one is taken second.
        let kps = vec![kp(1.0, 1.0, 50.0), kp(2.0, 2.0, 40.0), kp(3.0, 3.0, 30.0), kp(40.0, 1.0, 10.0)];
        let out = select_spread(kps, 2, 32);
        assert_eq!(out.iter().map(|k| k.response()).collect::<Vec<_>>(), vec![50.0, 10.0]);
    }

    #[test]
    fn config_validation_names_the_field() {
        let cfg = ExtractorSettings { scale_factor: 0.5, ..ExtractorSettings::default() };
        assert!(matches!(cfg.validate(), Err(FeatureError::InvalidConfig { field: "scale_factor", .. })));
        let cfg = ExtractorSettings { levels: 0, ..ExtractorSettings::default() };
        assert!(matches!(cfg.validate(), Err(FeatureError::InvalidConfig { field: "levels", .. })));
        assert!(ExtractorSettings::default().validate().is_ok());
    }

    fn good_kp() -> Keypoint {
        Keypoint { x: 10.0, y: 20.0, size: 7.0, angle: 45.0, response: 30.0, octave: 0 }
    }

    #[test]
    fn precomputed_accepts_valid_input() {
        let f = from_precomputed(64, 48, vec![good_kp(); 2], &[7u8; 128], &KeypointLimitSettings::default()).unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(f.descriptors[1], [7u8; 64]);
    }

    #[test]
    fn precomputed_rejects_each_violation() {
        let limits = KeypointLimitSettings::default();
        let check = |k: Keypoint, field: &str| {
            let err = from_precomputed(64, 48, vec![good_kp(), k], &[0u8; 128], &limits).unwrap_err();
            match err {
                FeatureError::InvalidKeypoint { index: 1, field: f, .. } => assert_eq!(f, field),
                other => panic!("expected {field} error, got {other}"),
            }
        };
        check(Keypoint { x: f32::NAN, ..good_kp() }, "x");
        check(Keypoint { y: f32::INFINITY, ..good_kp() }, "y");
        check(Keypoint { x: 64.0, ..good_kp() }, "x");
        check(Keypoint { y: -0.5, ..good_kp() }, "y");
        check(Keypoint { size: 0.0, ..good_kp() }, "size");
        check(Keypoint { size: 5000.0, ..good_kp() }, "size");
        check(Keypoint { angle: 720.0, ..good_kp() }, "angle");
        check(Keypoint { octave: -1, ..good_kp() }, "octave");
        check(Keypoint { response: f32::NAN, ..good_kp() }, "response");
        let err = from_precomputed(64, 48, vec![good_kp(); 2], &[0u8; 127], &limits).unwrap_err();
        assert!(matches!(err, FeatureError::InvalidDescriptors { .. }), "{err}");
        let small = KeypointLimitSettings { max_keypoints: 1, ..limits };
        let err = from_precomputed(64, 48, vec![good_kp(); 2], &[0u8; 128], &small).unwrap_err();
        assert!(matches!(err, FeatureError::TooManyKeypoints { count: 2, max: 1 }), "{err}");
    }

    #[test]
    fn negative_angles_are_normalised() {
        let k = Keypoint { angle: -90.0, ..good_kp() };
        let f = from_precomputed(64, 48, vec![k], &[0u8; 64], &KeypointLimitSettings::default()).unwrap();
        assert_eq!(f.keypoints[0].angle, 270.0);
    }
}
