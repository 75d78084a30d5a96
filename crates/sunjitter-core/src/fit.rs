//! Robust similarity fit and its covariance (paper §3.3 and §4.2).
//!
//! Model, in the contract's convention (`crate::geometry`): a reference point `p` appears in
//! the frame at `f(p) = s·R(θ)·(p − c) + c + (dx, dy)`, `c` given by the caller.
//! Written with `a = s cos θ`, `b = s sin θ` the model is linear in `(a, b, dx, dy)`, so the
//! least-squares fit has a closed form; it is reported as `(s, θ, dx, dy)`, and every
//! covariance here is over `(scale, rotation_rad, dx, dy)` in that order.
//!
//! Pipeline: RANSAC on 2-point minimal samples (seeded, deterministic, adaptive stop) →
//! least-squares refit on the consensus set, re-classified until it is stable → UABJM
//! `Cov = (JᵀJ)⁻¹σ²`. The plain UABJM assumes independent residuals; flow vectors are
//! correlated over the flow window, so three calibration aids are provided as well: a spatial
//! block jackknife, an effective-sample-size inflation, and a sandwich covariance for a given
//! residual correlation model.
//!
//! **Degrees of freedom.** Each correspondence gives two scalar equations, so with `n` points
//! J has `N = 2n` rows and the unbiased residual variance per coordinate is
//! `σ² = S/(2n − 4)` ([`Uabjm::sigma2`], used for the covariance). The paper writes
//! `σ² = S/(n − p)` with `n` "the sample size"; read with `n` = number of points that is
//! `S/(n − 4)`, about twice as large for large n (σ larger by √2); it is kept as
//! [`Uabjm::sigma2_point_convention`] for comparison.

use crate::geometry::Similarity;
use crate::sampling::Correspondence;
use crate::stats::SplitMix64;
use nalgebra::Matrix4;
use std::collections::BTreeMap;

/// Why a fit could not be made.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitFailure {
    #[error("too few usable correspondences: {have} (need at least {need})")]
    TooFewPoints { have: usize, need: usize },
    #[error("degenerate geometry: {0}")]
    Degenerate(String),
    #[error("no consensus: best model has {best} inliers of {total} (need {need})")]
    NoConsensus {
        best: usize,
        total: usize,
        need: usize,
    },
}

impl From<FitFailure> for crate::Error {
    fn from(f: FitFailure) -> Self {
        crate::Error::AlignmentFailed(f.to_string())
    }
}

/// RANSAC settings. `threshold_px` is the largest 2-D residual `|f(p) − p_frame|` of an inlier.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacParams {
    pub threshold_px: f64,
    pub max_trials: usize,
    pub seed: u64,
    /// Fewest inliers for a fit to count (never fewer than 3: UABJM needs 2n − 4 > 0).
    pub min_inliers: usize,
    /// Probability of having drawn at least one all-inlier pair when the adaptive stop fires.
    pub confidence: f64,
}

impl Default for RansacParams {
    fn default() -> Self {
        RansacParams {
            threshold_px: 1.0,
            max_trials: 2000,
            seed: 0,
            min_inliers: 6,
            confidence: 0.9999,
        }
    }
}

/// `v > 0`, false for NaN.
fn is_positive(v: f64) -> bool {
    v > 0.0
}

/// Parameter order of every covariance matrix here.
pub const PARAMS: [&str; 4] = ["scale", "rotation_rad", "dx", "dy"];

#[derive(Debug, Clone, PartialEq)]
pub struct SimilarityFit {
    pub transform: Similarity,
    /// One flag per input point (non-finite points are never inliers).
    pub inliers: Vec<bool>,
    pub n_inliers: usize,
    /// RMS of the inliers' 2-D residual lengths, `√(S/n)`.
    pub residual_rms_px: f64,
    /// Residual variance per coordinate, `S/(2n − 4)`.
    pub sigma2: f64,
    /// The paper's σ² read with n = number of points, `S/(n − 4)` (see module docs).
    pub sigma2_point_convention: f64,
    /// Plain UABJM `(JᵀJ)⁻¹σ²` over (scale, rotation_rad, dx, dy).
    pub covariance: [[f64; 4]; 4],
    /// RANSAC trials actually run.
    pub trials: usize,
}

impl SimilarityFit {
    /// The inlier correspondences (what the covariance estimators below should be given).
    pub fn inlier_points(&self, points: &[Correspondence]) -> Vec<Correspondence> {
        points
            .iter()
            .zip(&self.inliers)
            .filter(|(_, &i)| i)
            .map(|(p, _)| *p)
            .collect()
    }
}

/// Multiply every element of a covariance by `factor`.
pub fn scaled(cov: &[[f64; 4]; 4], factor: f64) -> [[f64; 4]; 4] {
    cov.map(|row| row.map(|v| v * factor))
}

