//! Final direct intensity refinement of the similarity (Lucas–Kanade, Gauss–Newton).
//!
//! The flow stage measures motion through polynomial expansions averaged over windows and
//! then keeps one median vector per grid cell: robust, but far from the Cramér–Rao bound when
//! the images are noisy. This stage starts from the flow's answer and minimises the intensity
//! difference itself over every usable pixel of the RANSAC-inlier cells:
//!
//! `ref(p) ≈ α · frame(T(U(p))) + β`, `U(p) = p + D(p)·δ`,
//! `D(p) = [[qx, −qy, 1, 0], [qy, qx, 0, 1]]`, `q = p − c`,
//!
//! with the current estimate `T`, a small similarity update `U` (δ = (a − 1, b, dx, dy) about
//! the reference centre `c`), and a gain `α` and offset `β` so that exposure and calibration
//! differences do not bias the geometry. The Jacobian uses the reference's gradient (fixed,
//! and free of the frame's interpolated noise: the interpolation smooths the frame's noise by
//! an amount that depends on the sub-pixel position, and a gradient taken from the warped frame
//! correlates with that noise and biases the shift towards half pixels). Residuals are
//! weighted with Tukey's biweight (scale from their MAD) so that features that changed between
//! the exposures do not pull the fit.
//!
//! Covariance: the pixels' residuals are correlated (interpolation and smoothing over a few
//! pixels, real structure differences over whole features), so `σ²(JᵀWJ)⁻¹` is too small.
//! The reported covariance is cluster-robust in its jackknife form over blocks (grid cells,
//! and 2 × 2 groups of them — the larger is kept; see `cluster_covariance`): it measures the
//! residuals' correlation instead of modelling it, as long as it is shorter than a block. The
//! method's systematic floor ([`self_test_floor`], once per reference) is added to it; the
//! plain `σ²H⁻¹` is kept as well.

use super::gaussian_reach;
use crate::geometry::{compose_with_covariance, Covariance4, Similarity};
use crate::resample::{HighOrder, HighOrderSpline, SplineImage};
use crate::sampling::Correspondence;
use nalgebra::{Matrix6, Vector6};
use ndarray::{s, Array2, ArrayView2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// When the intensity refinement runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RefineMode {
    /// When both images are of the same channel (default): there the intensities are the
    /// same physical quantity up to gain and offset. Between channels the flow's answer stays.
    #[default]
    SameChannel,
    /// Always (also between channels).
    Always,
    /// Never: the flow's answer is final.
    Off,
}

/// Settings of one refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineSettings {
    /// Gaussian σ applied to both images before matching, px (0: none).
    pub smoothing_px: f64,
    /// Extra Gaussian σ applied to the warped frame only (resolution matching), px.
    pub frame_smoothing_px: f64,
    /// Further Gaussian σ of the reference whose gradient weighs the residuals, px.
    pub gradient_smoothing_px: f64,
    pub max_iterations: usize,
    /// Stop when an update moves no pixel of the region by more than this, px.
    pub tolerance_px: f64,
    /// Also compute the covariance of the residuals' noise through the exact slope (the
    /// pair's own refinement; the self-test and the interpolation check need only the
    /// residual level at the flattest pixels).
    pub noise_covariance: bool,
}

impl Default for RefineSettings {
    fn default() -> Self {
        RefineSettings {
            smoothing_px: 0.0,
            frame_smoothing_px: 0.0,
            gradient_smoothing_px: 0.0,
            max_iterations: 16,
            tolerance_px: 1e-5,
            noise_covariance: false,
        }
    }
}

/// What the refinement found.
#[derive(Debug, Clone)]
pub struct Refined {
    /// Whole grid-to-grid transform.
    pub transform: Similarity,
    /// Cluster-robust covariance of (scale, rotation_rad, dx, dy).
    pub covariance: Covariance4,
    /// Plain `σ²(JᵀWJ)⁻¹`, independent pixels.
    pub plain_covariance: Covariance4,
    pub gain: f64,
    pub offset: f64,
    /// Pixels used (non-zero weight) at the end.
    pub pixels: usize,
    /// Blocks (grid cells) that held them.
    pub blocks: usize,
    pub iterations: usize,
    pub converged: bool,
    /// Robust (MAD) σ of the intensity residuals.
    pub residual_sigma: f64,
    /// Robust σ of the residuals at the flattest quarter of the pixels, where the model's
    /// misfit is least (see [`noise_covariance`]).
    pub flat_residual_sigma: Option<f64>,
    /// The covariance that residual noise of unit σ gives through the M-estimator's exact
    /// slope, when [`RefineSettings::noise_covariance`] asks for it.
    pub noise_covariance: Option<Covariance4>,
}

/// The grid of cells the flow sampling used, over the bounding box of its mask
/// (`crate::sampling::grid_median_sample_cells`): cell column of each x, cell row of each y.
pub struct CellGrid {
    x0: usize,
    y0: usize,
    col_of: Vec<usize>,
    row_of: Vec<usize>,
    sample: usize,
}

impl CellGrid {
    /// The grid over the bounding box of `mask`, `sample × sample` cells.
    pub fn new(mask: ArrayView2<bool>, sample: usize) -> Option<CellGrid> {
        Some(CellGrid::over_box(
            crate::sampling::mask_bounding_box(mask)?,
            sample,
        ))
    }

    /// The grid over the box (x0, y0, x1, y1, inclusive), `sample × sample` cells.
    pub fn over_box(bbox: (usize, usize, usize, usize), sample: usize) -> CellGrid {
        let (x0, y0, x1, y1) = bbox;
        let sample = sample.max(1);
        let split = |lo: usize, hi: usize| -> Vec<usize> {
            let n = hi - lo + 1;
            let mut of = vec![0; n];
            for i in 0..sample {
                for o in &mut of[i * n / sample..(i + 1) * n / sample] {
                    *o = i;
                }
            }
            of
        };
        CellGrid {
            x0,
            y0,
            col_of: split(x0, x1.max(x0)),
            row_of: split(y0, y1.max(y0)),
            sample,
        }
    }

    /// Cell index (row-major) of a pixel; pixels outside the grid belong to the nearest cell.
    pub fn cell_of(&self, x: usize, y: usize) -> Option<usize> {
        let clamp = |v: usize, lo: usize, of: &[usize]| {
            of.get(v.saturating_sub(lo).min(of.len().saturating_sub(1)))
                .copied()
        };
        let c = clamp(x, self.x0, &self.col_of)?;
        let r = clamp(y, self.y0, &self.row_of)?;
        Some(r * self.sample + c)
    }

    /// The cell holding a (real-valued) sample point.
    pub fn cell_of_point(&self, p: &Correspondence) -> Option<usize> {
        if !(p.x >= 0.0 && p.y >= 0.0) {
            return None;
        }
        self.cell_of(p.x.round() as usize, p.y.round() as usize)
    }

    /// The 2 × 2 group of cells a cell belongs to.
    fn group_of(&self, cell: usize) -> usize {
        let (r, c) = (cell / self.sample, cell % self.sample);
        (r / 2) * self.sample.div_ceil(2) + c / 2
    }
}

/// Pixels of an `h × w` grid that are `usable`, inside the cells that hold at least one of
/// `inliers`, with their cell, on a regular lattice (every `k`-th row and column) that keeps
/// them to about `max`.
pub fn inlier_cell_pixels(
    (h, w): (usize, usize),
    usable: impl Fn(usize, usize) -> bool + Sync,
    grid: &CellGrid,
    inliers: &[Correspondence],
    max: usize,
) -> Vec<(usize, usize, usize)> {
    let mut keep = vec![false; grid.sample * grid.sample];
    for p in inliers {
        if let Some(c) = grid.cell_of_point(p) {
            keep[c] = true;
        }
    }
    lattice_pixels((h, w), usable, grid, max, |c| keep[c])
}

