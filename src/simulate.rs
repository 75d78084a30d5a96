//! The paper's Monte Carlo (§4.1): random similarity transforms of one image, aligned back,
//! residuals against the injected truth, and how well the reported σ cover them.
//!
//! The test frame for a trial with truth `T` is `frame(q) = reference(T⁻¹(q))`, so reference
//! content at `p` appears in the frame at `T(p)` — the contract's convention. Frames are made
//! by the caller-supplied `warp` (a float-coordinate spline, never a grid-quantised warp).

use crate::geometry::{Similarity, ARCSEC_PER_RAD};
use crate::stats::SplitMix64;
use serde::{Deserialize, Serialize};

/// Ranges of the random transforms (the paper's defaults).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrialRanges {
    pub scale: (f64, f64),
    pub rotation_rad: (f64, f64),
    pub shift_px: (f64, f64),
}

impl Default for TrialRanges {
    fn default() -> Self {
        TrialRanges {
            scale: (0.995, 1.005),
            rotation_rad: (-0.01, 0.01),
            shift_px: (-5.0, 5.0),
        }
    }
}

/// Draw `n` truths about `center`, deterministically from `seed`.
pub fn draw_truths(n: usize, seed: u64, ranges: &TrialRanges, center: [f64; 2]) -> Vec<Similarity> {
    let mut rng = SplitMix64::new(seed);
    (0..n)
        .map(|_| Similarity {
            scale: rng.uniform(ranges.scale.0, ranges.scale.1),
            rotation_rad: rng.uniform(ranges.rotation_rad.0, ranges.rotation_rad.1),
            dx: rng.uniform(ranges.shift_px.0, ranges.shift_px.1),
            dy: rng.uniform(ranges.shift_px.0, ranges.shift_px.1),
            center,
        })
        .collect()
}

/// What one trial measured, in the contract's units (scale, arcsec, px, px).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrialOutcome {
    pub truth: [f64; 4],
    pub estimate: Option<[f64; 4]>,
    pub sigma: Option<[f64; 4]>,
    pub uabjm_sigma: Option<[f64; 4]>,
    /// Cross-correlation baseline (dx, dy), when run.
    pub cc: Option<[f64; 2]>,
}

/// Contract units of a transform: (scale, rotation arcsec, dx px, dy px).
pub fn contract_units(t: &Similarity) -> [f64; 4] {
    [t.scale, t.rotation_rad * ARCSEC_PER_RAD, t.dx, t.dy]
}

/// Per-parameter figures of a Monte Carlo run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ParameterSummary {
    /// RMSE of estimate − truth.
    pub rmse: f64,
    /// Mean of estimate − truth (systematic bias).
    pub bias: f64,
    /// RMS of the reported (calibrated) σ.
    pub rms_sigma: f64,
    pub within_1sigma: f64,
    pub within_3sigma: f64,
    /// The paper's plain UABJM σ: RMS, and coverage.
    pub rms_uabjm_sigma: f64,
    pub uabjm_within_1sigma: f64,
    pub uabjm_within_3sigma: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MonteCarloSummary {
    pub trials: usize,
    pub succeeded: usize,
    pub scale: ParameterSummary,
    pub rotation_arcsec: ParameterSummary,
    pub dx_px: ParameterSummary,
    pub dy_px: ParameterSummary,
    /// RMSE of the cross-correlation baseline (dx, dy), when it was run.
    pub cc_rmse_px: Option<[f64; 2]>,
}

