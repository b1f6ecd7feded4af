//! The pose of a short track against a map: several frames with known poses relative to each other (a phone's
//! tracker, a rig's extrinsics), each with its own 2D-3D matches, located together.
//!
//! The unknown is the track-to-map transform `S` (`X_map = s R X_track + t`): rigid (`s = 1`, 6 degrees of
//! freedom) or with scale (7) when the map's units are not the track's. Frame f, whose camera-to-track pose is
//! `Q_f`, sees a map point `X` at `K_f Q_f⁻¹ S⁻¹ X`.
//!
//! 1. **Hypotheses**, each mapped into the track's frame: every frame's own pose (its single-frame PnP, when it
//!    has one) and poses from minimal sets of one frame's matches (OpenCV's P3P on three correspondences drawn
//!    from its best ones, a fourth to choose among P3P's solutions). With scale, a hypothesis takes its rotation
//!    from one frame's pose and its scale from the distance between two frames' camera centres, in the map and
//!    in the track.
//! 2. **Scoring:** every hypothesis on every frame's matches (reprojection error within the threshold); the one
//!    with the most inliers in total wins.
//! 3. **Refinement:** Levenberg-Marquardt (the `levenberg-marquardt` crate) of `S` over every frame's inliers,
//!    selected again and refined again. Its covariance is the images' `σ² (JᵀJ)⁻¹` plus what the tracker's
//!    error ([`TrackerError`]) does to the answer: every frame but 0 carries a 6-dof error of its pose in the
//!    track, propagated through the least squares to `S` (first order). With exact relative poses (a rig) only
//!    the images' part is left.
//! 4. **Frames that disagree** (a blurred frame, a wrong relative pose): a frame whose own pose had at least
//!    `min_inliers` inliers but keeps fewer than half of them under `S` is dropped and `S` refined without it;
//!    the answer says which.
//! 5. **Never worse than one frame:** when the joint estimate's inliers are fewer than the best single frame's,
//!    the answer is that frame's pose carried into the track (`S = P_f Q_f⁻¹`, rigid).

use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::{
    DMatrix, DVector, Dyn, Isometry3, Matrix3, Matrix6, Owned, Point3, Rotation3, Similarity3, UnitQuaternion, Vector3,
};
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;
use rand::{Rng, SeedableRng};

use crate::camera::Camera;
use crate::error::PoseError;
use crate::pose::absolute::AbsolutePose;
use crate::pose::ransac::RansacSettings;

/// Whether the track's units are the map's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrackScale {
    /// Metric track against a metric map: 6 degrees of freedom.
    Rigid,
    /// The scale between track and map is estimated too: 7 degrees of freedom.
    Free,
}

/// One frame of a track, with what its own relocalisation found.
#[derive(Debug, Clone)]
pub struct TrackFrame {
    /// Camera-to-track pose (OpenCV camera axes).
    pub camera_to_track: Isometry3<f64>,
    /// Pinhole camera the 2D points are in (undistorted).
    pub camera: Camera,
    /// The frame's 2D-3D matches, best first: map points and pixels.
    pub points3d: Vec<[f64; 3]>,
    pub points2d: Vec<(f32, f32)>,
    /// Its single-frame pose, when it has one (a hypothesis, and the answer if no joint estimate beats it).
    pub own: Option<AbsolutePose>,
}

/// How far a track's relative poses may be off, for the answer's covariance (root mean square sizes, in no
/// preferred direction): frame `f`'s position relative to frame 0 by `translation_share` of their distance, its
/// orientation by `degrees_per_frame` per frame between it and frame 0 in the track's order. The default is a
/// phone's visual-inertial tracker over a few metres (about a percent); zeros are a rig's calibrated extrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerError {
    pub translation_share: f64,
    pub degrees_per_frame: f64,
}

impl Default for TrackerError {
    fn default() -> Self {
        Self { translation_share: 0.01, degrees_per_frame: 0.5 }
    }
}

impl TrackerError {
    /// Why this error cannot be used, if it cannot: each part finite, the share in [0, 1], the degrees in
    /// [0, 45].
    pub fn problem(&self) -> Option<String> {
        let ok = |v: f64, max: f64| v.is_finite() && (0.0..=max).contains(&v);
        if !ok(self.translation_share, 1.0) {
            return Some(format!("translation_share must be in [0, 1], got {}", self.translation_share));
        }
        if !ok(self.degrees_per_frame, 45.0) {
            return Some(format!("degrees_per_frame must be in [0, 45], got {}", self.degrees_per_frame));
        }
        None
    }