/// Least-squares similarity about `center`, optionally weighted (weights ≥ 0, finite).
/// Closed form: with q = p − c and centroids removed (q̃, ũ),
/// `a − 1 = Σw q̃·ũ / Σw|q̃|²`, `b = Σw q̃×ũ / Σw|q̃|²`, then the translation from the
/// centroids. Solving for `a − 1` rather than `a` keeps full precision for tiny scale changes.
pub fn least_squares(
    points: &[Correspondence],
    weights: Option<&[f64]>,
    center: [f64; 2],
) -> Result<Similarity, FitFailure> {
    if let Some(w) = weights {
        if w.len() != points.len() {
            return Err(FitFailure::Degenerate(format!(
                "{} weights for {} points",
                w.len(),
                points.len()
            )));
        }
        if w.iter().any(|v| !v.is_finite() || *v < 0.0) {
            return Err(FitFailure::Degenerate(
                "weights must be finite and non-negative".into(),
            ));
        }
    }
    let weight = |i: usize| weights.map_or(1.0, |w| w[i]);
    let used = (0..points.len())
        .filter(|&i| points[i].is_finite() && weight(i) > 0.0)
        .count();
    if used < 2 {
        return Err(FitFailure::TooFewPoints {
            have: used,
            need: 2,
        });
    }
    let (mut sw, mut qx, mut qy, mut ux, mut uy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (i, p) in points.iter().enumerate() {
        let w = weight(i);
        if p.is_finite() && w > 0.0 {
            sw += w;
            qx += w * (p.x - center[0]);
            qy += w * (p.y - center[1]);
            ux += w * p.u;
            uy += w * p.v;
        }
    }
    let (qx, qy, ux, uy) = (qx / sw, qy / sw, ux / sw, uy / sw);
    let (mut sqq, mut sdot, mut scross) = (0.0, 0.0, 0.0);
    for (i, p) in points.iter().enumerate() {
        let w = weight(i);
        if p.is_finite() && w > 0.0 {
            let (ex, ey) = (p.x - center[0] - qx, p.y - center[1] - qy);
            let (fx, fy) = (p.u - ux, p.v - uy);
            sqq += w * (ex * ex + ey * ey);
            sdot += w * (ex * fx + ey * fy);
            scross += w * (ex * fy - ey * fx);
        }
    }
    // Points spread over less than a micro-pixel fix no rotation or scale.
    if !is_positive(sqq / sw - 1e-12) {
        return Err(FitFailure::Degenerate("all points coincide".into()));
    }
    let am1 = sdot / sqq;
    let b = scross / sqq;
    let a = 1.0 + am1;
    Ok(Similarity {
        scale: a.hypot(b),
        rotation_rad: b.atan2(a),
        dx: ux - am1 * qx + b * qy,
        dy: uy - b * qx - am1 * qy,
        center,
    })
}

/// 2-D residual `p_frame − f(p)` of one correspondence.
pub fn residual(p: &Correspondence, t: &Similarity) -> [f64; 2] {
    let f = t.apply([p.x, p.y]);
    [p.x + p.u - f[0], p.y + p.v - f[1]]
}

/// Jacobian of the model `f(p)` w.r.t. (s, θ, dx, dy): rows `[∂f_x, ∂f_y]` for each point.
/// (The residuals' Jacobian is its negative; JᵀJ is the same.)
pub fn jacobian(points: &[Correspondence], t: &Similarity) -> Vec<[[f64; 4]; 2]> {
    let (cos, sin) = (t.rotation_rad.cos(), t.rotation_rad.sin());
    points
        .iter()
        .map(|p| {
            let (qx, qy) = (p.x - t.center[0], p.y - t.center[1]);
            let rx = cos * qx - sin * qy; // R(θ)q
            let ry = sin * qx + cos * qy;
            [[rx, -t.scale * ry, 1.0, 0.0], [ry, t.scale * rx, 0.0, 1.0]]
        })
        .collect()
}

fn jtj(jac: &[[[f64; 4]; 2]]) -> Matrix4<f64> {
    let mut m = Matrix4::zeros();
    for rows in jac {
        for r in rows {
            for i in 0..4 {
                for j in 0..4 {
                    m[(i, j)] += r[i] * r[j];
                }
            }
        }
    }
    m
}

fn to_array(m: &Matrix4<f64>) -> [[f64; 4]; 4] {
    [0, 1, 2, 3].map(|i| [0, 1, 2, 3].map(|j| m[(i, j)]))
}

fn invert(m: &Matrix4<f64>) -> Result<Matrix4<f64>, FitFailure> {
    // Cholesky both inverts and proves positive definiteness (full rank).
    m.cholesky()
        .map(|c| c.inverse())
        .ok_or_else(|| FitFailure::Degenerate("JᵀJ is singular (points coincide)".into()))
}

/// Full UABJM result.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Uabjm {
    /// `(JᵀJ)⁻¹σ²` over (scale, rotation_rad, dx, dy).
    pub covariance: [[f64; 4]; 4],
    /// `(JᵀJ)⁻¹` alone, for rescaling with another σ².
    pub inverse_normal: [[f64; 4]; 4],
    /// Residual sum of squares S over both coordinates.
    pub sum_squares: f64,
    /// `S/(2n − 4)`: variance per scalar equation.
    pub sigma2: f64,
    /// `S/(n − 4)`: the paper's formula with n = number of points (NaN for n ≤ 4).
    pub sigma2_point_convention: f64,
    pub n_points: usize,
}

/// UABJM at `transform` for the given (inlier) points.
pub fn uabjm_detail(
    points: &[Correspondence],
    transform: &Similarity,
) -> Result<Uabjm, FitFailure> {
    let pts: Vec<Correspondence> = points.iter().copied().filter(|p| p.is_finite()).collect();
    let n = pts.len();
    if n < 3 {
        return Err(FitFailure::TooFewPoints { have: n, need: 3 });
    }
    let inv = invert(&jtj(&jacobian(&pts, transform)))?;
    let s: f64 = pts
        .iter()
        .map(|p| {
            let r = residual(p, transform);
            r[0] * r[0] + r[1] * r[1]
        })
        .sum();
    let sigma2 = s / (2 * n - 4) as f64;
    Ok(Uabjm {
        covariance: to_array(&(inv * sigma2)),
        inverse_normal: to_array(&inv),
        sum_squares: s,
        sigma2,
        sigma2_point_convention: if n > 4 { s / (n - 4) as f64 } else { f64::NAN },
        n_points: n,
    })
}

/// The paper's UABJM: `(Cov, σ²)` with `σ² = S/(2n − 4)`.
pub fn uabjm(
    points: &[Correspondence],
    transform: &Similarity,
) -> Result<([[f64; 4]; 4], f64), FitFailure> {
    uabjm_detail(points, transform).map(|u| (u.covariance, u.sigma2))
}

