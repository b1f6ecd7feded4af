//! Pictures of what the service matched, for people debugging it (hloc's `visualization` draws the same):
//! two frames side by side with their putative matches (inliers green, outliers red), and a localised frame
//! with its 2D-3D matches and the reprojection of the inlier landmarks at the estimated pose. Each picture
//! carries a caption band (method, counts, pose) and is encoded as PNG.
//!
//! Frames given as keypoints (no image) are drawn on a grey canvas of the keypoint set's size. Pictures are
//! scaled so that the taller frame is at most [`MAX_HEIGHT`] pixels high. Callers run this on the CPU pool,
//! like every other OpenCV call of a request.

use opencv::core::{Mat, Point, Scalar, Size, Vector, CV_8UC3};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};

use crate::error::FeatureError;

/// Height of a drawn frame at most, pixels.
pub const MAX_HEIGHT: u32 = 720;
/// Width of a drawn frame at most, pixels (a pair picture is at most twice as wide).
pub const MAX_WIDTH: u32 = 1440;

const CAPTION_LINE: i32 = 22;
const BACKGROUND: f64 = 60.0;

/// What a frame is drawn on.
#[derive(Debug, Clone, Copy)]
pub enum Backdrop<'a> {
    /// The frame's encoded image (PNG or JPEG), already checked by the service.
    Image(&'a [u8]),
    /// No image (the frame came as keypoints): a grey canvas of this size.
    Blank { width: u32, height: u32 },
}

fn bgr(b: f64, g: f64, r: f64) -> Scalar {
    Scalar::new(b, g, r, 0.0)
}

fn inlier_colour() -> Scalar {
    bgr(60.0, 220.0, 60.0)
}

fn outlier_colour() -> Scalar {
    bgr(60.0, 60.0, 230.0)
}