    /// The covariance of frame `f`'s pose error `(rotation vector, translation)` in its own camera axes; `None`
    /// when the frame's relative pose is exact (frame 0, or a rig).
    fn covariance(&self, frames: &[TrackFrame], f: usize) -> Option<Matrix6<f64>> {
        let distance =
            (frames[f].camera_to_track.translation.vector - frames[0].camera_to_track.translation.vector).norm();
        // Per axis: a root mean square size spread evenly over three axes.
        let sigma_t = self.translation_share * distance / 3f64.sqrt();
        let sigma_r = self.degrees_per_frame.to_radians() * f as f64 / 3f64.sqrt();
        if f == 0 || (sigma_t <= 0.0 && sigma_r <= 0.0) {
            return None;
        }
        let (vt, vr) = (sigma_t.powi(2), sigma_r.powi(2));
        Some(Matrix6::from_diagonal(&nalgebra::Vector6::new(vr, vr, vr, vt, vt, vt)))
    }
}

/// What became of one frame in the joint estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameOutcome {
    /// Indices into the frame's matches that are inliers of the answer.
    pub inliers: Vec<usize>,
    /// Dropped from the estimate: its own pose disagreed with the others'.
    pub dropped: bool,
}

/// A track located in the map.
#[derive(Debug, Clone)]
pub struct TrackPose {
    /// Track to map: `X_map = s R X_track + t` (`s = 1` when rigid).
    pub map_from_track: Similarity3<f64>,
    pub frames: Vec<FrameOutcome>,
    /// Mean reprojection error of the inliers, pixels.
    pub reprojection_error: f64,
    /// Covariance of frame 0's world-to-camera `(rvec, tvec)` as OpenCV writes them (the single-frame answer's
    /// [`AbsolutePose::covariance_w2c`]), the scale marginalised out; `None` when singular.
    pub covariance_w2c: Option<Matrix6<f64>>,
    /// The answer is this frame's own pose: no joint estimate had more inliers.
    pub single_frame: Option<usize>,
}

impl TrackPose {
    /// Frame `f`'s camera-to-map pose (the scale applies to positions only).
    pub fn camera_to_map(&self, camera_to_track: &Isometry3<f64>) -> Isometry3<f64> {
        camera_to_map(&self.map_from_track, camera_to_track)
    }

    pub fn inlier_count(&self) -> usize {
        self.frames.iter().map(|f| f.inliers.len()).sum()
    }
}

fn camera_to_map(s: &Similarity3<f64>, q: &Isometry3<f64>) -> Isometry3<f64> {
    let rotation = s.isometry.rotation * q.rotation;
    let centre = s.transform_point(&Point3::from(q.translation.vector));
    Isometry3::from_parts(centre.coords.into(), rotation)
}

/// Minimal-set hypotheses drawn per frame with matches.
const MINIMAL_SETS: usize = 200;
/// The best correspondences of a frame that minimal sets are drawn from (its matches come best first).
const SAMPLE_HEAD: usize = 100;

