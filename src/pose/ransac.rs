//! The RANSAC settings both estimators share, the essential-matrix search, and the adaptive stopping rule.

use serde::{Deserialize, Serialize};

/// RANSAC settings shared by both estimators.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RansacSettings {
    /// Inlier threshold in pixels.
    pub threshold_px: f64,
    pub confidence: f64,
    pub max_iters: i32,
    /// The essential-matrix estimator (relative pose only; PnP always refines its inliers).
    pub essential: EssentialMethod,
    /// Relative pose only: a correspondence within this many pixels of an earlier one in both images (one
    /// corner matched again through its copies on other pyramid levels) is left out of the estimation and
    /// takes that one's inlier flag. 0 = off.
    pub duplicate_px: f64,
    /// The absolute-pose (PnP) estimator (relocalisation only).
    pub pnp: PnpMethod,
}

/// The relative-pose defaults: 1 px, USAC_ACCURATE, and a search of up to 10,000 iterations at confidence
/// 0.9999. OpenCV's own defaults (1,000 at 0.999) stop short on wide baselines: at 30 % inliers a 5-point
/// search needs about 2,800 iterations for 0.999, and on the selection split (5 standard scenes + 4
/// wide-orbit sequences) the larger budget raised mean AUC@10 from 0.678 to 0.694 for SConE and from 0.684 to
/// 0.707 for FREAK. Relocalisation sets its own PnP parameters (`map::localize`).
impl Default for RansacSettings {
    fn default() -> Self {
        Self {
            threshold_px: 1.0,
            confidence: 0.9999,
            max_iters: 10_000,
            essential: EssentialMethod::UsacAccurate,
            duplicate_px: 0.0,
            pnp: PnpMethod::default(),
        }
    }
}

impl RansacSettings {
    /// A finite positive threshold, a confidence strictly between 0 and 1 and at least one iteration.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.threshold_px.is_finite() && self.threshold_px > 0.0) {
            return Err(format!("threshold_px must be a positive number, got {}", self.threshold_px));
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(format!("confidence must lie strictly between 0 and 1, got {}", self.confidence));
        }
        if self.max_iters < 1 {
            return Err(format!("max_iters must be at least 1, got {}", self.max_iters));
        }
        if !(self.duplicate_px.is_finite() && self.duplicate_px >= 0.0) {
            return Err(format!("duplicate_px must be a number >= 0, got {}", self.duplicate_px));
        }
        Ok(())
    }

    /// Relocalisation's PnP defaults: 4 px, up to 2,000 iterations at confidence 0.999, USAC with P3P samples of
    /// 3, MSAC scoring and local optimisation ([`PnpMethod::Usac`]). USAC was chosen over EPnP's 5-point RANSAC
    /// by a rule written before scoring (`docs/results/relocalisation/estimator/`): far queries of four
    /// training scenes, every descriptor through the same pipeline, placed 110 against 99, in half the time.
    pub fn relocalisation() -> Self {
        Self { threshold_px: 4.0, confidence: 0.999, max_iters: 2000, pnp: PnpMethod::Usac, ..Self::default() }
    }

    /// OpenCV's `findEssentialMat` defaults (plain RANSAC, 1,000 iterations, confidence 0.999) at `threshold_px`:
    /// the data README's baseline pipeline.
    pub fn opencv(threshold_px: f64) -> Self {
        Self {
            threshold_px,
            confidence: 0.999,
            max_iters: 1000,
            essential: EssentialMethod::Ransac,
            duplicate_px: 0.0,
            pnp: PnpMethod::default(),
        }
    }
}

/// How `findEssentialMat` searches. The default is `UsacAccurate`: on the selection split (rendered
/// sequences 36-39 and castle frames 20-29) it raised pair AUC@10 from 0.676 to 0.806 for FREAK and from 0.629
/// to 0.796 for SConE over `Ransac`, because the plain estimator returns an unrefined 5-point model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum EssentialMethod {
    /// Classic RANSAC over 5-point samples; the best sample's model is returned as it is (OpenCV's `RANSAC`,
    /// the data README's configuration).
    Ransac,
    /// OpenCV's USAC with local optimisation of the best model on its inliers (`USAC_ACCURATE`).
    UsacAccurate,
    /// OpenCV's USAC with MAGSAC++ scoring (`USAC_MAGSAC`).
    UsacMagsac,
}