fn residual_len2(p: &Correspondence, t: &Similarity) -> f64 {
    let r = residual(p, t);
    r[0] * r[0] + r[1] * r[1]
}

/// RANSAC + least-squares refit + UABJM.
pub fn fit_similarity(
    points: &[Correspondence],
    center: [f64; 2],
    params: &RansacParams,
) -> Result<SimilarityFit, FitFailure> {
    let need = params.min_inliers.max(3);
    let valid: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].is_finite())
        .collect();
    let n = valid.len();
    if n < need {
        return Err(FitFailure::TooFewPoints { have: n, need });
    }
    if !is_positive(params.threshold_px) {
        return Err(FitFailure::Degenerate(
            "RANSAC threshold must be positive".into(),
        ));
    }
    let vpts: Vec<Correspondence> = valid.iter().map(|&i| points[i]).collect();
    // Also rejects coincident point sets before sampling.
    let all_fit = least_squares(&vpts, None, center)?;
    let (mx, my) = (
        vpts.iter().map(|p| p.x).sum::<f64>() / n as f64,
        vpts.iter().map(|p| p.y).sum::<f64>() / n as f64,
    );
    let spread2 = vpts
        .iter()
        .map(|p| (p.x - mx).powi(2) + (p.y - my).powi(2))
        .sum::<f64>()
        / n as f64;
    // Pairs much closer than the point cloud's size turn noise into wild rotation/scale.
    let min_sep2 = 0.01 * spread2;
    let thr2 = params.threshold_px * params.threshold_px;

    let score = |t: &Similarity| -> (usize, f64) {
        let mut count = 0;
        let mut sse = 0.0;
        for p in &vpts {
            let r2 = residual_len2(p, t);
            if r2 <= thr2 {
                count += 1;
                sse += r2;
            }
        }
        (count, sse)
    };

    let conf = params.confidence.clamp(0.0, 1.0 - 1e-12);
    // Trials needed to draw one all-inlier pair with probability `conf` at inlier ratio w.
    let trials_needed = |count: usize| -> usize {
        let w = count as f64 / n as f64;
        let p_good = w * w;
        if p_good >= 1.0 {
            0
        } else {
            let t = ((1.0 - conf).ln() / (1.0 - p_good).ln()).ceil();
            if t.is_finite() && t > 0.0 {
                t.min(usize::MAX as f64) as usize
            } else {
                usize::MAX
            }
        }
    };
    let mut rng = SplitMix64::new(params.seed);
    // Start from the all-points fit: it wins whenever there are no outliers.
    let mut best = all_fit;
    let (mut best_count, mut best_sse) = score(&all_fit);
    let mut needed = trials_needed(best_count);
    let mut trials = 0;
    let mut draws = 0;
    while trials < needed.min(params.max_trials) && draws < 20 * params.max_trials.max(1) {
        draws += 1;
        let i = rng.below(n);
        let mut j = rng.below(n - 1);
        if j >= i {
            j += 1;
        }
        let (pi, pj) = (vpts[i], vpts[j]);
        if (pi.x - pj.x).powi(2) + (pi.y - pj.y).powi(2) < min_sep2 {
            continue;
        }
        trials += 1;
        let Ok(model) = least_squares(&[pi, pj], None, center) else {
            continue;
        };
        let (count, sse) = score(&model);
        if count > best_count || (count == best_count && sse < best_sse) {
            best = model;
            best_count = count;
            best_sse = sse;
            needed = trials_needed(best_count);
        }
    }

    // Refit on the consensus set and re-classify until the set stops changing.
    let classify = |t: &Similarity| -> Vec<bool> {
        vpts.iter().map(|p| residual_len2(p, t) <= thr2).collect()
    };
    let mut set = classify(&best);
    for _ in 0..50 {
        let inl: Vec<Correspondence> = vpts
            .iter()
            .zip(&set)
            .filter(|(_, &k)| k)
            .map(|(p, _)| *p)
            .collect();
        if inl.len() < need {
            break;
        }
        let next = classify(&least_squares(&inl, None, center)?);
        // Keep the last set that was large enough rather than collapse below the minimum.
        if next == set || next.iter().filter(|&&k| k).count() < need {
            break;
        }
        set = next;
    }
    let inl: Vec<Correspondence> = vpts
        .iter()
        .zip(&set)
        .filter(|(_, &k)| k)
        .map(|(p, _)| *p)
        .collect();
    if inl.len() < need {
        return Err(FitFailure::NoConsensus {
            best: inl.len(),
            total: n,
            need,
        });
    }
    // The model is the least-squares fit of exactly the reported inliers.
    let model = least_squares(&inl, None, center)?;
    let u = uabjm_detail(&inl, &model)?;
    let mut inliers = vec![false; points.len()];
    for (k, &i) in valid.iter().enumerate() {
        inliers[i] = set[k];
    }
    Ok(SimilarityFit {
        transform: model,
        inliers,
        n_inliers: inl.len(),
        residual_rms_px: (u.sum_squares / inl.len() as f64).sqrt(),
        sigma2: u.sigma2,
        sigma2_point_convention: u.sigma2_point_convention,
        covariance: u.covariance,
        trials,
    })
}

fn params_of(t: &Similarity) -> [f64; 4] {
    [t.scale, t.rotation_rad, t.dx, t.dy]
}