/// Locates a track (module docs); `None` when no hypothesis reaches `min_inliers` over all frames. `seed` makes
/// the minimal sets repeatable; `tracker` is how far the frames' poses in the track may be off (covariance only).
pub fn track_pose(
    frames: &[TrackFrame],
    scale: TrackScale,
    params: &RansacSettings,
    min_inliers: usize,
    seed: u64,
    tracker: &TrackerError,
) -> Result<Option<TrackPose>, PoseError> {
    let mut hypotheses = own_hypotheses(frames, scale);
    hypotheses.extend(minimal_hypotheses(frames, scale, seed)?);
    let keep: Vec<bool> = vec![true; frames.len()];
    // The hypothesis with the most inliers over every frame (the last of equals); one that can no longer reach
    // the best so far stops counting.
    let mut best: Option<(usize, Similarity3<f64>)> = None;
    for h in hypotheses {
        let floor = best.as_ref().map_or(0, |b| b.0);
        if let Some(n) = inlier_count_reaching(frames, &h, params.threshold_px, floor) {
            best = Some((n, h));
        }
    }
    let Some((_, best)) = best else {
        return Ok(None);
    };
    let mut estimate = refine(frames, best, scale, params.threshold_px, &keep, tracker);
    // Frames whose own pose the estimate throws away are dropped, once, and the rest refined again.
    let mut dropped = vec![false; frames.len()];
    let per_frame = inliers(frames, &estimate.0, params.threshold_px, &keep).0;
    for (f, frame) in frames.iter().enumerate() {
        if let Some(own) = &frame.own {
            dropped[f] = own.inliers.len() >= min_inliers && 2 * per_frame[f].len() < own.inliers.len();
        }
    }
    if dropped.iter().any(|&d| d) && dropped.iter().filter(|&&d| !d).count() > 0 {
        let keep: Vec<bool> = dropped.iter().map(|&d| !d).collect();
        estimate = refine(frames, estimate.0, scale, params.threshold_px, &keep, tracker);
    } else {
        dropped.fill(false);
    }
    let keep: Vec<bool> = dropped.iter().map(|&d| !d).collect();
    let (per_frame, total) = inliers(frames, &estimate.0, params.threshold_px, &keep);
    // The answer is never worse than the best frame alone.
    let best_single = frames
        .iter()
        .enumerate()
        .filter_map(|(f, fr)| fr.own.as_ref().map(|p| (f, p.inliers.len())))
        .max_by_key(|&(_, n)| n);
    if let Some((f, _)) = best_single.filter(|&(_, n)| n > total) {
        let own = frames[f].own.as_ref().expect("a single-frame pose");
        let mut outcomes: Vec<FrameOutcome> = vec![FrameOutcome { inliers: Vec::new(), dropped: false }; frames.len()];
        outcomes[f].inliers = own.inliers.clone();
        let map_from_track = from_frame(&own.camera_to_world, &frames[f]);
        // Frame 0 is where frame f's pose and the track put it: f's images and f's relative pose both count.
        let covariance_w2c = if f == 0 {
            own.covariance_w2c
        } else {
            let terms = own.inliers.iter().map(|&i| (f, i)).collect();
            let alone =
                Residuals { frames, base: map_from_track, scale: TrackScale::Rigid, terms, params: DVector::zeros(6) };
            parameter_covariance(&alone, tracker)
                .map(|c| frame_covariance(&map_from_track, TrackScale::Rigid, &frames[0], &c))
        };
        return Ok(Some(TrackPose {
            map_from_track,
            frames: outcomes,
            reprojection_error: own.reprojection_error,
            covariance_w2c,
            single_frame: Some(f),
        }));
    }
    if total < min_inliers {
        return Ok(None);
    }
    let error = mean_error(frames, &estimate.0, &per_frame);
    Ok(Some(TrackPose {
        map_from_track: estimate.0,
        frames: per_frame
            .into_iter()
            .zip(&dropped)
            .map(|(inliers, &dropped)| FrameOutcome { inliers: if dropped { Vec::new() } else { inliers }, dropped })
            .collect(),
        reprojection_error: error,
        covariance_w2c: estimate.1.map(|c| frame_covariance(&estimate.0, scale, &frames[0], &c)),
        single_frame: None,
    }))
}

/// How one frame sees map points under a transform `S`: camera coordinates `A x + b` (`Q⁻¹ S⁻¹` as one affine
/// map, made once per transform and frame), then the pinhole. Scoring and refinement project every match of
/// every frame many times; this is their inner loop.
struct Projector {
    a: Matrix3<f64>,
    b: Vector3<f64>,
    camera: Camera,
}

impl Projector {
    fn new(s: &Similarity3<f64>, camera_to_track: &Isometry3<f64>, camera: &Camera) -> Self {
        // Q⁻¹ S⁻¹ x = Rqᵀ (Rsᵀ (x - ts) / s - tq).
        let rs = s.isometry.rotation.to_rotation_matrix().into_inner();
        let rq = camera_to_track.rotation.to_rotation_matrix().into_inner();
        let a = rq.transpose() * rs.transpose() / s.scaling();
        let b = -(a * s.isometry.translation.vector) - rq.transpose() * camera_to_track.translation.vector;
        Self { a, b, camera: *camera }
    }

    fn of(s: &Similarity3<f64>, frame: &TrackFrame) -> Self {
        Self::new(s, &frame.camera_to_track, &frame.camera)
    }