/// Usable pixels of an `h × w` grid in the cells `wanted`, thinned to a lattice of about `max`
/// of them. The lattice step is chosen from their count first (estimated on every second row
/// and column of a large grid), so that no full-size array is made.
fn lattice_pixels(
    (h, w): (usize, usize),
    usable: impl Fn(usize, usize) -> bool + Sync,
    grid: &CellGrid,
    max: usize,
    wanted: impl Fn(usize) -> bool + Sync,
) -> Vec<(usize, usize, usize)> {
    let take = |x: usize, y: usize| {
        if usable(x, y) {
            grid.cell_of(x, y).filter(|&c| wanted(c))
        } else {
            None
        }
    };
    let count_every = |step: usize| -> usize {
        (0..h)
            .into_par_iter()
            .step_by(step)
            .map(|y| {
                (0..w)
                    .step_by(step)
                    .filter(|&x| take(x, y).is_some())
                    .count()
            })
            .sum()
    };
    let count = if h * w <= 4 * max {
        count_every(1)
    } else {
        4 * count_every(2)
    };
    let k = lattice_step(count, max);
    (0..h)
        .into_par_iter()
        .step_by(k)
        .flat_map_iter(|y| {
            let take = &take;
            (0..w)
                .step_by(k)
                .filter_map(move |x| take(x, y).map(|c| (x, y, c)))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// Lattice step (every `k`-th row and column) that brings `count` pixels to at most about `max`.
fn lattice_step(count: usize, max: usize) -> usize {
    if count <= max {
        1
    } else {
        ((count as f64 / max.max(1) as f64).sqrt().ceil() as usize).max(2)
    }
}

/// One pixel of the fit: position, cell, reference value, and the reference's weighting
/// gradient and neighbour mean (the instruments of the geometric and gain equations).
struct Pixel {
    x: usize,
    y: usize,
    cell: usize,
    value: f64,
    gx: f64,
    gy: f64,
    neighbours: f64,
}

/// Iterations that may recompute the Tukey weights; later ones keep them. Reweighting to
/// convergence matters (AIA 171 128²: 16″ rotation RMSE after three, 8″ after ten; on TRACE
/// the reweighted estimate still moves by half of its previous step each time), but on real
/// pairs with evolving structure it never settles (IRIS 1400, four minutes apart: the estimate
/// wanders by its σ for as long as the weights change); with them fixed Gauss–Newton converges.
const REWEIGHTED_ITERATIONS: usize = 10;

/// Least `Σψ′/Σw` the covariance uses (0.83 for Gaussian residuals; lower with heavy tails):
/// a floor that keeps a nearly flat ψ′ from inflating the variance without bound.
const MIN_PSI_RATIO: f64 = 0.5;

/// Tukey biweight tuning constant (95 % efficiency for Gaussian residuals).
const TUKEY_C: f64 = 4.685;

/// Central-difference gradient of `img` at `(x, y)` (interior points only).
fn gradient(img: &ArrayView2<f32>, x: usize, y: usize) -> (f64, f64) {
    (
        (img[[y, x + 1]] as f64 - img[[y, x - 1]] as f64) / 2.0,
        (img[[y + 1, x]] as f64 - img[[y - 1, x]] as f64) / 2.0,
    )
}

/// Refine `start` (the whole grid-to-grid transform) on `pixels` (x, y, cell) of the reference
/// grid. `reference` is the reference as the flow stage saw it; `frame` the frame's spline.
///
/// The estimating equation is `Σ w·J_ref·r = 0` with `J_ref` built from the reference's
/// gradient (smoothed by `gradient_smoothing_px`: it only weighs the residuals, and a noisy
/// weight costs precision) and, for the gain, the mean of the reference's four neighbours.
/// Neither involves the pixel's own noise, nor the frame's: weighing the gain equation with the
/// noisy warped value itself biases the gain low (errors in variables, −2e-3 at 3× TRACE's
/// background noise), and through the gain's coupling with the geometry, the scale. Its slope,
/// which both the Newton step and the covariance need, is `A = Σ w·J_ref·J_frameᵀ` with the
/// warped frame's own gradient: with noisy images
/// `Σ J_ref J_refᵀ` overstates the slope by the gradient noise's variance (by 2× at 3×
/// TRACE's background noise), which would halve the σ and slow convergence.
pub fn refine(
    reference: &RefineReference,
    frame: &FrameWindow,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    start: Similarity,
    settings: &RefineSettings,
) -> Result<Refined, RefineFailure> {
    use RefineFailure::{RanOff, Unusable};
    // A failure on the first iteration is the start's pixels' (no structure, identical
    // images); on a later one, where the iterations went.
    let failed = |iterations: usize, why: &str| match iterations {
        1 => Unusable(why.to_string()),
        _ => RanOff(why.to_string()),
    };
    if pixels.len() < 64 {
        return Err(Unusable(format!(
            "{} usable pixels in the inlier cells; too few to refine",
            pixels.len()
        )));
    }
    let (h, w) = reference.smoothed.dim();
    let center = start.center;
    // The gain's instrument: the reference at four points far enough for the smoothed noise
    // to be uncorrelated with this pixel's (ρ = e^{−d²/4σ²} < 2 % at d = 4σ).
    let reach_gain = ((4.0 * reference.smoothing_px).ceil() as usize).max(1);
    let (smoothed, weighting) = (reference.smoothed.view(), reference.weighting());
    let ref_pixels: Vec<Pixel> = pixels
        .par_iter()
        .filter_map(|&(x, y, cell)| {
            if x < reach_gain || y < reach_gain || x + reach_gain >= w || y + reach_gain >= h {
                return None;
            }
            let value = smoothed[[y, x]] as f64;
            let (gx, gy) = gradient(&weighting, x, y);
            let d = reach_gain;
            let neighbours = (smoothed[[y, x - d]] as f64
                + smoothed[[y, x + d]] as f64
                + smoothed[[y - d, x]] as f64
                + smoothed[[y + d, x]] as f64)
                / 4.0;
            let finite = [value, gx, gy, neighbours].iter().all(|v| v.is_finite());
            finite.then_some(Pixel {
                x,
                y,
                cell,
                value,
                gx,
                gy,
                neighbours,
            })
        })
        .collect();
    if ref_pixels.len() < 64 {
        return Err(Unusable("too few finite reference pixels to refine".into()));
    }
    // Lever arm for conditioning: the scale/rotation columns are q/R.
    let lever = (sum_in_chunks(
        ref_pixels.len(),
        |range| {
            ref_pixels[range]
                .iter()
                .map(|p| (p.x as f64 - center[0]).powi(2) + (p.y as f64 - center[1]).powi(2))
                .sum::<f64>()
        },
        |a, b| a + b,
    ) / ref_pixels.len() as f64)
        .sqrt()
        .max(1.0);
    let rows = |gx: f64, gy: f64, qx: f64, qy: f64, v: f64| -> Vector6<f64> {
        Vector6::new(gx * qx + gy * qy, -gx * qy + gy * qx, gx, gy, v, 1.0)
    };
    let lever_arm = |p: &Pixel| {
        (
            (p.x as f64 - center[0]) / lever,
            (p.y as f64 - center[1]) / lever,
        )
    };
    // The instruments do not change between iterations.
    let jac: Vec<[f64; 6]> = ref_pixels
        .par_iter()
        .map(|p| {
            let (qx, qy) = lever_arm(p);
            rows(p.gx, p.gy, qx, qy, p.neighbours).into()
        })
        .collect();

    let mut estimate = start;
    let carried = frame.carried_positions(&ref_pixels);
    let carried = carried.as_deref();
    let mut sampled = frame.sample(&ref_pixels, carried, &estimate);
    let (mut gain, mut offset) = initial_photometry(&ref_pixels, &sampled);
    let mut iterations = 0;
    let mut residuals: Vec<f64> = vec![0.0; ref_pixels.len()];
    let mut weights: Vec<f64> = vec![0.0; ref_pixels.len()];
    let mut scale = f64::NAN;
    loop {
        iterations += 1;
        if iterations > 1 {
            sampled = frame.sample(&ref_pixels, carried, &estimate);
        }
        // The pixels were chosen to map inside the frame from the start: most of them
        // leaving it means the iterations ran away from the start (HMI 100² with a zero sky:
        // from a flow 4.5 px off, the gain turns negative and the estimate leaves the frame).
        let inside = sampled
            .par_iter()
            .filter(|s| s.iter().all(|v| v.is_finite()))
            .count();
        if 2 * inside < sampled.len() {
            return Err(RanOff(format!(
                "its estimate left the frame ({inside} of {} pixels map inside it)",
                sampled.len()
            )));
        }
        residuals
            .par_iter_mut()
            .zip(&ref_pixels)
            .zip(&sampled)
            .for_each(|((r, p), s)| *r = p.value - gain * s[0] - offset);
        // Iteratively reweighted for the first iterations, then with the weights frozen: on
        // real pairs (IRIS 1400 frames four minutes apart) reweighting every step keeps the
        // estimate wandering by about its σ, while with fixed weights Gauss–Newton converges.
        if iterations <= REWEIGHTED_ITERATIONS {
            scale = robust_sigma(&residuals)
                .ok_or_else(|| failed(iterations, "no finite residuals in the refinement"))?;
            if scale.is_nan() || scale <= 0.0 {
                return Err(failed(
                    iterations,
                    "the refinement's residuals vanish exactly; nothing to weigh",
                ));
            }
            weights
                .par_iter_mut()
                .zip(&residuals)
                .zip(&sampled)
                .for_each(|((w, r), s)| {
                    *w = if s.iter().all(|v| v.is_finite()) {
                        tukey_weight(*r, TUKEY_C * scale)
                    } else {
                        0.0
                    };
                });
        } else {
            weights.par_iter_mut().zip(&sampled).for_each(|(w, s)| {
                if !s.iter().all(|v| v.is_finite()) {
                    *w = 0.0;
                }
            });
        }
        // Its slope, `Σ w·J_ref·J_frameᵀ`, in fixed chunks summed in order (deterministic).
        let (slope, score) = sum_in_chunks(
            ref_pixels.len(),
            |range| {
                let mut slope = Matrix6::<f64>::zeros();
                let mut score = Vector6::<f64>::zeros();
                for k in range {
                    let wt = weights[k];
                    if wt <= 0.0 {
                        continue;
                    }
                    let (qx, qy) = lever_arm(&ref_pixels[k]);
                    let [v, fx, fy] = sampled[k];
                    let f = rows(gain * fx, gain * fy, qx, qy, v);
                    let jv = Vector6::from(jac[k]);
                    slope += jv * f.transpose() * wt;
                    score += jv * (wt * residuals[k]);
                }
                (slope, score)
            },
            |(a, b), (c, d)| (a + c, b + d),
        );
        let lu = slope.lu();
        let step = lu.solve(&score).ok_or_else(|| {
            failed(
                iterations,
                "the refinement's equations are singular (no structure)",
            )
        })?;
        let delta = [step[0] / lever, step[1] / lever, step[2], step[3]];
        let update = Similarity {
            scale: (1.0 + delta[0]).hypot(delta[1]),
            rotation_rad: delta[1].atan2(1.0 + delta[0]),
            dx: delta[2],
            dy: delta[3],
            center,
        };
        let moved = (delta[2].hypot(delta[3])) + delta[0].hypot(delta[1]) * lever * 2.0;
        if !moved.is_finite() {
            return Err(failed(iterations, "the refinement diverged"));
        }
        let converged = moved < settings.tolerance_px;
        tracing::trace!(iterations, moved, scale, "refinement step");
        if converged || iterations >= settings.max_iterations.max(1) {
            // Covariance at this linearisation point (the last step is below tolerance).
            let ainv = lu.try_inverse().ok_or_else(|| {
                failed(
                    iterations,
                    "the refinement's equations are singular (no structure)",
                )
            })?;
            // Per chunk: (used, Σw, Σψ′, Σw²JJᵀ, Σw·r²), summed in order.
            let (used, sum_w, sum_psi, white, s2) = sum_in_chunks(
                ref_pixels.len(),
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
            let frame_row = |k: usize| {
                let (qx, qy) = lever_arm(&ref_pixels[k]);
                let [v, fx, fy] = sampled[k];
                rows(gain * fx, gain * fy, qx, qy, v)
            };
            // The estimate's sensitivity to the data is that of the M-estimator `Σ ψ(r)·J = 0`
            // (the weights were set by these residuals): the slope weighs by ψ′, not by w.
            // Huber's scalar form, `w · Σψ′/Σw`, because per pixel ψ′ turns negative beyond
            // 0.45 c and makes the slope of small images nearly singular (EIT 128²: a few
            // trials' σ 30× too large).
            let psi_ratio = (sum_psi / sum_w).clamp(MIN_PSI_RATIO, 1.0);
            let fits = ClusterFit {
                jac: &jac,
                residuals: &residuals,
                weights: &weights,
                slope_per_weight: psi_ratio,
            };
            let cells = block_sums(&fits, frame_row, |k| ref_pixels[k].cell);
            let mut groups: std::collections::BTreeMap<usize, BlockSums> = Default::default();
            for (&cell, sums) in &cells {
                let g = groups.entry(grid.group_of(cell)).or_default();
                g.0 += sums.0;
                g.1 += sums.1;
            }
            let by_cell = cluster_covariance(&cells);
            let by_group = cluster_covariance(&groups);
            let (robust, blocks) = match (by_cell, by_group) {
                (Some(a), Some(b)) => {
                    if geometric_trace_ratio(&b.0, &a.0) > 1.0 {
                        b
                    } else {
                        a
                    }
                }
                (Some(a), None) | (None, Some(a)) => a,
                (None, None) => (plain, 1),
            };
            let noise = noise_covariance(
                &ref_pixels,
                &fits,
                frame_row,
                TUKEY_C * scale,
                settings.smoothing_px,
                settings.noise_covariance,
            );
            let flat_residual_sigma = noise.as_ref().map(|n| n.1);
            let final_t = estimate.after(&update);
            let to4 = |m: &Matrix6<f64>| -> Covariance4 {
                let unlever = [1.0 / lever, 1.0 / lever, 1.0, 1.0];
                std::array::from_fn(|i| {
                    std::array::from_fn(|j| m[(i, j)] * unlever[i] * unlever[j])
                })
            };
            let identity = Similarity::identity(center);
            let zero = [[0.0; 4]; 4];
            let (_, covariance) =
                compose_with_covariance(&final_t, &zero, &identity, &to4(&robust));
            let (_, plain_covariance) =
                compose_with_covariance(&final_t, &zero, &identity, &to4(&plain));
            let noise_covariance = noise
                .and_then(|n| n.0)
                .map(|unit| compose_with_covariance(&final_t, &zero, &identity, &to4(&unit)).1);
            return Ok(Refined {
                transform: final_t,
                covariance,
                plain_covariance,
                gain: gain + step[4],
                offset: offset + step[5],
                pixels: used,
                blocks,
                iterations,
                converged,
                residual_sigma: scale,
                flat_residual_sigma,
                noise_covariance,
            });
        }
        estimate = estimate.after(&update);
        gain += step[4];
        offset += step[5];
    }
}

/// `f` over consecutive chunks of `0..n` in parallel, combined in order with `add`: the same
/// sum whatever the thread count.
fn sum_in_chunks<T: Send>(
    n: usize,
    f: impl Fn(std::ops::Range<usize>) -> T + Sync,
    add: impl Fn(T, T) -> T,
) -> T {
    const CHUNK: usize = 1 << 14;
    let parts: Vec<T> = (0..n.div_ceil(CHUNK).max(1))
        .into_par_iter()
        .map(|c| f(c * CHUNK..((c + 1) * CHUNK).min(n)))
        .collect();
    let mut parts = parts.into_iter();
    let first = parts.next().expect("at least one chunk");
    parts.fold(first, add)
}

/// The reference as every refinement against it reads it, made once per reference: smoothed
/// by the refinement's `smoothing_px`, and the copy smoothed further whose gradient weighs
/// the residuals.
pub struct RefineReference {
    smoothed: Array2<f32>,
    /// `None` when no further smoothing is configured (the gradient is `smoothed`'s).
    weighting: Option<Array2<f32>>,
    smoothing_px: f64,
}

impl RefineReference {
    pub fn new(reference: ArrayView2<f32>, settings: &RefineSettings) -> RefineReference {
        let smoothed = crate::preprocess::gaussian_smooth(reference, settings.smoothing_px);
        let weighting = (settings.gradient_smoothing_px > 0.0).then(|| {
            crate::preprocess::gaussian_smooth(smoothed.view(), settings.gradient_smoothing_px)
        });
        RefineReference {
            smoothed,
            weighting,
            smoothing_px: settings.smoothing_px.max(0.0),
        }
    }

    fn weighting(&self) -> ArrayView2<'_, f32> {
        self.weighting.as_ref().unwrap_or(&self.smoothed).view()
    }
}

/// The refinement's model of the frame between its samples: a quintic B-spline. A real frame
/// is a new sampling of the sky, band-limited by the optics, and a spline moves structure near
/// the Nyquist frequency differently from it: for a Fourier (band-limited) shift of TRACE
/// 1024², the cubic spline's answer is 3–6e-4 px off, the quintic's about 4× less
/// (`tools/other_instruments/fourier_shifts.py`). It costs 36 taps per sample against 16.
pub const MODEL: HighOrder = HighOrder::Quintic;

/// The frame as the refinement compares it: smoothed, prefiltered for spline sampling, on
/// the window of its grid that the pixels map into. Smoothing before the warp instead of
/// after is the same to first order in the scale change (a Gaussian is isotropic), and lets
/// every iteration sample only the pixels the fit uses instead of warping the whole box.
pub struct FrameWindow {
    /// One tile for a pair's refinement; several, far apart, for a self-test on tiles.
    tiles: Vec<WindowTile>,
    /// The Sun's motion between the two times: pixels are sampled at `T(S(p))`.
    carried: Option<super::derotate::Carried>,
}

/// A part of the frame, prefiltered for spline sampling.
struct WindowTile {
    spline: HighOrderSpline,
    /// Frame-grid position of the tile's first column and row.
    origin: [f64; 2],
    /// Frame-grid position of its last column and row.
    end: [f64; 2],
}

impl WindowTile {
    /// How far `(x, y)` lies inside the tile, px (negative outside).
    fn depth(&self, x: f64, y: f64) -> f64 {
        (x - self.origin[0])
            .min(self.end[0] - x)
            .min(y - self.origin[1])
            .min(self.end[1] - y)
    }
}

/// Pixels sampled per task.
const SAMPLE_CHUNK: usize = 4096;

/// Room around the pixels' image in the frame: the smoothing's reach, the model spline's
/// support (3 px) and prefilter border transient (0.431^17 < 1e-6), and the motion of the
/// iterations.
fn window_margin(sigma_px: f64) -> f64 {
    (gaussian_reach(sigma_px) + 3 + 17 + 8) as f64
}

impl FrameWindow {
    /// The part of `frame` that the pixels in `bbox` (reference grid) map into through `t`,
    /// smoothed by `sigma_px`; `None` when that lies outside the frame.
    pub fn new(
        frame: ArrayView2<f32>,
        bbox: (usize, usize, usize, usize),
        t: &Similarity,
        sigma_px: f64,
        carried: Option<&super::derotate::Carried>,
    ) -> Option<FrameWindow> {
        let (h, w) = frame.dim();
        let moved = carried.map_or(0.0, |c| c.max_px.ceil());
        let (x0, y0, x1, y1) = mapped_window(bbox, t, window_margin(sigma_px) + moved, w, h)?;
        let smoothed =
            crate::preprocess::gaussian_smooth(frame.slice(s![y0..=y1, x0..=x1]), sigma_px);
        Some(FrameWindow {
            tiles: vec![WindowTile {
                spline: HighOrderSpline::new(smoothed.view(), MODEL),
                origin: [x0 as f64, y0 as f64],
                end: [x1 as f64, y1 as f64],
            }],
            carried: carried.cloned(),
        })
    }

    /// Where the Sun carried each pixel (`None`: no rotation to follow); the same for every
    /// iteration.
    fn carried_positions(&self, pixels: &[Pixel]) -> Option<Vec<(f64, f64)>> {
        let c = self.carried.as_ref()?;
        Some(
            pixels
                .par_iter()
                .map(|p| c.at(p.x as f64, p.y as f64))
                .collect(),
        )
    }

    /// The tile that frame position `p` lies deepest in.
    fn tile_of(&self, p: [f64; 2]) -> usize {
        if self.tiles.len() == 1 {
            return 0;
        }
        let depth = |k: usize| self.tiles[k].depth(p[0], p[1]);
        (1..self.tiles.len()).fold(0, |best, k| if depth(k) > depth(best) { k } else { best })
    }

    /// Value and reference-grid gradient of the frame at the image of each pixel through `t`
    /// (of each pixel's carried position, when given).
    fn sample(
        &self,
        pixels: &[Pixel],
        carried: Option<&[(f64, f64)]>,
        t: &Similarity,
    ) -> Vec<[f64; 3]> {
        let (a, b) = t.ab();
        let map = crate::resample::similarity_map(t);
        let mut out = vec![[0.0; 3]; pixels.len()];
        out.par_chunks_mut(SAMPLE_CHUNK)
            .zip(pixels.par_chunks(SAMPLE_CHUNK))
            .enumerate()
            .for_each(|(k, (out, pixels))| {
                let moved = carried.map(|c| &c[k * SAMPLE_CHUNK..]);
                let mut positions: Vec<[f64; 2]> = pixels
                    .iter()
                    .enumerate()
                    .map(|(i, p)| {
                        let (px, py) = moved.map_or((p.x as f64, p.y as f64), |m| m[i]);
                        let (x, y) = map(px, py);
                        [x, y]
                    })
                    .collect();
                // Runs of positions in one tile, each sampled from the tile it lies deepest in.
                let mut start = 0;
                while start < positions.len() {
                    let tile = self.tile_of(positions[start]);
                    let mut stop = start + 1;
                    while stop < positions.len() && self.tile_of(positions[stop]) == tile {
                        stop += 1;
                    }
                    let t = &self.tiles[tile];
                    for q in &mut positions[start..stop] {
                        *q = [q[0] - t.origin[0], q[1] - t.origin[1]];
                    }
                    t.spline
                        .sample_with_gradient_at(&positions[start..stop], &mut out[start..stop]);
                    start = stop;
                }
                for s in out.iter_mut() {
                    let [v, fx, fy] = *s;
                    // ∇(frame ∘ T) = Jᵀ ∇frame with J = [[a, −b], [b, a]].
                    *s = [v, a * fx + b * fy, -b * fx + a * fy];
                }
            });
        out
    }
}

/// Bounding box (inclusive) on a `w × h` grid of the image of `bbox` through `t`, grown by
/// `margin`; `None` when it misses the grid or the transform is not finite.
fn mapped_window(
    bbox: (usize, usize, usize, usize),
    t: &Similarity,
    margin: f64,
    w: usize,
    h: usize,
) -> Option<(usize, usize, usize, usize)> {
    let (bx0, by0, bx1, by1) = bbox;
    let corners = [(bx0, by0), (bx1, by0), (bx0, by1), (bx1, by1)]
        .map(|(x, y)| t.apply([x as f64, y as f64]));
    if corners.iter().flatten().any(|v| !v.is_finite()) || w < 8 || h < 8 {
        return None;
    }
    let lo = |k: usize| corners.iter().map(|c| c[k]).fold(f64::INFINITY, f64::min) - margin;
    let hi = |k: usize| {
        corners
            .iter()
            .map(|c| c[k])
            .fold(f64::NEG_INFINITY, f64::max)
            + margin
    };
    let (x0, x1) = (lo(0).floor().max(0.0), hi(0).ceil().min(w as f64 - 1.0));
    let (y0, y1) = (lo(1).floor().max(0.0), hi(1).ceil().min(h as f64 - 1.0));
    (x1 - x0 >= 8.0 && y1 - y0 >= 8.0).then_some((
        x0 as usize,
        y0 as usize,
        x1 as usize,
        y1 as usize,
    ))
}

/// Gain and offset of the sampled frame against the reference (least squares over the pixels).
fn initial_photometry(pixels: &[Pixel], sampled: &[[f64; 3]]) -> (f64, f64) {
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

/// What the cluster-robust covariance needs of a converged fit: per pixel the instruments
/// `J`, residuals `r` and weights `w` (the score is `Σ w·r·J`), and the factor that turns a
/// weight into the slope of the weighted residual (the sensitivity is `Σ factor·w·J·Fᵀ`).
struct ClusterFit<'a> {
    jac: &'a [[f64; 6]],
    residuals: &'a [f64],
    weights: &'a [f64],
    slope_per_weight: f64,
}

/// Cluster-robust covariance, jackknife form (CR3): `(G−1)/G · Σ_b d_b d_bᵀ` with
/// `d_b = (A − A_b)⁻¹ s_b`, the change of the estimate when block `b` is left out, where
/// `s_b = Σ_{i∈b} w_i r_i J_i` is the block's score, `A = Σ ψ′_i J_i F_iᵀ` the M-estimator's
/// slope and `A_b` the block's share of it. On solar images a few blocks (active regions)
/// hold most of the structure; the plain sandwich `A⁻¹ Σ s_b s_bᵀ A⁻ᵀ` then understates the
/// variance (on the noisy TRACE Monte Carlo by 1.3–1.4× in σ), because each dominant block
/// pulls the fit towards itself and its residuals look smaller than its errors. The slope
/// must follow ψ′ = (1 − u²)(1 − 5u²), not the weight w = (1 − u²)²: the weights follow the
/// residuals, and for Gaussian residuals E[w]/E[ψ′] = 1.21, the σ deficit the noisy Monte
/// Carlo shows with `w` (RMS of error/σ 1.20–1.25). `None` with fewer than 8 blocks.
fn cluster_covariance(
    blocks: &std::collections::BTreeMap<usize, BlockSums>,
) -> Option<(Matrix6<f64>, usize)> {
    let g = blocks.len();
    if g < 8 {
        return None;
    }
    let slope: Matrix6<f64> = blocks.values().map(|(_, share)| share).sum();
    let mut sum = Matrix6::<f64>::zeros();
    for (score, share) in blocks.values() {
        let d = (slope - share).lu().solve(score)?;
        sum += d * d.transpose();
    }
    let factor = (g as f64 - 1.0) / g as f64;
    Some((sum * factor, g))
}

/// A block's score `Σ w·r·J` and its share `Σ ψ′·J·Fᵀ` of the slope.
type BlockSums = (Vector6<f64>, Matrix6<f64>);

/// The score and slope share of every block (`block_of` each pixel), summed over pixels in
/// parallel chunks, in order.
fn block_sums(
    fit: &ClusterFit,
    frame_row: impl Fn(usize) -> Vector6<f64> + Sync,
    block_of: impl Fn(usize) -> usize + Sync,
) -> std::collections::BTreeMap<usize, BlockSums> {
    type Blocks = std::collections::BTreeMap<usize, BlockSums>;
    sum_in_chunks(
        fit.jac.len(),
        |range| {
            let mut blocks = Blocks::new();
            // Pixels come in runs of the same block: add each run's sum once.
            let mut current: Option<(usize, BlockSums)> = None;
            for k in range {
                let (r, w) = (fit.residuals[k], fit.weights[k]);
                if !(w > 0.0 && r.is_finite()) {
                    continue;
                }
                let b = block_of(k);
                if current.as_ref().is_some_and(|(cb, _)| *cb != b) {
                    let (cb, sums) = current.take().expect("checked");
                    let e = blocks.entry(cb).or_default();
                    e.0 += sums.0;
                    e.1 += sums.1;
                }
                let (_, sums) = current.get_or_insert_with(|| (b, Default::default()));
                let jv = Vector6::from(fit.jac[k]);
                sums.0 += jv * (w * r);
                sums.1 += jv * frame_row(k).transpose() * (w * fit.slope_per_weight);
            }
            if let Some((cb, sums)) = current {
                let e = blocks.entry(cb).or_default();
                e.0 += sums.0;
                e.1 += sums.1;
            }
            blocks
        },
        |mut a, b| {
            for (k, (s, m)) in b {
                let e = a.entry(k).or_default();
                e.0 += s;
                e.1 += m;
            }
            a
        },
    )
}

/// The estimate's covariance from residual noise of unit σ, through the M-estimator's exact
/// slope: `A⁻¹·B·A⁻ᵀ` with `A = Σ ψ′·J·Fᵀ` and `B = Σᵢ Σⱼ ρᵢⱼ ψ′ᵢψ′ⱼ Jᵢ Jⱼᵀ`, ρ the
/// correlation exp(−d²/4s²) of white noise smoothed by `smoothing_px`. Tukey's weights follow
/// the residuals, so pixels whose misfit puts them on its descending side (ψ′ < 0: the limb of
/// an undersampled disk) make the answer more sensitive to the noise than the weights say.
/// First, the robust σ of the residuals at the flattest quarter of the pixels, where the
/// model's misfit is least; the covariance only `with_covariance` (and not with a singular
/// slope). `None` with too few pixels.
fn noise_covariance(
    pixels: &[Pixel],
    fit: &ClusterFit,
    frame_row: impl Fn(usize) -> Vector6<f64> + Sync,
    tukey_c: f64,
    smoothing_px: f64,
    with_covariance: bool,
) -> Option<(Option<Matrix6<f64>>, f64)> {
    let (jac, residuals, weights) = (fit.jac, fit.residuals, fit.weights);
    let counts = |k: usize| weights[k] > 0.0 && residuals[k].is_finite();
    let used: Vec<usize> = (0..pixels.len()).filter(|&k| counts(k)).collect();
    if used.len() < 64 {
        return None;
    }
    let gradient = |k: usize| pixels[k].gx.hypot(pixels[k].gy);
    let mut gradients: Vec<f64> = used.iter().map(|&k| gradient(k)).collect();
    let (_, &mut flattest, _) = gradients.select_nth_unstable_by(used.len() / 4, f64::total_cmp);
    let flat: Vec<f64> = used
        .iter()
        .filter(|&&k| gradient(k) <= flattest)
        .map(|&k| residuals[k])
        .collect();
    let flat_sigma = robust_sigma(&flat)?;
    if !with_covariance {
        return Some((None, flat_sigma));
    }
    let u: Vec<Vector6<f64>> = (0..pixels.len())
        .map(|k| match counts(k) {
            true => Vector6::from(jac[k]) * tukey_psi_slope(residuals[k], tukey_c),
            false => Vector6::zeros(),
        })
        .collect();
    // Summed in fixed chunks, in order: the same σ whatever the thread count.
    let slope = sum_in_chunks(
        used.len(),
        |range| {
            used[range].iter().fold(Matrix6::zeros(), |acc, &k| {
                let psi = tukey_psi_slope(residuals[k], tukey_c);
                acc + Vector6::from(jac[k]) * frame_row(k).transpose() * psi
            })
        },
        |a, b| a + b,
    );
    // The pixels lie on a lattice of every `step`-th row and column.
    let step = pixels
        .windows(2)
        .filter(|p| p[0].y == p[1].y && p[1].x > p[0].x)
        .map(|p| p[1].x - p[0].x)
        .min()
        .unwrap_or(1);
    let (gw, gh) = (
        pixels.iter().map(|p| p.x).max()? / step + 1,
        pixels.iter().map(|p| p.y).max()? / step + 1,
    );
    let mut index = Array2::<u32>::from_elem((gh, gw), u32::MAX);
    for (k, p) in pixels.iter().enumerate() {
        index[[p.y / step, p.x / step]] = k as u32;
    }
    let s = smoothing_px.max(0.1);
    let reach = (3.0 * std::f64::consts::SQRT_2 * s / step as f64).ceil() as isize;
    let side = (2 * reach + 1) as usize;
    let correlation: Vec<f64> = (0..side * side)
        .map(|t| {
            let (dx, dy) = ((t % side) as isize - reach, (t / side) as isize - reach);
            let d2 = ((dx * dx + dy * dy) as usize * step * step) as f64;
            (-d2 / (4.0 * s * s)).exp()
        })
        .collect();
    let near_product = |i: usize| {
        let (cx, cy) = ((pixels[i].x / step) as isize, (pixels[i].y / step) as isize);
        let mut near = Vector6::<f64>::zeros();
        for dy in -reach..=reach {
            for dx in -reach..=reach {
                let (x, y) = (cx + dx, cy + dy);
                if x < 0 || y < 0 || x >= gw as isize || y >= gh as isize {
                    continue;
                }
                let j = index[[y as usize, x as usize]];
                if j != u32::MAX {
                    let t = (dy + reach) as usize * side + (dx + reach) as usize;
                    near += u[j as usize] * correlation[t];
                }
            }
        }
        u[i] * near.transpose()
    };
    let meat = sum_in_chunks(
        used.len(),
        |range| {
            used[range]
                .iter()
                .fold(Matrix6::zeros(), |acc, &i| acc + near_product(i))
        },
        |a, b| a + b,
    );
    let meat = (meat + meat.transpose()) * 0.5;
    let covariance = slope
        .try_inverse()
        .map(|inverse| inverse * meat * inverse.transpose());
    Some((covariance, flat_sigma))
}

/// Geometric mean of the ratios of the four geometric variances, `b` over `a`.
fn geometric_trace_ratio(b: &Matrix6<f64>, a: &Matrix6<f64>) -> f64 {
    ((0..4)
        .map(|k| (b[(k, k)].max(f64::MIN_POSITIVE) / a[(k, k)].max(f64::MIN_POSITIVE)).ln())
        .sum::<f64>()
        / 4.0)
        .exp()
}

/// Slope of Tukey's ψ(r) = r·w(r): (1 − u²)(1 − 5u²) with u = r/c, zero beyond c.
fn tukey_psi_slope(r: f64, c: f64) -> f64 {
    let u2 = (r / c).powi(2);
    if !u2.is_finite() || u2 >= 1.0 {
        0.0
    } else {
        (1.0 - u2) * (1.0 - 5.0 * u2)
    }
}

fn tukey_weight(r: f64, c: f64) -> f64 {
    if !r.is_finite() {
        return 0.0;
    }
    let u = r / c;
    if u.abs() >= 1.0 {
        0.0
    } else {
        (1.0 - u * u).powi(2)
    }
}

/// 1.4826 × median absolute deviation about the median, over the finite values.
fn robust_sigma(values: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = values
        .par_iter()
        .copied()
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    let median = crate::stats::par_select(&v, mid);
    v.par_iter_mut().for_each(|x| *x = (*x - median).abs());
    let mad = crate::stats::par_select(&v, mid);
    Some(1.482_602_218_505_602 * mad)
}

/// The refinement's settings under `cfg`, for a frame smoothed by `frame_smoothing_px` to
/// match the reference's resolution.
pub fn settings(cfg: &super::EngineConfig, frame_smoothing_px: f64) -> RefineSettings {
    RefineSettings {
        smoothing_px: cfg.refine_smoothing_px,
        gradient_smoothing_px: cfg.refine_gradient_smoothing_px,
        frame_smoothing_px,
        ..RefineSettings::default()
    }
}

/// Whether the refinement runs for this pair.
pub fn wanted(
    mode: RefineMode,
    reference: &crate::meta::FrameMeta,
    frame: &crate::meta::FrameMeta,
) -> bool {
    match mode {
        RefineMode::Off => false,
        RefineMode::Always => true,
        RefineMode::SameChannel => reference.channel == frame.channel,
    }
}

/// Refine the flow stage's `transform` in place (and its `covariance`), or leave both as they
/// are when the refinement is not possible or disagrees with the flow. `flow_slack_px` is
/// how far the flow's answer may be from its converged value (0 when it converged; a seed
/// finished on a coarse level is further). Returns a note for the result's message: `Ok`
/// when the refinement's answer was taken, `Err` when the flow's stands.
#[allow(clippy::too_many_arguments)]
pub fn apply(
    transform: &mut Similarity,
    covariance: &mut Covariance4,
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    frame: ArrayView2<f32>,
    mask: &Array2<bool>,
    sample_box: Option<(usize, usize, usize, usize)>,
    inliers: &[Correspondence],
    frame_smoothing_px: f64,
    blur: Option<crate::blur::BlurDifference>,
    flow_slack_px: f64,
    carried: Option<&super::derotate::Carried>,
    self_test: impl FnOnce(&RefineSettings) -> Option<SelfTest>,
    cfg: &super::EngineConfig,
) -> Result<String, Rejected> {
    let Some(sample_box) = sample_box else {
        return Err(Rejected::skipped(
            "intensity refinement skipped: empty sampling mask",
        ));
    };
    let grid = CellGrid::over_box(sample_box, cfg.sample);
    let base_settings = settings(cfg, frame_smoothing_px);
    // A blur difference the model cannot absorb: the sharper image is blurred to the other's.
    let BlurMatch {
        reference_extra,
        frame_smoothing_px,
        uncertainty_px2: blur_uncertainty,
    } = blur_matching(blur, frame_smoothing_px, base_settings.smoothing_px);
    let blurred_reference;
    let (prepared, settings) = if reference_extra > 0.0 {
        let settings = RefineSettings {
            smoothing_px: base_settings.smoothing_px.hypot(reference_extra),
            ..base_settings
        };
        blurred_reference = RefineReference::new(reference, &settings);
        (&blurred_reference, settings)
    } else {
        (prepared, base_settings)
    };
    let frame_sigma = base_settings.smoothing_px.hypot(frame_smoothing_px);
    let margin = gaussian_reach(frame_sigma.max(settings.smoothing_px)) + 3;
    let region = refinement_region(mask, reference, frame, transform, carried, margin);
    let pixels = inlier_cell_pixels(
        reference.dim(),
        |x, y| region.usable(x, y),
        &grid,
        inliers,
        MAX_PIXELS,
    );
    drop(region);
    let Some(bbox) = pixel_box(&pixels) else {
        return Err(Rejected::skipped(
            "intensity refinement skipped: no pixels in the inlier cells",
        ));
    };
    let started = std::time::Instant::now();
    let Some(window) = FrameWindow::new(frame, bbox, transform, frame_sigma, carried) else {
        return Err(Rejected::skipped(
            "intensity refinement skipped: the pixels map outside the frame",
        ));
    };
    let window_at = started.elapsed();
    let pair_settings = RefineSettings {
        noise_covariance: true,
        ..settings
    };
    let refined = match refine(
        prepared,
        &window,
        &pixels,
        &grid,
        *transform,
        &pair_settings,
    ) {
        Ok(r) => r,
        Err(RefineFailure::Unusable(e)) => {
            return Err(Rejected::skipped(format!(
                "intensity refinement skipped: {e}"
            )))
        }
        Err(RefineFailure::RanOff(e)) => {
            return Err(Rejected::ran_off(format!(
                "intensity refinement ran off: {e}"
            )))
        }
    };
    tracing::debug!(
        flow = ?transform.params(),
        refined = ?refined.transform.params(),
        flow_sigma = ?crate::geometry::sigmas(covariance),
        robust_sigma = ?crate::geometry::sigmas(&refined.covariance),
        plain_sigma = ?crate::geometry::sigmas(&refined.plain_covariance),
        refined.blocks, refined.pixels, refined.iterations, refined.converged, refined.gain,
        refined.residual_sigma,
        ?window_at,
        refined_at = ?started.elapsed(),
        "intensity refinement"
    );
    let mut cov = match cfg.sigma {
        super::SigmaMethod::Calibrated => refined.covariance,
        super::SigmaMethod::Uabjm => refined.plain_covariance,
    };
    let mut note = String::new();
    // What the agreement test below weighs: the σ with the floor but not the interpolation
    // check. The check bounds how far the model may be from frames made otherwise; taken as
    // agreement, it would let a cubic model's refinement 9e-3 px off replace a flow 2e-3 px off
    // (HMI continuum, 8-bit, Fourier-shifted).
    let mut agreement_cov = cov;
    if cfg.sigma == super::SigmaMethod::Calibrated {
        // The method's systematic floor for this reference, measured once per reference;
        // without it, the configured floor.
        let self_tested = self_test(&base_settings);
        let floor = self_tested.map(|t| t.floor);
        tracing::debug!(self_tested_at = ?started.elapsed(), "refinement self-test");
        if let Some(factors) = noise_factors(&refined, self_tested, &agreement_cov) {
            tracing::debug!(?factors, "σ raised to the residual noise's");
            for i in 0..4 {
                for j in 0..4 {
                    agreement_cov[i][j] *= factors[i] * factors[j];
                }
            }
        }
        let check_pixels = central_pixels(&pixels, bbox, CHECK_MAX_SIDE);
        let check = interpolation_check(
            reference,
            prepared,
            &check_pixels,
            &grid,
            &refined.transform,
            &settings,
        );
        let blur_term = blur_uncertainty.and_then(|mismatch| {
            blur_check(
                reference,
                prepared,
                &check_pixels,
                &grid,
                &refined.transform,
                &settings,
                mismatch,
            )
        });
        if let Some(b) = blur_term {
            for (k, bk) in b.iter().enumerate() {
                agreement_cov[k][k] += bk * bk;
            }
        }
        // Both measure the interpolation error beyond the σ: the floor as a typical frame's,
        // this frame's transform as it is. Summed, they count it twice (EIT 171 128²: 97 % of
        // trials within 1σ in scale); the larger stands.
        match floor {
            Some(f) => {
                for (k, b) in f.iter().enumerate() {
                    agreement_cov[k][k] += b * b;
                }
            }
            None => super::sigma::add_floor(
                &mut agreement_cov,
                inliers,
                transform.center,
                cfg.systematic_floor_px,
            ),
        }
        cov = agreement_cov;
        if let Some(c) = check {
            for (k, ck) in c.iter().enumerate() {
                let fk = floor.map_or(0.0, |f| f[k]);
                cov[k][k] += ck.max(fk).powi(2) - fk * fk;
            }
        }
        let show = |t: Option<[f64; 4]>, failed: &str| {
            t.map_or(failed.to_string(), |t| {
                format!(
                    "{:.1e} / {:.3}″ / {:.1e} / {:.1e}",
                    t[0],
                    t[1] * crate::geometry::ARCSEC_PER_RAD,
                    t[2],
                    t[3]
                )
            })
        };
        note = format!(
            ", self-test floor {}, interpolation check {}{}",
            show(floor, "failed (configured floor)"),
            show(check, "failed"),
            blur_term.map_or(String::new(), |b| format!(
                ", blur check {}",
                show(Some(b), "")
            ))
        );
        tracing::debug!(checked_at = ?started.elapsed(), "interpolation check");
    }
    // Both answers measure the same motion; a large disagreement means the intensities do not
    // follow one similarity (changed scene, different channels): keep the flow's.
    let (a, b) = (transform.params(), refined.transform.params());
    let mut flow_cov = *covariance;
    super::sigma::add_floor(&mut flow_cov, inliers, transform.center, flow_slack_px);
    let (sa, sb) = (
        crate::geometry::sigmas(&flow_cov),
        crate::geometry::sigmas(&agreement_cov),
    );
    let worst = (0..4)
        .map(|k| (a[k] - b[k]).abs() / sa[k].hypot(sb[k]).max(f64::MIN_POSITIVE))
        .fold(0.0, f64::max);
    // A refinement that ran off (IRIS 1400 frames 50→52: scale 0.48 and a 17° turn from a flow
    // at 1.006 ± 0.003) reports σ so large that it "agrees" with anything. Gauss–Newton on
    // intensities is a sub-pixel method: σ beyond a pixel say it is outside its basin.
    let widest = sb[2].max(sb[3]);
    if widest.is_nan() || widest > MAX_REFINED_SIGMA_PX {
        return Err(Rejected::ran_off(format!(
            "intensity refinement rejected: its σ reach {widest:.2} px"
        )));
    }
    if worst.is_nan() || worst > MAX_DISAGREEMENT_SIGMA {
        return Err(Rejected {
            note: format!("intensity refinement rejected: {worst:.1}σ from the flow's answer"),
            disagreeing: (!worst.is_nan() && refined.converged).then_some(refined.transform),
            ran_off: false,
        });
    }
    if !refined.converged {
        return Err(Rejected::skipped(format!(
            "intensity refinement rejected: not converged in {} iterations",
            refined.iterations
        )));
    }
    *transform = refined.transform;
    *covariance = cov;
    let matched = match (blur, blur_uncertainty) {
        (Some(b), Some(u)) => format!(
            ", blur matched (frame blurrier by {:.3} ± {u:.3} px²)",
            b.variance_px2 + base_settings.frame_smoothing_px.powi(2),
        ),
        _ => String::new(),
    };
    Ok(format!(
        "intensity refinement on {} px in {} blocks, {} iterations{matched}{note}",
        refined.pixels, refined.blocks, refined.iterations
    ))
}

/// Smallest blur difference matched, as a fraction of the refinement's smoothing variance:
/// below it, what a difference does is within the noise-free σ (on a 512² TRACE crop the
/// answer moves by about 5e-3 px per px² of difference).
const MIN_MATCHED_BLUR_FRACTION: f64 = 0.02;

/// Standard errors a blur difference must exceed to be matched. Not 3: the Hann window
/// correlates neighbouring frequency bins, so the fit's scatter understates its error.
const MIN_BLUR_SIGNIFICANCE: f64 = 5.0;

/// How the sharper image is blurred to the other's, and how uncertain that is. A difference
/// (the frame's resolution-matching smoothing included) is matched when it is beyond
/// [`MIN_BLUR_SIGNIFICANCE`] standard errors and [`MIN_MATCHED_BLUR_FRACTION`] of the
/// smoothing variance.
fn blur_matching(
    blur: Option<crate::blur::BlurDifference>,
    frame_smoothing_px: f64,
    smoothing_px: f64,
) -> BlurMatch {
    let unmatched = BlurMatch {
        reference_extra: 0.0,
        frame_smoothing_px,
        uncertainty_px2: None,
    };
    let Some(b) = blur else {
        return unmatched;
    };
    // The frame's resolution-matching smoothing is part of its blur.
    let excess = b.variance_px2 + frame_smoothing_px * frame_smoothing_px;
    let significant = excess.abs() > MIN_BLUR_SIGNIFICANCE * b.sigma_px2
        && excess.abs() > MIN_MATCHED_BLUR_FRACTION * smoothing_px * smoothing_px;
    if !significant || !excess.is_finite() {
        return unmatched;
    }
    let uncertainty_px2 = Some(
        (BLUR_SIGMA_UNDERSTATEMENT * b.sigma_px2)
            .hypot(BLUR_SYSTEMATIC_FRACTION * excess)
            .hypot(b.shape_px2),
    );
    if excess > 0.0 {
        BlurMatch {
            reference_extra: excess.sqrt(),
            frame_smoothing_px,
            uncertainty_px2,
        }
    } else {
        BlurMatch {
            reference_extra: 0.0,
            frame_smoothing_px: (-b.variance_px2).max(0.0).sqrt(),
            uncertainty_px2,
        }
    }
}

/// How a blur difference is matched.
#[derive(Debug, Clone, Copy, PartialEq)]
struct BlurMatch {
    /// σ of the Gaussian added to the reference, px (0: none).
    reference_extra: f64,
    /// The frame's smoothing σ, px.
    frame_smoothing_px: f64,
    /// 1-σ error of the matched difference, px² (`None`: nothing matched).
    uncertainty_px2: Option<f64>,
}

/// The fit's standard error understates the blur difference's: neighbouring frequency bins
/// are correlated through the window.
const BLUR_SIGMA_UNDERSTATEMENT: f64 = 2.0;
/// And the spectra carry errors proportional to it: a 0.8 px Gaussian on the TRACE crop reads
/// 0.629 px² for 0.640, and one on a copy with its noise blurred too reads 2–3 % over.
const BLUR_SYSTEMATIC_FRACTION: f64 = 0.03;

/// What a blur left unmatched by `mismatch_px2` does to the answer, per parameter: a frame
/// made from the reference by the refinement's own interpolator through `transform` and
/// blurred by that much more is refined from the exact answer.
fn blur_check(
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
        settings,
        mismatch_px2.max(0.0).sqrt(),
        FrameMaker::Model,
    )?;
    tracing::debug!(bias = ?test.bias, mismatch_px2, "blur check");
    Some(test.bias.map(f64::abs))
}

/// A self-test at `transform` with its shift reduced to the fractional part (the same
/// sub-pixel positions, and a synthetic frame that stays inside the reference), its frame
/// smoothed by `frame_smoothing_px` beyond the reference's.
#[allow(clippy::too_many_arguments)]
fn check_at_fractional_shift(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    pixels: &[(usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
    frame_smoothing_px: f64,
    maker: FrameMaker,
) -> Option<SelfTestCase> {
    let settings = RefineSettings {
        frame_smoothing_px,
        ..*settings
    };
    let local = Similarity {
        dx: transform.dx - transform.dx.round(),
        dy: transform.dy - transform.dy.round(),
        ..*transform
    };
    let whole = [pixel_box(pixels)?];
    self_test_bias(
        reference, prepared, pixels, &whole, grid, &local, &settings, maker,
    )
}

/// Factors (1 to 2) that raise each geometric σ of `cov` to what the residuals' noise gives
/// through the exact slope. The noise is the part of the residual level at the flattest
/// pixels that the model's misfit alone (the self-test's, noise-free by construction) does
/// not explain; `None` when there is none or nothing to measure it with.
fn noise_factors(
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
const MAX_NOISE_INFLATION: f64 = 1.0 / MIN_PSI_RATIO;

/// Reference pixels the refinement may use: inside `mask`, with a finite reference, and at
/// least `margin` px (the smoothing's and the spline's reach) from the edges of both images
/// (the frame's through `t`) and from the frame's blanks. This is wider than the flow's
/// sample mask, which keeps half a window (60 px and more) from every edge: scale and
/// rotation are measured best at the largest lever arm.
struct RefinementRegion<'a, M: Fn(f64, f64) -> (f64, f64)> {
    mask: &'a Array2<bool>,
    reference: ArrayView2<'a, f32>,
    frame_dim: (usize, usize),
    /// Frame pixels at least `margin` from any blank (`None`: the frame has none).
    frame_blank_free: Option<Array2<bool>>,
    map: M,
    margin: f64,
}

fn refinement_region<'a>(
    mask: &'a Array2<bool>,
    reference: ArrayView2<'a, f32>,
    frame: ArrayView2<f32>,
    t: &Similarity,
    carried: Option<&'a super::derotate::Carried>,
    margin: usize,
) -> RefinementRegion<'a, impl Fn(f64, f64) -> (f64, f64) + 'a> {
    let frame_blank_free = if crate::stats::all_finite(frame) {
        None
    } else {
        Some(super::erode(&frame.mapv(f32::is_finite), margin))
    };
    RefinementRegion {
        mask,
        reference,
        frame_dim: frame.dim(),
        frame_blank_free,
        map: {
            let map = crate::resample::similarity_map(t);
            move |x, y| {
                let (sx, sy) = carried.map_or((x, y), |c| c.at(x, y));
                map(sx, sy)
            }
        },
        margin: margin as f64,
    }
}

impl<M: Fn(f64, f64) -> (f64, f64)> RefinementRegion<'_, M> {
    fn inside(&self, v: f64, n: usize) -> bool {
        v >= self.margin && v <= n as f64 - 1.0 - self.margin
    }

    fn usable(&self, x: usize, y: usize) -> bool {
        let (h, w) = self.reference.dim();
        let (fh, fw) = self.frame_dim;
        if !(self.inside(x as f64, w)
            && self.inside(y as f64, h)
            && self.mask[[y, x]]
            && self.reference[[y, x]].is_finite())
        {
            return false;
        }
        let (fx, fy) = (self.map)(x as f64, y as f64);
        self.inside(fx, fw)
            && self.inside(fy, fh)
            && self
                .frame_blank_free
                .as_ref()
                .is_none_or(|ok| ok[[fy.round() as usize, fx.round() as usize]])
    }
}

/// Side of the region the interpolation check refines, px: its synthetic frame is dense, so
/// on large images it runs on the central part only (4096²: 0.07 s, where the whole field
/// would take about 1 s, against 0.57 s for the rest of a frame's alignment). Less of the
/// field means less averaging of the error over sub-pixel positions when the frame is rotated
/// or scaled: a larger term, not a smaller one.
const CHECK_MAX_SIDE: usize = 1024;

/// The pixels inside the `side`×`side` square at the centre of `bbox` (all of them when the
/// box is no larger).
fn central_pixels(
    pixels: &[(usize, usize, usize)],
    (x0, y0, x1, y1): (usize, usize, usize, usize),
    side: usize,
) -> Vec<(usize, usize, usize)> {
    let span = |a: usize, b: usize| {
        let extent = b - a + 1;
        let start = a + extent.saturating_sub(side) / 2;
        start..start + side.min(extent)
    };
    let (xs, ys) = (span(x0, x1), span(y0, y1));
    pixels
        .iter()
        .filter(|&&(x, y, _)| xs.contains(&x) && ys.contains(&y))
        .copied()
        .collect()
}

/// The error this frame's own transform may bring from the refinement's interpolator, per
/// parameter, beyond the variance the check reported (quadratic excess): a frame made from the
/// reference through `transform` with a cubic spline (see [`FrameMaker::CubicSpline`]) is
/// refined from the exact answer on the same pixels. The error depends on the sub-pixel
/// positions the pixels land on. When they are nearly the same across the field (a shift with
/// little rotation or scale change: pointing jitter), it does not average out. On
/// tests/data/trace_fourier_shift the quintic model's answer is 7e-5 px off; this check says
/// 4.2e-4 (a cubic-spline frame's error, which bounds it); a cubic model's σ without such a
/// term is 20× short of its 5.4e-4 px error. The shift is reduced to its fractional part (same
/// sub-pixel positions), so that the synthetic frame stays inside the reference. `None` when
/// the check cannot run.
fn interpolation_check(
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
        settings,
        0.0,
        FrameMaker::CubicSpline,
    )?;
    tracing::debug!(bias = ?test.bias, variance = ?test.variance, "interpolation check");
    Some(std::array::from_fn(|k| {
        (test.bias[k] * test.bias[k] - test.variance[k])
            .max(0.0)
            .sqrt()
    }))
}

/// The method's systematic floor for a reference: per parameter, the RMS of the self-test
/// errors (`self_test_bias`) over the cases of `self_test_case`, on the lattice of the whole
/// `mask`, beyond the σ those refinements reported themselves (quadratic excess). The error
/// depends on the sub-pixel positions the pixels land on, so the cases spread the shift over
/// the unit square and rotate and scale the lever arm by a fraction of a
/// pixel (which varies the positions across the image); their RMS is the typical error of a
/// frame, whatever its own transform. `None` when a case fails.
pub fn self_test_floor(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    mask: &Array2<bool>,
    sample: usize,
    settings: &RefineSettings,
) -> Option<SelfTest> {
    let (h, w) = reference.dim();
    let grid = CellGrid::new(mask.view(), sample)?;
    let usable = |x: usize, y: usize| mask[[y, x]] && reference[[y, x]].is_finite();
    let tiles = self_test_tiles(mask);
    let (pixels, boxes) = if tiles.is_empty() {
        let pixels = lattice_pixels((h, w), usable, &grid, MAX_PIXELS, |_| true);
        let whole = pixel_box(&pixels)?;
        (pixels, vec![whole])
    } else {
        // Every pixel of every tile, tile by tile (the order the sampling reads them in).
        let pixels = tiles
            .par_iter()
            .flat_map_iter(|&(x0, y0, x1, y1)| {
                let (usable, grid) = (&usable, &grid);
                (y0..=y1).flat_map(move |y| {
                    (x0..=x1).filter_map(move |x| {
                        usable(x, y)
                            .then(|| grid.cell_of(x, y).map(|c| (x, y, c)))
                            .flatten()
                    })
                })
            })
            .collect();
        (pixels, tiles)
    };
    if pixels.is_empty() {
        return None;
    }
    let center = Similarity::array_center(w, h);
    let lever = (pixels
        .iter()
        .map(|&(x, y, _)| (x as f64 - center[0]).powi(2) + (y as f64 - center[1]).powi(2))
        .sum::<f64>()
        / pixels.len() as f64)
        .sqrt()
        .max(1.0);
    let settings = RefineSettings {
        frame_smoothing_px: 0.0,
        ..*settings
    };
    // More cases where they are cheap: the RMS of four is uncertain by about ±35 %, and on
    // small undersampled images the error varies strongly with the sub-pixel position.
    let cases = (SELF_TEST_PIXEL_BUDGET / pixels.len().max(1)).clamp(4, 16);
    let cases = if boxes.len() > 1 { 4 } else { cases };
    let (mut sum, mut seen) = ([0.0; 4], [0.0; 4]);
    let mut flat = Vec::with_capacity(cases);
    for case in 0..cases {
        let (dx, dy, turn_px, stretch_px) = self_test_case(case);
        let t = Similarity {
            scale: 1.0 + stretch_px / lever,
            rotation_rad: turn_px / lever,
            dx,
            dy,
            center,
        };
        let test = self_test_bias(
            reference,
            prepared,
            &pixels,
            &boxes,
            &grid,
            &t,
            &settings,
            FrameMaker::Model,
        )?;
        tracing::trace!(case, bias = ?test.bias, "self-test case");
        for k in 0..4 {
            sum[k] += test.bias[k] * test.bias[k];
            seen[k] += test.variance[k];
        }
        flat.extend(test.flat_sigma);
    }
    // Only the error the residuals do not already show: without noise the cluster covariance
    // is made of these same interpolation residuals, and counting both overstates the σ
    // (TRACE 1024², no noise: 86–95 % of trials within 1σ).
    Some(SelfTest {
        floor: std::array::from_fn(|k| ((sum[k] - seen[k]) / cases as f64).max(0.0).sqrt()),
        flat_sigma: (!flat.is_empty())
            .then(|| (flat.iter().map(|s| s * s).sum::<f64>() / flat.len() as f64).sqrt()),
    })
}

/// Tiles (inclusive boxes) of the self-test on a large mask: a 5 × 5 layout over the mask's
/// bounding box, the tiles wholly inside the mask kept, [`SELF_TEST_TILE_PIXELS`] in all.
/// Tiles keep the lever arm of the whole mask and every sub-pixel position while the
/// synthetic frames are made only where the refinement reads them. Empty when the mask is
/// small enough to be tested whole.
fn self_test_tiles(mask: &Array2<bool>) -> Vec<(usize, usize, usize, usize)> {
    const LAYOUT: usize = 5;
    let Some(roi) = bounding_box(mask) else {
        return Vec::new();
    };
    let (x0, y0, x1, y1) = roi;
    let (bw, bh) = (x1 - x0 + 1, y1 - y0 + 1);
    if bw * bh < SELF_TEST_TILED_ABOVE {
        return Vec::new();
    }
    let side = ((SELF_TEST_TILE_PIXELS / (LAYOUT * LAYOUT - 4)) as f64).sqrt() as usize;
    let side = side.min(bw / LAYOUT).min(bh / LAYOUT);
    let tiles: Vec<_> = (0..LAYOUT * LAYOUT)
        .map(|k| {
            let centre = |i: usize, n: usize, at: usize| at + ((2 * i + 1) * n) / (2 * LAYOUT);
            let (cx, cy) = (centre(k % LAYOUT, bw, x0), centre(k / LAYOUT, bh, y0));
            (
                cx - side / 2,
                cy - side / 2,
                cx - side / 2 + side - 1,
                cy - side / 2 + side - 1,
            )
        })
        .filter(|&(tx0, ty0, tx1, ty1)| mask.slice(s![ty0..=ty1, tx0..=tx1]).iter().all(|&m| m))
        .collect();
    // Too few tiles inside (a ring-shaped or ragged mask): test the whole mask.
    if tiles.len() < LAYOUT * LAYOUT / 2 {
        return Vec::new();
    }
    tiles
}

/// Bounding box (x0, y0, x1, y1), inclusive, of the true pixels of `mask`.
fn bounding_box(mask: &Array2<bool>) -> Option<(usize, usize, usize, usize)> {
    let rows: Vec<usize> = (0..mask.nrows())
        .filter(|&y| mask.row(y).iter().any(|&m| m))
        .collect();
    let cols: Vec<usize> = (0..mask.ncols())
        .filter(|&x| mask.column(x).iter().any(|&m| m))
        .collect();
    Some((*cols.first()?, *rows.first()?, *cols.last()?, *rows.last()?))
}

/// Mask bounding-box area above which the self-test runs on tiles, px.
const SELF_TEST_TILED_ABOVE: usize = 2000 * 2000;

/// Pixels in all the self-test's tiles.
const SELF_TEST_TILE_PIXELS: usize = 1 << 18;

/// Pixels (summed over the cases) the self-test may refine on a whole mask: 4 cases at 2²⁰
/// pixels, up to 16 on smaller images (on tiles, always 4).
const SELF_TEST_PIXEL_BUDGET: usize = 4 << 20;

/// The `k`-th self-test transform: (dx, dy, rotation and scale change as a motion of the
/// lever arm), px. Shifts follow the R2 low-discrepancy sequence over the unit square; the
/// turn and stretch are ±0.3–0.5 px with alternating signs.
fn self_test_case(k: usize) -> (f64, f64, f64, f64) {
    // R2: fractional parts of k·(1/g, 1/g²), g the plastic number.
    const G: f64 = 1.324_717_957_244_746;
    let n = k as f64 + 1.0;
    let (dx, dy) = ((0.5 + n / G).fract(), (0.5 + n / (G * G)).fract());
    let sign = |b: bool| if b { 1.0 } else { -1.0 };
    let turn = sign(k.is_multiple_of(2)) * (0.3 + 0.2 * ((k / 2) % 2) as f64);
    let stretch = sign(k % 4 < 2) * (0.5 - 0.2 * ((k / 2) % 2) as f64);
    (dx, dy, turn, stretch)
}

/// How a self-test makes its synthetic frame from the reference.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FrameMaker {
    /// The refinement's own interpolator: what is left is the method's error on frames it
    /// can model exactly (double interpolation, f32, the weights).
    Model,
    /// A cubic spline, one order below the model: a real frame is a new sampling of the sky,
    /// not the model's resampling of the reference, and the two differ in how they move
    /// structure near the Nyquist frequency. Band-limited frames sit on the model's other
    /// side, about a third as far (TRACE: a Fourier shift's error 2e-4 px, a cubic spline's
    /// 7e-4), so the cubic frame's error bounds theirs; and frames that were made by cubic
    /// resampling (scipy's default) are covered exactly.
    CubicSpline,
}