/// Spatial delete-one-block jackknife of the least-squares fit (give it the inliers).
///
/// Points are grouped into square blocks of `block_px` (anchored at the smallest x, y); each
/// block is left out in turn and the fit redone. Correlation across block borders is ignored,
/// so blocks must be well above the residuals' correlation length — about twice the Farneback
/// box window (docs/validation.md#jackknife-blocks-of-two-windows) — and there should still be
/// ≳ 20 blocks.
/// Unequal block sizes use the delete-m_k jackknife of Busing, Meijer & van der Leeden (1999):
/// pseudo-values `θ̃_k = h_k θ̂ − (h_k − 1) θ̂₋ₖ` with `h_k = n/m_k`,
/// `Cov = (1/g) Σ (θ̃_k − θ̃)(θ̃_k − θ̃)ᵀ/(h_k − 1)`, `θ̃ = gθ̂ − Σ(1 − m_k/n) θ̂₋ₖ`;
/// for equal blocks this is the usual `(g − 1)/g Σ (θ̂₋ₖ − θ̄)(θ̂₋ₖ − θ̄)ᵀ`.
pub fn block_jackknife_covariance(
    points: &[Correspondence],
    center: [f64; 2],
    block_px: f64,
) -> Result<[[f64; 4]; 4], FitFailure> {
    let pts: Vec<Correspondence> = points.iter().copied().filter(|p| p.is_finite()).collect();
    if !(block_px > 0.0 && block_px.is_finite()) {
        return Err(FitFailure::Degenerate("block size must be positive".into()));
    }
    let n = pts.len();
    if n < 3 {
        return Err(FitFailure::TooFewPoints { have: n, need: 3 });
    }
    let x0 = pts.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
    let y0 = pts.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
    let mut blocks: BTreeMap<(i64, i64), Vec<usize>> = BTreeMap::new();
    for (i, p) in pts.iter().enumerate() {
        let key = (
            ((p.x - x0) / block_px).floor() as i64,
            ((p.y - y0) / block_px).floor() as i64,
        );
        blocks.entry(key).or_default().push(i);
    }
    let g = blocks.len();
    if g < 3 {
        return Err(FitFailure::TooFewPoints { have: g, need: 3 });
    }
    let full = params_of(&least_squares(&pts, None, center)?);
    let mut pseudo: Vec<([f64; 4], f64)> = Vec::with_capacity(g);
    let mut keep = vec![true; n];
    for members in blocks.values() {
        for &i in members {
            keep[i] = false;
        }
        let rest: Vec<Correspondence> = pts
            .iter()
            .zip(&keep)
            .filter(|(_, &k)| k)
            .map(|(p, _)| *p)
            .collect();
        for &i in members {
            keep[i] = true;
        }
        let loo = params_of(&least_squares(&rest, None, center)?);
        let h = n as f64 / members.len() as f64;
        let value = [0, 1, 2, 3].map(|k| h * full[k] - (h - 1.0) * loo[k]);
        pseudo.push((value, h));
    }
    // θ̃ = gθ̂ − Σ(1 − 1/h_k)θ̂₋ₖ, written through the pseudo-values: Σ θ̃_k / h_k.
    let centre_value = [0, 1, 2, 3].map(|k| pseudo.iter().map(|(v, h)| v[k] / h).sum::<f64>());
    let mut cov = [[0.0; 4]; 4];
    for (v, h) in &pseudo {
        for i in 0..4 {
            for j in 0..4 {
                cov[i][j] += (v[i] - centre_value[i]) * (v[j] - centre_value[j]) / (h - 1.0);
            }
        }
    }
    Ok(scaled(&cov, 1.0 / g as f64))
}

/// Variance inflation `n / n_eff` for `n` points spread over `area_px2` whose residuals are
/// correlated over `correlation_length_px`: `n_eff = area / L²`, clamped to `[1, n]`.
/// `L²` is the integral of the residual correlation function: a box window of width w gives
/// `L = w`; a Gaussian correlation `exp(−r²/2ℓ²)` gives `L = √(2π)·ℓ`.
/// Multiply a UABJM covariance by this factor (σ by its square root).
pub fn ess_inflation_factor(n_points: usize, area_px2: f64, correlation_length_px: f64) -> f64 {
    let n = n_points as f64;
    if n_points == 0 || !is_positive(area_px2) || !is_positive(correlation_length_px) {
        return 1.0;
    }
    let n_eff = (area_px2 / (correlation_length_px * correlation_length_px)).clamp(1.0, n);
    n / n_eff
}

/// Correlation of two residual components of the same axis at separation (dx, dy);
/// components of different axes are taken as uncorrelated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CorrelationModel {
    /// Autocorrelation of a `width_px` box average of white noise (Farneback box window):
    /// `(1 − |dx|/w)₊ (1 − |dy|/w)₊`.
    Box { width_px: f64 },
    /// `exp(−r²/2ℓ²)`.
    Gaussian { sigma_px: f64 },
}

impl CorrelationModel {
    pub fn rho(&self, dx: f64, dy: f64) -> f64 {
        match *self {
            CorrelationModel::Box { width_px } => {
                ((1.0 - dx.abs() / width_px).max(0.0)) * ((1.0 - dy.abs() / width_px).max(0.0))
            }
            CorrelationModel::Gaussian { sigma_px } => {
                (-(dx * dx + dy * dy) / (2.0 * sigma_px * sigma_px)).exp()
            }
        }
    }
}

