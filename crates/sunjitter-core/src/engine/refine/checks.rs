//! The checks a pair's refinement runs at its own answer: the interpolation and blur terms of
//! its σ, and the residual noise the σ must cover.

use super::pixels::{pixel_box, CellGrid};
use super::reference::RefineReference;
use super::self_test::{self_test_bias, FrameMaker, SelfTest, SelfTestCase};
use super::solve::{FitPixels, MIN_PSI_RATIO};
use super::{RefineSettings, Refined};
use crate::geometry::{Covariance4, Similarity};
use ndarray::ArrayView2;

/// Side of the region the interpolation check refines, px: its synthetic frame is dense, so
/// on large images it runs on the central part only; the whole field would cost more than the
/// rest of a frame's alignment (docs/validation.md#interpolation-check-on-the-central-part).
/// Less of the field means less averaging of the error over sub-pixel positions when the frame
/// is rotated or scaled: a larger term, not a smaller one.
pub(super) const CHECK_MAX_SIDE: usize = 1024;

/// The error this frame's own transform may bring from the refinement's interpolator, per
/// parameter, beyond the variance the check reported (quadratic excess): a frame made from the
/// reference through `transform` with a cubic spline (see [`FrameMaker::CubicSpline`]) is
/// refined from the exact answer on the same pixels. The error depends on the sub-pixel
/// positions the pixels land on. When they are nearly the same across the field (a shift with
/// little rotation or scale change: pointing jitter), it does not average out, and σ without
/// such a term fall far short of the error on band-limited frames; the cubic-spline frame's
/// error bounds it (docs/validation.md#check-frames-made-by-a-cubic-spline). The shift is
/// reduced to its fractional part (same sub-pixel positions), so that the synthetic frame
/// stays inside the reference. `None` when the check cannot run.
pub(super) fn interpolation_check(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
) -> Option<[f64; 4]> {
    let test = check_at_fractional_shift(
        reference,
        prepared,
        pixels,
        grid,
        transform,
        &RefineSettings {
            frame_smoothing_px: 0.0,
            ..*settings
        },
        FrameMaker::CubicSpline,
    )?;
    tracing::debug!(bias = ?test.bias, variance = ?test.variance, "interpolation check");
    Some(std::array::from_fn(|k| {
        (test.bias[k] * test.bias[k] - test.variance[k])
            .max(0.0)
            .sqrt()
    }))
}

/// What a blur left unmatched by `mismatch_px2` does to the answer, per parameter: a frame
/// made from the reference by the refinement's own interpolator through `transform` and
/// blurred by that much more is refined from the exact answer.
pub(super) fn blur_check(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
    mismatch_px2: f64,
) -> Option<[f64; 4]> {
    let test = check_at_fractional_shift(
        reference,
        prepared,
        pixels,
        grid,
        transform,
        &RefineSettings {
            frame_smoothing_px: mismatch_px2.max(0.0).sqrt(),
            ..*settings
        },
        FrameMaker::Model,
    )?;
    tracing::debug!(bias = ?test.bias, mismatch_px2, "blur check");
    Some(test.bias.map(f64::abs))
}

/// A self-test at `transform` with its shift reduced to the fractional part (the same
/// sub-pixel positions, and a synthetic frame that stays inside the reference), its frame
/// smoothed by `settings.frame_smoothing_px` beyond the reference's.
pub(super) fn check_at_fractional_shift(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
    maker: FrameMaker,
) -> Option<SelfTestCase> {
    let local = Similarity {
        dx: transform.dx - transform.dx.round(),
        dy: transform.dy - transform.dy.round(),
        ..*transform
    };
    let whole = [pixel_box(pixels)?];
    let fit = FitPixels::new(prepared, pixels, local.center).ok()?;
    self_test_bias(reference, &fit, &whole, grid, &local, settings, maker)
}

/// Factors (1 to 2) that raise each geometric σ of `cov` to what the residuals' noise gives
/// through the exact slope. The noise is the part of the residual level at the flattest
/// pixels that the model's misfit alone (the self-test's, noise-free by construction) does
/// not explain; `None` when there is none or nothing to measure it with.
pub(super) fn noise_factors(
    refined: &Refined,
    self_test: Option<SelfTest>,
    cov: &Covariance4,
) -> Option<[f64; 4]> {
    let (unit, pair_sigma) = (refined.noise_covariance?, refined.flat_residual_sigma?);
    let misfit_sigma = self_test?.flat_sigma?;
    let noise_var = pair_sigma * pair_sigma - misfit_sigma * misfit_sigma;
    (noise_var > 0.0).then(|| {
        std::array::from_fn(|k| {
            let ratio = unit[k][k] * noise_var / cov[k][k];
            if ratio.is_finite() {
                ratio.clamp(1.0, MAX_NOISE_INFLATION.powi(2)).sqrt()
            } else {
                1.0
            }
        })
    })
}

/// Most a σ is raised to the residual noise's (as the scalar ψ′ ratio's floor bounds it).
pub(super) const MAX_NOISE_INFLATION: f64 = 1.0 / MIN_PSI_RATIO;