    /// Where the frame sees map point `x`, in pixels; `None` behind the camera.
    fn project(&self, x: &[f64; 3]) -> Option<(f64, f64)> {
        let c = self.a * Vector3::new(x[0], x[1], x[2]) + self.b;
        if c.z <= 1e-9 {
            return None;
        }
        let cam = &self.camera;
        Some((cam.fx * c.x / c.z + cam.cx, cam.fy * c.y / c.z + cam.cy))
    }

    /// Whether match `i` of `frame` is within `threshold` pixels.
    fn fits(&self, frame: &TrackFrame, i: usize, threshold: f64) -> bool {
        self.project(&frame.points3d[i]).is_some_and(|(u, v)| {
            let (du, dv) = (u - frame.points2d[i].0 as f64, v - frame.points2d[i].1 as f64);
            du * du + dv * dv <= threshold * threshold
        })
    }
}

/// Each kept frame's inliers of `s` within `threshold` pixels, and their total.
fn inliers(frames: &[TrackFrame], s: &Similarity3<f64>, threshold: f64, keep: &[bool]) -> (Vec<Vec<usize>>, usize) {
    let per: Vec<Vec<usize>> = frames
        .iter()
        .zip(keep)
        .map(|(f, &k)| {
            if !k {
                return Vec::new();
            }
            let p = Projector::of(s, f);
            (0..f.points3d.len()).filter(|&i| p.fits(f, i, threshold)).collect()
        })
        .collect();
    let total = per.iter().map(Vec::len).sum();
    (per, total)
}

/// [`inliers`]' total over every frame, without the lists (the score of a hypothesis), when it reaches `floor`;
/// `None` as soon as the matches left cannot bring it there.
fn inlier_count_reaching(frames: &[TrackFrame], s: &Similarity3<f64>, threshold: f64, floor: usize) -> Option<usize> {
    let mut left: usize = frames.iter().map(|f| f.points3d.len()).sum();
    let mut count = 0;
    for f in frames {
        let p = Projector::of(s, f);
        for i in 0..f.points3d.len() {
            if count + left < floor {
                return None;
            }
            left -= 1;
            count += usize::from(p.fits(f, i, threshold));
        }
    }
    (count >= floor).then_some(count)
}

fn mean_error(frames: &[TrackFrame], s: &Similarity3<f64>, per_frame: &[Vec<usize>]) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for (f, ids) in frames.iter().zip(per_frame) {
        let p = Projector::of(s, f);
        for &i in ids {
            if let Some((u, v)) = p.project(&f.points3d[i]) {
                sum += (u - f.points2d[i].0 as f64).hypot(v - f.points2d[i].1 as f64);
                n += 1;
            }
        }
    }
    sum / n.max(1) as f64
}

/// The transform that puts frame `f` at camera-to-map pose `p` (rigid).
fn from_frame(p: &Isometry3<f64>, frame: &TrackFrame) -> Similarity3<f64> {
    Similarity3::from_isometry(p * frame.camera_to_track.inverse(), 1.0)
}

/// The transform with frame `f` at `pf` and frame `g`'s camera centre at `pg`'s, scale from the two centres'
/// distances in map and track; `None` when the track's baseline is too short to carry a scale.
fn from_two_frames(
    pf: &Isometry3<f64>,
    f: &TrackFrame,
    pg: &Isometry3<f64>,
    g: &TrackFrame,
) -> Option<Similarity3<f64>> {
    let (mf, mg) = (pf.translation.vector, pg.translation.vector);
    let (tf, tg) = (f.camera_to_track.translation.vector, g.camera_to_track.translation.vector);
    let track_baseline = (tf - tg).norm();
    if track_baseline < 1e-9 {
        return None;
    }
    let scale = (mf - mg).norm() / track_baseline;
    if !(scale.is_finite() && scale > 1e-9) {
        return None;
    }
    let rotation = pf.rotation * f.camera_to_track.rotation.inverse();
    let translation = mf - scale * (rotation * tf);
    Some(Similarity3::from_parts(translation.into(), rotation, scale))
}

