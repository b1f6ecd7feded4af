//! The ring context: each keypoint described together with the image around it, sampled at fixed places in
//! the keypoint's own frame (its position, size and FREAK orientation). Unlike a constellation of detected
//! neighbours, every sample exists in the other view by construction; its error comes only from the
//! keypoint's scale and angle.
//!
//! For a keypoint at (x, y) with size s and orientation theta (degrees, image axes), the samples are the
//! centre and [`RINGS`] rings of [`ANGLES`] points, ring i at radius `RADII[i] * s`, point j at angle
//! theta + 360 j / ANGLES. theta is quantised to [`ANGLE_BINS`] bins (`round(theta / 360 * ANGLE_BINS)`), so
//! the positions come from one table of offsets in units of s, computed once in f64. Each sample is the mean
//! of a square box of the grey image centred on the sample's pixel (`floor(x + s * dx + 0.5)`, clamped into
//! the image) with half-width `floor(BOX * r * s + 0.5)` pixels (r the ring's radius factor; 0 at the centre,
//! one pixel), cut to the image, read from OpenCV's integral image and rounded half up to 0..255: from the
//! positions on the arithmetic is exact (integer sums, see [`sample`]), so `training/scone_train/data/ring_context.py`
//! (the reference the network was trained on) and a client computing it from the same image agree byte for
//! byte.

use std::sync::LazyLock;

use opencv::core::{Mat, CV_32S, CV_64F};
use opencv::imgproc;
use opencv::prelude::*;

use crate::describe::decode::GreyImage;
use crate::error::FeatureError;

/// Ring radii in units of the keypoint's size.
pub const RADII: [f64; 7] = [0.5, 1.0, 1.5, 2.25, 3.25, 4.5, 6.0];
pub const RINGS: usize = RADII.len();
/// Points per ring.
pub const ANGLES: usize = 16;
/// Orientation bins of the offset table.
pub const ANGLE_BINS: usize = 256;
/// A sample's box half-width as a share of its ring's radius.
pub const BOX: f64 = 0.2;
/// Bytes of one keypoint's context: the centre and every ring point.
pub const SAMPLES: usize = 1 + RINGS * ANGLES;

/// One keypoint's context.
pub type Context = [u8; SAMPLES];

/// A keypoint's own frame, where its ring is drawn: position (pixels), size (pixels) and orientation (degrees,
/// image axes), as `features::Keypoint` holds them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KeypointFrame {
    pub x: f32,
    pub y: f32,
    pub size: f32,
    pub angle: f32,
}

/// Sample offsets (in units of the keypoint size) per orientation bin, and each sample's box half-width
/// factor.
struct Table {
    dx: Vec<[f64; SAMPLES]>,
    dy: Vec<[f64; SAMPLES]>,
    half: [f64; SAMPLES],
}

static TABLE: LazyLock<Table> = LazyLock::new(|| {
    let mut dx = vec![[0.0; SAMPLES]; ANGLE_BINS];
    let mut dy = vec![[0.0; SAMPLES]; ANGLE_BINS];
    let mut half = [0.0; SAMPLES];
    let step = ANGLE_BINS / ANGLES;
    for a in 0..ANGLE_BINS {
        for (i, r) in RADII.iter().enumerate() {
            for j in 0..ANGLES {
                let m = (a + j * step) % ANGLE_BINS;
                let t = 2.0 * std::f64::consts::PI * m as f64 / ANGLE_BINS as f64;
                dx[a][1 + i * ANGLES + j] = r * t.cos();
                dy[a][1 + i * ANGLES + j] = r * t.sin();
            }
        }
    }
    for (i, r) in RADII.iter().enumerate() {
        half[1 + i * ANGLES..1 + (i + 1) * ANGLES].fill(BOX * r);
    }
    Table { dx, dy, half }
});

/// The offset table's bin of an orientation in degrees (any range).
pub fn angle_bin(angle_deg: f32) -> usize {
    let a = (f64::from(angle_deg) * (ANGLE_BINS as f64 / 360.0) + 0.5).floor() as i64;
    a.rem_euclid(ANGLE_BINS as i64) as usize
}

