//! The neighbour share and the ring share (module docs of `homography`): how much of a keypoint's context, its
//! constellation or its ring, survives the true homography before any network sees it, above chance.

use nalgebra::Matrix3;

use crate::describe::constellation::{self, Constellations, NeighbourRule};
use crate::describe::decode::GreyImage;
use crate::describe::features::Keypoint;
use crate::describe::ring_context::{sample_positions, KeypointFrame, SAMPLES};
use crate::offline::eval::homography::geometry::{apply, LocalGeometry};
use crate::offline::eval::homography::protocol::HomographyConfig;
use crate::offline::eval::homography::report::RuleShare;
use crate::offline::eval::homography::sequence::Sequence;

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// For each keypoint of `a`, the keypoint of `b` nearest to its image under `h`, when within `px`.
fn correspondences(a: &[Keypoint], b: &[Keypoint], h: &Matrix3<f64>, px: f64) -> Vec<Option<usize>> {
    let cell = px.max(1.0) as f32;
    let mut grid: std::collections::HashMap<(i32, i32), Vec<usize>> = std::collections::HashMap::new();
    for (j, k) in b.iter().enumerate() {
        grid.entry(((k.x / cell).floor() as i32, (k.y / cell).floor() as i32)).or_default().push(j);
    }
    a.iter()
        .map(|k| {
            let (x, y) = apply(h, k.x as f64, k.y as f64)?;
            let (cx, cy) = ((x as f32 / cell).floor() as i32, (y as f32 / cell).floor() as i32);
            let mut best: Option<(f64, usize)> = None;
            for gx in cx - 1..=cx + 1 {
                for gy in cy - 1..=cy + 1 {
                    for &j in grid.get(&(gx, gy)).map(Vec::as_slice).unwrap_or(&[]) {
                        let d = (b[j].x as f64 - x).hypot(b[j].y as f64 - y);
                        if d <= px && best.is_none_or(|(bd, _)| d < bd) {
                            best = Some((d, j));
                        }
                    }
                }
            }
            best.map(|(_, j)| j)
        })
        .collect()
}

/// A share of what survives a homography, averaged over the corresponding keypoints, and what chance alone
/// keeps: the same count with the warped places turned 90 degrees about the warped keypoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Share {
    pub share: f64,
    pub chance: f64,
    /// Corresponding keypoints averaged over.
    pub keypoints: usize,
}

impl Share {
    /// The share above chance.
    pub fn above_chance(&self) -> f64 {
        self.share - self.chance
    }
}

/// `(x, y)` turned 90 degrees about `(cx, cy)`.
fn turned(x: f64, y: f64, (cx, cy): (f64, f64)) -> (f64, f64) {
    (cx - (y - cy), cy + (x - cx))
}

/// Mean share of constellation members that survive `h` (the `homography` module docs), per slot of k, with
/// its chance level; None when no keypoint corresponds.
pub fn neighbour_share(
    a: &[Keypoint],
    ca: &Constellations,
    b: &[Keypoint],
    cb: &Constellations,
    h: &Matrix3<f64>,
    px: f64,
) -> Option<Share> {
    let corr = correspondences(a, b, h, px);
    let (mut sum, mut chance, mut n) = (0.0, 0.0, 0usize);
    for (i, j) in corr.iter().enumerate() {
        let Some(j) = *j else { continue };
        let members_b: Vec<&Keypoint> = cb
            .neighbours_of(j)
            .iter()
            .zip(cb.mask_of(j))
            .filter(|(_, &m)| m > 0)
            .map(|(&m, _)| &b[m as usize])
            .collect();
        let members_a: Vec<usize> =
            ca.neighbours_of(i).iter().zip(ca.mask_of(i)).filter(|(_, &m)| m > 0).map(|(&m, _)| m as usize).collect();
        let Some(centre) = apply(h, a[i].x as f64, a[i].y as f64) else { continue };
        if members_a.is_empty() || ca.k == 0 {
            continue;
        }
        let near_b = |(x, y): (f64, f64)| members_b.iter().any(|q| (q.x as f64 - x).hypot(q.y as f64 - y) <= px);
        let warped: Vec<(f64, f64)> =
            members_a.iter().filter_map(|&m| apply(h, a[m].x as f64, a[m].y as f64)).collect();
        sum += warped.iter().filter(|&&p| near_b(p)).count() as f64 / ca.k as f64;
        chance += warped.iter().filter(|&&(x, y)| near_b(turned(x, y, centre))).count() as f64 / ca.k as f64;
        n += 1;
    }
    (n > 0).then(|| Share { share: sum / n as f64, chance: chance / n as f64, keypoints: n })
}

