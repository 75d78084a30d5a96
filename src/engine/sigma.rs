//! Which standard errors the engine reports, and how they are calibrated.

use crate::fit::{correlated_covariance, CorrelationModel, SimilarityFit};
use crate::geometry::Covariance4;
use crate::sampling::Correspondence;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SigmaMethod {
    /// UABJM with the flow vectors' spatial correlation accounted for (the default): flow
    /// vectors closer than the averaging window share pixels, so their errors are
    /// correlated and the plain UABJM counts too many independent measurements.
    #[default]
    Calibrated,
    /// The paper's plain UABJM, `(JᵀJ)⁻¹σ²`.
    Uabjm,
}

/// The covariance reported as `sigma_*`.
pub fn calibrated_covariance(
    method: SigmaMethod,
    inliers: &[Correspondence],
    fit: &SimilarityFit,
    winsize_px: usize,
) -> Covariance4 {
    match method {
        SigmaMethod::Uabjm => fit.covariance,
        SigmaMethod::Calibrated => correlated_covariance(
            inliers,
            &fit.transform,
            CorrelationModel::Box {
                width_px: winsize_px as f64,
            },
        )
        .map(|(cov, _)| cov)
        .unwrap_or(fit.covariance),
    }
}