/// Where a keypoint's samples lie, in pixels (before rounding and clamping): the centre, then ring 0's points
/// in order, ring 1's, ... For `scone eval homography`'s share of samples that land on their counterparts.
pub fn sample_positions(k: &KeypointFrame) -> [(f64, f64); SAMPLES] {
    let table = &*TABLE;
    let a = angle_bin(k.angle);
    let (x, y, s) = (f64::from(k.x), f64::from(k.y), f64::from(k.size));
    std::array::from_fn(|n| (x + s * table.dx[a][n], y + s * table.dy[a][n]))
}

/// The ring context of every keypoint, on the image the keypoints were detected on
/// (`features::Features::sample_context` for a frame's keypoints).
///
/// The integral image is 32-bit where its largest sum fits (255 x the pixel count below 2^31: up to 8.4 Mpx),
/// half the memory of f64, whose sums are exact far beyond the largest image (255 x 12 Mpx < 2^53). Both are
/// read as f64: every sum is an integer below 2^53, so the box sum is exact, and so is the rounded mean
/// `floor((S + floor(A / 2)) / A)` taken as one f64 division and a floor (a quotient below 256 that is not an
/// integer lies at least 1 / A from one, far above the division's rounding error).
pub fn sample(image: &GreyImage, keypoints: &[KeypointFrame]) -> Result<Vec<Context>, FeatureError> {
    if keypoints.is_empty() {
        return Ok(Vec::new());
    }
    Ok(RingSampler::new(image)?.sample(keypoints, true))
}

/// An image's integral, made once, from which the ring contexts of any of its keypoints are sampled: what
/// [`sample`] does in one call, for a caller that samples an image's keypoints in parts (the pipelined
/// describe, `crate::describe::pipeline`).
pub struct RingSampler<'a> {
    image: &'a GreyImage,
    integral: Mat,
}

impl<'a> RingSampler<'a> {
    /// The integral of `image`: 32-bit where its largest sum fits, f64 beyond (see [`sample`]).
    pub fn new(image: &'a GreyImage) -> Result<Self, FeatureError> {
        let mut integral = Mat::default();
        let pixels = image.width() as u64 * image.height() as u64;
        let depth = if pixels * 255 < i32::MAX as u64 { CV_32S } else { CV_64F };
        imgproc::integral(image.mat(), &mut integral, depth)?;
        Ok(Self { image, integral })
    }

    /// The ring context of each of `keypoints`; `two_threads`: whether a large set may take a second thread
    /// (see [`sample`]'s bands), which a caller that already runs parts on both cores turns off.
    pub fn sample(&self, keypoints: &[KeypointFrame], two_threads: bool) -> Vec<Context> {
        let stride = self.integral.cols() as usize;
        match self.integral.data_typed::<i32>() {
            Ok(sums) => sample_sums(sums, stride, self.image, keypoints, two_threads),
            // Not 32-bit: `new` made it f64.
            Err(_) => sample_sums(
                self.integral.data_typed::<f64>().expect("the integral is i32 or f64"),
                stride,
                self.image,
                keypoints,
                two_threads,
            ),
        }
    }
}

/// `floor(v)` as an integer, for |v| < 2^63. `f64::floor` is a call into libm on the baseline x86-64 target (no
/// SSE4.1 rounding instruction), which was a third of [`sample`]'s time.
fn floor(v: f64) -> i64 {
    let t = v as i64;
    t - i64::from((t as f64) > v)
}

/// Keypoints below which [`sample`] stays on the calling thread.
const PARALLEL_FROM: usize = 500;

