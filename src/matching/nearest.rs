//! Brute-force nearest neighbours in both directions, OpenCV's answer to the bit at a fraction of its time:
//! the mutual check of stage 2 of Localize and of map building's candidate matching
//! (`matching::match_descriptors_masked` with `mutual`).

use opencv::core::{Mat, NORM_HAMMING, NORM_L2};
use opencv::prelude::*;

use crate::error::FeatureError;

/// Brute-force nearest neighbours in both directions from one distance matrix: what OpenCV's
/// `BFMatcher::knnMatch(query, train, k, mask)` and `BFMatcher::match(train, query, maskᵀ)` answer, at half
/// their distance computations. Both call `cv::batchDistance` with the same per-pair arithmetic, which is
/// symmetric, so one matrix serves both; it is computed here in bands of query rows
/// ([`BOTH_WAYS_BAND_VALUES`] distances at a time) and read with OpenCV's own orders: a query row's neighbours
/// by ascending distance, ties in train order, and a train row's nearest query row the first of the smallest.
/// A pair the mask leaves out has batchDistance's "no distance" (`FLT_MAX`, or `INT_MAX` for Hamming) and is
/// never a neighbour, as in OpenCV.
pub struct BothWays {
    /// Per query row, its `k` nearest train rows (fewer when `train` or the mask admits fewer): (train row,
    /// distance).
    pub forward: Vec<Vec<(usize, f32)>>,
    /// Per train row, its nearest query row (none when the mask admits none).
    pub back: Vec<Option<usize>>,
}

/// The most distances [`nearest_both_ways`] holds at once (16 MB of f32).
pub const BOTH_WAYS_BAND_VALUES: usize = 1 << 22;

/// [`BothWays`] of `query` against `train` (the same type: f32 rows with `NORM_L2`, bytes with
/// `NORM_HAMMING`), only the pairs `mask` admits (`query.rows() x train.rows()`, `CV_8U`; empty admits all).
/// Empty when either has no rows.
pub fn nearest_both_ways(query: &Mat, train: &Mat, norm: i32, k: usize, mask: &Mat) -> Result<BothWays, FeatureError> {
    let pairs = query.rows().max(0) as usize * train.rows().max(0) as usize;
    if norm == NORM_L2 && pairs >= BY_PRODUCT_MIN_PAIRS {
        let parts = rayon::current_num_threads().min(query.rows() as usize / PART_MIN_ROWS).max(1);
        if let Some(both) = l2_by_product(query, train, k, mask, BOTH_WAYS_BAND_VALUES, parts)? {
            return Ok(both);
        }
    }
    nearest_both_ways_in_bands(query, train, norm, k, mask, BOTH_WAYS_BAND_VALUES)
}

/// Estimates scanned per vector compare in [`l2_by_product`].
const SCAN_CHUNK: usize = 32;

/// Below this many pairs, OpenCV's distances alone ([`nearest_both_ways`]).
const BY_PRODUCT_MIN_PAIRS: usize = 1 << 16;

