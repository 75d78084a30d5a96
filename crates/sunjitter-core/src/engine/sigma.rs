//! Which standard errors the engine reports, and how they are calibrated.
//!
//! The paper's UABJM treats every flow vector as an independent measurement. They are not:
//! vectors closer than the averaging window share pixels, and between channels the residuals
//! follow real structure differences that extend over whole features. The calibrated σ uses
//! the sandwich covariance `σ²(JᵀJ)⁻¹JᵀRJ(JᵀJ)⁻¹` with the larger of two correlation models:
//! the window's own overlap (a box of the window's width), and a Gaussian whose length is
//! measured from the residuals themselves.

use crate::fit::{
    block_jackknife_covariance, correlated_covariance, residual, CorrelationModel, SimilarityFit,
};
use crate::geometry::Covariance4;
use crate::sampling::Correspondence;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SigmaMethod {
    /// UABJM with the spatial correlation of the flow residuals accounted for (default).
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
    if method == SigmaMethod::Uabjm {
        return fit.covariance;
    }
    let sandwich = |model| {
        correlated_covariance(inliers, &fit.transform, model)
            .map(|(cov, _)| cov)
            .ok()
    };
    let window = sandwich(CorrelationModel::Box {
        width_px: winsize_px as f64,
    });
    let measured = residual_correlation_length(inliers, fit)
        .and_then(|l| sandwich(CorrelationModel::Gaussian { sigma_px: l }));
    // Resampling the data itself: leave out one block (twice the window) at a time.
    let jackknife =
        block_jackknife_covariance(inliers, fit.transform.center, 2.0 * winsize_px as f64)
            .ok()
            .filter(|_| enough_blocks(inliers, 2.0 * winsize_px as f64));
    [window, measured, jackknife]
        .into_iter()
        .flatten()
        .reduce(|a, b| if mean_log_ratio(&b, &a) > 0.0 { b } else { a })
        .unwrap_or(fit.covariance)
}

/// Add a systematic floor of `floor_px` (in quadrature): fully to the translations, and as
/// the rotation/scale that moves the vectors by `floor_px` at their RMS radius.
pub fn add_floor(
    cov: &mut Covariance4,
    points: &[Correspondence],
    center: [f64; 2],
    floor_px: f64,
) {
    if floor_px.is_nan() || floor_px <= 0.0 || points.is_empty() {
        return;
    }
    let r2 = points
        .iter()
        .map(|p| (p.x - center[0]).powi(2) + (p.y - center[1]).powi(2))
        .sum::<f64>()
        / points.len() as f64;
    let lever = r2.sqrt().max(1.0);
    let f2 = floor_px * floor_px;
    cov[0][0] += f2 / (lever * lever);
    cov[1][1] += f2 / (lever * lever);
    cov[2][2] += f2;
    cov[3][3] += f2;
}

/// The jackknife needs enough blocks to estimate a 4×4 covariance.
fn enough_blocks(points: &[Correspondence], block_px: f64) -> bool {
    let blocks: std::collections::HashSet<(i64, i64)> = points
        .iter()
        .map(|p| {
            (
                (p.x / block_px).floor() as i64,
                (p.y / block_px).floor() as i64,
            )
        })
        .collect();
    blocks.len() >= 20
}

/// Average of `ln(b_kk / a_kk)` over the parameters: which covariance is larger overall.
fn mean_log_ratio(b: &Covariance4, a: &Covariance4) -> f64 {
    (0..4)
        .map(|k| (b[k][k].max(f64::MIN_POSITIVE) / a[k][k].max(f64::MIN_POSITIVE)).ln())
        .sum::<f64>()
        / 4.0
}

