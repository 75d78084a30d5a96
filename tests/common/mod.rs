//! Shared by the integration tests: the contract's field lists (CONTRACT.md), written once,
//! and the reader of `inspect --csv` output.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::Path;

/// `align --json`: the contract's fields plus the paper's plain-UABJM σ.
pub const ALIGN_FIELDS: [&str; 27] = [
    "reference",
    "frame",
    "scale",
    "rotation_arcsec",
    "dx_px",
    "dy_px",
    "dx_arcsec",
    "dy_arcsec",
    "sigma_scale",
    "sigma_rotation_arcsec",
    "sigma_dx_px",
    "sigma_dy_px",
    "sigma_dx_arcsec",
    "sigma_dy_arcsec",
    "uabjm_sigma_scale",
    "uabjm_sigma_rotation_arcsec",
    "uabjm_sigma_dx_px",
    "uabjm_sigma_dy_px",
    "header_residual",
    "solar_rotation",
    "points",
    "inliers",
    "residual_rms_px",
    "similarity",
    "status",
    "message",
    "elapsed_ms",
];

/// A `/jitter/<channel>` message adds the stream context to the `align --json` fields.
pub const STREAM_FIELDS: [&str; 12] = [
    "channel",
    "obs_time",
    "sequence",
    "reference_kind",
    "chained_dx_px",
    "chained_dy_px",
    "chained_rotation_arcsec",
    "chained_scale",
    "sigma_chained_dx_px",
    "sigma_chained_dy_px",
    "sigma_chained_rotation_arcsec",
    "sigma_chained_scale",
];

/// Every field of a `/jitter/<channel>` message.
pub fn jitter_fields() -> Vec<&'static str> {
    ALIGN_FIELDS
        .iter()
        .chain(STREAM_FIELDS.iter())
        .copied()
        .collect()
}

/// Rows of a simple CSV (no quoted commas in the columns read here) keyed by header name.
pub fn read_csv(path: &Path) -> Vec<HashMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("csv written");
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(String::from))
                .collect()
        })
        .collect()
}
