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

use crate::describe::features::Keypoint;

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

    /// Mask of keypoint `i`'s neighbour slots (1 real, 0 padding).
    pub fn mask_of(&self, i: usize) -> &[u8] {
        &self.mask[i * self.k..(i + 1) * self.k]
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
    KeypointFrame::of(centre).relative(&KeypointFrame::of(neighbour))
}

/// What the relative geometry needs of one keypoint, computed once per keypoint rather than once for each of the
/// ~k constellations it is a member of (the sine, cosine and logarithm were most of the build's time).
#[derive(Debug, Clone, Copy)]
struct KeypointFrame {
    x: f32,
    y: f32,
    theta: f32,
    sin: f32,
    cos: f32,
    inv_size: f32,
    ln_size: f32,
}

impl KeypointFrame {
    fn of(p: &Keypoint) -> Self {
        let theta = p.angle.to_radians();
        let (sin, cos) = theta.sin_cos();
        Self { x: p.x, y: p.y, theta, sin, cos, inv_size: 1.0 / p.size, ln_size: p.size.ln() }
    }

    /// `other` in this keypoint's frame: u, v in its sizes, dθ wrapped into [−π, π), ln of the size ratio.
    fn relative(&self, other: &Self) -> [f32; GEOMETRY_DIM] {
        use std::f32::consts::PI;
        let dx = other.x - self.x;
        let dy = other.y - self.y;
        // Both angles come from [0°, 360°), so one turn at most brings the difference into range; the general
        // `wrap_angle` handles anything else.
        let d = other.theta - self.theta;
        let dtheta = if (-3.0 * PI..3.0 * PI).contains(&d) {
            if d >= PI {
                d - 2.0 * PI
            } else if d < -PI {
                d + 2.0 * PI
            } else {
                d
            }
        } else {
            wrap_angle(d)
        };
        [
            (self.cos * dx + self.sin * dy) * self.inv_size,
            (-self.sin * dx + self.cos * dy) * self.inv_size,
            dtheta,
            other.ln_size - self.ln_size,
        ]
    }
}

/// A uniform grid over keypoint positions for exact k-nearest-neighbour search.
struct Grid {
    x0: f32,
    y0: f32,
    cell: f32,
    cols: i64,
    rows: i64,
    /// Keypoint indices sorted by cell; `starts[c]..starts[c + 1]` are the members of cell `c`.
    order: Vec<u32>,
    starts: Vec<u32>,
}

impl Grid {
    /// Cells sized so that one holds about `per_cell` keypoints on average.
    fn new(keypoints: &[Keypoint], per_cell: f32) -> Self {
        let (mut x0, mut y0, mut x1, mut y1) = (f32::MAX, f32::MAX, f32::MIN, f32::MIN);
        for p in keypoints {
            x0 = x0.min(p.x);
            y0 = y0.min(p.y);
            x1 = x1.max(p.x);
            y1 = y1.max(p.y);
        }
        let area = ((x1 - x0).max(1.0)) * ((y1 - y0).max(1.0));
        let cell = (area * per_cell / keypoints.len().max(1) as f32).sqrt().max(1.0);
        let cols = ((x1 - x0) / cell) as i64 + 1;
        let rows = ((y1 - y0) / cell) as i64 + 1;
        let mut grid = Self { x0, y0, cell, cols, rows, order: Vec::new(), starts: Vec::new() };
        let cell_of: Vec<u32> = keypoints.iter().map(|p| grid.cell_index(p) as u32).collect();
        let mut counts = vec![0u32; (cols * rows) as usize + 1];
        for &c in &cell_of {
            counts[c as usize + 1] += 1;
        }
        for i in 1..counts.len() {
            counts[i] += counts[i - 1];
        }
        let mut fill = counts.clone();
        let mut order = vec![0u32; keypoints.len()];
        for (i, &c) in cell_of.iter().enumerate() {
            order[fill[c as usize] as usize] = i as u32;
            fill[c as usize] += 1;
        }
        grid.order = order;
        grid.starts = counts;
        grid
    }

    fn coords(&self, p: &Keypoint) -> (i64, i64) {
        (((p.x - self.x0) / self.cell) as i64, ((p.y - self.y0) / self.cell) as i64)
    }

    fn cell_index(&self, p: &Keypoint) -> i64 {
        let (cx, cy) = self.coords(p);
        cy * self.cols + cx
    }

    /// Members of cell (cx, cy), empty outside the grid.
    fn members(&self, cx: i64, cy: i64) -> &[u32] {
        if cx < 0 || cy < 0 || cx >= self.cols || cy >= self.rows {
            return &[];
        }
        let c = (cy * self.cols + cx) as usize;
        &self.order[self.starts[c] as usize..self.starts[c + 1] as usize]
    }

