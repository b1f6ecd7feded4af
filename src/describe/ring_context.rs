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

use strength_reduce::StrengthReducedU32;

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
/// half the memory of f64, whose sums are exact far beyond the largest image (255 x 12 Mpx < 2^53). Either is
/// read as the integer it holds (every sum is an integer below 2^53), so the box sum S is exact, and so is the
/// rounded mean `floor((S + floor(A / 2)) / A)`: for a box the border does not cut, whose area A is the same
/// for a whole ring (up to 2^24 pixels), a division by a divisor reduced once (`Interior`); for one it cuts or a
/// larger one, one f64 division and a floor (a quotient below 256 that is not an integer lies at least 1 / A from
/// one, far above the division's rounding error).
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

/// An integral image's element (i32 or f64, see [`sample`]), read as the exact integer it holds.
trait Integral: Copy + Sync {
    /// The pixel sum of a box from its integral's corners: bottom right, top right, bottom left, top left.
    fn total(d: Self, b: Self, c: Self, a: Self) -> i64;
}

impl Integral for i32 {
    fn total(d: i32, b: i32, c: i32, a: i32) -> i64 {
        i64::from(d) - i64::from(b) - i64::from(c) + i64::from(a)
    }
}

impl Integral for f64 {
    /// Exact: every sum is an integer below 2^53 (see [`sample`]).
    fn total(d: f64, b: f64, c: f64, a: f64) -> i64 {
        (d - b - c + a) as i64
    }
}

/// Where a ring's boxes of half-width `hw` lie whole inside the image, and how their rounded mean is taken
/// there: the box of side `side = 2 hw + 1` whose top-left pixel is (left, top) is whole where
/// `left < columns` and `top < rows` (as `u64`, so that a negative one is not), its corners are that pixel's
/// index in the integral plus 0, `side`, `down` and `down_right`, and its area is `A = side^2`.
///
/// The mean `floor(n / A)`, `n = S + floor(A / 2)`, is the `u32` division by A that `strength_reduce` makes a
/// multiply and shifts (exact for every `u32`); `n < 256 A` (S is at most 255 A), so it fits 32 bits up to
/// `A = 2^24`. Larger boxes (a side above 4,095 pixels, so only on an image of more than 8.4 Mpx, whose integral
/// is f64) are left to the f64 division, as are the boxes the border cuts: `columns` and `rows` are 0 where no
/// box of that side fits the image whole.
struct Interior {
    columns: u64,
    rows: u64,
    side: usize,
    down: usize,
    down_right: usize,
    half: u32,
    by: StrengthReducedU32,
}

/// The largest box area whose rounded means [`Interior`] takes in 32 bits: 2^24, since `n < 256 A`.
const LARGEST_AREA: i64 = 1 << 24;

impl Interior {
    /// For boxes of half-width `hw` on a `w` x `h` image whose integral rows are `stride` apart.
    fn new(hw: i64, w: i64, h: i64, stride: usize) -> Self {
        let side = 2 * hw.clamp(0, w.min(h)) + 1;
        let area = side * side;
        if hw < 0 || side > w.min(h) || area > LARGEST_AREA {
            return Self {
                columns: 0,
                rows: 0,
                side: 0,
                down: 0,
                down_right: 0,
                half: 0,
                by: StrengthReducedU32::new(1),
            };
        }
        let (area, side_u) = (area as u32, side as usize);
        Self {
            columns: (w - side + 1) as u64,
            rows: (h - side + 1) as u64,
            side: side_u,
            down: side_u * stride,
            down_right: side_u * stride + side_u,
            half: area / 2,
            by: StrengthReducedU32::new(area),
        }
    }

    /// The rounded mean of a whole box of pixel sum `total`.
    fn mean(&self, total: i64) -> u8 {
        ((total as u32 + self.half) / self.by) as u8
    }
}

/// A sample's pixel column (or row) from its position `v`: `floor(v)` clamped into `0..=max` (NaN to 0), as
/// Rust's saturating conversion to `u32` gives it: NaN and anything below 0 to 0, anything from 2^32 on to
/// `u32::MAX`, the rest truncated, which is the floor of a non-negative value. Three instructions on the
/// baseline x86-64 target (no SSE4.1 rounding instruction, where `f64::floor` is a call into libm).
/// A position below -2^63 (never a validated keypoint's) gives 0, as the Python reference's clamp does.
fn floor_into(v: f64, max: u32) -> i64 {
    i64::from((v as u32).min(max))
}

/// Keypoints below which [`sample`] stays on the calling thread.
const PARALLEL_FROM: usize = 500;

