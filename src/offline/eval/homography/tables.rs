//! A homography report as markdown: each method's figures, the figures per bin of zoom, of rotation and of tilt,
//! and the neighbour share per rule.

use crate::offline::eval::homography::report::{
    bin_labels, rotation_bin, zoom_bin, HomographyReport, RuleShare, ROTATION_EDGES, ZOOM_EDGES,
};
use crate::offline::eval::stats::markdown_table;

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map(|x| format!("{x:.digits$}")).unwrap_or_else(|| "-".into())
}

/// The summaries and the bins as markdown.
pub fn markdown(report: &HomographyReport) -> String {
    let c = &report.config;
    let mut s = format!(
        "{} sequences, {} pairs per method; ratio {}, same-corner radius {} px, SConE matcher {}, MAGSAC++ {} px, correct within {} px\n\n",
        report.sequences.len(),
        report.summaries.first().map(|m| m.pairs).unwrap_or(0),
        c.ratio,
        c.same_corner_px,
        c.scone_matcher.name(),
        c.ransac_px,
        c.correct_px
    );
    let headers = [
        "method",
        "within 3 px",
        "within 5 px",
        "within 10 px",
        "MMA@3",
        "correct",
        "matches",
        "median corner error px",
        "neighbour share",
        "neighbours above chance",
        "ring above chance",
        "describe ms",
    ];
    s.push_str(&markdown_table(
        &headers,
        report.summaries.iter().map(|m| {
            vec![
                m.method.name().to_string(),
                format!("{:.3}", m.within[0]),
                format!("{:.3}", m.within[1]),
                format!("{:.3}", m.within[2]),
                format!("{:.3}", m.mma),
                format!("{:.1}", m.mean_correct),
                format!("{:.1}", m.mean_matches),
                opt(m.median_corner_error_px, 2),
                opt(m.mean_neighbour_share, 3),
                opt(m.mean_neighbour_above_chance, 3),
                opt(m.mean_ring_above_chance, 3),
                format!("{:.1}", m.describe_ms),
            ]
        }),
    ));
    for axis in ["zoom", "rotation", "tilt"] {
        s.push_str(&format!(
            "\nBy {axis} (within 5 px / correct matches / MMA@3; pairs per bin; the shares above chance):\n\n"
        ));
        let mut headers: Vec<String> =
            vec![axis.to_string(), "pairs".into(), "neighbours above chance".into(), "ring above chance".into()];
        headers.extend(report.summaries.iter().map(|m| m.method.name().to_string()));
        let hs: Vec<&str> = headers.iter().map(String::as_str).collect();
        s.push_str(&markdown_table(
            &hs,
            report.bins.iter().filter(|b| b.axis == axis).map(|b| {
                let neighbours = b.summaries.iter().find_map(|m| m.mean_neighbour_above_chance);
                let ring = b.summaries.iter().find_map(|m| m.mean_ring_above_chance);
                let pairs = b.summaries.first().map(|m| m.pairs).unwrap_or(0).to_string();
                let mut row = vec![b.label.clone(), pairs, opt(neighbours, 3), opt(ring, 3)];
                row.extend(
                    b.summaries.iter().map(|m| format!("{:.2} / {:.0} / {:.2}", m.within[1], m.mean_correct, m.mma)),
                );
                row
            }),
        ));
    }
    if !report.rule_shares.is_empty() {
        s.push_str("\nNeighbour share by rule (mean over the pairs of each bin; the last column: all pairs):\n\n");
        let zooms = bin_labels(report.rule_shares.iter().map(|r| r.zoom), zoom_bin, 1.0, &ZOOM_EDGES);
        let rots = bin_labels(report.rule_shares.iter().map(|r| r.rotation_deg), rotation_bin, 0.0, &ROTATION_EDGES);
        let mut headers: Vec<String> = vec!["rule".into()];
        headers.extend(zooms.iter().cloned());
        headers.extend(rots.iter().cloned());
        headers.push("all".into());
        let hs: Vec<&str> = headers.iter().map(String::as_str).collect();
        let mean = |f: &dyn Fn(&RuleShare) -> bool| {
            let v: Vec<f64> = report.rule_shares.iter().filter(|r| f(r)).filter_map(|r| r.share).collect();
            if v.is_empty() {
                "-".to_string()
            } else {
                format!("{:.3}", v.iter().sum::<f64>() / v.len() as f64)
            }
        };
        s.push_str(&markdown_table(
            &hs,
            report.config.neighbour_rules.iter().map(|&rule| {
                let mut row = vec![format!("{rule:?}")];
                row.extend(zooms.iter().map(|l| mean(&|r| r.rule == rule && zoom_bin(r.zoom) == *l)));
                row.extend(rots.iter().map(|l| mean(&|r| r.rule == rule && rotation_bin(r.rotation_deg) == *l)));
                row.push(mean(&|r| r.rule == rule));
                row
            }),
        ));
    }
    s
}
