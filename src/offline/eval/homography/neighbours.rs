//! The neighbour share (module docs of `homography`): how much of a keypoint's constellation survives the
//! true homography, before any network sees it.

use nalgebra::Matrix3;

use crate::constellation::{self, Constellations, NeighbourRule};
use crate::decode::GreyImage;
use crate::features::Keypoint;
use crate::offline::eval::homography::geometry::apply;
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

/// Mean share of constellation members that survive `h` (the `homography` module docs), and the corresponding keypoints it is
/// averaged over; None when no keypoint corresponds.
pub fn neighbour_share(
    a: &[Keypoint],
    ca: &Constellations,
    b: &[Keypoint],
    cb: &Constellations,
    h: &Matrix3<f64>,
    px: f64,
) -> Option<(f64, usize)> {
    let corr = correspondences(a, b, h, px);
    let (mut sum, mut n) = (0.0, 0usize);
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
        if members_a.is_empty() || ca.k == 0 {
            continue;
        }
        let kept = members_a
            .iter()
            .filter(|&&m| {
                apply(h, a[m].x as f64, a[m].y as f64)
                    .is_some_and(|(x, y)| members_b.iter().any(|q| (q.x as f64 - x).hypot(q.y as f64 - y) <= px))
            })
            .count();
        sum += kept as f64 / ca.k as f64;
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64, n))
}

/// The neighbour share of every pair `(1, k)` of `seq` on the project's keypoints: under the shipped rule
/// ([`NeighbourRule::Nearest`]), and under each of `cfg.neighbour_rules` as [`RuleShare`]s. `geometry` holds
/// each pair's zoom and rotation.
pub(super) fn sequence_shares(
    seq: &Sequence,
    images: &[GreyImage],
    geometry: &[(f64, f64)],
    cfg: &HomographyConfig,
) -> Result<(Vec<Option<f64>>, Vec<RuleShare>), BoxError> {
    let kps: Vec<Vec<Keypoint>> = images
        .iter()
        .map(|im| crate::features::extract(im, &cfg.extractor).map(|f| f.keypoints))
        .collect::<Result<_, _>>()?;
    // Each pair's share under `rule`.
    let shares_of = |rule: NeighbourRule| -> Vec<Option<f64>> {
        let cons: Vec<Constellations> = kps.iter().map(|k| constellation::build_with(k, cfg.k, rule)).collect();
        let share = |(i, h): (usize, &Matrix3<f64>)| {
            neighbour_share(&kps[0], &cons[0], &kps[i + 1], &cons[i + 1], h, cfg.correct_px).map(|s| s.0)
        };
        seq.homographies.iter().enumerate().map(share).collect()
    };
    let nearest = shares_of(NeighbourRule::Nearest);
    let mut rule_shares = Vec::new();
    for &rule in &cfg.neighbour_rules {
        for (i, share) in shares_of(rule).into_iter().enumerate() {
            rule_shares.push(RuleShare {
                rule,
                sequence: seq.name.clone(),
                image: i + 2,
                zoom: geometry[i].0,
                rotation_deg: geometry[i].1,
                share,
            });
        }
    }
    Ok((nearest, rule_shares))
}