/// [`sample`] over an integral image `sums` of row stride `stride`. Keypoints are visited from top to bottom
/// (by their row, then column), so that consecutive ones read the same rows of the integral image while they
/// are in cache. With `two_threads`, from [`PARALLEL_FROM`] keypoints on, the rows are split in two bands, the lower one on a
/// scoped thread of its own (each core's cache then holds one band; a scoped thread ends with the call, so
/// nothing spins afterwards beside ONNX Runtime's threads). Each context is written at its keypoint's place.
fn sample_sums<T: Integral>(
    sums: &[T],
    stride: usize,
    image: &GreyImage,
    keypoints: &[KeypointFrame],
    two_threads: bool,
) -> Vec<Context> {
    let (w, h) = (image.width() as i64, image.height() as i64);
    let (w_max, h_max) = (image.width() - 1, image.height() - 1);
    let table = &*TABLE;
    let one = |k: &KeypointFrame, out: &mut Context| {
        let a = angle_bin(k.angle);
        let (dx, dy) = (&table.dx[a], &table.dy[a]);
        let (x, y, s) = (f64::from(k.x), f64::from(k.y), f64::from(k.size));
        // The centre and each ring: one half-width (non-negative, so truncation is the floor).
        for ring in 0..=RINGS {
            let samples = if ring == 0 { 0..1 } else { 1 + (ring - 1) * ANGLES..1 + ring * ANGLES };
            let hw = (table.half[samples.start] * s + 0.5) as i64;
            let inner = Interior::new(hw, w, h, stride);
            for n in samples {
                let cx = floor_into(x + s * dx[n] + 0.5, w_max);
                let cy = floor_into(y + s * dy[n] + 0.5, h_max);
                let (left, top) = (cx - hw, cy - hw);
                out[n] = if (left as u64) < inner.columns && (top as u64) < inner.rows {
                    let c = top as usize * stride + left as usize;
                    let total =
                        T::total(sums[c + inner.down_right], sums[c + inner.side], sums[c + inner.down], sums[c]);
                    inner.mean(total)
                } else {
                    // A box the border cuts: the same sum of its corners, cut to the image, and one f64 division
                    // (non-negative, so truncation is the floor).
                    let (x0, x1) = (left.max(0), (cx + hw + 1).min(w));
                    let (y0, y1) = (top.max(0), (cy + hw + 1).min(h));
                    let (r0, r1) = (y0 as usize * stride, y1 as usize * stride);
                    let (c0, c1) = (x0 as usize, x1 as usize);
                    let total = T::total(sums[r1 + c1], sums[r0 + c1], sums[r1 + c0], sums[r0 + c0]);
                    let area = (x1 - x0) * (y1 - y0);
                    ((total as f64 + (area / 2) as f64) / area as f64) as u8
                };
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

    /// The reference's `floor(v)` as an integer, for |v| < 2^63.
    fn floor(v: f64) -> i64 {
        let t = v as i64;
        t - i64::from((t as f64) > v)
    }

    #[test]
    fn floor_is_the_floor() {
        for v in [-2.5, -2.0, -1.999_999_9, -0.5, -0.0, 0.0, 0.3, 1.0, 2.5, 639.999_999, 1e12 + 0.5] {
            assert_eq!(floor(v), v.floor() as i64, "{v}");
        }
    }

    #[test]
    fn floor_into_is_the_clamped_floor() {
        let max = 639u32;
        let edges = [-9.2e18, -1e12, -2.5, -1.0, -0.5, -1e-300, -0.0, 0.0, 1e-300, 0.5, 0.999_999_9, 1.0, 2.5];
        let more = [638.999_999, 639.0, 639.5, 640.0, 4_294_967_295.5, 4_294_967_296.0, 1e12, 9.2e18];
        for v in edges.into_iter().chain(more) {
            assert_eq!(floor_into(v, max), floor(v).clamp(0, i64::from(max)), "{v}");
        }
        for v in [f64::NAN, f64::NEG_INFINITY, -1e300] {
            assert_eq!(floor_into(v, max), 0, "{v}");
        }
        for v in [1e300, f64::INFINITY] {
            assert_eq!(floor_into(v, max), 639, "{v}");
        }
    }

    /// The interior's mean is the rounded integer mean for every pixel sum a whole box can have (0 to 255 A): all
    /// of them for the small boxes, the edges of every quotient for every side up to the largest.
    #[test]
    fn the_interior_mean_is_the_rounded_integer_mean() {
        let big = 4200;
        for side in (1..=4095i64).step_by(2) {
            let inner = Interior::new(side / 2, big, big, big as usize + 1);
            let area = side * side;
            assert_eq!((inner.side as i64, inner.columns), (side, (big - side + 1) as u64));
            let mut check =
                |total: i64| assert_eq!(i64::from(inner.mean(total)), (total + area / 2) / area, "{total} / {area}");
            if side <= 41 {
                (0..=255 * area).for_each(&mut check);
            } else {
                // Each quotient's first dividends and last ones (the rounding adds A / 2 to the sum).
                for q in 0..256 {
                    for r in [0, 1, area / 2, area - 1] {
                        let n = q * area + r;
                        if n >= area / 2 && n - area / 2 <= 255 * area {
                            check(n - area / 2);
                        }
                    }
                }
            }
        }
        // Past the largest area, and for boxes wider or taller than the image: no interior.
        assert_eq!(Interior::new(2048, big, big, big as usize + 1).columns, 0);
        assert_eq!(Interior::new(3, 6, 100, 7).columns, 0);
        assert_eq!(Interior::new(3, 100, 6, 101).rows, 0);
    }

    /// The reference for one keypoint: `training/scone_train/data/ring_context.py`'s formula in f64 throughout
    /// (the corners' sum, the rounding and the division), which the integer paths match byte for byte.
    fn reference<T: Copy + Into<f64>>(sums: &[T], stride: usize, (w, h): (i64, i64), k: &KeypointFrame) -> Context {
        let table = &*TABLE;
        let at = |x: i64, y: i64| -> f64 { sums[y as usize * stride + x as usize].into() };
        let a = angle_bin(k.angle);
        let (x, y, s) = (f64::from(k.x), f64::from(k.y), f64::from(k.size));
        std::array::from_fn(|n| {
            let hw = (table.half[n] * s + 0.5) as i64;
            let cx = floor(x + s * table.dx[a][n] + 0.5).clamp(0, w - 1);
            let cy = floor(y + s * table.dy[a][n] + 0.5).clamp(0, h - 1);
            let (x0, x1) = ((cx - hw).max(0), (cx + hw + 1).min(w));
            let (y0, y1) = ((cy - hw).max(0), (cy + hw + 1).min(h));
            let total = at(x1, y1) - at(x1, y0) - at(x0, y1) + at(x0, y0);
            let area = (x1 - x0) * (y1 - y0);
            ((total + (area / 2) as f64) / area as f64) as u8
        })
    }

    /// The integer paths (the interior's multiply and shift, the border's division) give the f64 reference's
    /// bytes, with either integral and either number of threads, for keypoints of every size and angle all over
    /// a noisy image and past its edges, on positions that fall on pixel edges too, and on images narrower than
    /// the largest boxes.
    #[test]
    fn the_integer_paths_give_the_f64_references_bytes() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(61);
        for (w, h) in [(640, 480), (97, 61), (23, 150), (9, 7)] {
            let pixels: Vec<u8> = (0..w * h).map(|_| rng.random()).collect();
            let img = image(w, h, |x, y| pixels[(y * w + x) as usize]);
            let kps: Vec<KeypointFrame> = (0..2000)
                .map(|i| {
                    // Half on FAST's pyramid sizes with positions on pixel edges, half anywhere.
                    let (x, y) = (rng.random_range(-20.0..w as f32 + 20.0), rng.random_range(-20.0..h as f32 + 20.0));
                    if i % 2 == 0 {
                        let size = 7.0 * 1.2f32.powi(rng.random_range(0..8));
                        keypoint(x.round() + 0.5 * rng.random_range(0..2) as f32, y.round(), size, 22.5 * i as f32)
                    } else {
                        keypoint(x, y, rng.random_range(0.5..120.0), rng.random_range(-360.0..720.0))
                    }
                })
                .collect();
            for depth in [CV_32S, CV_64F] {
                let mut integral = Mat::default();
                imgproc::integral(img.mat(), &mut integral, depth).unwrap();
                let stride = integral.cols() as usize;
                let (got, want): (Vec<Context>, Vec<Context>) = if depth == CV_32S {
                    let sums = integral.data_typed::<i32>().unwrap();
                    let want = kps.iter().map(|k| reference(sums, stride, (w.into(), h.into()), k)).collect();
                    (sample_sums(sums, stride, &img, &kps, false), want)
                } else {
                    let sums = integral.data_typed::<f64>().unwrap();
                    let want = kps.iter().map(|k| reference(sums, stride, (w.into(), h.into()), k)).collect();
                    assert_eq!(sample_sums(sums, stride, &img, &kps, true), want, "{w}x{h}, f64, two threads");
                    (sample_sums(sums, stride, &img, &kps, false), want)
                };
                for (i, (g, r)) in got.iter().zip(&want).enumerate() {
                    assert_eq!(g, r, "{w}x{h}, depth {depth}, keypoint {:?}", kps[i]);
                }
            }
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