/// Sandwich covariance of the least-squares fit when the residuals are correlated as
/// `model` says: `Cov = σ²(JᵀJ)⁻¹(JᵀRJ)(JᵀJ)⁻¹`, with σ² estimated without bias under the
/// same model, `σ² = S / (2n − tr[(JᵀJ)⁻¹JᵀRJ])` (which is `S/(2n − 4)` for R = I).
/// Returns `(Cov, σ²)`. Cost O(n²): fine for the few hundred grid-cell points.
pub fn correlated_covariance(
    points: &[Correspondence],
    transform: &Similarity,
    model: CorrelationModel,
) -> Result<([[f64; 4]; 4], f64), FitFailure> {
    let pts: Vec<Correspondence> = points.iter().copied().filter(|p| p.is_finite()).collect();
    let n = pts.len();
    if n < 3 {
        return Err(FitFailure::TooFewPoints { have: n, need: 3 });
    }
    let valid_model = match model {
        CorrelationModel::Box { width_px } => width_px > 0.0 && width_px.is_finite(),
        CorrelationModel::Gaussian { sigma_px } => sigma_px > 0.0 && sigma_px.is_finite(),
    };
    if !valid_model {
        return Err(FitFailure::Degenerate(
            "correlation length must be positive".into(),
        ));
    }
    let jac = jacobian(&pts, transform);
    let inv = invert(&jtj(&jac))?;
    // meat = Σ_axis Jₐᵀ R Jₐ, via (R Jₐ) row by row: 8 multiply-adds per pair.
    let mut meat = Matrix4::<f64>::zeros();
    for i in 0..n {
        let mut rj = [[0.0; 4]; 2];
        for j in 0..n {
            let rho = model.rho(pts[i].x - pts[j].x, pts[i].y - pts[j].y);
            if rho == 0.0 {
                continue;
            }
            for axis in 0..2 {
                for a in 0..4 {
                    rj[axis][a] += rho * jac[j][axis][a];
                }
            }
        }
        for axis in 0..2 {
            for a in 0..4 {
                for b in 0..4 {
                    meat[(a, b)] += jac[i][axis][a] * rj[axis][b];
                }
            }
        }
    }
    let s: f64 = pts.iter().map(|p| residual_len2(p, transform)).sum();
    let dof = 2.0 * n as f64 - (inv * meat).trace();
    if !is_positive(dof) {
        return Err(FitFailure::TooFewPoints { have: n, need: 3 });
    }
    let sigma2 = s / dof;
    Ok((to_array(&(inv * meat * inv * sigma2)), sigma2))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::sigmas;
    use nalgebra::DMatrix;

    fn truth(seed: u64, center: [f64; 2]) -> Similarity {
        // The paper's Monte Carlo ranges (table 1).
        let mut r = SplitMix64::new(seed ^ 0xA5A5_5A5A);
        Similarity {
            scale: r.uniform(0.995, 1.005),
            rotation_rad: r.uniform(-0.01, 0.01),
            dx: r.uniform(-5.0, 5.0),
            dy: r.uniform(-5.0, 5.0),
            center,
        }
    }

    fn grid(n: usize, spacing: f64, origin: f64) -> Vec<[f64; 2]> {
        let mut v = Vec::new();
        for j in 0..n {
            for i in 0..n {
                v.push([origin + i as f64 * spacing, origin + j as f64 * spacing]);
            }
        }
        v
    }

    /// Correspondences of `t` at `pts`, with per-point additive errors `(eu, ev)`.
    fn corr(pts: &[[f64; 2]], t: &Similarity, eu: &[f64], ev: &[f64]) -> Vec<Correspondence> {
        pts.iter()
            .enumerate()
            .map(|(k, p)| {
                let q = t.apply(*p);
                Correspondence {
                    x: p[0],
                    y: p[1],
                    u: q[0] - p[0] + eu[k],
                    v: q[1] - p[1] + ev[k],
                }
            })
            .collect()
    }

    fn errors(est: &Similarity, t: &Similarity) -> [f64; 4] {
        [
            est.scale - t.scale,
            est.rotation_rad - t.rotation_rad,
            est.dx - t.dx,
            est.dy - t.dy,
        ]
    }

    #[test]
    fn noiseless_correspondences_give_the_injected_similarity() {
        let c = [511.5, 511.5];
        let t = Similarity {
            scale: 1.0031,
            rotation_rad: 0.0087,
            dx: 3.3,
            dy: -4.7,
            center: c,
        };
        let pts = grid(12, 80.0, 70.0);
        let zero = vec![0.0; pts.len()];
        let cs = corr(&pts, &t, &zero, &zero);
        let fit = fit_similarity(&cs, c, &RansacParams::default()).unwrap();
        assert_eq!(fit.n_inliers, pts.len());
        // Every point agrees with the all-points fit, so the adaptive stop needs no trial.
        assert_eq!(fit.trials, 0);
        for e in errors(&fit.transform, &t) {
            assert!(e.abs() < 1e-9, "{e}");
        }
        assert!(fit.residual_rms_px < 1e-9);
        // Weighted least squares of exact data is exact too.
        let w: Vec<f64> = (0..cs.len()).map(|k| 1.0 + (k % 5) as f64).collect();
        let ls = least_squares(&cs, Some(&w), c).unwrap();
        for e in errors(&ls, &t) {
            assert!(e.abs() < 1e-9, "{e}");
        }
    }

    #[test]
    fn uabjm_matches_scipy_curve_fit() {
        // Oracle (numpy/scipy, Python 3.11): c = [50, 40]; pts, uv as below; frame = pts + uv.
        // Parameters: numpy.linalg.lstsq on the linear form (a, b, dx, dy), s = hypot(a, b),
        // θ = atan2(b, a). Covariance: scipy.optimize.curve_fit started there, with
        //   model(_, s, th, dx, dy) = (s·(pts − c)·R(th)ᵀ + c + [dx, dy]).ravel(),
        //   ftol = xtol = gtol = 1e-15; its pcov is (JᵀJ)⁻¹·S/(2n − 4) (2n residuals).
        let c = [50.0, 40.0];
        let pts = [
            [3., 5.],
            [90., 12.],
            [47., 77.],
            [20., 60.],
            [71., 33.],
            [88., 79.],
            [10., 30.],
            [55., 5.],
        ];
        let uv = [
            [1.21, -0.48],
            [1.63, 0.02],
            [0.71, -0.10],
            [0.85, -0.61],
            [1.42, -0.22],
            [1.19, 0.33],
            [1.02, -0.71],
            [1.55, -0.47],
        ];
        let cs: Vec<Correspondence> = pts
            .iter()
            .zip(&uv)
            .map(|(p, d)| Correspondence {
                x: p[0],
                y: p[1],
                u: d[0],
                v: d[1],
            })
            .collect();
        let want_params = [
            1.0050813014022288,
            0.00814801108270881,
            1.188146233693959,
            -0.25163250162322776,
        ];
        let want_cov: [[f64; 4]; 4] = [
            [
                1.3888039524e-06,
                2.4820506580e-13,
                2.7506502536e-06,
                3.3209176966e-06,
            ],
            [
                2.4820506580e-13,
                1.3747958701e-06,
                -3.3041746682e-06,
                2.7367459211e-06,
            ],
            [
                2.7506502536e-06,
                -3.3041746682e-06,
                2.5868221782e-03,
                -1.0126779647e-10,
            ],
            [
                3.3209176966e-06,
                2.7367459211e-06,
                -1.0126779647e-10,
                2.5868194174e-03,
            ],
        ];
        let t = least_squares(&cs, None, c).unwrap();
        let got = [t.scale, t.rotation_rad, t.dx, t.dy];
        for k in 0..4 {
            assert!(
                (got[k] - want_params[k]).abs() < 1e-12,
                "param {k}: {} vs {}",
                got[k],
                want_params[k]
            );
        }
        let (cov, _) = uabjm(&cs, &t).unwrap();
        for i in 0..4 {
            for j in 0..4 {
                // curve_fit's pcov moves by ~1e-6 relative between runs from other starts.
                let scale = (want_cov[i][i] * want_cov[j][j]).sqrt();
                assert!(
                    (cov[i][j] - want_cov[i][j]).abs() < 1e-5 * scale,
                    "cov[{i}][{j}]: {} vs {}",
                    cov[i][j],
                    want_cov[i][j]
                );
            }
        }
    }

    #[test]
    fn collinear_points_still_fix_a_similarity() {
        // Two distinct points determine all four parameters, so a line is not degenerate.
        let c = [100.0, 100.0];
        let t = Similarity {
            scale: 0.998,
            rotation_rad: -0.004,
            dx: 1.5,
            dy: 0.25,
            center: c,
        };
        let pts: Vec<[f64; 2]> = (0..10).map(|k| [10.0 + 20.0 * k as f64, 50.0]).collect();
        let zero = vec![0.0; pts.len()];
        let fit =
            fit_similarity(&corr(&pts, &t, &zero, &zero), c, &RansacParams::default()).unwrap();
        for e in errors(&fit.transform, &t) {
            assert!(e.abs() < 1e-9, "{e}");
        }
    }

    #[test]
    fn thirty_percent_gross_outliers_are_rejected() {
        let c = [479.5, 479.5];
        let t = truth(3, c);
        let pts = grid(16, 60.0, 30.0);
        let n = pts.len();
        let mut r = SplitMix64::new(11);
        let sigma_n = 0.02;
        let mut eu: Vec<f64> = (0..n).map(|_| sigma_n * r.gaussian()).collect();
        let mut ev: Vec<f64> = (0..n).map(|_| sigma_n * r.gaussian()).collect();
        let mut is_outlier = vec![false; n];
        let mut placed = 0;
        while placed < n * 3 / 10 {
            let k = r.below(n);
            if is_outlier[k] {
                continue;
            }
            is_outlier[k] = true;
            placed += 1;
            let (mag, ang) = (r.uniform(3.0, 30.0), r.uniform(0.0, std::f64::consts::TAU));
            eu[k] = mag * ang.cos();
            ev[k] = mag * ang.sin();
        }
        let cs = corr(&pts, &t, &eu, &ev);
        let params = RansacParams {
            threshold_px: 0.5,
            ..RansacParams::default()
        };
        let fit = fit_similarity(&cs, c, &params).unwrap();
        let expected_inliers: Vec<bool> = is_outlier.iter().map(|o| !o).collect();
        assert_eq!(fit.inliers, expected_inliers);
        // Inlier ratio 0.7: ln(1 − 0.9999)/ln(1 − 0.49) = 13.7, so 14 trials after the best
        // model is found (if found on trial k, at most k + 14 in all).
        assert!(fit.trials < 100, "{} trials", fit.trials);
        let sig = sigmas(&fit.covariance);
        let err = errors(&fit.transform, &t);
        for k in 0..4 {
            assert!(
                err[k].abs() < 4.0 * sig[k],
                "param {k}: {} vs σ {}",
                err[k],
                sig[k]
            );
        }
        assert!(err[2].abs() < 0.01 && err[3].abs() < 0.01);
        // The residual variance estimate recovers the injected noise level (179 inliers:
        // relative standard error of σ² is about 7.5 %).
        assert!(
            (fit.sigma2 / (sigma_n * sigma_n) - 1.0).abs() < 0.25,
            "{}",
            fit.sigma2
        );
        // Same seed, same answer; and plain least squares is ruined by the outliers.
        assert_eq!(fit_similarity(&cs, c, &params).unwrap(), fit);
        let naive = least_squares(&cs, None, c).unwrap();
        assert!((naive.dx - t.dx).abs().max((naive.dy - t.dy).abs()) > 0.1);
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let c = [300.0, 200.0];
        let t = Similarity {
            scale: 1.004,
            rotation_rad: 0.3,
            dx: -2.0,
            dy: 7.0,
            center: c,
        };
        let pts = [[0.0, 0.0], [620.0, 15.0], [310.0, 410.0], [77.0, 333.0]];
        let cs: Vec<Correspondence> = pts
            .iter()
            .map(|p| Correspondence {
                x: p[0],
                y: p[1],
                u: 0.0,
                v: 0.0,
            })
            .collect();
        let jac = jacobian(&cs, &t);
        let steps = [1e-6, 1e-6, 1e-4, 1e-4];
        for (k, p) in pts.iter().enumerate() {
            for param in 0..4 {
                let shifted = |sign: f64| {
                    let mut q = t;
                    let h = sign * steps[param];
                    match param {
                        0 => q.scale += h,
                        1 => q.rotation_rad += h,
                        2 => q.dx += h,
                        _ => q.dy += h,
                    }
                    q.apply(*p)
                };
                let (plus, minus) = (shifted(1.0), shifted(-1.0));
                for axis in 0..2 {
                    let fd = (plus[axis] - minus[axis]) / (2.0 * steps[param]);
                    let an = jac[k][axis][param];
                    assert!(
                        (fd - an).abs() < 1e-6 * (1.0 + an.abs()),
                        "pt {k} axis {axis} param {param}: {fd} vs {an}"
                    );
                }
            }
        }
    }

    #[test]
    fn degenerate_inputs_are_errors_not_panics() {
        let c = [0.0, 0.0];
        let p = RansacParams::default();
        let at = |x: f64, y: f64, u: f64, v: f64| Correspondence { x, y, u, v };
        assert!(matches!(
            fit_similarity(&[], c, &p),
            Err(FitFailure::TooFewPoints { have: 0, .. })
        ));
        let two = [at(0.0, 0.0, 1.0, 1.0), at(5.0, 0.0, 1.0, 1.0)];
        assert!(matches!(
            fit_similarity(&two, c, &p),
            Err(FitFailure::TooFewPoints { .. })
        ));
        assert!(matches!(
            uabjm(&two, &Similarity::identity(c)),
            Err(FitFailure::TooFewPoints { .. })
        ));
        let same = vec![at(4.0, 4.0, 1.0, 1.0); 10];
        assert!(matches!(
            fit_similarity(&same, c, &p),
            Err(FitFailure::Degenerate(_))
        ));
        assert!(matches!(
            least_squares(&same, None, c),
            Err(FitFailure::Degenerate(_))
        ));
        let nan = vec![at(f64::NAN, 1.0, 0.0, 0.0); 10];
        assert!(matches!(
            fit_similarity(&nan, c, &p),
            Err(FitFailure::TooFewPoints { have: 0, .. })
        ));
        // Unrelated displacements: no model explains more than its own sample pair.
        let mut r = SplitMix64::new(5);
        let random: Vec<Correspondence> = grid(10, 50.0, 0.0)
            .iter()
            .map(|q| at(q[0], q[1], r.uniform(-50.0, 50.0), r.uniform(-50.0, 50.0)))
            .collect();
        let tight = RansacParams {
            threshold_px: 0.1,
            ..p
        };
        assert!(matches!(
            fit_similarity(&random, c, &tight),
            Err(FitFailure::NoConsensus { .. })
        ));
        let zero_thr = RansacParams {
            threshold_px: 0.0,
            ..p
        };
        assert!(matches!(
            fit_similarity(&random, c, &zero_thr),
            Err(FitFailure::Degenerate(_))
        ));
        assert!(least_squares(&random, Some(&[1.0]), c).is_err());
        assert!(least_squares(&random, Some(&vec![f64::NAN; random.len()]), c).is_err());
        assert!(block_jackknife_covariance(&random, c, 0.0).is_err());
        assert!(block_jackknife_covariance(&random, c, 1e4).is_err());
        let bad_model = CorrelationModel::Gaussian { sigma_px: 0.0 };
        assert!(correlated_covariance(&random, &Similarity::identity(c), bad_model).is_err());
    }

    #[test]
    fn failures_become_alignment_failed_with_exit_code_1() {
        let e: crate::Error = FitFailure::TooFewPoints { have: 1, need: 6 }.into();
        assert_eq!(e.exit_code(), crate::error::ExitCode::Failed);
        assert_eq!(
            e.to_string(),
            "alignment failed: too few usable correspondences: 1 (need at least 6)"
        );
    }

    #[test]
    fn ess_factor_on_hand_values() {
        // 400 points over 1000² px with L = 100 → n_eff = 100 → factor 4.
        assert!((ess_inflation_factor(400, 1e6, 100.0) - 4.0).abs() < 1e-12);
        // Correlation shorter than the spacing: no inflation.
        assert_eq!(ess_inflation_factor(400, 1e6, 10.0), 1.0);
        // Correlation longer than the field: one effective sample.
        assert_eq!(ess_inflation_factor(400, 1e6, 5000.0), 400.0);
        assert_eq!(ess_inflation_factor(0, 1e6, 10.0), 1.0);
        let b = CorrelationModel::Box { width_px: 10.0 };
        assert!((b.rho(5.0, -2.5) - 0.5 * 0.75).abs() < 1e-15);
        assert_eq!(b.rho(10.0, 0.0), 0.0);
    }

    /// Coverage tallies: per parameter, how many trials had |error| ≤ σ and ≤ 3σ.
    #[derive(Default)]
    struct Coverage {
        within1: [usize; 4],
        within3: [usize; 4],
        trials: usize,
    }

    impl Coverage {
        fn add(&mut self, err: &[f64; 4], sig: &[f64; 4]) {
            self.trials += 1;
            for k in 0..4 {
                self.within1[k] += (err[k].abs() <= sig[k]) as usize;
                self.within3[k] += (err[k].abs() <= 3.0 * sig[k]) as usize;
            }
        }
        fn f1(&self) -> [f64; 4] {
            self.within1.map(|c| c as f64 / self.trials as f64)
        }
        fn f3(&self) -> [f64; 4] {
            self.within3.map(|c| c as f64 / self.trials as f64)
        }
    }

    #[test]
    fn iid_noise_coverage_of_uabjm_and_jackknife() {
        // 500 Monte Carlo trials, i.i.d. Gaussian flow errors of 0.05 px per component on a
        // 16×16 grid. Expected: 68.3 % within 1σ (binomial σ of the fraction: 2.1 %),
        // 99.7 % within 3σ. The jackknife has 64 blocks of 2×2 points.
        let c = [479.5, 479.5];
        let pts = grid(16, 60.0, 30.0);
        let n = pts.len();
        let (mut plain, mut paper, mut jack) = (
            Coverage::default(),
            Coverage::default(),
            Coverage::default(),
        );
        for seed in 0..500u64 {
            let t = truth(seed, c);
            let mut r = SplitMix64::new(seed);
            let eu: Vec<f64> = (0..n).map(|_| 0.05 * r.gaussian()).collect();
            let ev: Vec<f64> = (0..n).map(|_| 0.05 * r.gaussian()).collect();
            let cs = corr(&pts, &t, &eu, &ev);
            let fit = fit_similarity(
                &cs,
                c,
                &RansacParams {
                    seed,
                    ..RansacParams::default()
                },
            )
            .unwrap();
            assert_eq!(fit.n_inliers, n);
            let err = errors(&fit.transform, &t);
            plain.add(&err, &sigmas(&fit.covariance));
            let ratio = fit.sigma2_point_convention / fit.sigma2;
            paper.add(&err, &sigmas(&scaled(&fit.covariance, ratio)));
            let jk = block_jackknife_covariance(&fit.inlier_points(&cs), c, 120.0).unwrap();
            jack.add(&err, &sigmas(&jk));
        }
        eprintln!(
            "iid 1σ: uabjm {:?} paper {:?} jackknife {:?}",
            plain.f1(),
            paper.f1(),
            jack.f1()
        );
        eprintln!("iid 3σ: uabjm {:?} jackknife {:?}", plain.f3(), jack.f3());
        for (k, name) in PARAMS.iter().enumerate() {
            let (u1, j1, p1) = (plain.f1()[k], jack.f1()[k], paper.f1()[k]);
            assert!(
                (0.62..=0.75).contains(&u1),
                "UABJM 1σ coverage of {name}: {u1}"
            );
            assert!(
                (0.62..=0.75).contains(&j1),
                "jackknife 1σ coverage of {name}: {j1}"
            );
            assert!(plain.f3()[k] >= 0.98 && jack.f3()[k] >= 0.98);
            // σ² = S/(n − 4) makes σ √2 too large: 84 % within 1σ.
            assert!(
                (0.79..=0.89).contains(&p1),
                "point-convention coverage of {name}: {p1}"
            );
        }
    }

    #[test]
    fn correlated_noise_breaks_uabjm_but_not_jackknife_or_sandwich() {
        // Flow errors correlated like exp(−r²/2ℓ²), ℓ = 40 px, on a 24×24 grid of 40 px spacing
        // (so neighbours correlate at 0.61), drawn through a Cholesky factor of the exact
        // correlation matrix. 400 trials: binomial σ of a 68 % fraction is 2.3 %.
        let c = [479.5, 479.5];
        let ell = 40.0;
        let pts = grid(24, 40.0, 20.0);
        let n = pts.len();
        let model = CorrelationModel::Gaussian { sigma_px: ell };
        let corr_matrix = DMatrix::from_fn(n, n, |i, j| {
            model.rho(pts[i][0] - pts[j][0], pts[i][1] - pts[j][1])
                + if i == j { 1e-9 } else { 0.0 }
        });
        let chol = corr_matrix
            .cholesky()
            .expect("correlation matrix is positive definite");
        let l = chol.l();
        let area = n as f64 * 40.0 * 40.0;
        let ess = ess_inflation_factor(n, area, (std::f64::consts::TAU).sqrt() * ell);
        let (mut plain, mut jack, mut sand, mut infl) = (
            Coverage::default(),
            Coverage::default(),
            Coverage::default(),
            Coverage::default(),
        );
        for seed in 0..400u64 {
            let t = truth(seed, c);
            let mut r = SplitMix64::new(1000 + seed);
            let zu = nalgebra::DVector::from_fn(n, |_, _| r.gaussian());
            let zv = nalgebra::DVector::from_fn(n, |_, _| r.gaussian());
            let (eu, ev) = ((&l * zu) * 0.05, (&l * zv) * 0.05);
            let cs = corr(&pts, &t, eu.as_slice(), ev.as_slice());
            let fit = fit_similarity(
                &cs,
                c,
                &RansacParams {
                    seed,
                    ..RansacParams::default()
                },
            )
            .unwrap();
            let err = errors(&fit.transform, &t);
            plain.add(&err, &sigmas(&fit.covariance));
            infl.add(&err, &sigmas(&scaled(&fit.covariance, ess)));
            let inl = fit.inlier_points(&cs);
            jack.add(
                &err,
                &sigmas(&block_jackknife_covariance(&inl, c, 200.0).unwrap()),
            );
            let (cov, _) = correlated_covariance(&inl, &fit.transform, model).unwrap();
            sand.add(&err, &sigmas(&cov));
        }
        eprintln!(
            "correlated 1σ: uabjm {:?} jackknife {:?} sandwich {:?} ess×{ess:.2} {:?}",
            plain.f1(),
            jack.f1(),
            sand.f1(),
            infl.f1()
        );
        eprintln!(
            "correlated 3σ: uabjm {:?} jackknife {:?} sandwich {:?} ess {:?}",
            plain.f3(),
            jack.f3(),
            sand.f3(),
            infl.f3()
        );
        for (k, name) in PARAMS.iter().enumerate() {
            let (p1, j1, s1, i1) = (plain.f1()[k], jack.f1()[k], sand.f1()[k], infl.f1()[k]);
            assert!(p1 < 0.45, "UABJM should under-cover {name}: {p1}");
            assert!(
                (0.59..=0.76).contains(&j1),
                "jackknife 1σ coverage of {name}: {j1}"
            );
            assert!(
                (0.62..=0.75).contains(&s1),
                "sandwich 1σ coverage of {name}: {s1}"
            );
            assert!(
                (0.60..=0.85).contains(&i1),
                "ESS-inflated 1σ coverage of {name}: {i1}"
            );
            assert!(jack.f3()[k] >= 0.95 && sand.f3()[k] >= 0.97, "{name} 3σ");
        }
    }
}