    /// The `k` nearest keypoints to keypoint `i` (itself excluded), ordered by (distance, index), written to
    /// `out`. Rings of cells are visited outwards until the k-th candidate is closer than any unvisited cell.
    fn nearest(&self, keypoints: &[Keypoint], i: usize, k: usize, out: &mut Vec<(f32, u32)>) {
        out.clear();
        let c = &keypoints[i];
        let (cx, cy) = self.coords(c);
        let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        let max_ring = self.cols.max(self.rows);
        for r in 0..=max_ring {
            for gy in cy - r..=cy + r {
                for gx in cx - r..=cx + r {
                    if (gy - cy).abs() != r && (gx - cx).abs() != r {
                        continue;
                    }
                    for &j in self.members(gx, gy) {
                        if j as usize != i {
                            let p = &keypoints[j as usize];
                            let (dx, dy) = (p.x - c.x, p.y - c.y);
                            out.push((dx * dx + dy * dy, j));
                        }
                    }
                }
            }
            if out.len() >= k {
                if out.len() > k {
                    out.select_nth_unstable_by(k - 1, order);
                    out.truncate(k);
                }
                // Every keypoint outside rings 0..=r is at least r cells away from c.
                let reach = r as f32 * self.cell;
                let kth = out.iter().map(|d| d.0).fold(0.0f32, f32::max);
                if kth < reach * reach {
                    break;
                }
            }
        }
        out.sort_unstable_by(order);
        out.truncate(k);
    }
}

/// Which keypoints make a constellation. [`NeighbourRule::Nearest`] is the shipped model's (the module docs);
/// the others are candidates for zoom (constellations meant to keep their members when the scale changes,
/// measured by `scone eval homography`'s neighbour share), built by brute force.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum NeighbourRule {
    /// The k nearest keypoints in pixels.
    #[default]
    Nearest,
    /// The k nearest among keypoints within one pyramid level (a factor 1.2 in size) of the central one.
    Window1,
    /// The same within two levels.
    Window2,
    /// The k smallest distances in units of the neighbour's own size (`d / s_j`): under a zoom both scale
    /// alike, and structure only the finer image resolves (small `s_j`) ranks far.
    SizeUnits,
    /// [`NeighbourRule::SizeUnits`] among keypoints within two pyramid levels of the central one.
    SizeUnitsWindow2,
}

impl NeighbourRule {
    fn window_levels(self) -> Option<f32> {
        match self {
            NeighbourRule::Window1 => Some(1.0),
            NeighbourRule::Window2 | NeighbourRule::SizeUnitsWindow2 => Some(2.0),
            _ => None,
        }
    }
}

/// Builds the constellations of `keypoints` by `rule`.
pub fn build_with(keypoints: &[Keypoint], k: usize, rule: NeighbourRule) -> Constellations {
    if rule == NeighbourRule::Nearest {
        return build(keypoints, k);
    }
    let level = 1.2f32.ln();
    let window = rule.window_levels().map(|w| w * level + 1e-3);
    let size_units = matches!(rule, NeighbourRule::SizeUnits | NeighbourRule::SizeUnitsWindow2);
    let n = keypoints.len();
    let frames: Vec<KeypointFrame> = keypoints.iter().map(KeypointFrame::of).collect();
    let mut out = Constellations::with_capacity(n, k);
    let mut cands: Vec<(f32, u32)> = Vec::with_capacity(n);
    for (i, c) in keypoints.iter().enumerate() {
        cands.clear();
        for (j, p) in keypoints.iter().enumerate() {
            if j == i || window.is_some_and(|w| (p.size / c.size).ln().abs() > w) {
                continue;
            }
            let d = (p.x - c.x).hypot(p.y - c.y);
            cands.push((if size_units { d / p.size } else { d }, j as u32));
        }
        let order = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
        if cands.len() > k && k > 0 {
            cands.select_nth_unstable_by(k - 1, order);
        }
        cands.truncate(k);
        cands.sort_unstable_by(order);
        out.push(&frames, i, &cands);
    }
    out
}

impl Constellations {
    fn with_capacity(n: usize, k: usize) -> Self {
        Self {
            k,
            neighbours: Vec::with_capacity(n * k),
            mask: Vec::with_capacity(n * k),
            relative: Vec::with_capacity(n * k),
        }
    }

    /// Appends keypoint `i`'s constellation: `members` (key, index) in order, then padding up to k.
    fn push(&mut self, frames: &[KeypointFrame], i: usize, members: &[(f32, u32)]) {
        let c = &frames[i];
        for &(_, j) in members {
            self.neighbours.push(j);
            self.mask.push(1);
            self.relative.push(c.relative(&frames[j as usize]));
        }
        for _ in members.len()..self.k {
            self.neighbours.push(i as u32);
            self.mask.push(0);
            self.relative.push([0.0; GEOMETRY_DIM]);
        }
    }
}

