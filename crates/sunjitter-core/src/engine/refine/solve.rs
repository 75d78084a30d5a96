//! The Gauss–Newton iterations and the covariance at their answer.

use super::covariance::{noise_covariance, robust_covariance, ClusterFit};
use super::pixels::CellGrid;
use super::reference::{Pixel, RefineReference};
use super::robust::{robust_sigma, sum_in_chunks, tukey_psi_slope, tukey_weight};
use super::window::FrameWindow;
use super::{RefineFailure, RefineSettings, Refined};
use crate::geometry::{compose_with_covariance, Covariance4, Similarity};
use nalgebra::{Matrix6, Vector6};
use rayon::prelude::*;

/// Iterations that may recompute the Tukey weights; later ones keep them. Reweighting to
/// convergence matters, but on real pairs with evolving structure it never settles (the
/// estimate wanders by its σ for as long as the weights change); with them fixed Gauss–Newton
/// converges (docs/validation.md#reweighting-then-frozen-weights).
pub(super) const REWEIGHTED_ITERATIONS: usize = 10;

/// Reweighted steps shorter than this, px, are taken as Newton steps of the M-estimator
/// (the iterations are near their answer; [`step`]).
const LOCAL_STEP_PX: f64 = 0.01;

/// Least `Σψ′/Σw` the covariance uses (0.83 for Gaussian residuals; lower with heavy tails):
/// a floor that keeps a nearly flat ψ′ from inflating the variance without bound.
pub(super) const MIN_PSI_RATIO: f64 = 0.5;

/// Tukey biweight tuning constant (95 % efficiency for Gaussian residuals).
pub(super) const TUKEY_C: f64 = 4.685;

/// Refine `start` (the whole grid-to-grid transform) on `pixels` (x, y, cell) of the reference
/// grid. `reference` is the reference as the flow stage saw it; `frame` the frame's spline.
///
/// The estimating equation is `Σ w·J_ref·r = 0` with `J_ref` built from the reference's
/// gradient (smoothed by `gradient_smoothing_px`: it only weighs the residuals, and a noisy
/// weight costs precision) and, for the gain, the mean of the reference's four neighbours.
/// Neither involves the pixel's own noise, nor the frame's: weighing the gain equation with the
/// noisy warped value itself biases the gain low (errors in variables), and through the gain's
/// coupling with the geometry, the scale. Its slope, which both the Newton step and the
/// covariance need, is `A = Σ w·J_ref·J_frameᵀ` with the warped frame's own gradient: with
/// noisy images `Σ J_ref J_refᵀ` overstates the slope by the gradient noise's variance, which
/// would shrink the σ and slow convergence (docs/validation.md#gain-instrument-and-slope).
pub fn refine(
    reference: &RefineReference,
    frame: &FrameWindow,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    start: Similarity,
    settings: &RefineSettings,
) -> Result<Refined, RefineFailure> {
    let fit = FitPixels::new(reference, pixels, start.center)?;
    refine_fitted(&fit, frame, grid, start, settings)
}

/// [`refine`] on pixels whose instruments are made already: refinements of several frames
/// against one reference on the same pixels (a self-test's cases) share them.
pub(super) fn refine_fitted(
    fit: &FitPixels,
    frame: &FrameWindow,
    grid: &CellGrid,
    start: Similarity,
    settings: &RefineSettings,
) -> Result<Refined, RefineFailure> {
    debug_assert!(
        start.center == fit.center,
        "the pixels' lever arms are about the start's centre"
    );
    let problem = Problem {
        carried: frame.carried_positions(&fit.pixels),
        fit,
        frame,
        grid,
        settings,
    };
    let mut state = SolverState::start(&problem, start);
    loop {
        match step(&problem, state)? {
            Next::Continue(next) => state = next,
            Next::Done(refined) => return Ok(*refined),
        }
    }
}

/// A failure on the first iteration is the start's pixels' (no structure, identical images);
/// on a later one, where the iterations went.
fn failed(iterations: usize, why: &str) -> RefineFailure {
    match iterations {
        1 => RefineFailure::Unusable(why.to_string()),
        _ => RefineFailure::RanOff(why.to_string()),
    }
}

