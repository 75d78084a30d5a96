//! The covariance of a converged fit: cluster-robust over blocks of pixels, and that of the
//! residual noise through the exact slope.

use super::pixels::CellGrid;
use super::reference::Pixel;
use super::robust::{robust_sigma_where, sum_in_chunks, tukey_psi_slope};
use nalgebra::{Matrix6, Vector6};
use ndarray::Array2;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// What the cluster-robust covariance needs of a converged fit: per pixel the instruments
/// `J`, residuals `r` and weights `w` (the score is `Σ w·r·J`), and the factor that turns a
/// weight into the slope of the weighted residual (the sensitivity is `Σ factor·w·J·Fᵀ`).
pub(super) struct ClusterFit<'a> {
    pub(super) jac: &'a [[f64; 6]],
    pub(super) residuals: &'a [f64],
    pub(super) weights: &'a [f64],
    pub(super) slope_per_weight: f64,
}

/// Cluster-robust covariance, jackknife form (CR3): `(G−1)/G · Σ_b d_b d_bᵀ` with
/// `d_b = (A − A_b)⁻¹ s_b`, the change of the estimate when block `b` is left out, where
/// `s_b = Σ_{i∈b} w_i r_i J_i` is the block's score, `A = Σ ψ′_i J_i F_iᵀ` the M-estimator's
/// slope and `A_b` the block's share of it. On solar images a few blocks (active regions)
/// hold most of the structure; the plain sandwich `A⁻¹ Σ s_b s_bᵀ A⁻ᵀ` then understates the
/// variance, because each dominant block pulls the fit towards itself and its residuals look
/// smaller than its errors. The slope must follow ψ′ = (1 − u²)(1 − 5u²), not the weight
/// w = (1 − u²)²: the weights follow the residuals, and for Gaussian residuals
/// E[w]/E[ψ′] = 1.21, a σ deficit of as much with `w`
/// (docs/validation.md#cluster-covariance-in-jackknife-form). `None` with fewer than 8 blocks.
pub(super) fn cluster_covariance(
    blocks: &BTreeMap<usize, BlockSums>,
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

/// The cluster-robust covariance over grid cells or over 2 × 2 groups of them, whichever is
/// larger, with the number of blocks; `plain` when there are too few blocks either way.
pub(super) fn robust_covariance(
    fits: &ClusterFit,
    frame_row: impl Fn(usize) -> Vector6<f64> + Sync,
    pixels: &[Pixel],
    grid: &CellGrid,
    plain: Matrix6<f64>,
) -> (Matrix6<f64>, usize) {
    let cells = block_sums(fits, frame_row, |k| pixels[k].cell);
    let mut groups: BTreeMap<usize, BlockSums> = Default::default();
    for (&cell, sums) in &cells {
        let g = groups.entry(grid.group_of(cell)).or_default();
        g.0 += sums.0;
        g.1 += sums.1;
    }
    let by_cell = cluster_covariance(&cells);
    let by_group = cluster_covariance(&groups);
    match (by_cell, by_group) {
        (Some(a), Some(b)) => {
            if geometric_trace_ratio(&b.0, &a.0) > 1.0 {
                b
            } else {
                a
            }
        }
        (Some(a), None) | (None, Some(a)) => a,
        (None, None) => (plain, 1),
    }
}

/// A block's score `Σ w·r·J` and its share `Σ ψ′·J·Fᵀ` of the slope.
pub(super) type BlockSums = (Vector6<f64>, Matrix6<f64>);

/// The score and slope share of every block (`block_of` each pixel), summed over pixels in
/// parallel chunks, in order.
pub(super) fn block_sums(
    fit: &ClusterFit,
    frame_row: impl Fn(usize) -> Vector6<f64> + Sync,
    block_of: impl Fn(usize) -> usize + Sync,
) -> BTreeMap<usize, BlockSums> {
    type Blocks = BTreeMap<usize, BlockSums>;
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
pub(super) fn noise_covariance(
    pixels: &[Pixel],
    fit: &ClusterFit,
    frame_row: impl Fn(usize) -> Vector6<f64> + Sync,
    tukey_c: f64,
    smoothing_px: f64,
    with_covariance: bool,
) -> Option<(Option<Matrix6<f64>>, f64)> {
    let (jac, residuals, weights) = (fit.jac, fit.residuals, fit.weights);
    let counts = |k: usize| weights[k] > 0.0 && residuals[k].is_finite();
    let counted = (0..pixels.len())
        .into_par_iter()
        .filter(|&k| counts(k))
        .count();
    if counted < 64 {
        return None;
    }
    let slope_of = |k: usize| counts(k).then(|| pixels[k].slope);
    let flattest = crate::stats::par_select_where(pixels.len(), counted / 4, slope_of)?;
    let flat_sigma = robust_sigma_where(pixels.len(), |k| {
        slope_of(k).filter(|&g| g <= flattest).map(|_| residuals[k])
    })?;
    if !with_covariance {
        return Some((None, flat_sigma));
    }
    let used: Vec<usize> = (0..pixels.len())
        .into_par_iter()
        .filter(|&k| counts(k))
        .collect();
    // Each counted pixel's ψ′; its row `ψ′·J` is made where it is read, instead of a frame
    // of 6-vectors.
    let psi: Vec<f64> = (0..pixels.len())
        .into_par_iter()
        .map(|k| match counts(k) {
            true => tukey_psi_slope(residuals[k], tukey_c),
            false => 0.0,
        })
        .collect();
    let u = |k: usize| match counts(k) {
        true => Vector6::from(jac[k]) * psi[k],
        false => Vector6::zeros(),
    };
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
    let lattice = Lattice::of(pixels)?;
    let s = smoothing_px.max(0.1);
    let reach = (3.0 * std::f64::consts::SQRT_2 * s / lattice.step as f64).ceil() as usize;
    let side = 2 * reach + 1;
    let correlation: Vec<f64> = (0..side * side)
        .map(|t| {
            let (dx, dy) = (t % side, t / side);
            let (dx, dy) = (dx.abs_diff(reach), dy.abs_diff(reach));
            let d2 = ((dx * dx + dy * dy) * lattice.step * lattice.step) as f64;
            (-d2 / (4.0 * s * s)).exp()
        })
        .collect();
    let (gh, gw) = lattice.index.dim();
    let near_product = |i: usize| {
        let (cx, cy) = lattice.cell(&pixels[i]);
        let mut near = Vector6::<f64>::zeros();
        // The neighbourhood clipped to the lattice, visited row by row as the table is laid.
        let (x0, x1) = (cx.saturating_sub(reach), (cx + reach).min(gw - 1));
        for y in cy.saturating_sub(reach)..=(cy + reach).min(gh - 1) {
            let row = lattice.index.row(y);
            let weights = &correlation[(y + reach - cy) * side..][..side];
            for x in x0..=x1 {
                let j = row[x];
                if j != u32::MAX {
                    near += u(j as usize) * weights[x + reach - cx];
                }
            }
        }
        u(i) * near.transpose()
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

/// Where each pixel sits on the lattice of every `step`-th row and column that the pixels
/// were taken on, over their bounding box only.
struct Lattice {
    step: usize,
    origin: (usize, usize),
    /// Pixel index at each lattice node, `u32::MAX` where there is none.
    index: Array2<u32>,
}

impl Lattice {
    fn of(pixels: &[Pixel]) -> Option<Lattice> {
        if pixels.is_empty() {
            return None;
        }
        let step = pixels
            .par_windows(2)
            .filter(|p| p[0].y == p[1].y && p[1].x > p[0].x)
            .map(|p| p[1].x - p[0].x)
            .min()
            .unwrap_or(1);
        let (x0, y0, x1, y1) = pixels
            .par_iter()
            .fold(
                || (usize::MAX, usize::MAX, 0, 0),
                |b, p| (b.0.min(p.x), b.1.min(p.y), b.2.max(p.x), b.3.max(p.y)),
            )
            .reduce(
                || (usize::MAX, usize::MAX, 0, 0),
                |a, b| (a.0.min(b.0), a.1.min(b.1), a.2.max(b.2), a.3.max(b.3)),
            );
        let origin = (x0 / step, y0 / step);
        let mut lattice = Lattice {
            step,
            origin,
            index: Array2::from_elem(
                (y1 / step - origin.1 + 1, x1 / step - origin.0 + 1),
                u32::MAX,
            ),
        };
        for (k, p) in pixels.iter().enumerate() {
            let (x, y) = lattice.cell(p);
            lattice.index[[y, x]] = k as u32;
        }
        Some(lattice)
    }

    /// The pixel's node (column, row).
    fn cell(&self, p: &Pixel) -> (usize, usize) {
        (
            p.x / self.step - self.origin.0,
            p.y / self.step - self.origin.1,
        )
    }
}

/// Geometric mean of the ratios of the four geometric variances, `b` over `a`.
pub(super) fn geometric_trace_ratio(b: &Matrix6<f64>, a: &Matrix6<f64>) -> f64 {
    ((0..4)
        .map(|k| (b[(k, k)].max(f64::MIN_POSITIVE) / a[(k, k)].max(f64::MIN_POSITIVE)).ln())
        .sum::<f64>()
        / 4.0)
        .exp()
}

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
                    slope: 1.0 + i as f64,
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
}
