//! `scone eval homography`: matching under exact homographies (zoom, rotation, viewpoint, light, blur, JPEG),
//! per method, on sequences in the HPatches layout.
//!
//! A sequence is a folder holding `1.<ext> .. N.<ext>` (png, ppm, jpg) and `H_1_k` for k = 2..N, each a 3x3
//! matrix in text that sends pixels of image 1 to pixels of image k. Every pair (1, k) is scored per method:
//!
//! - **putative matches**: the method's keypoints and descriptors, the ratio test with the same-corner rule
//!   (SConE by the evaluation's matcher, as `scone eval pairs`);
//! - **correct matches**: those whose keypoint in image 1, sent through the true H, lands within `correct_px`
//!   of the matched keypoint; the **mean matching accuracy** (MMA) is their share of the putative matches;
//! - **homography accuracy**: H is fitted to the putative matches with MAGSAC++ (`ransac_px`); its error is the
//!   mean distance between where the fitted and the true H send image 1's four corners (infinite when no H is
//!   found), and the report gives the share of pairs within 3 / 5 / 10 px.
//!
//! Pairs are binned by the zoom, the in-plane rotation and the tilt of the true H at image 1's centre, from its
//! Jacobian there: the zoom is `max(s1, 1/s1)` with `s1` the larger singular value (a tilt alone is no zoom),
//! the rotation the angle of the nearest similarity, the tilt `acos(s2 / s1)`.
//!
//! **Neighbour share**: for the project's keypoints (SConE's and FREAK's), the number of a keypoint's
//! constellation members whose image under the true H lies within `correct_px` of a member of the
//! constellation of its corresponding keypoint (the keypoint of image k nearest to its own image, when within
//! `correct_px`), per slot of the constellation (k). It measures how much of a constellation survives the
//! change, before any network sees it; with `neighbour_rules` it is measured for each candidate rule of
//! `constellation::NeighbourRule` as well. **Ring share**: the same for the ring context
//! ([`crate::describe::ring_context`]): of a keypoint's 112 ring samples, those whose image under the true H lies within
//! `correct_px` of the same sample of its corresponding keypoint. Both come with their **chance level**, the
//! same count with the warped members or samples turned 90 degrees about the keypoint; the summaries give the
//! share above chance.
//!
//! Rooms: `protocol.rs` (the settings), `sequence.rs` (the HPatches layout), `geometry.rs` (what a homography
//! does to an image, and its fit), `neighbours.rs` (the neighbour and ring shares), `report.rs` (records, summaries and
//! bins), `tables.rs` (the markdown); here, the run over the sequences.

use std::path::PathBuf;

use crate::describe::decode::GreyImage;
use crate::describe::embedding::Embedder;
use crate::matching::{RatioTest, SconeMatcher};
use crate::offline::eval::methods::{describe, putative_matches, Described, Method};
use crate::offline::progress::Progress;

mod geometry;
mod neighbours;
mod protocol;
mod report;
mod sequence;
mod tables;
#[cfg(test)]
mod tests;

pub use geometry::{apply, corner_error, fit_homography, local_geometry, LocalGeometry};
pub use neighbours::{neighbour_share, ring_share, Share};
pub use protocol::HomographyConfig;
pub use report::{
    rotation_bin, zoom_bin, HomographyBin, HomographyPair, HomographyReport, HomographySummary, RuleShare, CORNER_PX,
    ROTATION_EDGES, ZOOM_EDGES,
};
pub use sequence::{find_sequences, read_homography, Sequence};
pub use tables::markdown;