/// Every frame's own pose as a hypothesis (with scale: every pair of frames with poses).
fn own_hypotheses(frames: &[TrackFrame], scale: TrackScale) -> Vec<Similarity3<f64>> {
    let posed: Vec<(usize, &AbsolutePose)> =
        frames.iter().enumerate().filter_map(|(f, fr)| fr.own.as_ref().map(|p| (f, p))).collect();
    match scale {
        TrackScale::Rigid => posed.iter().map(|&(f, p)| from_frame(&p.camera_to_world, &frames[f])).collect(),
        TrackScale::Free => posed
            .iter()
            .flat_map(|&(f, pf)| {
                posed.iter().filter(move |&&(g, _)| g != f).filter_map(move |&(g, pg)| {
                    from_two_frames(&pf.camera_to_world, &frames[f], &pg.camera_to_world, &frames[g])
                })
            })
            .collect(),
    }
}

/// Camera-to-map poses of `frame` from P3P on three correspondences, checked on a fourth.
fn p3p(frame: &TrackFrame, idx: [usize; 4]) -> Result<Option<Isometry3<f64>>, PoseError> {
    let obj: Vector<Point3f> = idx[..3]
        .iter()
        .map(|&i| frame.points3d[i])
        .map(|p| Point3f::new(p[0] as f32, p[1] as f32, p[2] as f32))
        .collect();
    let img: Vector<Point2f> = idx[..3].iter().map(|&i| frame.points2d[i]).map(|(x, y)| Point2f::new(x, y)).collect();
    let k = Mat::from_slice_2d(&frame.camera.k())?;
    let (mut rvecs, mut tvecs) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let n = opencv::calib3d::solve_p3p(
        &obj,
        &img,
        &k,
        &Mat::default(),
        &mut rvecs,
        &mut tvecs,
        opencv::calib3d::SOLVEPNP_P3P,
    )?;
    let mut best: Option<(f64, Isometry3<f64>)> = None;
    for s in 0..n.max(0) as usize {
        let (r, t) = (rvecs.get(s)?, tvecs.get(s)?);
        let rv = Vector3::new(*r.at::<f64>(0)?, *r.at::<f64>(1)?, *r.at::<f64>(2)?);
        let tv = Vector3::new(*t.at::<f64>(0)?, *t.at::<f64>(1)?, *t.at::<f64>(2)?);
        if !rv.iter().chain(tv.iter()).all(|v| v.is_finite()) {
            continue;
        }
        let w2c = Isometry3::from_parts(tv.into(), UnitQuaternion::from_scaled_axis(rv));
        let x = frame.points3d[idx[3]];
        let c = w2c * Point3::new(x[0], x[1], x[2]);
        if c.z <= 1e-9 {
            continue;
        }
        let cam = &frame.camera;
        let (u, v) = (cam.fx * c.x / c.z + cam.cx, cam.fy * c.y / c.z + cam.cy);
        let e = (u - frame.points2d[idx[3]].0 as f64).hypot(v - frame.points2d[idx[3]].1 as f64);
        if best.as_ref().is_none_or(|(b, _)| e < *b) {
            best = Some((e, w2c.inverse()));
        }
    }
    Ok(best.map(|(_, p)| p))
}

/// Hypotheses from minimal sets of each frame's best matches ([`MINIMAL_SETS`] per frame): P3P mapped into the
/// track; with scale, paired with another frame's own pose or minimal-set pose for the scale.
fn minimal_hypotheses(frames: &[TrackFrame], scale: TrackScale, seed: u64) -> Result<Vec<Similarity3<f64>>, PoseError> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let draw = |frame: &TrackFrame, rng: &mut rand::rngs::StdRng| -> Result<Option<Isometry3<f64>>, PoseError> {
        let head = frame.points3d.len().min(SAMPLE_HEAD);
        if head < 4 {
            return Ok(None);
        }
        let mut idx = [0usize; 4];
        for k in 0..4 {
            loop {
                let i = rng.random_range(0..head);
                if !idx[..k].contains(&i) {
                    idx[k] = i;
                    break;
                }
            }
        }
        p3p(frame, idx)
    };
    let mut out = Vec::new();
    for (f, frame) in frames.iter().enumerate() {
        if frame.points3d.len() < 4 {
            continue;
        }
        for _ in 0..MINIMAL_SETS {
            let Some(pf) = draw(frame, &mut rng)? else { continue };
            match scale {
                TrackScale::Rigid => out.push(from_frame(&pf, frame)),
                TrackScale::Free => {
                    let g = (f + 1 + rng.random_range(0..frames.len().max(2) - 1)) % frames.len();
                    if g == f {
                        continue;
                    }
                    let pg = match &frames[g].own {
                        Some(p) if rng.random_bool(0.5) => Some(p.camera_to_world),
                        _ => draw(&frames[g], &mut rng)?,
                    };
                    if let Some(s) = pg.and_then(|pg| from_two_frames(&pf, frame, &pg, &frames[g])) {
                        out.push(s);
                    }
                }
            }
        }
    }
    Ok(out)
}