/// [`sample`] over an integral image `sums` of row stride `stride`. Keypoints are visited from top to bottom
/// (by their row, then column), so that consecutive ones read the same rows of the integral image while they
/// are in cache. With `two_threads`, from [`PARALLEL_FROM`] keypoints on, the rows are split in two bands, the lower one on a
/// scoped thread of its own (each core's cache then holds one band; a scoped thread ends with the call, so
/// nothing spins afterwards beside ONNX Runtime's threads). Each context is written at its keypoint's place.
fn sample_sums<T: Copy + Into<f64> + Sync>(
    sums: &[T],
    stride: usize,
    image: &GreyImage,
    keypoints: &[KeypointFrame],
    two_threads: bool,
) -> Vec<Context> {
    let (w, h) = (image.width() as i64, image.height() as i64);
    let table = &*TABLE;
    let one = |k: &KeypointFrame, out: &mut Context| {
        let at = |x: i64, y: i64| -> f64 { sums[y as usize * stride + x as usize].into() };
        let a = angle_bin(k.angle);
        let (dx, dy) = (&table.dx[a], &table.dy[a]);
        let (x, y, s) = (f64::from(k.x), f64::from(k.y), f64::from(k.size));
        // The centre and each ring: one half-width (non-negative, so truncation is the floor).
        for ring in 0..=RINGS {
            let samples = if ring == 0 { 0..1 } else { 1 + (ring - 1) * ANGLES..1 + ring * ANGLES };
            let hw = (table.half[samples.start] * s + 0.5) as i64;
            for n in samples {
                let cx = floor(x + s * dx[n] + 0.5).clamp(0, w - 1);
                let cy = floor(y + s * dy[n] + 0.5).clamp(0, h - 1);
                let (x0, x1) = ((cx - hw).max(0), (cx + hw + 1).min(w));
                let (y0, y1) = ((cy - hw).max(0), (cy + hw + 1).min(h));
                let total = at(x1, y1) - at(x1, y0) - at(x0, y1) + at(x0, y0);
                let area = (x1 - x0) * (y1 - y0);
                // Non-negative: truncation is the floor.
                out[n] = ((total + (area / 2) as f64) / area as f64) as u8;
            }
        }
    };
    let mut order: Vec<usize> = (0..keypoints.len()).collect();
    order.sort_unstable_by(|&i, &j| {
        let (a, b) = (&keypoints[i], &keypoints[j]);
        a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x))
    });
    let band = |idx: &[usize]| -> Vec<Context> {
        idx.iter()
            .map(|&i| {
                let mut c = [0u8; SAMPLES];
                one(&keypoints[i], &mut c);
                c
            })
            .collect()
    };
    let two = two_threads && keypoints.len() >= PARALLEL_FROM && crate::cpu_pool::cores() > 1;
    let (upper, lower) = order.split_at(if two { order.len() / 2 } else { order.len() });
    let (a, b) = std::thread::scope(|scope| {
        // A thread the system refuses (a process limit) leaves the lower band to this one.
        let other = (!lower.is_empty()).then(|| std::thread::Builder::new().spawn_scoped(scope, || band(lower)));
        let a = band(upper);
        let b = match other {
            None => Vec::new(),
            Some(Ok(t)) => t.join().expect("a ring-context thread panicked"),
            Some(Err(e)) => {
                tracing::debug!(error = %e, "no second thread for the ring contexts");
                band(lower)
            }
        };
        (a, b)
    });
    let mut contexts = vec![[0u8; SAMPLES]; keypoints.len()];
    for (&i, c) in order.iter().zip(a.into_iter().chain(b)) {
        contexts[i] = c;
    }
    contexts
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keypoint(x: f32, y: f32, size: f32, angle: f32) -> KeypointFrame {
        KeypointFrame { x, y, size, angle }
    }

    fn image(w: i32, h: i32, f: impl Fn(i32, i32) -> u8) -> GreyImage {
        let mut m = Mat::new_rows_cols_with_default(h, w, opencv::core::CV_8UC1, 0.into()).unwrap();
        for y in 0..h {
            for x in 0..w {
                *m.at_2d_mut::<u8>(y, x).unwrap() = f(x, y);
            }
        }
        GreyImage::from_mat(m).unwrap()
    }

    #[test]
    fn a_flat_image_gives_its_grey_everywhere_even_past_the_border() {
        let img = image(64, 48, |_, _| 77);
        let c = sample(&img, &[keypoint(2.0, 3.0, 12.0, 31.0), keypoint(40.0, 20.0, 7.0, 300.0)]).unwrap();
        assert!(c.iter().all(|k| k.iter().all(|&v| v == 77)));
    }

    #[test]
    fn samples_follow_the_orientation_and_boxes_average_with_half_up_rounding() {
        // Left half 0, right half 200: at angle 0 the first ring point (j = 0) lies to the right, at 180 to
        // the left; the centre box of a keypoint on the edge averages both halves.
        let img = image(200, 100, |x, _| if x >= 100 { 200 } else { 0 });
        let c = sample(&img, &[keypoint(100.0, 50.0, 10.0, 0.0), keypoint(100.0, 50.0, 10.0, 180.0)]).unwrap();
        let ring = |i: usize, j: usize| 1 + i * ANGLES + j;
        assert_eq!((c[0][ring(3, 0)], c[1][ring(3, 0)]), (200, 0));
        assert_eq!((c[0][ring(3, ANGLES / 2)], c[1][ring(3, ANGLES / 2)]), (0, 200));
        // The centre is one pixel: (100, 50), on the bright side.
        assert_eq!(c[0][0], 200);
        // Ring 0 (radius 5 px, half-width 1): the box at angle 90 (x = 100) spans x 99..=101, 2 of 3 bright.
        assert_eq!(c[0][ring(0, ANGLES / 4)], ((2 * 200 * 3 + 4) / 9) as u8);
    }

    /// Both integral widths and the f64 mean give what integer arithmetic on the pixels gives, on a noisy
    /// image with keypoints of every size, angle and place (the border included).
    #[test]
    fn the_rounded_box_means_are_exact_with_either_integral() {
        let (w, h) = (97i32, 61i32);
        let px = |x: i32, y: i32| ((x * 7919 + y * 104_729 + x * y * 31) % 256) as u8;
        let img = image(w, h, px);
        let kps: Vec<KeypointFrame> = (0..300)
            .map(|i| {
                keypoint((i * 37 % 97) as f32 + 0.3, (i * 53 % 61) as f32 - 0.2, 7.0 + (i % 9) as f32, i as f32 * 7.3)
            })
            .collect();
        let mut i32s = Mat::default();
        imgproc::integral(img.mat(), &mut i32s, CV_32S).unwrap();
        let mut f64s = Mat::default();
        imgproc::integral(img.mat(), &mut f64s, CV_64F).unwrap();
        let a = sample_sums(i32s.data_typed::<i32>().unwrap(), i32s.cols() as usize, &img, &kps, true);
        let b = sample_sums(f64s.data_typed::<f64>().unwrap(), f64s.cols() as usize, &img, &kps, false);
        assert_eq!(a, b);
        assert_eq!(a, sample(&img, &kps).unwrap());
        let table = &*TABLE;
        for (k, got) in kps.iter().zip(&a) {
            let (x, y, s) = (f64::from(k.x), f64::from(k.y), f64::from(k.size));
            let bin = angle_bin(k.angle);
            for (n, &value) in got.iter().enumerate() {
                let cx = ((x + s * table.dx[bin][n] + 0.5).floor() as i64).clamp(0, w as i64 - 1);
                let cy = ((y + s * table.dy[bin][n] + 0.5).floor() as i64).clamp(0, h as i64 - 1);
                let hw = ((table.half[n] * s + 0.5).floor() as i64).max(0);
                let (mut total, mut area) = (0i64, 0i64);
                for yy in (cy - hw).max(0)..(cy + hw + 1).min(h as i64) {
                    for xx in (cx - hw).max(0)..(cx + hw + 1).min(w as i64) {
                        total += i64::from(px(xx as i32, yy as i32));
                        area += 1;
                    }
                }
                assert_eq!(i64::from(value), (total + area / 2) / area, "sample {n} of {k:?}");
            }
        }
    }

    /// One integral sampled in parts, on one thread, gives what one call on two threads gives.
    #[test]
    fn a_sampler_in_parts_is_one_call() {
        let img = image(160, 120, |x, y| ((x * 31 + y * 17 + x * y) % 251) as u8);
        let kps: Vec<KeypointFrame> = (0..900)
            .map(|i| keypoint((i * 37 % 160) as f32 + 0.4, (i * 53 % 120) as f32, 7.0 + (i % 5) as f32, i as f32 * 3.1))
            .collect();
        let whole = sample(&img, &kps).unwrap();
        let sampler = RingSampler::new(&img).unwrap();
        let parts: Vec<Context> = kps.chunks(256).flat_map(|c| sampler.sample(c, false)).collect();
        assert_eq!(parts, whole);
        assert_eq!(sampler.sample(&kps, true), whole);
    }

    #[test]
    fn floor_is_the_floor() {
        for v in [-2.5, -2.0, -1.999_999_9, -0.5, -0.0, 0.0, 0.3, 1.0, 2.5, 639.999_999, 1e12 + 0.5] {
            assert_eq!(floor(v), v.floor() as i64, "{v}");
        }
    }

    #[test]
    fn angle_bins_wrap_and_round_half_up() {
        assert_eq!(angle_bin(0.0), 0);
        assert_eq!(angle_bin(359.9), 0);
        assert_eq!(angle_bin(-1.40625), 255);
        assert_eq!(angle_bin(0.703125), 1);
        assert_eq!(angle_bin(90.0), 64);
    }
}