/// Correlation length of the fit residuals, px: the separation at which their normalised
/// autocorrelation falls to `e^{-1/2}` (the σ of a Gaussian correlation), or `None` when
/// neighbouring residuals are not significantly correlated.
pub fn residual_correlation_length(points: &[Correspondence], fit: &SimilarityFit) -> Option<f64> {
    let res: Vec<([f64; 2], [f64; 2])> = points
        .iter()
        .map(|p| ([p.x, p.y], residual(p, &fit.transform)))
        .filter(|(_, r)| r[0].is_finite() && r[1].is_finite())
        .collect();
    let n = res.len();
    if n < 20 {
        return None;
    }
    let mean = [
        res.iter().map(|r| r.1[0]).sum::<f64>() / n as f64,
        res.iter().map(|r| r.1[1]).sum::<f64>() / n as f64,
    ];
    let var = res
        .iter()
        .map(|r| (r.1[0] - mean[0]).powi(2) + (r.1[1] - mean[1]).powi(2))
        .sum::<f64>()
        / n as f64;
    if var.is_nan() || var <= 0.0 {
        return None;
    }
    // Bin width: the typical nearest-neighbour spacing of the sample points.
    let spacing = typical_spacing(&res.iter().map(|r| r.0).collect::<Vec<_>>())?;
    const BINS: usize = 24;
    let mut sum = [0.0f64; BINS];
    let mut count = [0usize; BINS];
    for i in 0..n {
        for j in i + 1..n {
            let d =
                ((res[i].0[0] - res[j].0[0]).powi(2) + (res[i].0[1] - res[j].0[1]).powi(2)).sqrt();
            let k = (d / spacing).round() as usize;
            if (1..BINS).contains(&k) {
                let a = res[i].1;
                let b = res[j].1;
                sum[k] += (a[0] - mean[0]) * (b[0] - mean[0]) + (a[1] - mean[1]) * (b[1] - mean[1]);
                count[k] += 1;
            }
        }
    }
    let rho = |k: usize| (count[k] >= 10).then(|| sum[k] / count[k] as f64 / var);
    let threshold = (-0.5f64).exp();
    // Not correlated at the nearest spacing: independent residuals.
    let first = rho(1)?;
    if first < 0.2 {
        return None;
    }
    let (mut prev_d, mut prev_r) = (0.0, 1.0);
    for k in 1..BINS {
        let Some(r) = rho(k) else { continue };
        let d = k as f64 * spacing;
        if r < threshold {
            // Linear interpolation between the last bin above and this one.
            return Some(prev_d + (d - prev_d) * (prev_r - threshold) / (prev_r - r));
        }
        (prev_d, prev_r) = (d, r);
    }
    Some(prev_d)
}

fn typical_spacing(points: &[[f64; 2]]) -> Option<f64> {
    let mut nearest: Vec<f64> = points
        .iter()
        .enumerate()
        .map(|(i, p)| {
            points
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt())
                .fold(f64::INFINITY, f64::min)
        })
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    if nearest.is_empty() {
        return None;
    }
    nearest.sort_by(f64::total_cmp);
    Some(nearest[nearest.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::{fit_similarity, RansacParams};
    use crate::geometry::Similarity;
    use crate::stats::SplitMix64;

    /// Residuals drawn as a smooth random field with a known Gaussian correlation length:
    /// the estimate must find it (within the bin resolution), and find none for white noise.
    #[test]
    fn measures_known_residual_correlation_length() {
        let ell = 60.0;
        let mut rng = SplitMix64::new(9);
        // A smooth field: sum of Gaussian bumps of width ell/√2 at random places
        // (autocorrelation of that field is Gaussian with σ = ell).
        let bumps: Vec<([f64; 2], f64, f64)> = (0..400)
            .map(|_| {
                (
                    [rng.uniform(-100.0, 1124.0), rng.uniform(-100.0, 1124.0)],
                    rng.gaussian(),
                    rng.gaussian(),
                )
            })
            .collect();
        let field = |x: f64, y: f64| -> (f64, f64) {
            let w = ell / std::f64::consts::SQRT_2;
            bumps.iter().fold((0.0, 0.0), |(u, v), (c, a, b)| {
                let g = (-((x - c[0]).powi(2) + (y - c[1]).powi(2)) / (2.0 * w * w)).exp();
                (u + a * g, v + b * g)
            })
        };
        let mut smooth = Vec::new();
        let mut white = Vec::new();
        for j in 0..24 {
            for i in 0..24 {
                let (x, y) = (20.0 + 40.0 * i as f64, 20.0 + 40.0 * j as f64);
                let (u, v) = field(x, y);
                smooth.push(Correspondence {
                    x,
                    y,
                    u: 0.05 * u,
                    v: 0.05 * v,
                });
                white.push(Correspondence {
                    x,
                    y,
                    u: 0.05 * rng.gaussian(),
                    v: 0.05 * rng.gaussian(),
                });
            }
        }
        let params = RansacParams {
            threshold_px: 10.0,
            ..RansacParams::default()
        };
        let c = Similarity::array_center(1024, 1024);
        let fit = fit_similarity(&smooth, c, &params).unwrap();
        let l = residual_correlation_length(&smooth, &fit).unwrap();
        assert!((l - ell).abs() < 0.35 * ell, "measured {l}, true {ell}");
        let fit = fit_similarity(&white, c, &params).unwrap();
        assert_eq!(residual_correlation_length(&white, &fit), None);
    }
}