/// Mean share of ring samples ([`crate::describe::ring_context`], the centre left out) that survive `h`: sample n of a
/// keypoint of `a`, sent through `h`, within `px` of sample n of its corresponding keypoint of `b` (its own
/// size and FREAK angle), with its chance level; None when no keypoint corresponds.
pub fn ring_share(a: &[Keypoint], b: &[Keypoint], h: &Matrix3<f64>, px: f64) -> Option<Share> {
    let frame = |k: &Keypoint| KeypointFrame { x: k.x, y: k.y, size: k.size, angle: k.angle };
    let corr = correspondences(a, b, h, px);
    let ring = SAMPLES - 1;
    let (mut sum, mut chance, mut n) = (0.0, 0.0, 0usize);
    for (i, j) in corr.iter().enumerate() {
        let Some(j) = *j else { continue };
        let Some(centre) = apply(h, a[i].x as f64, a[i].y as f64) else { continue };
        let (pa, pb) = (sample_positions(&frame(&a[i])), sample_positions(&frame(&b[j])));
        let (mut kept, mut lucky) = (0usize, 0usize);
        for n in 1..SAMPLES {
            let Some((x, y)) = apply(h, pa[n].0, pa[n].1) else { continue };
            let near = |(u, v): (f64, f64)| (pb[n].0 - u).hypot(pb[n].1 - v) <= px;
            kept += usize::from(near((x, y)));
            lucky += usize::from(near(turned(x, y, centre)));
        }
        sum += kept as f64 / ring as f64;
        chance += lucky as f64 / ring as f64;
        n += 1;
    }
    (n > 0).then(|| Share { share: sum / n as f64, chance: chance / n as f64, keypoints: n })
}

/// The shares of every pair `(1, k)` of `seq` on the project's keypoints: the neighbour share under the
/// shipped rule ([`NeighbourRule::Nearest`]) and the ring share, and the neighbour share under each of
/// `cfg.neighbour_rules` as [`RuleShare`]s. `geometry` holds each pair's zoom, rotation and tilt.
pub(super) fn sequence_shares(
    seq: &Sequence,
    images: &[GreyImage],
    geometry: &[LocalGeometry],
    cfg: &HomographyConfig,
) -> Result<(Vec<PairShares>, Vec<RuleShare>), BoxError> {
    let kps: Vec<Vec<Keypoint>> = images
        .iter()
        .map(|im| crate::describe::features::extract(im, &cfg.extractor).map(|f| f.keypoints))
        .collect::<Result<_, _>>()?;
    // Each pair's share under `rule`.
    let shares_of = |rule: NeighbourRule| -> Vec<Option<Share>> {
        let cons: Vec<Constellations> = kps.iter().map(|k| constellation::build_with(k, cfg.k, rule)).collect();
        let share = |(i, h): (usize, &Matrix3<f64>)| {
            neighbour_share(&kps[0], &cons[0], &kps[i + 1], &cons[i + 1], h, cfg.correct_px)
        };
        seq.homographies.iter().enumerate().map(share).collect()
    };
    let pairs = shares_of(NeighbourRule::Nearest)
        .into_iter()
        .zip(&seq.homographies)
        .enumerate()
        .map(|(i, (neighbours, h))| PairShares {
            neighbours,
            ring: ring_share(&kps[0], &kps[i + 1], h, cfg.correct_px),
        })
        .collect();
    let mut rule_shares = Vec::new();
    for &rule in &cfg.neighbour_rules {
        for (i, share) in shares_of(rule).into_iter().enumerate() {
            rule_shares.push(RuleShare {
                rule,
                sequence: seq.name.clone(),
                image: i + 2,
                zoom: geometry[i].zoom,
                rotation_deg: geometry[i].rotation_deg,
                tilt_deg: geometry[i].tilt_deg,
                share: share.map(|s| s.share),
            });
        }
    }
    Ok((pairs, rule_shares))
}

/// One pair's shares on the project's keypoints.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct PairShares {
    pub neighbours: Option<Share>,
    pub ring: Option<Share>,
}