impl EssentialMethod {
    pub(super) fn flag(self) -> i32 {
        match self {
            EssentialMethod::Ransac => opencv::calib3d::RANSAC,
            EssentialMethod::UsacAccurate => opencv::calib3d::USAC_ACCURATE,
            EssentialMethod::UsacMagsac => opencv::calib3d::USAC_MAGSAC,
        }
    }
}

/// How `solvePnPRansac` searches for an absolute pose. Every method draws its hypotheses from the best
/// correspondences, passed best first, and the inliers are then taken from all of them and refined the same
/// way (`pose::absolute_pose`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum PnpMethod {
    /// Classic RANSAC over EPnP on samples of 5 correspondences (OpenCV's `SOLVEPNP_EPNP`): at an inlier ratio
    /// w a sample is clean with probability w^5.
    #[default]
    Epnp,
    /// Classic RANSAC over AP3P on samples of 4 (three for the solver, one to choose among its solutions):
    /// clean with probability w^4, ten times as often as EPnP's at 10 % inliers.
    P3p,
    /// OpenCV's USAC with P3P minimal samples of 3, MSAC scoring and local optimisation of the best model
    /// (`USAC_DEFAULT`).
    Usac,
    /// USAC with PROSAC's sampling, which draws from the best-ranked correspondences first (`USAC_PROSAC`).
    UsacProsac,
    /// USAC with MAGSAC++ scoring, which marginalises the threshold, and its sigma-consensus local
    /// optimisation (`USAC_MAGSAC`).
    UsacMagsac,
    /// USAC with PROSAC's sampling, MAGSAC++ scoring and sigma-consensus local optimisation together
    /// (OpenCV's `UsacParams`; no preset has all three).
    UsacProsacMagsac,
}

impl PnpMethod {
    /// The `flags` of OpenCV's `solvePnPRansac`: a PnP solver for classic RANSAC, a USAC preset otherwise;
    /// `None` for the method that needs `UsacParams` ([`PnpMethod::usac_params`]).
    pub(super) fn flag(self) -> Option<i32> {
        match self {
            PnpMethod::Epnp => Some(opencv::calib3d::SOLVEPNP_EPNP),
            PnpMethod::P3p => Some(opencv::calib3d::SOLVEPNP_AP3P),
            PnpMethod::Usac => Some(opencv::calib3d::USAC_DEFAULT),
            PnpMethod::UsacProsac => Some(opencv::calib3d::USAC_PROSAC),
            PnpMethod::UsacMagsac => Some(opencv::calib3d::USAC_MAGSAC),
            PnpMethod::UsacProsacMagsac => None,
        }
    }

    /// OpenCV's `UsacParams` for [`PnpMethod::UsacProsacMagsac`] at `params`' threshold, confidence and cap.
    pub(super) fn usac_params(params: &RansacSettings) -> opencv::Result<opencv::calib3d::UsacParams> {
        use opencv::calib3d::{LocalOptimMethod, SamplingMethod, ScoreMethod, UsacParams};
        let mut p = UsacParams::default()?;
        p.sampler = SamplingMethod::SAMPLING_PROSAC;
        p.score = ScoreMethod::SCORE_METHOD_MAGSAC;
        p.lo_method = LocalOptimMethod::LOCAL_OPTIM_SIGMA;
        p.threshold = params.threshold_px;
        p.confidence = params.confidence;
        p.max_iterations = params.max_iters;
        Ok(p)
    }
}

/// Iterations a RANSAC with a minimal sample of `sample` points needs to find an all-inlier sample with
/// `confidence`, at inlier ratio `w`: `ln(1 - confidence) / ln(1 - w^sample)` (the adaptive stopping rule).
pub fn ransac_iterations_needed(w: f64, sample: i32, confidence: f64) -> f64 {
    if w <= 0.0 {
        return f64::INFINITY;
    }
    let p = w.powi(sample);
    if p >= 1.0 {
        return 1.0;
    }
    ((1.0 - confidence).ln() / (1.0 - p).ln()).max(1.0)
}