/// Reduce trial outcomes to the paper's table figures.
pub fn summarise(outcomes: &[TrialOutcome]) -> MonteCarloSummary {
    let ok: Vec<&TrialOutcome> = outcomes
        .iter()
        .filter(|o| o.estimate.is_some() && o.sigma.is_some())
        .collect();
    let param = |k: usize| -> ParameterSummary {
        let n = ok.len().max(1) as f64;
        let mut s = ParameterSummary {
            rmse: 0.0,
            bias: 0.0,
            rms_sigma: 0.0,
            within_1sigma: 0.0,
            within_3sigma: 0.0,
            rms_uabjm_sigma: 0.0,
            uabjm_within_1sigma: 0.0,
            uabjm_within_3sigma: 0.0,
        };
        for o in &ok {
            let (Some(est), Some(sig)) = (o.estimate, o.sigma) else {
                continue;
            };
            let r = est[k] - o.truth[k];
            s.rmse += r * r;
            s.bias += r;
            s.rms_sigma += sig[k] * sig[k];
            s.within_1sigma += f64::from(u8::from(r.abs() <= sig[k]));
            s.within_3sigma += f64::from(u8::from(r.abs() <= 3.0 * sig[k]));
            if let Some(u) = o.uabjm_sigma {
                s.rms_uabjm_sigma += u[k] * u[k];
                s.uabjm_within_1sigma += f64::from(u8::from(r.abs() <= u[k]));
                s.uabjm_within_3sigma += f64::from(u8::from(r.abs() <= 3.0 * u[k]));
            }
        }
        s.rmse = (s.rmse / n).sqrt();
        s.bias /= n;
        s.rms_sigma = (s.rms_sigma / n).sqrt();
        s.rms_uabjm_sigma = (s.rms_uabjm_sigma / n).sqrt();
        s.within_1sigma /= n;
        s.within_3sigma /= n;
        s.uabjm_within_1sigma /= n;
        s.uabjm_within_3sigma /= n;
        s
    };
    let cc: Vec<([f64; 2], [f64; 4])> = outcomes
        .iter()
        .filter_map(|o| o.cc.map(|c| (c, o.truth)))
        .collect();
    let cc_rmse_px = (!cc.is_empty()).then(|| {
        let n = cc.len() as f64;
        let ex = cc.iter().map(|(c, t)| (c[0] - t[2]).powi(2)).sum::<f64>() / n;
        let ey = cc.iter().map(|(c, t)| (c[1] - t[3]).powi(2)).sum::<f64>() / n;
        [ex.sqrt(), ey.sqrt()]
    });
    MonteCarloSummary {
        trials: outcomes.len(),
        succeeded: ok.len(),
        scale: param(0),
        rotation_arcsec: param(1),
        dx_px: param(2),
        dy_px: param(3),
        cc_rmse_px,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn summary_of_known_residuals() {
        // Residuals ±0.1 px with σ 0.2: RMSE 0.1, all within 1σ; a 0.5 px residual is outside 1σ
        // and inside 3σ.
        let mk = |r: f64, s: f64| TrialOutcome {
            truth: [1.0, 0.0, 0.0, 0.0],
            estimate: Some([1.0, 0.0, r, -r]),
            sigma: Some([1e-6, 1.0, s, s]),
            uabjm_sigma: Some([1e-6, 1.0, s / 10.0, s / 10.0]),
            cc: Some([2.0 * r, 0.0]),
        };
        let s = summarise(&[mk(0.1, 0.2), mk(-0.1, 0.2), mk(0.5, 0.2), mk(-0.5, 0.2)]);
        let expected_rmse = ((0.01 + 0.01 + 0.25 + 0.25) / 4.0f64).sqrt();
        assert!((s.dx_px.rmse - expected_rmse).abs() < 1e-12);
        assert!((s.dx_px.within_1sigma - 0.5).abs() < 1e-12);
        assert!((s.dx_px.within_3sigma - 1.0).abs() < 1e-12);
        assert!((s.dx_px.uabjm_within_1sigma - 0.0).abs() < 1e-12);
        assert!(s.dx_px.bias.abs() < 1e-12);
        assert!((s.cc_rmse_px.unwrap()[0] - 2.0 * expected_rmse).abs() < 1e-12);
    }

    #[test]
    fn truths_stay_in_range_and_are_reproducible() {
        let r = TrialRanges::default();
        let a = draw_truths(100, 7, &r, [10.0, 10.0]);
        assert_eq!(a, draw_truths(100, 7, &r, [10.0, 10.0]));
        assert!(a.iter().all(|t| (0.995..=1.005).contains(&t.scale)
            && t.rotation_rad.abs() <= 0.01
            && t.dx.abs() <= 5.0
            && t.dy.abs() <= 5.0));
    }
}