/// The reprojection residuals of every kept frame's inliers as a function of a perturbation of `S`: rotation
/// vector (applied on the left), translation, and with scale the log of a scale factor.
struct Residuals<'a> {
    frames: &'a [TrackFrame],
    base: Similarity3<f64>,
    scale: TrackScale,
    /// (frame, match) of every residual pair.
    terms: Vec<(usize, usize)>,
    params: DVector<f64>,
}

impl Residuals<'_> {
    fn transform(&self, p: &DVector<f64>) -> Similarity3<f64> {
        let r = Rotation3::new(Vector3::new(p[0], p[1], p[2]));
        let rotation = UnitQuaternion::from_rotation_matrix(&r) * self.base.isometry.rotation;
        let translation = self.base.isometry.translation.vector + Vector3::new(p[3], p[4], p[5]);
        let s = match self.scale {
            TrackScale::Rigid => self.base.scaling(),
            TrackScale::Free => self.base.scaling() * p[6].exp(),
        };
        Similarity3::from_parts(translation.into(), rotation, s)
    }

    fn at(&self, p: &DVector<f64>) -> Option<DVector<f64>> {
        let s = self.transform(p);
        let projectors: Vec<Projector> = self.frames.iter().map(|f| Projector::of(&s, f)).collect();
        let mut r = DVector::zeros(2 * self.terms.len());
        for (k, &(f, i)) in self.terms.iter().enumerate() {
            let frame = &self.frames[f];
            let (u, v) = projectors[f].project(&frame.points3d[i])?;
            r[2 * k] = u - frame.points2d[i].0 as f64;
            r[2 * k + 1] = v - frame.points2d[i].1 as f64;
        }
        Some(r)
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for Residuals<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.params.copy_from(x);
    }

    fn params(&self) -> DVector<f64> {
        self.params.clone()
    }

    fn residuals(&self) -> Option<DVector<f64>> {
        self.at(&self.params)
    }

    /// Central differences (the residuals are cheap: one projection each).
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        let n = self.params.len();
        let mut j = DMatrix::zeros(2 * self.terms.len(), n);
        for c in 0..n {
            let h = 1e-6 * self.params[c].abs().max(1.0);
            let (mut plus, mut minus) = (self.params.clone(), self.params.clone());
            plus[c] += h;
            minus[c] -= h;
            let d = (self.at(&plus)? - self.at(&minus)?) / (2.0 * h);
            j.set_column(c, &d);
        }
        Some(j)
    }
}

/// `s` refined on every kept frame's inliers: select, refine, select, refine; with the covariance of the
/// perturbation parameters at the answer.
fn refine(
    frames: &[TrackFrame],
    s: Similarity3<f64>,
    scale: TrackScale,
    threshold: f64,
    keep: &[bool],
    tracker: &TrackerError,
) -> (Similarity3<f64>, Option<DMatrix<f64>>) {
    let n = if scale == TrackScale::Free { 7 } else { 6 };
    let mut current = s;
    let mut covariance = None;
    for _ in 0..2 {
        let (per_frame, total) = inliers(frames, &current, threshold, keep);
        if total < n {
            break;
        }
        let terms = per_frame.iter().enumerate().flat_map(|(f, ids)| ids.iter().map(move |&i| (f, i))).collect();
        let problem = Residuals { frames, base: current, scale, terms, params: DVector::zeros(n) };
        let (solved, report) = LevenbergMarquardt::new().minimize(problem);
        if !report.termination.was_successful() && report.objective_function.is_nan() {
            break;
        }
        current = solved.transform(&solved.params);
        covariance = parameter_covariance(&solved, tracker);
    }
    (current, covariance)
}