/// [`nearest_both_ways`] for `NORM_L2` with the same answer to the bit, most distances never computed by
/// OpenCV. A matrix product (ndarray's, `|q|² + |t|² - 2 q·t`) estimates every squared distance with an error
/// bounded by `(6 dim + 32) u (|q|² + |t|²)` (u the unit roundoff of f32: each dot product, norm and the two
/// sums are sums of at most `dim` terms, plus the error of OpenCV's own value and of its square root). The
/// pairs whose estimate lies within twice that bound of a row's k-th estimate or of a column's smallest can be
/// among OpenCV's answers; only those are measured again by `cv::batchDistance` (the very values BFMatcher
/// compares, whatever else is in the call) and ranked in OpenCV's orders. `None` when the rows are not
/// continuous f32 or their norms are not finite and below 1e30: then only OpenCV's path gives its answer.
/// The query rows are scanned and measured in `parts` contiguous parts on rayon's threads; a column's limit is
/// the smallest over every part, and the parts' answers are joined in row order, so the answer does not depend
/// on `parts`.
fn l2_by_product(
    query: &Mat,
    train: &Mat,
    k: usize,
    mask: &Mat,
    band_values: usize,
    parts: usize,
) -> Result<Option<BothWays>, FeatureError> {
    let (nq, nt, dim) = (query.rows().max(0) as usize, train.rows().max(0) as usize, query.cols().max(0) as usize);
    let continuous = query.is_continuous() && train.is_continuous() && (mask.empty() || mask.is_continuous());
    let f32_rows = query.typ() == opencv::core::CV_32F && train.typ() == opencv::core::CV_32F;
    if nq == 0 || nt == 0 || dim == 0 || train.cols() != query.cols() || !continuous || !f32_rows {
        return Ok(None);
    }
    let (q, t) = (query.data_typed::<f32>()?, train.data_typed::<f32>()?);
    let norms = |x: &[f32]| -> Vec<f32> { x.chunks_exact(dim).map(|r| r.iter().map(|v| v * v).sum()).collect() };
    let (qn, tn) = (norms(q), norms(t));
    if !qn.iter().chain(&tn).all(|v| v.is_finite() && *v < 1e30) {
        return Ok(None);
    }
    let admitted: Option<&[u8]> = if mask.empty() { None } else { Some(mask.data_typed::<u8>()?) };
    let e = (6 * dim + 32) as f32 * (f32::EPSILON / 2.0);
    let (qmax, tmax) = (qn.iter().fold(0f32, |a, &b| a.max(b)), tn.iter().fold(0f32, |a, &b| a.max(b)));
    let col_slack: Vec<f32> = tn.iter().map(|&x| 2.0 * e * (qmax + x)).collect();
    let shared = Shared { q, t, qn: &qn, tn: &tn, admitted, dim, k: k.min(nt), e, tmax, col_slack: &col_slack };
    // Contiguous parts of the query rows, each scanned on a thread of rayon's with its own band of estimates.
    let parts = parts.clamp(1, nq);
    let bounds: Vec<(usize, usize)> = (0..parts).map(|p| (p * nq / parts, (p + 1) * nq / parts)).collect();
    let band = (band_values / parts / nt).clamp(1, nq);
    let scanned: Vec<Scanned> = par_map(bounds, |(a, b)| shared.scan(a, b, band))?;
    // A column's smallest estimate over every part sets its limit; a part's own limits were never below it,
    // so each part holds every pair under it.
    let mut col_limit = vec![f32::INFINITY; nt];
    for s in &scanned {
        col_limit.iter_mut().zip(&s.col_min).for_each(|(l, &m)| *l = l.min(m));
    }
    col_limit.iter_mut().zip(&col_slack).for_each(|(l, &s)| *l = if l.is_finite() { *l + s } else { f32::MAX });
    let measured: Vec<Measured> = par_map(scanned, |s| shared.measure(query, s, &col_limit))?;
    // Parts in row order, and a strict "below": a train row's nearest query row is the first of the smallest.
    let mut out = BothWays { forward: Vec::with_capacity(nq), back: vec![None; nt] };
    let mut best = vec![f32::MAX; nt];
    for m in measured {
        out.forward.extend(m.forward);
        for (j, (d, i)) in m.back.into_iter().enumerate() {
            if d < best[j] {
                best[j] = d;
                out.back[j] = Some(i);
            }
        }
    }
    Ok(Some(out))
}

/// Query rows below which a part of [`l2_by_product`] is not worth a thread of its own ([`nearest_both_ways`]).
const PART_MIN_ROWS: usize = 256;

/// [`l2_by_product`]'s parts of the query rows on rayon's threads (the one calling, alone), in order.
fn par_map<I: Send, O: Send>(
    mut items: Vec<I>,
    f: impl Fn(I) -> Result<O, FeatureError> + Sync + Send,
) -> Result<Vec<O>, FeatureError> {
    use rayon::prelude::*;
    if items.len() == 1 {
        return Ok(vec![f(items.pop().expect("one item"))?]);
    }
    items.into_par_iter().map(f).collect()
}

/// What every part of [`l2_by_product`] reads.
struct Shared<'a> {
    q: &'a [f32],
    t: &'a [f32],
    qn: &'a [f32],
    tn: &'a [f32],
    admitted: Option<&'a [u8]>,
    dim: usize,
    k: usize,
    /// The bound's factor: a squared distance's estimate errs by at most `e (|q|² + |t|²)`.
    e: f32,
    tmax: f32,
    col_slack: &'a [f32],
}

