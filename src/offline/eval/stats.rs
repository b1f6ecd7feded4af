//! Summary statistics of evaluation errors: AUC of the error curve, accuracy under a threshold, median.

/// AUC of the error curve up to `max_deg`: the mean over pairs of `max(0, 1 − err / max_deg)` (failures
/// count as 180 degrees, so they add 0).
pub fn auc(errors: &[f64], max_deg: f64) -> f64 {
    if errors.is_empty() {
        return 0.0;
    }
    errors.iter().map(|e| (1.0 - e / max_deg).max(0.0)).sum::<f64>() / errors.len() as f64
}

/// Share of errors at most `deg`.
pub fn accuracy(errors: &[f64], deg: f64) -> f64 {
    if errors.is_empty() {
        return 0.0;
    }
    errors.iter().filter(|&&e| e <= deg).count() as f64 / errors.len() as f64
}

pub fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auc_and_accuracy() {
        let e = [0.0, 5.0, 180.0, 10.0];
        assert!((auc(&e, 10.0) - (1.0 + 0.5 + 0.0 + 0.0) / 4.0).abs() < 1e-12);
        assert!((accuracy(&e, 5.0) - 0.5).abs() < 1e-12);
        assert_eq!(median(&e), 7.5);
    }
}
