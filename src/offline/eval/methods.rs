//! The description methods compared by the evaluation: SConE and the paper's baselines, each producing
//! keypoints and descriptors that OpenCV's brute-force matcher can match.

use std::time::Instant;

use opencv::core::{KeyPoint, Mat, Vector, NORM_HAMMING, NORM_L2};
use opencv::features2d::{ORB_ScoreType, ORB, SIFT};
use opencv::prelude::*;
use serde::{Deserialize, Serialize};

use crate::describe::decode::GreyImage;
use crate::describe::embedding::Embedder;
use crate::describe::features::{self, ExtractorSettings, Keypoint};
use crate::error::FeatureError;
use crate::matching::{embedding_mat, match_descriptors, match_scone_with, Match, RatioTest, SconeFrame, SconeMatcher};

/// The rows of a continuous f32 matrix as one slice (empty for an empty matrix).
fn mat_rows(m: &Mat) -> Result<&[f32], FeatureError> {
    if m.empty() {
        return Ok(&[]);
    }
    Ok(m.data_typed::<f32>()?)
}

/// A description method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Method {
    /// SConE on the project's FAST + FREAK keypoints, matched the way the service matches them (the
    /// evaluation's `scone_matcher`, by default the service's default).
    Scone,
    /// The plain SConE embedding (L2 nearest neighbour and ratio test), whatever the matcher.
    SconePlain,
    /// The same keypoints' FREAK descriptors (Hamming).
    Freak,
    /// FREAK nearest neighbours filtered by GMS (grid-based motion statistics) instead of the ratio test.
    FreakGms,
    /// OpenCV ORB, 2,000 features (Hamming).
    Orb,
    /// OpenCV SIFT, 2,000 features (L2).
    Sift,
    /// SIFT's keypoints (its detector, as [`Method::Sift`] finds them, one per place) described by FREAK as
    /// [`Method::Freak`] describes its own (Hamming): SIFT's detector with FREAK's descriptor.
    DogFreak,
    /// [`Method::Freak`]'s keypoints (FAST, FREAK's orientation and border check) described by SIFT's
    /// descriptor (L2): FREAK's keypoints with SIFT's descriptor.
    FastSift,
}

impl Method {
    pub fn name(&self) -> &'static str {
        match self {
            Method::Scone => "SConE",
            Method::SconePlain => "SConE (plain)",
            Method::Freak => "FREAK",
            Method::FreakGms => "FREAK+GMS",
            Method::Orb => "ORB",
            Method::Sift => "SIFT",
            Method::DogFreak => "DoG+FREAK",
            Method::FastSift => "FAST+SIFT",
        }
    }

    /// Whether the descriptors are FREAK's bits (Hamming distance).
    pub fn freak_bits(&self) -> bool {
        matches!(self, Method::Freak | Method::FreakGms | Method::DogFreak)
    }
}

/// One image described by one method.
pub struct Described {
    pub keypoints: Vec<Keypoint>,
    pub descriptors: Mat,
    pub norm: i32,
    /// SConE only: the keypoints' FREAK descriptors, for the matchers that combine the two.
    pub freak: Option<Mat>,
    /// Seconds spent detecting and describing (decode excluded).
    pub seconds: f64,
    pub width: u32,
    pub height: u32,
    cv_keypoints: Vector<KeyPoint>,
}

fn cv_keypoints(kps: &[Keypoint]) -> Result<Vector<KeyPoint>, FeatureError> {
    kps.iter().map(|k| k.to_cv().map_err(FeatureError::from)).collect()
}

fn from_cv(kps: &Vector<KeyPoint>) -> Vec<Keypoint> {
    kps.iter().map(|k| Keypoint::from_cv(&k)).collect()
}

/// OpenCV SIFT as the SIFT methods run it: 2,000 features, 3 layers an octave, contrast 0.04, edge 10, sigma 1.6.
fn sift() -> opencv::Result<opencv::core::Ptr<SIFT>> {
    SIFT::create(2000, 3, 0.04, 10.0, 1.6, false)
}

/// SIFT's keypoints, one per place: SIFT repeats a keypoint for each strong orientation, and FREAK, which
/// assigns its own, would describe the copies alike (identical descriptors fail each other's ratio test).
fn one_per_place(kps: &Vector<KeyPoint>) -> Vector<KeyPoint> {
    let mut seen = std::collections::HashSet::new();
    kps.iter().filter(|k| seen.insert((k.pt().x.to_bits(), k.pt().y.to_bits(), k.size().to_bits()))).collect()
}