/// A part's scan: per query row of `rows`, the train rows that may be among its k nearest; the pairs that may
/// hold a column's nearest row (train row, query row, estimate); and each column's smallest estimate.
struct Scanned {
    rows: (usize, usize),
    needed: Vec<Vec<u32>>,
    col_cands: Vec<(u32, u32, f32)>,
    col_min: Vec<f32>,
}

/// A part's answer: its rows' k nearest, and per train row its nearest query row of the part (distance, row;
/// `f32::MAX` where the mask admits none).
struct Measured {
    forward: Vec<Vec<(usize, f32)>>,
    back: Vec<(f32, usize)>,
}

impl Shared<'_> {
    fn scan(&self, first: usize, end: usize, band: usize) -> Result<Scanned, FeatureError> {
        let (dim, nt, k) = (self.dim, self.tn.len(), self.k);
        let shape =
            |e: ndarray::ShapeError| FeatureError::OpenCv(opencv::Error::new(opencv::core::StsBadArg, e.to_string()));
        let tv = ndarray::ArrayView2::from_shape((nt, dim), self.t).map_err(shape)?;
        let mut col_min = vec![f32::INFINITY; nt];
        // f32::MAX, not infinity: a pair the mask leaves out never gets under it.
        let mut col_limit = vec![f32::MAX; nt];
        let mut col_cands: Vec<(u32, u32, f32)> = Vec::new();
        let mut needed: Vec<Vec<u32>> = vec![Vec::new(); end - first];
        let mut estimate = vec![0f32; nt];
        let mut top: Vec<((), f32)> = Vec::with_capacity(k + 1);
        let mut start = first;
        while start < end {
            let stop = (start + band).min(end);
            let qv = ndarray::ArrayView2::from_shape((stop - start, dim), &self.q[start * dim..stop * dim])
                .map_err(shape)?;
            let products = qv.dot(&tv.t());
            for (r, row) in products.rows().into_iter().enumerate() {
                let i = start + r;
                for ((a, &g), &n) in estimate.iter_mut().zip(row.iter()).zip(self.tn) {
                    *a = self.qn[i] + n - 2.0 * g;
                }
                // A pair the mask leaves out is estimated at infinity: above every limit below (all finite).
                if let Some(m) = self.admitted {
                    for (a, &m) in estimate.iter_mut().zip(&m[i * nt..(i + 1) * nt]) {
                        *a = if m == 0 { f32::INFINITY } else { *a };
                    }
                }
                // The k smallest estimates; chunks with nothing below the k-th are skipped whole (vector
                // compares).
                top.clear();
                let mut kth = f32::INFINITY;
                for chunk in estimate.chunks(SCAN_CHUNK) {
                    if !chunk.iter().fold(false, |hit, &a| hit | (a < kth)) {
                        continue;
                    }
                    for &a in chunk {
                        if a < kth {
                            kth = keep_nearest(&mut top, ((), a), k).unwrap_or(kth);
                        }
                    }
                }
                let limit = (kth + 2.0 * self.e * (self.qn[i] + self.tmax)).min(f32::MAX);
                let mine = &mut needed[i - first];
                let chunks = estimate.chunks(SCAN_CHUNK).zip(col_limit.chunks_mut(SCAN_CHUNK));
                for (c, (chunk, limits)) in chunks.enumerate() {
                    let hit =
                        chunk.iter().zip(limits.iter()).fold(false, |hit, (&a, &l)| hit | (a <= limit) | (a <= l));
                    if !hit {
                        continue;
                    }
                    for (o, (&a, l)) in chunk.iter().zip(limits.iter_mut()).enumerate() {
                        let j = c * SCAN_CHUNK + o;
                        if a <= limit {
                            mine.push(j as u32);
                        }
                        if a <= *l {
                            col_cands.push((j as u32, i as u32, a));
                            if a < col_min[j] {
                                col_min[j] = a;
                                *l = a + self.col_slack[j];
                            }
                        }
                    }
                }
            }
            start = stop;
        }
        Ok(Scanned { rows: (first, end), needed, col_cands, col_min })
    }

    /// OpenCV's distances of the pairs a part kept (its column candidates under the limits of every part),
    /// row by row, read in its orders.
    fn measure(&self, query: &Mat, s: Scanned, col_limit: &[f32]) -> Result<Measured, FeatureError> {
        let (dim, nt, first) = (self.dim, self.tn.len(), s.rows.0);
        let mut needed = s.needed;
        for &(j, i, a) in &s.col_cands {
            if a <= col_limit[j as usize] {
                needed[i as usize - first].push(j);
            }
        }
        let mut out = Measured { forward: Vec::with_capacity(needed.len()), back: vec![(f32::MAX, 0); nt] };
        let (mut gathered, mut dist) = (Vec::<f32>::new(), Mat::default());
        for (r, js) in needed.iter_mut().enumerate() {
            let i = first + r;
            js.sort_unstable();
            js.dedup();
            if js.is_empty() {
                out.forward.push(Vec::new());
                continue;
            }
            gathered.clear();
            for &j in js.iter() {
                gathered.extend_from_slice(&self.t[j as usize * dim..(j as usize + 1) * dim]);
            }
            let rows = Mat::new_rows_cols_with_data(js.len() as i32, dim as i32, &gathered)?;
            let mut no_index = opencv::core::no_array();
            let no_mask = opencv::core::no_array();
            opencv::core::batch_distance(
                &query.row(i as i32)?,
                &rows,
                &mut dist,
                opencv::core::CV_32F,
                &mut no_index,
                NORM_L2,
                0,
                &no_mask,
                0,
                false,
            )?;
            let d = dist.data_typed::<f32>()?;
            let mut near: Vec<(usize, f32)> = js.iter().zip(d).map(|(&j, &d)| (j as usize, d)).collect();
            for &(j, d) in &near {
                if d < out.back[j].0 {
                    out.back[j] = (d, i);
                }
            }
            near.sort_by(|x, y| x.1.total_cmp(&y.1).then(x.0.cmp(&y.0)));
            near.truncate(self.k);
            out.forward.push(near);
        }
        Ok(out)
    }
}