/// The pixels of a refinement against one reference, their instruments, and the lever arm
/// that conditions the scale and rotation columns (they are `q / lever`) about `center`.
pub(super) struct FitPixels {
    pixels: Vec<Pixel>,
    /// The instruments, one row per pixel.
    jac: Vec<[f64; 6]>,
    center: [f64; 2],
    lever: f64,
}

impl FitPixels {
    pub(super) fn new(
        reference: &RefineReference,
        pixels: &[(usize, usize, usize)],
        center: [f64; 2],
    ) -> Result<FitPixels, RefineFailure> {
        if pixels.len() < 64 {
            return Err(RefineFailure::Unusable(format!(
                "{} usable pixels in the inlier cells; too few to refine",
                pixels.len()
            )));
        }
        let pixels = reference.fit_pixels(pixels);
        if pixels.len() < 64 {
            return Err(RefineFailure::Unusable(
                "too few finite reference pixels to refine".into(),
            ));
        }
        let lever = (sum_in_chunks(
            pixels.len(),
            |range| {
                pixels[range]
                    .iter()
                    .map(|p| (p.x as f64 - center[0]).powi(2) + (p.y as f64 - center[1]).powi(2))
                    .sum::<f64>()
            },
            |a, b| a + b,
        ) / pixels.len() as f64)
            .sqrt()
            .max(1.0);
        let mut fit = FitPixels {
            pixels,
            jac: Vec::new(),
            center,
            lever,
        };
        fit.jac = fit
            .pixels
            .par_iter()
            .map(|p| {
                let (qx, qy) = fit.lever_arm(p);
                rows(p.gx, p.gy, qx, qy, p.neighbours).into()
            })
            .collect();
        Ok(fit)
    }

    fn lever_arm(&self, p: &Pixel) -> (f64, f64) {
        (
            (p.x as f64 - self.center[0]) / self.lever,
            (p.y as f64 - self.center[1]) / self.lever,
        )
    }
}

/// What the iterations do not change: the pixels and their instruments, and the frame.
struct Problem<'a> {
    fit: &'a FitPixels,
    frame: &'a FrameWindow,
    /// Where the Sun carried each pixel, when it moved.
    carried: Option<Vec<(f64, f64)>>,
    grid: &'a CellGrid,
    settings: &'a RefineSettings,
}

/// A row of the equations: geometric columns from a gradient and lever arm, then gain, offset.
fn rows(gx: f64, gy: f64, qx: f64, qy: f64, v: f64) -> Vector6<f64> {
    Vector6::new(gx * qx + gy * qy, -gx * qy + gy * qx, gx, gy, v, 1.0)
}

impl<'a> Problem<'a> {
    /// Pixel `k`'s row of the slope: the warped frame's own gradient (times the gain).
    fn frame_row(&self, k: usize, gain: f64, sampled: &[[f64; 3]]) -> Vector6<f64> {
        let (qx, qy) = self.fit.lever_arm(&self.fit.pixels[k]);
        let [v, fx, fy] = sampled[k];
        rows(gain * fx, gain * fy, qx, qy, v)
    }

    /// The frame at the image of every pixel through `t`.
    fn sample(&self, t: &Similarity) -> Vec<[f64; 3]> {
        self.frame
            .sample(&self.fit.pixels, self.carried.as_deref(), t)
    }

    /// [`Self::sample`] into the buffer of the last one.
    fn resample(&self, t: &Similarity, out: &mut [[f64; 3]]) {
        self.frame
            .sample_into(&self.fit.pixels, self.carried.as_deref(), t, out)
    }
}

/// The iterations' state: the estimate and photometry, the frame sampled there, and the
/// weights and residual scale that the reweighting carries from one iteration to the next.
struct SolverState {
    estimate: Similarity,
    gain: f64,
    offset: f64,
    /// The frame at `estimate`.
    sampled: Vec<[f64; 3]>,
    /// The residuals' buffer, filled anew by every iteration.
    residuals: Vec<f64>,
    weights: Vec<f64>,
    scale: f64,
    iterations: usize,
}

