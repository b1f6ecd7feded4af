//! What the bench binaries share (each uses part of it).
#![allow(dead_code)]

/// Resident memory of this process, MB (`VmRSS` of `/proc/self/status`; 0 where there is none).
pub fn rss_mb() -> f64 {
    let s = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    s.lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// The shared real data: `$SCONE_DATA`, else `../shared/data` beside the checkout.
pub fn shared_data() -> std::path::PathBuf {
    std::env::var_os("SCONE_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data")))
}

/// The prefix outside the clone where heavy things live: `$SCONE_PREFIX`, else `~/.cache/scone`.
pub fn prefix() -> std::path::PathBuf {
    std::env::var_os("SCONE_PREFIX")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(std::env::var_os("HOME").unwrap()).join(".cache/scone"))
}

/// The median of `v` (the upper one of an even count), by total order.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}
