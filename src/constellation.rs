//! Constellations: each keypoint with its k nearest keypoints of the same image, in the keypoint's own frame.
//!
//! For a central keypoint `i` (position `p_i`, orientation `θ_i` in radians from the keypoint's `angle`
//! in degrees, size `s_i`) and a neighbour `j`, with `d = p_j - p_i` in pixels:
//!
//! ```text
//! u      = ( cos θ_i · d.x + sin θ_i · d.y) / s_i      position along the keypoint's orientation
//! v      = (−sin θ_i · d.x + cos θ_i · d.y) / s_i      position across it (image axes, y down)
//! dθ     = wrap(θ_j − θ_i) into [−π, π)                 relative orientation, radians
//! log_s  = ln(s_j / s_i)                                relative scale
//! ```
//!
//! Rotating the image by φ adds φ to every orientation and rotates every `d` by φ, and scaling it by `c`
//! multiplies every `d` and size by `c`, so all four values are unchanged: the constellation is invariant to
//! similarity transforms of the image up to detection noise.
//!
//! Neighbours are the `k` keypoints nearest to `p_i` in pixel distance (the keypoint itself excluded),
//! ordered nearest first; equal distances are ordered by keypoint index. An image with `n <= k` keypoints
//! yields `n − 1` real neighbours per keypoint and `k − n + 1` padding slots: a padding slot holds the
//! central keypoint's own index, zero geometry and mask 0, so the network can ignore it and tensors keep
//! their fixed `[N, k]` shape.

use crate::features::Keypoint;

/// Number of values of relative geometry per neighbour: u, v, dθ, ln scale ratio.
pub const GEOMETRY_DIM: usize = 4;
/// The paper's constellation size.
pub const DEFAULT_K: usize = 20;

/// Constellations of all keypoints of one image, row-major `[N, k]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Constellations {
    pub k: usize,
    /// Neighbour keypoint indices, `[N, k]`, nearest first.
    pub neighbours: Vec<u32>,
    /// 1 for a real neighbour, 0 for padding, `[N, k]`.
    pub mask: Vec<u8>,
    /// Relative geometry `[u, v, dθ, ln(s_j/s_i)]`, `[N, k]`.
    pub relative: Vec<[f32; GEOMETRY_DIM]>,
}

impl Constellations {
    pub fn len(&self) -> usize {
        self.neighbours.len().checked_div(self.k).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.neighbours.is_empty()
    }

    /// Neighbour indices of keypoint `i`.
    pub fn neighbours_of(&self, i: usize) -> &[u32] {
        &self.neighbours[i * self.k..(i + 1) * self.k]
    }

    /// Relative geometry of keypoint `i`'s neighbours.
    pub fn relative_of(&self, i: usize) -> &[[f32; GEOMETRY_DIM]] {
        &self.relative[i * self.k..(i + 1) * self.k]
    }
}

/// Wraps an angle in radians into [−π, π).
pub fn wrap_angle(a: f32) -> f32 {
    use std::f32::consts::PI;
    (a + PI).rem_euclid(2.0 * PI) - PI
}

/// Relative geometry of `neighbour` in the frame of `centre` (the formulas of the module docs).
pub fn relative_geometry(centre: &Keypoint, neighbour: &Keypoint) -> [f32; GEOMETRY_DIM] {
    let theta = centre.angle.to_radians();
    let (sin, cos) = theta.sin_cos();
    let dx = neighbour.x - centre.x;
    let dy = neighbour.y - centre.y;
    [
        (cos * dx + sin * dy) / centre.size,
        (-sin * dx + cos * dy) / centre.size,
        wrap_angle(neighbour.angle.to_radians() - theta),
        (neighbour.size / centre.size).ln(),
    ]
}