impl SolverState {
    fn start(problem: &Problem, start: Similarity) -> SolverState {
        let sampled = problem.sample(&start);
        let (gain, offset) = initial_photometry(&problem.fit.pixels, &sampled);
        SolverState {
            estimate: start,
            gain,
            offset,
            sampled,
            residuals: vec![0.0; problem.fit.pixels.len()],
            weights: vec![0.0; problem.fit.pixels.len()],
            scale: f64::NAN,
            iterations: 0,
        }
    }
}

/// What one iteration leaves.
enum Next {
    Continue(SolverState),
    Done(Box<Refined>),
}

/// One Gauss–Newton iteration: state in, state out (or the answer, once converged or out of
/// iterations).
fn step(problem: &Problem, mut state: SolverState) -> Result<Next, RefineFailure> {
    state.iterations += 1;
    let iterations = state.iterations;
    let pixels = &problem.fit.pixels;
    let sampled = &state.sampled;
    // The pixels were chosen to map inside the frame from the start: most of them
    // leaving it means the iterations ran away from the start (from a flow far off on a
    // featureless disk the gain can turn negative and the estimate leave the frame;
    // docs/validation.md#run-away-most-pixels-leave-the-frame).
    let inside = sampled
        .par_iter()
        .filter(|s| s.iter().all(|v| v.is_finite()))
        .count();
    if 2 * inside < sampled.len() {
        return Err(RefineFailure::RanOff(format!(
            "its estimate left the frame ({inside} of {} pixels map inside it)",
            sampled.len()
        )));
    }
    let (gain, offset) = (state.gain, state.offset);
    let mut residuals = std::mem::take(&mut state.residuals);
    residuals
        .par_iter_mut()
        .zip(pixels)
        .zip(sampled)
        .for_each(|((r, p), s)| *r = p.value - gain * s[0] - offset);
    reweigh(&mut state, &residuals)?;
    let (sampled, weights) = (&state.sampled, &state.weights);
    // Its slope, `Σ w·J_ref·J_frameᵀ`, in fixed chunks summed in order (deterministic);
    // with `Σw` and `Σψ′` for the reweighted step.
    let c = TUKEY_C * state.scale;
    let (slope, score, sum_w, sum_psi) = sum_in_chunks(
        pixels.len(),
        |range| {
            let mut slope = Matrix6::<f64>::zeros();
            let mut score = Vector6::<f64>::zeros();
            let (mut sum_w, mut sum_psi) = (0.0, 0.0);
            for k in range {
                let wt = weights[k];
                if wt <= 0.0 {
                    continue;
                }
                let f = problem.frame_row(k, gain, sampled);
                let jv = Vector6::from(problem.fit.jac[k]);
                slope += jv * f.transpose() * wt;
                score += jv * (wt * residuals[k]);
                sum_w += wt;
                sum_psi += tukey_psi_slope(residuals[k], c);
            }
            (slope, score, sum_w, sum_psi)
        },
        |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2, a.3 + b.3),
    );
    let lu = slope.lu();
    let step = lu.solve(&score).ok_or_else(|| {
        failed(
            iterations,
            "the refinement's equations are singular (no structure)",
        )
    })?;
    // While the weights follow the residuals, the score `Σ ψ(r)·J` changes with the estimate
    // by `Σ ψ′·J·Fᵀ`, not by the slope `Σ w·J·Fᵀ` that holds them fixed: near the answer the
    // reweighted step falls short by about `1 − Σψ′/Σw` and converges only linearly. There
    // its Newton step takes the slope in Huber's scalar form, as the covariance does. A step
    // of a hundredth of a pixel or more is still choosing which pixels count (real pairs with
    // evolving structure), and stays as it is (docs/validation.md#reweighting-then-frozen-weights).
    let lever = problem.fit.lever;
    let near = iterations <= REWEIGHTED_ITERATIONS && moved_px(&step, lever) < LOCAL_STEP_PX;
    let step = match near {
        true => step / (sum_psi / sum_w).clamp(MIN_PSI_RATIO, 1.0),
        false => step,
    };
    let delta = [step[0] / lever, step[1] / lever, step[2], step[3]];
    let update = Similarity {
        scale: (1.0 + delta[0]).hypot(delta[1]),
        rotation_rad: delta[1].atan2(1.0 + delta[0]),
        dx: delta[2],
        dy: delta[3],
        center: problem.fit.center,
    };
    let moved = moved_px(&step, lever);
    if !moved.is_finite() {
        return Err(failed(iterations, "the refinement diverged"));
    }
    let converged = moved < problem.settings.tolerance_px;
    tracing::trace!(iterations, moved, scale = state.scale, "refinement step");
    if converged || iterations >= problem.settings.max_iterations.max(1) {
        let last = LastStep {
            residuals: &residuals,
            slope: lu,
            step,
            update,
            converged,
        };
        return finish(problem, &state, last).map(|r| Next::Done(Box::new(r)));
    }
    state.estimate = state.estimate.after(&update);
    state.gain += step[4];
    state.offset += step[5];
    state.residuals = residuals;
    problem.resample(&state.estimate, &mut state.sampled);
    Ok(Next::Continue(state))
}