/// The method's systematic error for this image and transform, measured: a frame made from
/// the reference itself through `transform` (by `maker`) is refined from the exact answer,
/// and what the refinement reports instead is its bias (interpolation of sharp or
/// undersampled structure, mostly), with the variance it reported.
#[allow(clippy::too_many_arguments)]
fn self_test_bias(
    reference: ArrayView2<f32>,
    prepared: &RefineReference,
    pixels: &[(usize, usize, usize)],
    boxes: &[(usize, usize, usize, usize)],
    grid: &CellGrid,
    transform: &Similarity,
    settings: &RefineSettings,
    maker: FrameMaker,
) -> Option<SelfTestCase> {
    let tiles = boxes
        .par_iter()
        .map(|&bbox| synthetic_tile(reference, bbox, transform, settings, maker))
        .collect::<Option<Vec<_>>>()?;
    let window = FrameWindow {
        tiles,
        carried: None,
    };
    let test = refine(prepared, &window, pixels, grid, *transform, settings).ok()?;
    let (a, b) = (transform.params(), test.transform.params());
    let bias = [0, 1, 2, 3].map(|k| b[k] - a[k]);
    let variance = [0, 1, 2, 3].map(|k| test.covariance[k][k]);
    let flat_sigma = test.flat_residual_sigma;
    (bias.iter().chain(&variance).all(|v| v.is_finite())).then_some(SelfTestCase {
        bias,
        variance,
        flat_sigma,
    })
}