/// Builds the constellation of every keypoint (exact k-nearest neighbours in pixel distance).
pub fn build(keypoints: &[Keypoint], k: usize) -> Constellations {
    let n = keypoints.len();
    let mut neighbours = Vec::with_capacity(n * k);
    let mut mask = Vec::with_capacity(n * k);
    let mut relative = Vec::with_capacity(n * k);
    let mut dist: Vec<(f32, u32)> = Vec::with_capacity(n);
    for (i, c) in keypoints.iter().enumerate() {
        dist.clear();
        dist.extend(keypoints.iter().enumerate().filter(|&(j, _)| j != i).map(|(j, p)| {
            let dx = p.x - c.x;
            let dy = p.y - c.y;
            (dx * dx + dy * dy, j as u32)
        }));
        let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        let take = k.min(dist.len());
        if take > 0 && take < dist.len() {
            dist.select_nth_unstable_by(take - 1, order);
        }
        dist[..take].sort_unstable_by(order);
        for &(_, j) in &dist[..take] {
            neighbours.push(j);
            mask.push(1);
            relative.push(relative_geometry(c, &keypoints[j as usize]));
        }
        for _ in take..k {
            neighbours.push(i as u32);
            mask.push(0);
            relative.push([0.0; GEOMETRY_DIM]);
        }
    }
    Constellations { k, neighbours, mask, relative }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic pseudo-random keypoints (a tiny LCG keeps the test free of extra crates).
    fn keypoints(n: usize, seed: u64) -> Vec<Keypoint> {
        let mut s = seed;
        let mut next = move || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 33) as f64 / (1u64 << 31) as f64) as f32
        };
        (0..n)
            .map(|_| Keypoint {
                x: 20.0 + 600.0 * next(),
                y: 20.0 + 440.0 * next(),
                size: 7.0 * 1.2f32.powi((next() * 5.0) as i32),
                angle: 360.0 * next(),
                response: 10.0 + 50.0 * next(),
                octave: 0,
            })
            .collect()
    }

    #[test]
    fn neighbours_are_nearest_first_and_exclude_self() {
        let kps = keypoints(300, 7);
        let c = build(&kps, 20);
        assert_eq!(c.len(), 300);
        for i in 0..kps.len() {
            let nb = c.neighbours_of(i);
            assert!(!nb.contains(&(i as u32)));
            let d = |j: u32| {
                let p = &kps[j as usize];
                (p.x - kps[i].x).hypot(p.y - kps[i].y)
            };
            for w in nb.windows(2) {
                assert!(d(w[0]) <= d(w[1]));
            }
            // No keypoint outside the constellation is closer than its farthest member.
            let far = d(nb[19]);
            let closer = (0..kps.len() as u32).filter(|&j| j != i as u32 && d(j) < far).count();
            assert!(closer <= 19, "keypoint {i}: {closer} keypoints closer than the 20th neighbour");
        }
    }

    #[test]
    fn equal_distances_are_ordered_by_index() {
        let at = |x, y| Keypoint { x, y, size: 7.0, angle: 0.0, response: 1.0, octave: 0 };
        let kps = vec![at(0.0, 0.0), at(0.0, 5.0), at(5.0, 0.0), at(-5.0, 0.0), at(0.0, 1.0)];
        let c = build(&kps, 4);
        assert_eq!(c.neighbours_of(0), &[4, 1, 2, 3]);
    }

    #[test]
    fn geometry_is_invariant_to_rotation_and_scale() {
        let kps = keypoints(200, 11);
        let base = build(&kps, 20);
        for &(phi_deg, scale) in &[(37.0f32, 1.0f32), (-120.0, 0.7), (179.0, 1.4), (90.0, 1.1), (300.0, 0.85)] {
            let phi = phi_deg.to_radians();
            let (sin, cos) = phi.sin_cos();
            let moved: Vec<Keypoint> = kps
                .iter()
                .map(|k| Keypoint {
                    x: scale * (cos * k.x - sin * k.y) + 1000.0,
                    y: scale * (sin * k.x + cos * k.y) - 50.0,
                    size: k.size * scale,
                    angle: (k.angle + phi_deg).rem_euclid(360.0),
                    ..*k
                })
                .collect();
            let c = build(&moved, 20);
            assert_eq!(c.neighbours, base.neighbours, "neighbour order changed at {phi_deg} deg x{scale}");
            for (a, b) in c.relative.iter().zip(&base.relative) {
                assert!((a[0] - b[0]).abs() < 1e-3 && (a[1] - b[1]).abs() < 1e-3, "{a:?} vs {b:?}");
                assert!(wrap_angle(a[2] - b[2]).abs() < 1e-4, "{a:?} vs {b:?}");
                assert!((a[3] - b[3]).abs() < 1e-5, "{a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn relative_geometry_formula_examples() {
        let c = Keypoint { x: 10.0, y: 10.0, size: 10.0, angle: 90.0, response: 1.0, octave: 0 };
        // A neighbour 20 px along +y (the centre's orientation direction when angle = 90 degrees).
        let n = Keypoint { x: 10.0, y: 30.0, size: 20.0, angle: 180.0, ..c };
        let g = relative_geometry(&c, &n);
        assert!((g[0] - 2.0).abs() < 1e-6 && g[1].abs() < 1e-6, "{g:?}");
        assert!((g[2] - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        assert!((g[3] - 2f32.ln()).abs() < 1e-6);
    }

    #[test]
    fn fewer_than_k_plus_one_keypoints_are_padded() {
        let kps = keypoints(4, 3);
        let c = build(&kps, 20);
        for i in 0..4 {
            let m = &c.mask[i * 20..(i + 1) * 20];
            assert_eq!(m.iter().filter(|&&v| v == 1).count(), 3);
            assert!(m[3..].iter().all(|&v| v == 0));
            assert!(c.neighbours_of(i)[3..].iter().all(|&j| j == i as u32));
            assert!(c.relative_of(i)[3..].iter().all(|g| *g == [0.0; 4]));
        }
        assert!(build(&[], 20).is_empty());
        let one = build(&kps[..1], 20);
        assert_eq!(one.mask, vec![0; 20]);
    }

    #[test]
    fn wrap_angle_range() {
        use std::f32::consts::PI;
        for a in [-10.0f32, -PI, -0.1, 0.0, 3.0, PI, 7.0, 100.0] {
            let w = wrap_angle(a);
            assert!((-PI..PI).contains(&w), "{a} -> {w}");
            assert!(((a - w) / (2.0 * PI)).round() * 2.0 * PI - (a - w) < 1e-4);
        }
    }
}