/// How far a step moves the pixels, px: its shift, and twice what its scale and rotation
/// change move the lever arm.
fn moved_px(step: &Vector6<f64>, lever: f64) -> f64 {
    step[2].hypot(step[3]) + (step[0] / lever).hypot(step[1] / lever) * lever * 2.0
}

/// Iteratively reweighted for the first iterations, then with the weights frozen: on real
/// pairs with evolving structure reweighting every step keeps the estimate wandering by about
/// its σ, while with fixed weights Gauss–Newton converges
/// (docs/validation.md#reweighting-then-frozen-weights). Pixels that map outside the frame
/// weigh nothing either way.
fn reweigh(state: &mut SolverState, residuals: &[f64]) -> Result<(), RefineFailure> {
    let iterations = state.iterations;
    let sampled = &state.sampled;
    if iterations <= REWEIGHTED_ITERATIONS {
        let scale = robust_sigma(residuals)
            .ok_or_else(|| failed(iterations, "no finite residuals in the refinement"))?;
        state.scale = scale;
        if scale.is_nan() || scale <= 0.0 {
            return Err(failed(
                iterations,
                "the refinement's residuals vanish exactly; nothing to weigh",
            ));
        }
        state
            .weights
            .par_iter_mut()
            .zip(residuals)
            .zip(sampled)
            .for_each(|((w, r), s)| {
                *w = if s.iter().all(|v| v.is_finite()) {
                    tukey_weight(*r, TUKEY_C * scale)
                } else {
                    0.0
                };
            });
    } else {
        state
            .weights
            .par_iter_mut()
            .zip(sampled)
            .for_each(|(w, s)| {
                if !s.iter().all(|v| v.is_finite()) {
                    *w = 0.0;
                }
            });
    }
    Ok(())
}

/// The last iteration's linearisation, where the covariance is taken.
struct LastStep<'r> {
    residuals: &'r [f64],
    /// The slope `Σ w·J_ref·J_frameᵀ`, factorised.
    slope: nalgebra::LU<f64, nalgebra::U6, nalgebra::U6>,
    step: Vector6<f64>,
    update: Similarity,
    converged: bool,
}