/// The synthetic frame (the reference moved by `transform`, by `maker`) on the window that
/// the reference pixels in `bbox` map into.
fn synthetic_tile(
    reference: ArrayView2<f32>,
    bbox: (usize, usize, usize, usize),
    transform: &Similarity,
    settings: &RefineSettings,
    maker: FrameMaker,
) -> Option<WindowTile> {
    let (h, w) = reference.dim();
    // The synthetic frame is only needed on the window the refinement reads; it is made
    // there from the spline of the part of the reference that the window maps back to.
    let sigma = settings.smoothing_px;
    // The synthetic frame's own smoothing: a blur mismatch, for the blur check.
    let frame_sigma = sigma.hypot(settings.frame_smoothing_px);
    let (wx0, wy0, wx1, wy1) = mapped_window(bbox, transform, window_margin(frame_sigma), w, h)?;
    let back = mapped_window(
        (wx0, wy0, wx1, wy1),
        &transform.inverse(),
        // The model's support (3 px) and border transient (0.431^17 < 1e-6).
        window_margin(0.0),
        w,
        h,
    )?;
    let (sx0, sy0, sx1, sy1) = back;
    let source = reference.slice(s![sy0..=sy1, sx0..=sx1]);
    let inverse = transform.inverse();
    let to_source = Similarity {
        dx: inverse.dx - sx0 as f64,
        dy: inverse.dy - sy0 as f64,
        ..inverse
    };
    let (ww, wh) = (wx1 - wx0 + 1, wy1 - wy0 + 1);
    let synthetic = match maker {
        FrameMaker::Model => {
            HighOrderSpline::new(source, MODEL).warp_similarity_window(&to_source, wx0, wy0, ww, wh)
        }
        FrameMaker::CubicSpline => {
            SplineImage::new(source).warp_similarity_window(&to_source, wx0, wy0, ww, wh)
        }
    };
    Some(WindowTile {
        spline: HighOrderSpline::new(
            crate::preprocess::gaussian_smooth(synthetic.view(), frame_sigma).view(),
            MODEL,
        ),
        origin: [wx0 as f64, wy0 as f64],
        end: [wx1 as f64, wy1 as f64],
    })
}

