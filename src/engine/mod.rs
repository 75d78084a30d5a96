//! One alignment: coarse (headers) → flow → sampling → fit → σ. No I/O here.
//!
//! INTERFACE ONLY for now: `align_images` is a placeholder that reports `failed`.
//! The real engine lands with issue 3; callers (pipeline, commands) code against this API.

pub mod output;
pub mod quality;

use crate::geometry::Similarity;
use crate::meta::FrameMeta;
use crate::record::{AlignResult, Status};
use ndarray::Array2;
use serde::{Deserialize, Serialize};

/// An image and what its header says about it.
#[derive(Debug, Clone)]
pub struct Image {
    /// Pixel values, shape `(height, width)`, indexed `[y, x]`; NaN where blank.
    pub data: Array2<f32>,
    pub meta: FrameMeta,
}

/// Engine settings (filled from the configuration file; defaults generalise).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct EngineConfig {
    /// Farneback averaging window in arcsec (paper: about 63″), converted with the plate scale.
    pub window_arcsec: f64,
    /// Fraction of the solar radius kept in the disk mask (excludes the limb).
    pub mask_radius_fraction: f64,
    /// `sample × sample` grid of median vectors.
    pub sample: usize,
    pub ransac_threshold_px: f64,
    pub ransac_max_trials: usize,
    pub seed: u64,
}

impl Default for EngineConfig {
    fn default() -> Self {
        EngineConfig {
            window_arcsec: 63.0,
            mask_radius_fraction: 0.9,
            sample: 20,
            ransac_threshold_px: 0.5,
            ransac_max_trials: 1000,
            seed: 0,
        }
    }
}

/// The engine's full answer: the contract record plus what chained policies need.
#[derive(Debug, Clone)]
pub struct AlignOutcome {
    pub result: AlignResult,
    /// Whole grid-to-grid transform (coarse then fine), `None` when failed.
    pub transform: Option<Similarity>,
    /// Calibrated covariance of (scale, rotation_rad, dx_px, dy_px), `None` when failed.
    pub covariance: Option<[[f64; 4]; 4]>,
}

/// Align `frame` to `reference`.
pub fn align_images(reference: &Image, frame: &Image, _cfg: &EngineConfig) -> AlignOutcome {
    AlignOutcome {
        result: AlignResult {
            reference: reference.meta.file.display().to_string(),
            frame: frame.meta.file.display().to_string(),
            scale: None,
            rotation_arcsec: None,
            dx_px: None,
            dy_px: None,
            dx_arcsec: None,
            dy_arcsec: None,
            sigma_scale: None,
            sigma_rotation_arcsec: None,
            sigma_dx_px: None,
            sigma_dy_px: None,
            uabjm_sigma_scale: None,
            uabjm_sigma_rotation_arcsec: None,
            uabjm_sigma_dx_px: None,
            uabjm_sigma_dy_px: None,
            header_residual: None,
            points: 0,
            inliers: 0,
            residual_rms_px: None,
            similarity: None,
            status: Status::Failed,
            message: "engine not implemented yet".into(),
            elapsed_ms: 0.0,
        },
        transform: None,
        covariance: None,
    }
}