/// The answer at the last step, with its covariances (at this linearisation point: the last
/// step is below tolerance).
fn finish(
    problem: &Problem,
    state: &SolverState,
    last: LastStep,
) -> Result<Refined, RefineFailure> {
    let (pixels, jac, lever) = (&problem.fit.pixels, &problem.fit.jac, problem.fit.lever);
    let (residuals, weights, scale) = (last.residuals, &state.weights, state.scale);
    let ainv = last.slope.try_inverse().ok_or_else(|| {
        failed(
            state.iterations,
            "the refinement's equations are singular (no structure)",
        )
    })?;
    // Per chunk: (used, Σw, Σψ′, Σw²JJᵀ, Σw·r²), summed in order.
    let (used, sum_w, sum_psi, white, s2) = sum_in_chunks(
        pixels.len(),
        |range| {
            let mut acc = (0usize, 0.0, 0.0, Matrix6::<f64>::zeros(), 0.0);
            for k in range {
                let (wt, r) = (weights[k], residuals[k]);
                if wt > 0.0 {
                    let jv = Vector6::from(jac[k]);
                    acc.0 += 1;
                    acc.1 += wt;
                    acc.2 += tukey_psi_slope(r, TUKEY_C * scale);
                    acc.3 += jv * jv.transpose() * (wt * wt);
                    acc.4 += wt * r * r;
                }
            }
            acc
        },
        |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2, a.3 + b.3, a.4 + b.4),
    );
    let s2 = s2 / (sum_w - 6.0).max(1.0);
    let plain = ainv * white * ainv.transpose() * s2;
    let frame_row = |k: usize| problem.frame_row(k, state.gain, &state.sampled);
    // The estimate's sensitivity to the data is that of the M-estimator `Σ ψ(r)·J = 0`
    // (the weights were set by these residuals): the slope weighs by ψ′, not by w.
    // Huber's scalar form, `w · Σψ′/Σw`, because per pixel ψ′ turns negative beyond
    // 0.45 c and makes the slope of small images nearly singular, their σ far too large
    // (docs/validation.md#slope-in-hubers-scalar-form).
    let psi_ratio = (sum_psi / sum_w).clamp(MIN_PSI_RATIO, 1.0);
    let fits = ClusterFit {
        jac,
        residuals,
        weights,
        slope_per_weight: psi_ratio,
    };
    let (robust, blocks) = robust_covariance(&fits, frame_row, pixels, problem.grid, plain);
    let noise = noise_covariance(
        pixels,
        &fits,
        frame_row,
        TUKEY_C * scale,
        problem.settings.smoothing_px,
        problem.settings.noise_covariance,
    );
    let flat_residual_sigma = noise.as_ref().map(|n| n.1);
    let final_t = state.estimate.after(&last.update);
    let to4 = |m: &Matrix6<f64>| -> Covariance4 {
        let unlever = [1.0 / lever, 1.0 / lever, 1.0, 1.0];
        std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)] * unlever[i] * unlever[j]))
    };
    let identity = Similarity::identity(problem.fit.center);
    let zero = [[0.0; 4]; 4];
    let (_, covariance) = compose_with_covariance(&final_t, &zero, &identity, &to4(&robust));
    let (_, plain_covariance) = compose_with_covariance(&final_t, &zero, &identity, &to4(&plain));
    let noise_covariance = noise
        .and_then(|n| n.0)
        .map(|unit| compose_with_covariance(&final_t, &zero, &identity, &to4(&unit)).1);
    Ok(Refined {
        transform: final_t,
        covariance,
        plain_covariance,
        gain: state.gain + last.step[4],
        offset: state.offset + last.step[5],
        pixels: used,
        blocks,
        iterations: state.iterations,
        converged: last.converged,
        residual_sigma: scale,
        flat_residual_sigma,
        noise_covariance,
    })
}