use neighbours::{sequence_shares, PairShares};
use report::{binned, summarise};
use sequence::load_image;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Runs the evaluation on the sequences in `dirs`.
pub fn evaluate(
    dirs: &[PathBuf],
    cfg: &HomographyConfig,
    embedder: Option<&Embedder>,
) -> Result<HomographyReport, BoxError> {
    if cfg.scone_matcher == SconeMatcher::Freak {
        return Err("scone_matcher freak is FREAK, not SConE: compare with the freak method instead".into());
    }
    let sequences: Vec<Sequence> = dirs.iter().map(|d| Sequence::load(d)).collect::<Result<_, _>>()?;
    let total: usize = sequences.iter().map(|s| s.images.len() * cfg.methods.len()).sum();
    let mut progress = Progress::new("eval homography", total);
    let mut records = Vec::new();
    let mut rule_shares = Vec::new();
    let mut describe_seconds: std::collections::HashMap<Method, Vec<f64>> = Default::default();
    let test = RatioTest { ratio: cfg.ratio, mutual: false, same_corner_px: cfg.same_corner_px };
    for seq in &sequences {
        let images: Vec<GreyImage> = seq.images.iter().map(|p| load_image(p)).collect::<Result<_, _>>()?;
        let geometry: Vec<LocalGeometry> = seq
            .homographies
            .iter()
            .map(|h| local_geometry(h, images[0].width() as f64 / 2.0, images[0].height() as f64 / 2.0))
            .collect();
        // The project's keypoints (SConE, FREAK and FAST+SIFT share them): the neighbour share of every pair.
        let uses_project_keypoints = |m: Method| {
            matches!(m, Method::Scone | Method::SconePlain | Method::Freak | Method::FreakGms | Method::FastSift)
        };
        let mut shares = vec![PairShares::default(); seq.homographies.len()];
        if cfg.methods.iter().any(|&m| uses_project_keypoints(m)) || !cfg.neighbour_rules.is_empty() {
            let (nearest, by_rule) = sequence_shares(seq, &images, &geometry, cfg)?;
            shares = nearest;
            rule_shares.extend(by_rule);
        }
        for &method in &cfg.methods {
            let mut described: Vec<Described> = Vec::with_capacity(images.len());
            for im in &images {
                described.push(describe(method, im, &cfg.extractor, embedder)?);
                progress.step();
            }
            describe_seconds.entry(method).or_default().extend(described.iter().map(|d| d.seconds));
            let a = &described[0];
            let own = uses_project_keypoints(method);
            for (i, h) in seq.homographies.iter().enumerate() {
                let b = &described[i + 1];
                let t0 = std::time::Instant::now();
                let matches = putative_matches(method, a, b, &test, cfg.scone_matcher, cfg.scone_ratio)?;
                let match_seconds = t0.elapsed().as_secs_f64();
                let src: Vec<(f32, f32)> =
                    matches.iter().map(|m| (a.keypoints[m.query].x, a.keypoints[m.query].y)).collect();
                let dst: Vec<(f32, f32)> =
                    matches.iter().map(|m| (b.keypoints[m.train].x, b.keypoints[m.train].y)).collect();
                let correct = src
                    .iter()
                    .zip(&dst)
                    .filter(|(p, q)| {
                        apply(h, p.0 as f64, p.1 as f64)
                            .is_some_and(|(x, y)| (x - q.0 as f64).hypot(y - q.1 as f64) <= cfg.correct_px)
                    })
                    .count();
                let corner_error_px = match fit_homography(&src, &dst, cfg.ransac_px)? {
                    Some(est) => corner_error(&est, h, a.width, a.height),
                    None => f64::INFINITY,
                };
                records.push(HomographyPair {
                    method,
                    sequence: seq.name.clone(),
                    image: i + 2,
                    zoom: geometry[i].zoom,
                    rotation_deg: geometry[i].rotation_deg,
                    tilt_deg: geometry[i].tilt_deg,
                    matches: matches.len(),
                    correct,
                    corner_error_px,
                    neighbour_share: own.then_some(shares[i].neighbours).flatten().map(|s| s.share),
                    neighbour_chance: own.then_some(shares[i].neighbours).flatten().map(|s| s.chance),
                    ring_share: own.then_some(shares[i].ring).flatten().map(|s| s.share),
                    ring_chance: own.then_some(shares[i].ring).flatten().map(|s| s.chance),
                    match_seconds,
                });
            }
        }
    }
    let ms = |m: Method| {
        let s = describe_seconds.get(&m).map(Vec::as_slice).unwrap_or(&[]);
        1e3 * s.iter().sum::<f64>() / s.len().max(1) as f64
    };
    let all: Vec<&HomographyPair> = records.iter().collect();
    let summaries = cfg.methods.iter().map(|&m| summarise(m, &all, ms(m))).collect();
    let bins = binned(&records, &cfg.methods, ms);
    Ok(HomographyReport {
        config: cfg.clone(),
        sequences: sequences.iter().map(|s| s.name.clone()).collect(),
        summaries,
        bins,
        pairs: records,
        rule_shares,
    })
}