/// Builds the constellation of every keypoint (exact k-nearest neighbours in pixel distance, found with a
/// uniform grid: about `N·k` distance evaluations instead of `N²`).
pub fn build(keypoints: &[Keypoint], k: usize) -> Constellations {
    let mut out = Constellations::with_capacity(keypoints.len(), k);
    let frames: Vec<KeypointFrame> = keypoints.iter().map(KeypointFrame::of).collect();
    let grid = Grid::new(keypoints, (k as f32 / 4.0).max(1.0));
    let mut nearest: Vec<(f32, u32)> = Vec::with_capacity(4 * k);
    for i in 0..keypoints.len() {
        if k > 0 {
            grid.nearest(keypoints, i, k, &mut nearest);
        }
        out.push(&frames, i, &nearest);
    }
    out
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

    /// The candidate rules keep their promises: members within the size window, ordered by their key, padding
    /// only when too few keypoints qualify; and a zoom of the whole image leaves `size-units` sets unchanged.
    #[test]
    fn neighbour_rules_keep_their_windows_and_size_units_are_zoom_invariant() {
        let kps = keypoints(300, 11);
        for rule in [NeighbourRule::Window1, NeighbourRule::Window2, NeighbourRule::SizeUnitsWindow2] {
            let c = build_with(&kps, 20, rule);
            let w = rule.window_levels().unwrap() * 1.2f32.ln() + 1e-3;
            for i in 0..kps.len() {
                for (&j, &m) in c.neighbours_of(i).iter().zip(c.mask_of(i)) {
                    if m > 0 {
                        assert!((kps[j as usize].size / kps[i].size).ln().abs() <= w);
                    }
                }
            }
        }
        assert_eq!(build_with(&kps, 20, NeighbourRule::Nearest), build(&kps, 20));
        let zoomed: Vec<Keypoint> =
            kps.iter().map(|p| Keypoint { x: 2.0 * p.x + 5.0, y: 2.0 * p.y - 3.0, size: 2.0 * p.size, ..*p }).collect();
        let a = build_with(&kps, 20, NeighbourRule::SizeUnits);
        let b = build_with(&zoomed, 20, NeighbourRule::SizeUnits);
        assert_eq!(a.neighbours, b.neighbours);
        assert!(a.mask.iter().all(|&m| m == 1));
    }

    /// The grid search returns exactly what brute force returns, clustered and duplicated positions included.
    #[test]
    fn grid_search_equals_brute_force() {
        let mut kps = keypoints(700, 5);
        // A dense cluster, exact duplicates and a far outlier stress the ring stopping rule.
        for i in 0..60 {
            kps.push(Keypoint { x: 300.0 + (i % 8) as f32 * 0.5, y: 200.0 + (i / 8) as f32 * 0.5, ..kps[0] });
        }
        kps.push(kps[3]);
        kps.push(kps[3]);
        kps.push(Keypoint { x: 5000.0, y: -3000.0, ..kps[0] });
        for k in [1, 5, 20, 40] {
            let c = build(&kps, k);
            for (i, p) in kps.iter().enumerate() {
                let mut d: Vec<(f32, u32)> = kps
                    .iter()
                    .enumerate()
                    .filter(|&(j, _)| j != i)
                    .map(|(j, q)| ((q.x - p.x).powi(2) + (q.y - p.y).powi(2), j as u32))
                    .collect();
                d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let want: Vec<u32> = d.iter().take(k).map(|x| x.1).collect();
                assert_eq!(c.neighbours_of(i), &want[..], "keypoint {i}, k = {k}");
            }
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

    /// The per-keypoint frames give the module docs' formulas, computed directly, for every pair of a set that
    /// covers the angle wrap's edges (0°, 180°, 359.99°) and sizes from one pyramid end to the other.
    #[test]
    fn keypoint_frames_give_the_direct_formulas() {
        let mut kps = keypoints(40, 11);
        for (i, a) in [0.0f32, 180.0, 359.99, 90.0, 270.0, 0.001].into_iter().enumerate() {
            kps[i].angle = a;
            kps[i].size = 7.0 * 1.2f32.powi(i as i32);
        }
        for c in &kps {
            for n in &kps {
                let theta = c.angle.to_radians();
                let (dx, dy) = (n.x - c.x, n.y - c.y);
                let direct = [
                    (theta.cos() * dx + theta.sin() * dy) / c.size,
                    (-theta.sin() * dx + theta.cos() * dy) / c.size,
                    wrap_angle(n.angle.to_radians() - theta),
                    (n.size / c.size).ln(),
                ];
                let g = relative_geometry(c, n);
                for (a, b) in g.iter().zip(direct) {
                    assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{g:?} vs {direct:?}");
                }
                assert!((-std::f32::consts::PI..std::f32::consts::PI).contains(&g[2]), "{g:?}");
            }
        }
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
