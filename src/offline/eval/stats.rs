//! Summary statistics of evaluation errors (AUC of the error curve, accuracy under a threshold, median), and
//! the markdown tables the reports are written as.

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

/// A markdown table: the header row, the separator, then one line per row of cells already formatted.
pub fn markdown_table(headers: &[&str], rows: impl IntoIterator<Item = Vec<String>>) -> String {
    let mut s = format!("| {} |\n|{}\n", headers.join(" | "), "---|".repeat(headers.len()));
    for row in rows {
        s.push_str(&format!("| {} |\n", row.join(" | ")));
    }
    s
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

    #[test]
    fn markdown_tables_have_a_header_a_separator_and_a_line_per_row() {
        let t = markdown_table(&["method", "AUC@10"], [vec!["freak".to_string(), "0.474".to_string()]]);
        assert_eq!(t, "| method | AUC@10 |\n|---|---|\n| freak | 0.474 |\n");
    }
}