/// Gain and offset of the sampled frame against the reference (least squares over the pixels).
pub(super) fn initial_photometry(pixels: &[Pixel], sampled: &[[f64; 3]]) -> (f64, f64) {
    let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (p, s) in pixels.iter().zip(sampled) {
        let v = s[0];
        if v.is_finite() {
            n += 1.0;
            sx += v;
            sy += p.value;
            sxx += v * v;
            sxy += v * p.value;
        }
    }
    let var = sxx / n - (sx / n).powi(2);
    if !(n > 2.0 && var > 0.0) {
        return (1.0, 0.0);
    }
    let gain = (sxy / n - sx / n * sy / n) / var;
    (gain, sy / n - gain * sx / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn a_featureless_start_is_unusable_not_run_off() {
        // Identical constant images: the residuals vanish on the first iteration. That says
        // the pixels hold no structure, not that the iterations went anywhere.
        let image = Array2::<f32>::from_elem((64, 64), 100.0);
        let settings = RefineSettings::default();
        let reference = RefineReference::new(image.view(), &settings);
        let start = Similarity::identity([31.5, 31.5]);
        let bbox = (8, 8, 55, 55);
        let window = FrameWindow::new(image.view(), bbox, &start, 0.0, None).expect("inside");
        let grid = CellGrid::over_box(bbox, 4);
        let pixels: Vec<(usize, usize, usize)> = (8..56)
            .flat_map(|y| (8..56).map(move |x| (x, y)))
            .map(|(x, y)| (x, y, grid.cell_of(x, y).expect("in the box")))
            .collect();
        match refine(&reference, &window, &pixels, &grid, start, &settings) {
            Err(RefineFailure::Unusable(why)) => assert!(why.contains("vanish"), "{why}"),
            other => panic!("expected an unusable start, got {other:?}"),
        }
    }

    #[test]
    fn near_its_answer_a_reweighted_step_is_a_newton_step() {
        // A TRACE crop and a frame made from it through a known similarity, with noise: the
        // weights follow the residuals.
        let full = crate::test_data::read_real("trace_171_19980519T222143_1024.fits");
        let image = full.slice(ndarray::s![384..640, 384..640]).to_owned();
        let settings =
            crate::engine::refine::settings(&crate::engine::EngineConfig::default(), 0.0);
        let center = [127.5, 127.5];
        let truth = Similarity {
            scale: 1.0002,
            rotation_rad: 3e-4,
            dx: 0.31,
            dy: -0.17,
            center,
        };
        let mut frame =
            crate::resample::HighOrderSpline::new(image.view(), crate::engine::refine::MODEL)
                .warp_similarity_window(&truth.inverse(), 0, 0, 256, 256);
        let mut rng = crate::stats::SplitMix64::new(6);
        frame.mapv_inplace(|v| v + 3.0 * rng.gaussian() as f32);
        let reference = RefineReference::new(image.view(), &settings);
        let bbox = (24, 24, 231, 231);
        // The flow's answer a few thousandths of a pixel off, as it comes.
        let start = Similarity {
            dx: truth.dx + 0.004,
            dy: truth.dy - 0.003,
            ..truth
        };
        let window = FrameWindow::new(frame.view(), bbox, &start, settings.smoothing_px, None)
            .expect("inside");
        let grid = CellGrid::over_box(bbox, 8);
        let pixels: Vec<(usize, usize, usize)> = (24..232)
            .flat_map(|y| (24..232).map(move |x| (x, y)))
            .map(|(x, y)| (x, y, grid.cell_of(x, y).expect("in the box")))
            .collect();
        let refined =
            refine(&reference, &window, &pixels, &grid, start, &settings).expect("refines");
        let (got, want) = (refined.transform.params(), truth.params());
        for k in 0..4 {
            let sigma = refined.covariance[k][k].sqrt();
            assert!(
                (got[k] - want[k]).abs() < 3.0 * sigma,
                "parameter {k}: {} against {} (σ {sigma})",
                got[k],
                want[k]
            );
        }
        // Plain reweighted steps converge only linearly here, each a quarter to a third of the
        // last: five iterations to the tolerance. Newton steps take three.
        assert!(refined.converged);
        assert!(refined.iterations <= 4, "{} iterations", refined.iterations);
    }

    #[test]
    fn the_psi_slope_is_the_derivative_of_the_weighted_residual() {
        let c = 4.685;
        let psi = |r: f64| r * tukey_weight(r, c);
        for r in [-4.0, -2.5, -1.0, -0.2, 0.0, 0.7, 2.1, 3.3, 4.6] {
            let h = 1e-6;
            let numeric = (psi(r + h) - psi(r - h)) / (2.0 * h);
            assert!(
                (tukey_psi_slope(r, c) - numeric).abs() < 1e-6,
                "r {r}: {} vs {numeric}",
                tukey_psi_slope(r, c)
            );
        }
        assert_eq!(tukey_psi_slope(5.0, c), 0.0);
        assert_eq!(tukey_psi_slope(f64::NAN, c), 0.0);
    }
}