/// One self-test case: the error it made, and the (cluster-robust) variance it reported.
struct SelfTestCase {
    bias: [f64; 4],
    variance: [f64; 4],
    /// Robust σ of its residuals at the flattest pixels: the model's misfit alone.
    flat_sigma: Option<f64>,
}

/// What the self-test measured on a reference.
#[derive(Debug, Clone, Copy)]
pub struct SelfTest {
    /// The systematic floor per parameter (scale, rotation rad, dx, dy).
    pub floor: [f64; 4],
    /// RMS over the cases of the residuals' robust σ at the flattest pixels: the level the
    /// model's misfit alone leaves there, without noise.
    pub flat_sigma: Option<f64>,
}

/// Bounding box (x0, y0, x1, y1), inclusive, of `pixels`; `None` when there are none.
fn pixel_box(pixels: &[(usize, usize, usize)]) -> Option<(usize, usize, usize, usize)> {
    let (&(x, y, _), rest) = pixels.split_first()?;
    Some(
        rest.iter()
            .fold((x, y, x, y), |(x0, y0, x1, y1), &(x, y, _)| {
                (x0.min(x), y0.min(y), x1.max(x), y1.max(y))
            }),
    )
}

/// Why the refinement's answer was not taken.
#[derive(Debug, Clone)]
pub struct Rejected {
    pub note: String,
    /// The refinement's converged answer when it disagreed with the flow's beyond their σ:
    /// one of the two is wrong, and which one the data alone cannot say.
    pub disagreeing: Option<Similarity>,
    /// Gauss–Newton ran from the flow's answer and found no consistent solution near it:
    /// evidence against that answer, unlike a refinement that had too little to work with.
    pub ran_off: bool,
}