/// The covariance of the problem's parameters (module docs, step 3): the images' `H⁻¹`, `H = JᵀJ / σ²` with
/// `σ²` the residuals' variance, and what each frame's relative pose error does to the least-squares answer,
/// `H⁻¹ Bᵀ Q B H⁻¹` with `B` the cross term of the frame's residuals by `S` and by its own pose error, and `Q`
/// that error's covariance.
fn parameter_covariance(p: &Residuals, tracker: &TrackerError) -> Option<DMatrix<f64>> {
    let r = p.residuals()?;
    let j = p.jacobian()?;
    let dof = r.len().checked_sub(p.params.len()).filter(|&d| d > 0)?;
    let sigma2 = r.norm_squared() / dof as f64;
    let inverse = (j.transpose() * &j / sigma2).try_inverse()?;
    let mut spread = DMatrix::zeros(p.params.len(), p.params.len());
    for f in 0..p.frames.len() {
        let Some(q) = tracker.covariance(p.frames, f) else { continue };
        let rows: Vec<usize> = p.terms.iter().enumerate().filter(|(_, t)| t.0 == f).map(|(k, _)| k).collect();
        if rows.is_empty() {
            continue;
        }
        let jp = DMatrix::from_fn(2 * rows.len(), p.params.len(), |r, c| j[(2 * rows[r / 2] + r % 2, c)]);
        let b = jp.transpose() * frame_error_jacobian(p, f, &rows)? / sigma2;
        spread += &b * DMatrix::from_fn(6, 6, |r, c| q[(r, c)]) * b.transpose();
    }
    Some(&inverse + &inverse * spread * &inverse)
}

/// The derivatives of frame `f`'s residuals (`rows` of the problem's terms) by an error of its pose in the
/// track, `(rotation vector, translation)` in its camera axes (central differences).
fn frame_error_jacobian(p: &Residuals, f: usize, rows: &[usize]) -> Option<DMatrix<f64>> {
    let frame = &p.frames[f];
    let s = p.transform(&p.params);
    let residuals = |e: &nalgebra::Vector6<f64>| -> Option<DVector<f64>> {
        let error = Isometry3::new(Vector3::new(e[3], e[4], e[5]), Vector3::new(e[0], e[1], e[2]));
        let projector = Projector::new(&s, &(frame.camera_to_track * error), &frame.camera);
        let mut out = DVector::zeros(2 * rows.len());
        for (k, &row) in rows.iter().enumerate() {
            let i = p.terms[row].1;
            let (u, v) = projector.project(&frame.points3d[i])?;
            out[2 * k] = u - frame.points2d[i].0 as f64;
            out[2 * k + 1] = v - frame.points2d[i].1 as f64;
        }
        Some(out)
    };
    let mut j = DMatrix::zeros(2 * rows.len(), 6);
    for c in 0..6 {
        let h = 1e-6;
        let (mut plus, mut minus) = (nalgebra::Vector6::zeros(), nalgebra::Vector6::zeros());
        plus[c] = h;
        minus[c] = -h;
        j.set_column(c, &((residuals(&plus)? - residuals(&minus)?) / (2.0 * h)));
    }
    Some(j)
}

/// The covariance of frame 0's world-to-camera `(rvec, tvec)` under `s`, from the covariance of `s`'s
/// perturbation parameters (first-order propagation, central differences; a scale parameter marginalised).
fn frame_covariance(s: &Similarity3<f64>, scale: TrackScale, frame: &TrackFrame, cov: &DMatrix<f64>) -> Matrix6<f64> {
    let n = cov.nrows();
    let base = Residuals {
        frames: std::slice::from_ref(frame),
        base: *s,
        scale,
        terms: Vec::new(),
        params: DVector::zeros(n),
    };
    let w2c = |p: &DVector<f64>| {
        let pose = camera_to_map(&base.transform(p), &frame.camera_to_track).inverse();
        let rv = pose.rotation.scaled_axis();
        let tv = pose.translation.vector;
        DVector::from_vec(vec![rv.x, rv.y, rv.z, tv.x, tv.y, tv.z])
    };
    let mut g = DMatrix::zeros(6, n);
    for c in 0..n {
        let h = 1e-6;
        let (mut plus, mut minus) = (DVector::zeros(n), DVector::zeros(n));
        plus[c] = h;
        minus[c] = -h;
        g.set_column(c, &((w2c(&plus) - w2c(&minus)) / (2.0 * h)));
    }
    let out = &g * cov * g.transpose();
    Matrix6::from_fn(|r, c| out[(r, c)])
}