/// SIFT's descriptors of the project's `keypoints` (position, size and angle as they are), each computed on
/// the image of SIFT's Gaussian pyramid whose blur is nearest the FAST pyramid level it was found on (levels
/// `scale_factor` apart; SIFT reads `octave` as its octave | layer << 8, three layers an octave).
fn sift_descriptors(image: &GreyImage, keypoints: &[Keypoint], scale_factor: f64) -> Result<Mat, FeatureError> {
    let mut kps = Vector::<KeyPoint>::with_capacity(keypoints.len());
    for k in keypoints {
        let steps = (3.0 * f64::from(k.octave) * scale_factor.log2()).round() as i32;
        kps.push(Keypoint { octave: (steps / 3) | ((steps % 3) << 8), ..*k }.to_cv()?);
    }
    let mut d = Mat::default();
    sift()?.detect_and_compute(image.mat(), &Mat::default(), &mut kps, &mut d, true)?;
    Ok(d)
}

/// Describes an image with `method`. SConE needs the embedder.
pub fn describe(
    method: Method,
    image: &GreyImage,
    extractor: &ExtractorSettings,
    embedder: Option<&Embedder>,
) -> Result<Described, Box<dyn std::error::Error + Send + Sync>> {
    let t0 = Instant::now();
    let mut freak = None;
    let (keypoints, descriptors, norm) = match method {
        Method::Freak | Method::FreakGms => {
            let f = features::extract(image, extractor)?;
            let d = f.descriptor_mat()?;
            (f.keypoints, d, NORM_HAMMING)
        }
        Method::Scone | Method::SconePlain => {
            let embedder = embedder.ok_or("SConE needs a model (--model)")?;
            let f = crate::describe::pipeline::extract_for(image, extractor, embedder)?;
            let e = crate::describe::pipeline::embed(embedder, &f)?;
            freak = Some(f.descriptor_mat()?);
            (f.keypoints, embedding_mat(&e, embedder.dim())?, NORM_L2)
        }
        Method::Orb => {
            let mut orb = ORB::create(2000, 1.2, 8, 31, 0, 2, ORB_ScoreType::HARRIS_SCORE, 31, 20)?;
            let mut kps = Vector::<KeyPoint>::new();
            let mut d = Mat::default();
            orb.detect_and_compute(image.mat(), &Mat::default(), &mut kps, &mut d, false)?;
            (from_cv(&kps), d, NORM_HAMMING)
        }
        Method::Sift => {
            let mut kps = Vector::<KeyPoint>::new();
            let mut d = Mat::default();
            sift()?.detect_and_compute(image.mat(), &Mat::default(), &mut kps, &mut d, false)?;
            (from_cv(&kps), d, NORM_L2)
        }
        Method::DogFreak => {
            let mut kps = Vector::<KeyPoint>::new();
            sift()?.detect(image.mat(), &mut kps, &Mat::default())?;
            let f = features::describe(image, &mut one_per_place(&kps))?;
            let d = f.descriptor_mat()?;
            (f.keypoints, d, NORM_HAMMING)
        }
        Method::FastSift => {
            let f = features::extract(image, extractor)?;
            let d = sift_descriptors(image, &f.keypoints, extractor.scale_factor)?;
            (f.keypoints, d, NORM_L2)
        }
    };
    let seconds = t0.elapsed().as_secs_f64();
    let cv = cv_keypoints(&keypoints)?;
    Ok(Described {
        keypoints,
        descriptors,
        norm,
        freak,
        seconds,
        width: image.width(),
        height: image.height(),
        cv_keypoints: cv,
    })
}

