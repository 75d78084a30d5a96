//! The records sunjitter reports: `align --json` and the MCAP `/jitter/<channel>` messages.
//! Field names are the external contract (`../shared/docs/CONTRACT.md`); do not rename.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Ok,
    Degraded,
    Failed,
}

/// A transform in the contract's units (the `header_residual` object).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TransformFields {
    pub scale: f64,
    pub rotation_arcsec: f64,
    pub dx_px: f64,
    pub dy_px: f64,
}

/// The result of aligning one frame to one reference (`align --json`).
/// Numbers are `None` (JSON `null`) when `status` is `failed`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AlignResult {
    pub reference: String,
    pub frame: String,
    pub scale: Option<f64>,
    pub rotation_arcsec: Option<f64>,
    pub dx_px: Option<f64>,
    pub dy_px: Option<f64>,
    pub dx_arcsec: Option<f64>,
    pub dy_arcsec: Option<f64>,
    pub sigma_scale: Option<f64>,
    pub sigma_rotation_arcsec: Option<f64>,
    pub sigma_dx_px: Option<f64>,
    pub sigma_dy_px: Option<f64>,
    pub uabjm_sigma_scale: Option<f64>,
    pub uabjm_sigma_rotation_arcsec: Option<f64>,
    pub uabjm_sigma_dx_px: Option<f64>,
    pub uabjm_sigma_dy_px: Option<f64>,
    pub header_residual: Option<TransformFields>,
    pub points: usize,
    pub inliers: usize,
    pub residual_rms_px: Option<f64>,
    pub similarity: Option<f64>,
    pub status: Status,
    pub message: String,
    pub elapsed_ms: f64,
}

/// One `/jitter/<channel>` MCAP message: the align fields plus the stream context.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameAlignment {
    #[serde(flatten)]
    pub align: AlignResult,
    pub channel: String,
    /// ISO 8601 UTC.
    pub obs_time: String,
    pub sequence: u64,
    /// `self`, `previous`, `keyframe`, `fixed`, `channel`.
    pub reference_kind: String,
    pub chained_dx_px: Option<f64>,
    pub chained_dy_px: Option<f64>,
    pub chained_rotation_arcsec: Option<f64>,
    pub chained_scale: Option<f64>,
    pub sigma_chained_dx_px: Option<f64>,
    pub sigma_chained_dy_px: Option<f64>,
    pub sigma_chained_rotation_arcsec: Option<f64>,
    pub sigma_chained_scale: Option<f64>,
}