/// The backdrop as a colour image shrunk to fit [`MAX_WIDTH`] x [`MAX_HEIGHT`] (never enlarged), and the scale
/// applied. Images are decoded as the extraction decodes them: EXIF orientation ignored, so keypoints land on
/// their pixels.
fn canvas(b: &Backdrop) -> Result<(Mat, f64), FeatureError> {
    let full = match b {
        Backdrop::Image(bytes) => {
            let flags = imgcodecs::IMREAD_COLOR | imgcodecs::IMREAD_IGNORE_ORIENTATION;
            let decoded = imgcodecs::imdecode(&Vector::<u8>::from_slice(bytes), flags)?;
            if decoded.empty() {
                return Err(FeatureError::CorruptImage { reason: "the image could not be decoded to draw on".into() });
            }
            decoded
        }
        Backdrop::Blank { width, height } => Mat::new_rows_cols_with_default(
            (*height).max(1) as i32,
            (*width).max(1) as i32,
            CV_8UC3,
            Scalar::all(BACKGROUND),
        )?,
    };
    let (rows, cols) = (full.rows().max(1) as f64, full.cols().max(1) as f64);
    let scale = (MAX_HEIGHT as f64 / rows).min(MAX_WIDTH as f64 / cols).min(1.0);
    if scale >= 1.0 {
        return Ok((full, 1.0));
    }
    let size = Size::new(((cols * scale).round() as i32).max(1), ((rows * scale).round() as i32).max(1));
    let mut out = Mat::default();
    imgproc::resize(&full, &mut out, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    Ok((out, scale))
}

/// `m` padded at the bottom with the background to `rows` rows.
fn pad_to(m: Mat, rows: i32) -> Result<Mat, FeatureError> {
    if m.rows() >= rows {
        return Ok(m);
    }
    let mut out = Mat::default();
    opencv::core::copy_make_border(
        &m,
        &mut out,
        0,
        rows - m.rows(),
        0,
        0,
        opencv::core::BORDER_CONSTANT,
        Scalar::all(BACKGROUND),
    )?;
    Ok(out)
}

fn pt(p: (f64, f64)) -> Point {
    Point::new(p.0.round() as i32, p.1.round() as i32)
}

const FONT_SCALE: f64 = 0.55;

/// `lines` broken at spaces so that each fits in `width` pixels (a word longer than that stays whole).
fn wrap(lines: &[String], width: i32) -> Result<Vec<String>, FeatureError> {
    let fits = |text: &str| -> Result<bool, FeatureError> {
        let mut baseline = 0;
        let size = imgproc::get_text_size(text, imgproc::FONT_HERSHEY_SIMPLEX, FONT_SCALE, 1, &mut baseline)?;
        Ok(size.width <= width)
    };
    let mut out = Vec::new();
    for line in lines {
        let mut current = String::new();
        for word in line.split(' ') {
            let candidate = if current.is_empty() { word.to_string() } else { format!("{current} {word}") };
            if current.is_empty() || fits(&candidate)? {
                current = candidate;
            } else {
                out.push(std::mem::replace(&mut current, word.to_string()));
            }
        }
        out.push(current);
    }
    Ok(out)
}

/// `body` with the caption lines (wrapped to its width) in a dark band above it, encoded as PNG.
fn with_caption(body: &Mat, caption: &[String]) -> Result<Vec<u8>, FeatureError> {
    let caption = wrap(caption, body.cols() - 16)?;
    let band_h = CAPTION_LINE * caption.len() as i32 + 8;
    let mut band = Mat::new_rows_cols_with_default(band_h, body.cols(), CV_8UC3, Scalar::all(20.0))?;
    for (i, line) in caption.iter().enumerate() {
        imgproc::put_text(
            &mut band,
            line,
            Point::new(8, CAPTION_LINE * (i as i32 + 1)),
            imgproc::FONT_HERSHEY_SIMPLEX,
            FONT_SCALE,
            Scalar::all(235.0),
            1,
            imgproc::LINE_AA,
            false,
        )?;
    }
    let mut out = Mat::default();
    opencv::core::vconcat2(&band, body, &mut out)?;
    let mut png = Vector::<u8>::new();
    imgcodecs::imencode(".png", &out, &mut png, &Vector::<i32>::new())?;
    Ok(png.to_vec())
}

/// Two frames side by side with lines between matched keypoints: `matches` pairs indices of `points1` and
/// `points2`; `inliers[i]` says whether match `i` is an inlier of the pose (outliers are drawn first,
/// thinner, so inliers stay visible).
pub fn pair(
    frame1: &Backdrop,
    frame2: &Backdrop,
    points1: &[(f32, f32)],
    points2: &[(f32, f32)],
    matches: &[(usize, usize)],
    inliers: &[bool],
    caption: &[String],
) -> Result<Vec<u8>, FeatureError> {
    let (c1, s1) = canvas(frame1)?;
    let (c2, s2) = canvas(frame2)?;
    let h = c1.rows().max(c2.rows());
    let (c1, c2) = (pad_to(c1, h)?, pad_to(c2, h)?);
    let mut body = Mat::default();
    opencv::core::hconcat2(&c1, &c2, &mut body)?;
    let offset = c1.cols() as f64;
    let at1 = |i: usize| points1.get(i).map(|&(x, y)| (x as f64 * s1, y as f64 * s1));
    let at2 = |i: usize| points2.get(i).map(|&(x, y)| (x as f64 * s2 + offset, y as f64 * s2));
    for pass_inliers in [false, true] {
        for (k, &(i, j)) in matches.iter().enumerate() {
            let inlier = inliers.get(k).copied().unwrap_or(false);
            if inlier != pass_inliers {
                continue;
            }
            let (Some(a), Some(b)) = (at1(i), at2(j)) else { continue };
            let colour = if inlier { inlier_colour() } else { outlier_colour() };
            imgproc::line(&mut body, pt(a), pt(b), colour, 1, imgproc::LINE_AA, 0)?;
            imgproc::circle(&mut body, pt(a), 2, colour, imgproc::FILLED, imgproc::LINE_AA, 0)?;
            imgproc::circle(&mut body, pt(b), 2, colour, imgproc::FILLED, imgproc::LINE_AA, 0)?;
        }
    }
    with_caption(&body, caption)
}

/// One matched keypoint of a localised frame: its pixel, whether it is an inlier of the pose, and where its
/// landmark reprojects at the estimated pose (`None` without a pose or behind the camera).
#[derive(Debug, Clone, Copy)]
pub struct LocalizedPoint {
    pub pixel: (f32, f32),
    pub inlier: bool,
    pub reprojected: Option<(f64, f64)>,
}

/// A localised frame: every 2D-3D match as a dot (inliers green, outliers red), and for inliers the
/// landmark's reprojection (a cyan ring) joined to its keypoint by a yellow line (the residual).
pub fn localization(frame: &Backdrop, points: &[LocalizedPoint], caption: &[String]) -> Result<Vec<u8>, FeatureError> {
    let (mut body, s) = canvas(frame)?;
    let scaled = |p: (f64, f64)| (p.0 * s, p.1 * s);
    for pass_inliers in [false, true] {
        for p in points.iter().filter(|p| p.inlier == pass_inliers) {
            let px = scaled((p.pixel.0 as f64, p.pixel.1 as f64));
            if p.inlier {
                if let Some(r) = p.reprojected.map(scaled) {
                    imgproc::line(&mut body, pt(px), pt(r), bgr(0.0, 230.0, 255.0), 1, imgproc::LINE_AA, 0)?;
                    imgproc::circle(&mut body, pt(r), 4, bgr(255.0, 230.0, 0.0), 1, imgproc::LINE_AA, 0)?;
                }
                imgproc::circle(&mut body, pt(px), 2, inlier_colour(), imgproc::FILLED, imgproc::LINE_AA, 0)?;
            } else {
                imgproc::circle(&mut body, pt(px), 2, outlier_colour(), imgproc::FILLED, imgproc::LINE_AA, 0)?;
            }
        }
    }
    with_caption(&body, caption)
}

/// The caption of a MatchPair picture: the matcher, the counts, and the relative pose (rotation angle in
/// degrees and unit translation direction) when there is one.
pub fn pair_caption(
    matcher: &str,
    ratio: f32,
    putative: usize,
    inliers: usize,
    pose: Option<(f64, [f64; 3])>,
) -> [String; 3] {
    let pose = pose.map_or("no relative pose".to_string(), |(angle, t)| {
        format!("rotation {angle:.1} deg, translation direction ({:.2}, {:.2}, {:.2})", t[0], t[1], t[2])
    });
    [
        format!("MatchPair, matcher '{matcher}', ratio {ratio}"),
        format!("{putative} putative matches, {inliers} inliers (green), {} outliers (red)", putative - inliers),
        pose,
    ]
}

/// The caption of a Localize picture: the map, the counts, and the camera centre, reprojection error and
/// confidence when the frame was localised.
pub fn localization_caption(
    map: &str,
    matches: usize,
    inliers: usize,
    pose: Option<([f64; 3], f64, f64)>,
) -> [String; 3] {
    let pose = pose.map_or("not localised".to_string(), |(c, reprojection, confidence)| {
        format!(
            "camera at ({:.3}, {:.3}, {:.3}), reprojection error {reprojection:.2} px, confidence {confidence:.2}",
            c[0], c[1], c[2]
        )
    });
    [
        format!("Localize against map '{map}'"),
        format!(
            "{matches} 2D-3D matches, {inliers} inliers (green; landmarks reprojected in cyan), {} outliers (red)",
            matches - inliers
        ),
        pose,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(png: &[u8]) -> Mat {
        imgcodecs::imdecode(&Vector::<u8>::from_slice(png), imgcodecs::IMREAD_COLOR).unwrap()
    }

    fn pixel(m: &Mat, x: i32, y: i32) -> [u8; 3] {
        let v = m.at_2d::<opencv::core::Vec3b>(y, x).unwrap();
        [v[0], v[1], v[2]]
    }

    #[test]
    fn a_pair_picture_puts_the_frames_side_by_side_and_colours_inliers_and_outliers() {
        let blank = Backdrop::Blank { width: 200, height: 100 };
        let caption = vec!["line one".to_string(), "line two".to_string()];
        let png = pair(
            &blank,
            &blank,
            &[(20.0, 50.0), (20.0, 90.0)],
            &[(180.0, 50.0), (180.0, 90.0)],
            &[(0, 0), (1, 1)],
            &[true, false],
            &caption,
        )
        .unwrap();
        let m = decode(&png);
        let band = CAPTION_LINE * 2 + 8;
        assert_eq!((m.cols(), m.rows()), (400, 100 + band));
        // Midway along each line: green for the inlier, red for the outlier; the canvas stays grey.
        let [b, g, r] = pixel(&m, 200, band + 50);
        assert!(g > 150 && r < 120 && b < 120, "inlier {:?}", (b, g, r));
        let [b, g, r] = pixel(&m, 200, band + 90);
        assert!(r > 150 && g < 120 && b < 120, "outlier {:?}", (b, g, r));
        assert_eq!(pixel(&m, 100, band + 20), [BACKGROUND as u8; 3]);
    }

    #[test]
    fn a_localization_picture_scales_large_frames_and_draws_reprojections() {
        let blank = Backdrop::Blank { width: 2880, height: 1440 };
        let points = [LocalizedPoint { pixel: (1000.0, 700.0), inlier: true, reprojected: Some((1040.0, 700.0)) }];
        let m = decode(&localization(&blank, &points, &["c".to_string()]).unwrap());
        let band = CAPTION_LINE + 8;
        assert_eq!((m.cols(), m.rows()), (1440, MAX_HEIGHT as i32 + band));
        // The residual line between (500, 350) and (520, 350) at half scale is yellow.
        let [b, g, r] = pixel(&m, 510, band + 350);
        assert!(r > 200 && g > 180 && b < 100, "{:?}", (b, g, r));
    }

    #[test]
    fn long_caption_lines_wrap_to_the_picture() {
        let long = "word ".repeat(40);
        let lines = wrap(&[long.trim().to_string(), "short".to_string()], 300).unwrap();
        assert!(lines.len() > 3, "{lines:?}");
        assert_eq!(lines.last().unwrap(), "short");
        assert_eq!(lines[..lines.len() - 1].join(" "), long.trim());
        let m = decode(
            &localization(&Backdrop::Blank { width: 320, height: 240 }, &[], std::slice::from_ref(&long)).unwrap(),
        );
        let in_picture = wrap(&[long], 320 - 16).unwrap().len() as i32;
        assert!(in_picture > 3);
        assert_eq!(m.rows(), 240 + CAPTION_LINE * in_picture + 8);
    }

    #[test]
    fn odd_frame_shapes_stay_within_the_picture_bounds() {
        // A 4096 x 1 keypoint set beside a 720-high frame: each shrinks into its box, the short one is padded.
        let thin = Backdrop::Blank { width: 4096, height: 1 };
        let tall = Backdrop::Blank { width: 960, height: 720 };
        let m = decode(&pair(&thin, &tall, &[(4000.0, 0.0)], &[(10.0, 10.0)], &[(0, 0)], &[true], &[]).unwrap());
        assert_eq!((m.cols(), m.rows()), (MAX_WIDTH as i32 + 960, 720 + 8));
        let m = decode(&localization(&Backdrop::Blank { width: 1, height: 4096 }, &[], &[]).unwrap());
        assert!(m.cols() >= 1 && m.rows() == MAX_HEIGHT as i32 + 8);
    }

    #[test]
    fn an_image_that_does_not_decode_is_an_error() {
        assert!(localization(&Backdrop::Image(b"\x89PNG\r\n\x1a\nnot really"), &[], &[]).is_err());
    }
}
