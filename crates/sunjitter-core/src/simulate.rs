//! The paper's Monte Carlo (§4.1): random similarity transforms of one image, aligned back,
//! residuals against the injected truth, and how well the reported σ cover them.
//!
//! The test frame for a trial with truth `T` is `frame(q) = reference(T⁻¹(q))`, so reference
//! content at `p` appears in the frame at `T(p)` — the contract's convention. Frames are made
//! by the caller-supplied `warp` (a float-coordinate spline, never a grid-quantised warp).

use crate::geometry::{Similarity, ARCSEC_PER_RAD};
use crate::stats::SplitMix64;
use ndarray::ArrayView2;
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
    /// The alignment's status: `degraded` trials count in the figures (they carry a transform
    /// and σ), `failed` ones do not.
    pub status: crate::record::Status,
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
    /// Trials that returned a transform (`ok` or `degraded`).
    pub succeeded: usize,
    /// Of those, the `degraded` ones.
    pub degraded: usize,
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
    // With no aligned trial every figure is 0/0: NaN, `null` in JSON, never a perfect 0.
    let param = |k: usize| -> ParameterSummary {
        let n = ok.len() as f64;
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
        degraded: ok
            .iter()
            .filter(|o| o.status == crate::record::Status::Degraded)
            .count(),
        scale: param(0),
        rotation_arcsec: param(1),
        dx_px: param(2),
        dy_px: param(3),
        cc_rmse_px,
    }
}

/// Side of the blocks the background noise is measured in, px: many times a detector's or a
/// compressor's noise correlation length (a few px), so the block's quadratic surface does not
/// absorb the noise, and small enough that a quadratic describes the quiet Sun or sky in it.
pub const NOISE_BLOCK_PX: usize = 16;

/// The quantile of block noise levels taken as the background's: the quietest tenth of the
/// image (the sky beside a full disk, the darkest corona or quiet Sun in a partial field).
const BACKGROUND_QUANTILE: f64 = 0.10;
/// z of the standard normal at [`BACKGROUND_QUANTILE`].
const BACKGROUND_QUANTILE_Z: f64 = -1.281_551_565_545;

/// The image's background noise σ per pixel, the unit of `simulate --noise K`.
///
/// The image is cut into [`NOISE_BLOCK_PX`]² blocks; in each, the RMS residual from a fitted
/// quadratic surface estimates the local noise. The background's is the 10th percentile of
/// those, divided by where that percentile falls for pure noise (Wilson–Hilferty), so that
/// uniform noise is measured without bias. Blocks with a non-finite pixel, and constant ones
/// (padding), do not count. Unlike neighbour differences over the whole image, this does not
/// count a disk's structure as noise, and it sees most of a correlated noise's per-pixel σ
/// (about 90 % for noise smoothed over 3 px, where neighbour differences see 58 %).
/// `None` when no block qualifies.
pub fn background_noise(img: ArrayView2<f32>) -> Option<f64> {
    use rayon::prelude::*;
    let b = NOISE_BLOCK_PX;
    let (h, w) = img.dim();
    let half = (b - 1) as f64 / 2.0;
    let basis = |x: usize, y: usize| {
        let (u, v) = ((x as f64 - half) / half, (y as f64 - half) / half);
        nalgebra::Vector6::new(1.0, u, v, u * u, v * v, u * v)
    };
    let mut gram = nalgebra::Matrix6::zeros();
    for y in 0..b {
        for x in 0..b {
            let a = basis(x, y);
            gram += a * a.transpose();
        }
    }
    let gram_inv = gram.try_inverse()?;
    let dof = (b * b - 6) as f64;
    let blocks: Vec<(usize, usize)> = (0..h / b)
        .flat_map(|by| (0..w / b).map(move |bx| (by * b, bx * b)))
        .collect();
    let mut sigmas: Vec<f64> = blocks
        .par_iter()
        .filter_map(|&(y0, x0)| {
            // Offsetting by the block's first pixel keeps the sums small; the constant term
            // of the surface absorbs the offset.
            let first = img[[y0, x0]] as f64;
            let (mut atb, mut btb, mut varies) = (nalgebra::Vector6::zeros(), 0.0, false);
            for y in 0..b {
                for x in 0..b {
                    let v = img[[y0 + y, x0 + x]] as f64;
                    if !v.is_finite() {
                        return None;
                    }
                    let d = v - first;
                    varies |= d != 0.0;
                    atb += basis(x, y) * d;
                    btb += d * d;
                }
            }
            let coef = gram_inv * atb;
            let rss = (btb - coef.dot(&atb)).max(0.0);
            varies.then(|| (rss / dof).sqrt())
        })
        .collect();
    if sigmas.is_empty() {
        return None;
    }
    let k = ((sigmas.len() - 1) as f64 * BACKGROUND_QUANTILE).round() as usize;
    let (_, quantile, _) = sigmas.select_nth_unstable_by(k, f64::total_cmp);
    Some(*quantile / chi_quantile_ratio(dof, BACKGROUND_QUANTILE_Z))
}