/// Putative matches of `a` to `b`: `test` for every method but FREAK+GMS, which takes every nearest neighbour
/// and keeps those GMS supports (rotation and scale enabled, threshold factor 6). SConE is matched by
/// `scone_matcher` (SConE (plain) always by [`SconeMatcher::Plain`]), the embedding's ratio in the fused matchers
/// being `scone_ratio` where given (`matching::match_scone_with`).
pub fn putative_matches(
    method: Method,
    a: &Described,
    b: &Described,
    test: &RatioTest,
    scone_matcher: SconeMatcher,
    scone_ratio: Option<f32>,
) -> Result<Vec<Match>, FeatureError> {
    if method == Method::Scone && scone_matcher != SconeMatcher::Plain {
        let (ea, eb) = (mat_rows(&a.descriptors)?, mat_rows(&b.descriptors)?);
        let dim = a.descriptors.cols().max(0) as usize;
        let points = |d: &Described| -> Vec<(f32, f32)> { d.keypoints.iter().map(|k| (k.x, k.y)).collect() };
        let (pa, pb) = (points(a), points(b));
        let empty = Mat::default();
        let sizes = |d: &Described| -> Vec<f32> { d.keypoints.iter().map(|k| k.size).collect() };
        let (sa, sb) = (sizes(a), sizes(b));
        let fa = SconeFrame { embeddings: ea, dim, freak: a.freak.as_ref().unwrap_or(&empty), points: &pa, sizes: &sa };
        let fb = SconeFrame { embeddings: eb, dim, freak: b.freak.as_ref().unwrap_or(&empty), points: &pb, sizes: &sb };
        let embedding = RatioTest { ratio: scone_ratio.unwrap_or(test.ratio), ..*test };
        return match_scone_with(scone_matcher, &fa, &fb, test, &embedding);
    }
    if method != Method::FreakGms {
        let b_points: Vec<(f32, f32)> = b.keypoints.iter().map(|k| (k.x, k.y)).collect();
        return match_descriptors(&a.descriptors, &b.descriptors, a.norm, test, &b_points);
    }
    let all = match_descriptors(&a.descriptors, &b.descriptors, a.norm, &RatioTest::plain(1.01), &[])?;
    let dm: Vector<opencv::core::DMatch> = all
        .iter()
        .map(|m| opencv::core::DMatch::new(m.query as i32, m.train as i32, m.distance))
        .collect::<Result<_, _>>()?;
    let mut kept = Vector::<opencv::core::DMatch>::new();
    opencv::xfeatures2d::match_gms(
        opencv::core::Size::new(a.width as i32, a.height as i32),
        opencv::core::Size::new(b.width as i32, b.height as i32),
        &a.cv_keypoints,
        &b.cv_keypoints,
        &dm,
        &mut kept,
        true,
        true,
        6.0,
    )?;
    Ok(kept
        .iter()
        .map(|m| Match { query: m.query_idx as usize, train: m.train_idx as usize, distance: m.distance })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{CV_32F, CV_8U};

    fn coffee() -> GreyImage {
        let bytes = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/coffee-640x480.jpg")).unwrap();
        crate::describe::decode::decode_grey(&bytes, &Default::default()).unwrap()
    }

    #[test]
    fn swapped_detector_and_descriptor_describe_a_real_image() {
        let (image, settings) = (coffee(), ExtractorSettings::default());
        for (method, depth, cols) in [(Method::DogFreak, CV_8U, 64), (Method::FastSift, CV_32F, 128)] {
            let d = describe(method, &image, &settings, None).unwrap();
            assert!(!d.keypoints.is_empty(), "{method:?}");
            assert_eq!(d.descriptors.rows() as usize, d.keypoints.len(), "{method:?}");
            assert_eq!((d.descriptors.depth(), d.descriptors.cols()), (depth, cols), "{method:?}");
            assert_eq!(d.norm, if method.freak_bits() { NORM_HAMMING } else { NORM_L2 });
        }
    }

    #[test]
    fn fast_sift_describes_freaks_keypoints() {
        let (image, settings) = (coffee(), ExtractorSettings::default());
        let detected: Vec<(f32, f32)> =
            features::detect(&image, &settings).unwrap().iter().map(|k| (k.pt().x, k.pt().y)).collect();
        let freak = describe(Method::Freak, &image, &settings, None).unwrap();
        let fast_sift = describe(Method::FastSift, &image, &settings, None).unwrap();
        assert_eq!(fast_sift.keypoints, freak.keypoints);
        let described: Vec<(f32, f32)> = fast_sift.keypoints.iter().map(|k| (k.x, k.y)).collect();
        // FREAK's own border check may drop a few of the detected keypoints, never reorder or add any.
        let mut rest = detected.iter();
        assert!(described.iter().all(|p| rest.any(|q| q == p)));
        assert!(described.len() * 100 >= detected.len() * 99, "{} of {}", described.len(), detected.len());
    }
}