impl Rejected {
    fn skipped(note: impl Into<String>) -> Rejected {
        Rejected {
            note: note.into(),
            disagreeing: None,
            ran_off: false,
        }
    }

    fn ran_off(note: impl Into<String>) -> Rejected {
        Rejected {
            ran_off: true,
            ..Rejected::skipped(note)
        }
    }
}

/// Why a refinement gave no answer.
#[derive(Debug)]
pub enum RefineFailure {
    /// Too little to work with (pixels, finite reference values): says nothing of the start.
    Unusable(String),
    /// The iterations went away from the start and found no consistent solution near it.
    RanOff(String),
}

/// Most pixels one refinement uses. Its precision grows as √pixels while its cost and memory
/// grow linearly; beyond about a million pixels (a 1024² frame's disk) the other error terms
/// (the measured floors) dominate, so larger frames are thinned on a regular lattice.
const MAX_PIXELS: usize = 1 << 20;

/// Largest translation σ of a refinement whose answer is taken, px.
const MAX_REFINED_SIGMA_PX: f64 = 1.0;

/// Largest disagreement (in combined σ) between flow and refinement that keeps the refinement.
const MAX_DISAGREEMENT_SIGMA: f64 = 5.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_noise_covariance_of_independent_pixels_is_least_squares() {
        // Pixels far apart (no smoothing, so no correlation between them) with residuals far
        // inside Tukey's c (ψ′ = 1 to 1e-10): the covariance of unit noise is the least-squares
        // (ΣJJᵀ)⁻¹. With 6·n pixels whose instruments are a_k·e_k, that is diag(1/(n·a_k²)).
        let n = 50;
        let a = [2.0, 0.5, 1.0, 3.0, 0.25, 1.5];
        let (mut pixels, mut jac) = (Vec::new(), Vec::new());
        for k in 0..6 {
            for i in 0..n {
                pixels.push(Pixel {
                    x: 4 * i,
                    y: 4 * k,
                    cell: 0,
                    value: 0.0,
                    gx: 1.0 + i as f64,
                    gy: 0.0,
                    neighbours: 0.0,
                });
                let mut row = [0.0; 6];
                row[k] = a[k];
                jac.push(row);
            }
        }
        let residuals: Vec<f64> = (0..6 * n).map(|i| 1e-5 * (i % 7) as f64).collect();
        let weights = vec![1.0; 6 * n];
        let fit = ClusterFit {
            jac: &jac,
            residuals: &residuals,
            weights: &weights,
            slope_per_weight: 1.0,
        };
        let (cov, flat_sigma) =
            noise_covariance(&pixels, &fit, |k| Vector6::from(jac[k]), 1.0, 0.0, true)
                .expect("well posed");
        let cov = cov.expect("a regular slope");
        for k in 0..6 {
            for j in 0..6 {
                let want = if j == k {
                    1.0 / (n as f64 * a[k] * a[k])
                } else {
                    0.0
                };
                assert!(
                    (cov[(k, j)] - want).abs() <= 1e-9 * want.max(1.0),
                    "({k}, {j})"
                );
            }
        }
        assert!(flat_sigma > 0.0 && flat_sigma < 1e-4, "{flat_sigma}");
    }

    #[test]
    fn only_a_significant_blur_difference_is_matched_on_the_blurrier_side() {
        let blur = |v: f64, sd: f64| {
            Some(crate::blur::BlurDifference {
                variance_px2: v,
                sigma_px2: sd,
                shape_px2: 0.0,
                bins: 50,
            })
        };
        // Frame blurrier by 0.64 px²: the reference gets a Gaussian of that variance.
        let m = blur_matching(blur(0.64, 0.005), 0.0, 0.7);
        assert!((m.reference_extra - 0.8).abs() < 1e-12 && m.frame_smoothing_px == 0.0);
        assert!(m.uncertainty_px2.is_some());
        // Reference blurrier by 0.25 px²: the frame is smoothed by 0.5 px.
        let m = blur_matching(blur(-0.25, 0.005), 0.0, 0.7);
        assert!(m.reference_extra == 0.0 && (m.frame_smoothing_px - 0.5).abs() < 1e-12);
        // The frame's resolution-matching smoothing (0.3 px) is part of its blur.
        let m = blur_matching(blur(-0.25, 0.005), 0.3, 0.7);
        assert!((m.frame_smoothing_px - 0.5).abs() < 1e-12);
        // Within 5 standard errors, or under 2 % of the smoothing variance: nothing.
        for (v, sd) in [(0.04, 0.01), (0.009, 0.0001)] {
            let m = blur_matching(blur(v, sd), 0.0, 0.7);
            assert_eq!((m.reference_extra, m.frame_smoothing_px), (0.0, 0.0));
            assert!(m.uncertainty_px2.is_none());
        }
    }

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

    #[test]
    fn the_region_keeps_the_margin_from_both_images_edges() {
        // 40 × 30 reference, the same frame shifted by +3.4 px in x: pixel x maps to x + 3.4,
        // so with a 4 px margin x must satisfy 4 ≤ x and x + 3.4 ≤ 39 − 4 (x ≤ 31), 4 ≤ y ≤ 25.
        let (h, w) = (30, 40);
        let reference = Array2::from_elem((h, w), 1.0f32);
        let mut frame = Array2::from_elem((h, w), 1.0f32);
        let mask = Array2::from_elem((h, w), true);
        let t = Similarity {
            dx: 3.4,
            ..Similarity::identity(Similarity::array_center(w, h))
        };
        let region = refinement_region(&mask, reference.view(), frame.view(), &t, None, 4);
        for ((y, x), _) in mask.indexed_iter() {
            assert_eq!(
                region.usable(x, y),
                (4..=31).contains(&x) && (4..=25).contains(&y),
                "({x}, {y})"
            );
        }
        // A blank in the frame at (20, 15) removes the pixels mapping within 4 px of it.
        frame[[15, 20]] = f32::NAN;
        let region = refinement_region(&mask, reference.view(), frame.view(), &t, None, 4);
        // Pixel (x, y) maps to round(x + 3.4) = x + 3: excluded when |x + 3 − 20| ≤ 4 and
        // |y − 15| ≤ 4.
        for ((y, x), _) in mask.indexed_iter() {
            let r = region.usable(x, y);
            let inside = (4..=31).contains(&x) && (4..=25).contains(&y);
            let near_blank = (x + 3).abs_diff(20) <= 4 && y.abs_diff(15) <= 4;
            assert_eq!(r, inside && !near_blank, "({x}, {y})");
        }
    }

    #[test]
    fn the_check_region_is_the_central_square_of_the_box() {
        let pixels: Vec<(usize, usize, usize)> = (0..10)
            .flat_map(|y| (0..20).map(move |x| (x, y, 0)))
            .collect();
        // Box 20 wide, 10 high; a 4 px square starts at (20 − 4)/2 = 8 and (10 − 4)/2 = 3.
        let inner = central_pixels(&pixels, (0, 0, 19, 9), 4);
        assert_eq!(inner.len(), 16);
        assert!(inner
            .iter()
            .all(|&(x, y, _)| (8..12).contains(&x) && (3..7).contains(&y)));
        // A box no larger than the square keeps everything.
        assert_eq!(central_pixels(&pixels, (0, 0, 19, 9), 64).len(), 200);
    }

    #[test]
    fn the_lattice_keeps_every_kth_row_and_column_under_the_cap() {
        let region = Array2::from_elem((100, 100), true);
        let grid = CellGrid::new(region.view(), 4).expect("grid");
        // Under the cap: all 10 000.
        assert_eq!(
            lattice_pixels((100, 100), |_, _| true, &grid, 10_000, |_| true).len(),
            10_000
        );
        // Cap 2 500: every 2nd row and column, exactly 50 × 50.
        let kept = lattice_pixels((100, 100), |_, _| true, &grid, 2_500, |_| true);
        assert_eq!(kept.len(), 2_500);
        assert!(kept.iter().all(|&(x, y, _)| x % 2 == 0 && y % 2 == 0));
        // Cap 1 000: k = ⌈√10⌉ = 4, 25 × 25.
        assert_eq!(
            lattice_pixels((100, 100), |_, _| true, &grid, 1_000, |_| true).len(),
            625
        );
        // Only the wanted cells: one of 16 (25 × 25 px), all of it under the cap.
        let one = lattice_pixels((100, 100), |_, _| true, &grid, 10_000, |c| c == 5);
        assert_eq!(one.len(), 625);
        assert!(one
            .iter()
            .all(|&(x, y, c)| c == 5 && (25..50).contains(&x) && (25..50).contains(&y)));
    }
}