/// `cv::batchDistance`'s insertion of a distance below the k-th: `item` joins `near` (ascending, at most `k`)
/// after the equal distances. The k-th distance once there are `k`.
fn keep_nearest<T>(near: &mut Vec<(T, f32)>, item: (T, f32), k: usize) -> Option<f32> {
    let at = near.partition_point(|(_, e)| *e <= item.1);
    near.insert(at, item);
    near.truncate(k);
    (near.len() == k).then(|| near[k - 1].1)
}

fn nearest_both_ways_in_bands(
    query: &Mat,
    train: &Mat,
    norm: i32,
    k: usize,
    mask: &Mat,
    band_values: usize,
) -> Result<BothWays, FeatureError> {
    let (nq, nt) = (query.rows().max(0) as usize, train.rows().max(0) as usize);
    let mut out = BothWays { forward: Vec::with_capacity(nq), back: Vec::new() };
    if nq == 0 || nt == 0 {
        return Ok(out);
    }
    let k = k.min(nt);
    let hamming = norm == NORM_HAMMING;
    let (dtype, none) =
        if hamming { (opencv::core::CV_32S, i32::MAX as f32) } else { (opencv::core::CV_32F, f32::MAX) };
    let band = (band_values / nt).clamp(1, nq);
    let mut best = vec![none; nt];
    let mut back = vec![u32::MAX; nt];
    let (mut dist, mut as_f32) = (Mat::default(), Mat::default());
    let mut start = 0;
    while start < nq {
        let end = (start + band).min(nq);
        let rows = query.row_bounds(start as i32, end as i32)?;
        let mut no_index = opencv::core::no_array();
        if mask.empty() {
            opencv::core::batch_distance(&rows, train, &mut dist, dtype, &mut no_index, norm, 0, mask, 0, false)?;
        } else {
            let admitted = mask.row_bounds(start as i32, end as i32)?;
            opencv::core::batch_distance(&rows, train, &mut dist, dtype, &mut no_index, norm, 0, &admitted, 0, false)?;
        }
        // Hamming distances are small integers: exact in f32, as BFMatcher reports them.
        let values = if hamming {
            dist.convert_to(&mut as_f32, opencv::core::CV_32F, 1.0, 0.0)?;
            &as_f32
        } else {
            &dist
        };
        let values = values.data_typed::<f32>()?;
        for (r, row) in values.chunks_exact(nt).enumerate() {
            let q = start + r;
            // batchDistance's insertion: a distance enters only below the k-th.
            let mut near: Vec<(usize, f32)> = Vec::with_capacity(k + 1);
            let mut kth = none;
            for (t, &d) in row.iter().enumerate() {
                if d < kth {
                    kth = keep_nearest(&mut near, (t, d), k).unwrap_or(kth);
                }
            }
            out.forward.push(near);
            // Rows come in order, so a strict "below" keeps the first of equal distances.
            for ((b, back), &d) in best.iter_mut().zip(back.iter_mut()).zip(row) {
                let closer = d < *b;
                *b = if closer { d } else { *b };
                *back = if closer { q as u32 } else { *back };
            }
        }
        start = end;
    }
    out.back = back.into_iter().map(|q| (q != u32::MAX).then_some(q as usize)).collect();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::describe::features::DESCRIPTOR_BYTES;
    use crate::matching::{embedding_mat, train_and_distance};
    use opencv::core::{DMatch, Vector};
    use opencv::features2d::BFMatcher;

    /// OpenCV's two calls that [`nearest_both_ways`] stands for.
    fn bf_both_ways(query: &Mat, train: &Mat, norm: i32, k: usize, mask: &Mat) -> BothWays {
        let matcher = BFMatcher::new(norm, false).unwrap();
        let mut knn = Vector::<Vector<DMatch>>::new();
        matcher.knn_train_match(query, train, &mut knn, k as i32, mask, false).unwrap();
        let mut back_mask = Mat::default();
        if !mask.empty() {
            opencv::core::transpose(mask, &mut back_mask).unwrap();
        }
        let mut back = Vector::<DMatch>::new();
        matcher.train_match(train, query, &mut back, &back_mask).unwrap();
        let mut nearest = vec![None; train.rows() as usize];
        for m in back.iter() {
            nearest[m.query_idx as usize] = Some(m.train_idx as usize);
        }
        let forward = knn.iter().map(|hits| hits.iter().map(train_and_distance).collect()).collect();
        BothWays { forward, back: nearest }
    }

    #[test]
    fn both_ways_from_one_matrix_is_opencvs_answer_to_the_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::StdRng::seed_from_u64(7);
        // Embeddings rounded to a coarse grid, and repeated rows, so equal distances (ties) are common.
        let (nq, nt, dim) = (150, 97, 8);
        let mut grid = |n: usize| -> Vec<f32> { (0..n * dim).map(|_| rng.random_range(0..4) as f32 * 0.25).collect() };
        let mut q = grid(nq);
        let t = grid(nt);
        q[dim..2 * dim].copy_from_slice(&t[..dim]);
        let (qm, tm) = (embedding_mat(&q, dim).unwrap(), embedding_mat(&t, dim).unwrap());
        let bytes: Vec<u8> = (0..(nq + nt) * DESCRIPTOR_BYTES).map(|_| rng.random::<u8>() & 0x11).collect();
        let (qb, tb) = (
            crate::describe::features::bits_mat(&bytes[..nq * DESCRIPTOR_BYTES]).unwrap(),
            crate::describe::features::bits_mat(&bytes[nq * DESCRIPTOR_BYTES..]).unwrap(),
        );
        // A mask admitting a third of the pairs, with query row 3 and train row 5 admitting none.
        let mut admitted: Vec<u8> = (0..nq * nt).map(|_| u8::from(rng.random_range(0..3) == 0)).collect();
        admitted[3 * nt..4 * nt].fill(0);
        (0..nq).for_each(|i| admitted[i * nt + 5] = 0);
        let mask = Mat::new_rows_cols_with_data(nq as i32, nt as i32, &admitted).unwrap().try_clone().unwrap();
        // Near-ties below a product's resolution (it errs by about 1e-7 on the squared distance of unit
        // vectors): around 20 centres, four query rows 1e-4 away and eight train rows at 0.1 apart by 3e-7
        // (so a train row's nearest query row does not bring every near pair into the measured set); train
        // rows repeated exactly.
        let (nu, du) = (120, 48);
        let unit = |rng: &mut rand::rngs::StdRng, n: usize| -> Vec<f32> {
            let mut v: Vec<f32> = (0..n * du).map(|_| rng.random_range(-1.0f32..1.0)).collect();
            for r in v.chunks_exact_mut(du) {
                let n = r.iter().map(|x| x * x).sum::<f32>().sqrt();
                r.iter_mut().for_each(|x| *x /= n);
            }
            v
        };
        let mut qu = unit(&mut rng, nu);
        let mut tu = unit(&mut rng, nu + 40);
        let (centres, directions) = (unit(&mut rng, 20), unit(&mut rng, 240));
        for (j, row) in qu.chunks_exact_mut(du).take(80).chain(tu.chunks_exact_mut(du).take(160)).enumerate() {
            let (centre, r) =
                if j < 80 { (j / 4, 1e-4) } else { ((j - 80) / 8, 0.1 * (1.0 + ((j - 80) % 8) as f32 * 3e-6)) };
            for (c, x) in row.iter_mut().enumerate() {
                *x = centres[centre * du + c] + r * directions[j * du + c];
            }
        }
        let repeated = tu[..du].to_vec();
        tu[(nu + 30) * du..(nu + 31) * du].copy_from_slice(&repeated);
        let (qum, tum) = (embedding_mat(&qu, du).unwrap(), embedding_mat(&tu, du).unwrap());
        let admitted_u: Vec<u8> = (0..nu * (nu + 40)).map(|_| u8::from(rng.random_range(0..2) == 0)).collect();
        let mask_u =
            Mat::new_rows_cols_with_data(nu as i32, (nu + 40) as i32, &admitted_u).unwrap().try_clone().unwrap();
        let cases = [(&qm, &tm, NORM_L2, &mask), (&qb, &tb, NORM_HAMMING, &mask), (&qum, &tum, NORM_L2, &mask_u)];
        for (qm, tm, norm, some_mask) in cases {
            for mask in [&Mat::default(), some_mask] {
                for k in [1, 2, 7, 200] {
                    let want = bf_both_ways(qm, tm, norm, k, mask);
                    let nt = tm.rows() as usize;
                    // One band, bands of several rows, and a band per row; OpenCV's distances alone, and the
                    // product's estimates with OpenCV's distances where they decide.
                    for band in [usize::MAX, 5 * nt, 1] {
                        let case = format!("norm {norm}, {} rows, masked {}, k {k}, band {band}", nt, !mask.empty());
                        let got = nearest_both_ways_in_bands(qm, tm, norm, k, mask, band).unwrap();
                        assert_eq!(got.forward, want.forward, "{case}");
                        assert_eq!(got.back, want.back, "{case}");
                        // In one part, and in several on rayon's threads (rows split unevenly).
                        for parts in [1, 2, 3, 7] {
                            if norm == NORM_L2 {
                                let got = l2_by_product(qm, tm, k, mask, band, parts).unwrap().expect("finite rows");
                                assert_eq!(got.forward, want.forward, "by product, {parts} parts, {case}");
                                assert_eq!(got.back, want.back, "by product, {parts} parts, {case}");
                            }
                        }
                    }
                }
            }
        }
        let huge = embedding_mat(&[1e20; 8], 8).unwrap();
        assert!(l2_by_product(&huge, &huge, 1, &Mat::default(), usize::MAX, 2).unwrap().is_none(), "left to OpenCV");
        let masked = nearest_both_ways(&qm, &tm, NORM_L2, 2, &mask).unwrap();
        assert!(masked.forward[3].is_empty() && masked.back[5].is_none(), "rows the mask leaves out have no neighbour");
        let empty = nearest_both_ways(&Mat::default(), &tm, NORM_L2, 7, &Mat::default()).unwrap();
        assert!(empty.forward.is_empty() && empty.back.is_empty());
    }
}
