//! A relocalisation report as markdown: each method's summary, then its queries by viewing angle to the map.

use crate::offline::eval::reloc::report::{RelocReport, RelocSummary};
use crate::offline::eval::stats::markdown_table;

pub fn markdown(r: &RelocReport) -> String {
    let map = match r.config.map_block {
        Some((a, b)) => format!("the block {a:.2}-{b:.2} of the posed frames"),
        None => format!("every {}th frame", r.config.stride),
    };
    let mut s = format!(
        "{} (map: {map}; camera path extent {:.2} scene units; thresholds x {}; 2D-3D precision at {} px)\n\n",
        r.scene, r.path_extent, r.config.unit_scale, r.config.precision_px
    );
    let headers = [
        "method",
        "keyframes",
        "landmarks",
        "queries",
        "(0.25 m, 2°)",
        "(0.5 m, 5°)",
        "(5 m, 10°)",
        "not localised",
        "med. t",
        "med. R (deg)",
        "2D-3D precision",
        "matches",
        "query ms",
        "cov. 95 %",
        "confidence / within",
        "focal err.",
        "observations",
        "foreign localised",
    ];
    s.push_str(&markdown_table(
        &headers,
        r.summaries.iter().map(|m| {
            vec![
                row_name(m),
                m.map_keyframes.to_string(),
                m.landmarks.to_string(),
                m.queries.to_string(),
                format!("{:.2}", m.within_025m_2deg),
                format!("{:.2}", m.within_05m_5deg),
                format!("{:.2}", m.within_5m_10deg),
                format!("{:.2}", m.not_localised),
                format!("{:.3}", m.median_translation_error),
                format!("{:.2}", m.median_rotation_error_deg),
                format!("{:.3}", m.match_precision),
                format!("{:.0}", m.mean_matches),
                format!("{:.0}", m.mean_query_ms),
                format!("{:.2}", m.covariance_coverage),
                format!("{:.2} / {:.2}", m.mean_confidence, m.within_confidence_tolerance),
                format!("{:.3}", m.median_focal_error),
                m.observations.to_string(),
                format!("{} / {}", m.foreign_localised, m.foreign_queries),
            ]
        }),
    ));
    s.push_str("\nBy viewing angle to the most similarly oriented map keyframe (success within (5 cm, 5°) / (0.25 m, 2°) / (0.5 m, 5°); 2D-3D precision):\n\n");
    let headers = [
        "method",
        "distractor obs.",
        "angle (deg)",
        "queries",
        "median baseline",
        "(5 cm, 5°)",
        "(0.25 m, 2°)",
        "(0.5 m, 5°)",
        "precision",
    ];
    s.push_str(&markdown_table(
        &headers,
        r.summaries.iter().flat_map(|m| {
            m.bins.iter().filter(|b| b.queries > 0).map(move |b| {
                let hi = if b.angle_deg.1.is_finite() { format!("{:.0}", b.angle_deg.1) } else { "inf".into() };
                vec![
                    row_name(m),
                    m.distractor_observations.to_string(),
                    format!("{:.0}-{hi}", b.angle_deg.0),
                    b.queries.to_string(),
                    format!("{:.3}", b.median_baseline),
                    format!("{:.2}", b.within_5cm_5deg),
                    format!("{:.2}", b.within_025m_2deg),
                    format!("{:.2}", b.within_05m_5deg),
                    format!("{:.3}", b.match_precision),
                ]
            })
        }),
    ));
    s
}

/// The method, and stage 1's cap or the estimator where the row is one of `also_caps` or `also_pnp`.
fn row_name(m: &RelocSummary) -> String {
    match (m.stage1_cap, m.pnp) {
        (Some(cap), _) => format!("{}, stage 1 capped at {cap}", m.method.name()),
        (None, Some(p)) => format!("{}, PnP {:?} x {}", m.method.name(), p.method, p.max_iters),
        (None, None) => m.method.name().to_string(),
    }
}