/// √(χ²_ν quantile / ν) at standard-normal z, by Wilson–Hilferty: where the sample σ of ν
/// degrees of freedom falls, relative to the true σ, at that quantile.
fn chi_quantile_ratio(dof: f64, z: f64) -> f64 {
    let c = 2.0 / (9.0 * dof);
    (1.0 - c + z * c.sqrt()).powi(3).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::Status;

    #[test]
    fn summary_of_known_residuals() {
        // Residuals ±0.1 px with σ 0.2: RMSE 0.1, all within 1σ; a 0.5 px residual is outside 1σ
        // and inside 3σ.
        let mk = |r: f64, s: f64| TrialOutcome {
            truth: [1.0, 0.0, 0.0, 0.0],
            status: Status::Ok,
            estimate: Some([1.0, 0.0, r, -r]),
            sigma: Some([1e-6, 1.0, s, s]),
            uabjm_sigma: Some([1e-6, 1.0, s / 10.0, s / 10.0]),
            cc: Some([2.0 * r, 0.0]),
        };
        let degraded = TrialOutcome {
            status: Status::Degraded,
            ..mk(-0.5, 0.2)
        };
        let s = summarise(&[mk(0.1, 0.2), mk(-0.1, 0.2), mk(0.5, 0.2), degraded]);
        assert_eq!((s.succeeded, s.degraded), (4, 1));
        let expected_rmse = ((0.01 + 0.01 + 0.25 + 0.25) / 4.0f64).sqrt();
        assert!((s.dx_px.rmse - expected_rmse).abs() < 1e-12);
        assert!((s.dx_px.within_1sigma - 0.5).abs() < 1e-12);
        assert!((s.dx_px.within_3sigma - 1.0).abs() < 1e-12);
        assert!((s.dx_px.uabjm_within_1sigma - 0.0).abs() < 1e-12);
        assert!(s.dx_px.bias.abs() < 1e-12);
        assert!((s.cc_rmse_px.unwrap()[0] - 2.0 * expected_rmse).abs() < 1e-12);
    }

    #[test]
    fn a_run_without_aligned_trials_reports_no_figures() {
        let failed = TrialOutcome {
            truth: [1.0, 0.0, 0.0, 0.0],
            status: Status::Failed,
            estimate: None,
            sigma: None,
            uabjm_sigma: None,
            cc: None,
        };
        let s = summarise(&[failed, failed]);
        assert_eq!(s.succeeded, 0);
        assert!(s.dx_px.rmse.is_nan() && s.scale.within_1sigma.is_nan());
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

    /// A smooth scene (a slow ripple on a level) plus white noise of σ `noise`.
    fn scene(n: usize, noise: f64, seed: u64) -> ndarray::Array2<f32> {
        let mut rng = SplitMix64::new(seed);
        ndarray::Array2::from_shape_fn((n, n), |(y, x)| {
            let ripple = 20.0 * (x as f64 / 40.0).sin() * (y as f64 / 45.0).cos();
            (100.0 + ripple + noise * rng.gaussian()) as f32
        })
    }

    fn assert_close(measured: Option<f64>, truth: f64, tolerance: f64) {
        let m = measured.expect("a noise estimate");
        assert!(
            (m / truth - 1.0).abs() < tolerance,
            "measured {m}, injected {truth}"
        );
    }

    #[test]
    fn background_noise_recovers_injected_white_noise() {
        for (sigma, seed) in [(1.5, 1), (0.3, 2), (40.0, 3)] {
            assert_close(
                background_noise(scene(256, sigma, seed).view()),
                sigma,
                0.04,
            );
        }
    }

    #[test]
    fn background_noise_is_the_quiet_parts() {
        // A bright disk with 8× the sky's noise over half the image: the sky's noise is measured.
        let n = 256;
        let mut rng = SplitMix64::new(4);
        let img = ndarray::Array2::from_shape_fn((n, n), |(y, x)| {
            let r = ((x as f64 - 128.0).powi(2) + (y as f64 - 128.0).powi(2)).sqrt();
            let on_disk = r < 102.0;
            let level = if on_disk { 1000.0 } else { 10.0 };
            let sigma = if on_disk { 6.4 } else { 0.8 };
            (level + sigma * rng.gaussian()) as f32
        });
        assert_close(background_noise(img.view()), 0.8, 0.05);
    }

    #[test]
    fn background_noise_of_quantised_data() {
        // Integer data: the rounding adds a uniform error of variance 1/12.
        let img = scene(256, 1.5, 5).mapv(f32::round);
        assert_close(
            background_noise(img.view()),
            (1.5f64.powi(2) + 1.0 / 12.0).sqrt(),
            0.04,
        );
    }

    #[test]
    fn background_noise_of_correlated_noise_is_its_per_pixel_sigma() {
        // White noise smoothed by [1 2 1]/4 on each axis: per-pixel σ = 0.375 σ_white, of
        // which neighbour differences would see only √(1 − ρ₁) ≈ 58 %. The block's surface
        // absorbs a little of noise correlated over 3 px, and the percentile's correction
        // assumes independent pixels, so this reads about 10 % low.
        let n = 258;
        let white = scene(n, 4.0, 6) - &scene(n, 0.0, 6);
        let taps = [0.25, 0.5, 0.25];
        let img = ndarray::Array2::from_shape_fn((n - 2, n - 2), |(y, x)| {
            let mut v = 100.0;
            for (i, a) in taps.iter().enumerate() {
                for (j, b) in taps.iter().enumerate() {
                    v += a * b * white[[y + i, x + j]];
                }
            }
            v
        });
        assert_close(background_noise(img.view()), 0.375 * 4.0, 0.15);
    }

    #[test]
    fn background_noise_ignores_padding_blanks_and_hot_pixels() {
        let mut img = scene(256, 1.5, 7);
        let mut rng = SplitMix64::new(8);
        img.slice_mut(ndarray::s![.., ..64]).fill(0.0);
        img.slice_mut(ndarray::s![..40, 64..]).fill(f32::NAN);
        for _ in 0..200 {
            img[[rng.below(256), rng.below(256)]] += 1000.0;
        }
        assert_close(background_noise(img.view()), 1.5, 0.05);
    }

    #[test]
    fn background_noise_needs_a_varying_block() {
        assert_eq!(
            background_noise(ndarray::Array2::<f32>::zeros((10, 40)).view()),
            None
        );
        assert_eq!(
            background_noise(ndarray::Array2::<f32>::from_elem((64, 64), 3.0).view()),
            None
        );
    }
}
