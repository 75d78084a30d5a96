//! Chained ("absolute") pointing: the transform from a series' origin grid (its first
//! reference) to each frame's grid, built from frame-to-reference alignments, with its errors.
//!
//! A chain is the transform from the chain's origin grid (the first reference of the channel)
//! to a frame's grid, `T_F = A ∘ T_R`, where `A` maps reference `R` to frame `F` (the engine's
//! answer) and `T_R` is the reference's own chain. Parameters are `p = (s, θ, dx, dy)`.
//! With `T_R` about the origin centre `c_T` and `A` about the reference centre `c_A`:
//!
//! ```text
//! s = s_A s_T,  θ = θ_A + θ_T,  d = s_A R(θ_A) u + c_A + d_A − c_T,  u = c_T + d_T − c_A
//! ```
//!
//! The covariance is propagated to first order, treating `A` and `T_R` as independent
//! (they come from different image pairs): `Σ = J_A Σ_A J_Aᵀ + J_T Σ_T J_Tᵀ`
//! ([`crate::geometry::compose_with_covariance`]), where analytically
//! `∂s/∂s_A = s_T, ∂s/∂s_T = s_A; ∂θ/∂θ_A = ∂θ/∂θ_T = 1; ∂d/∂s_A = R_A u, ∂d/∂θ_A = s_A R'_A u,
//! ∂d/∂d_A = I, ∂d/∂d_T = s_A R_A`. `Σ_A` is the engine's calibrated covariance. The first
//! reference has the identity chain with zero covariance, so `sigma_chained_*` grow like a
//! random walk over keyframe hand-overs. Messages carry σ only; a restart continues from the
//! full covariance stored in the last `/reference` message.

use crate::engine::AlignOutcome;
use crate::geometry::{
    add, composition_jacobians, sandwich, sigmas, Covariance4 as Cov4, Matrix4, Similarity,
    ARCSEC_PER_RAD,
};
use crate::record::{FrameAlignment, Status};
/// A chained transform (origin grid → this grid) and its covariance, if known.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chain {
    pub transform: Similarity,
    pub covariance: Option<Cov4>,
    /// The plate scale (x, y; arcsec/px) alignments to the origin use: the origin grid's,
    /// in which the chained shifts are expressed.
    pub plate_scale_arcsec: Option<[f64; 2]>,
}

impl Chain {
    /// The chain of an origin: identity about its own centre, exactly known.
    pub fn origin(center: [f64; 2], plate_scale_arcsec: Option<[f64; 2]>) -> Chain {
        Chain {
            transform: Similarity::identity(center),
            covariance: Some([[0.0; 4]; 4]),
            plate_scale_arcsec,
        }
    }

    /// `chained_dx_px`, `chained_dy_px` in arcsec.
    pub fn shift_arcsec(&self) -> Option<[f64; 2]> {
        let p = self.plate_scale_arcsec?;
        Some([self.transform.dx * p[0], self.transform.dy * p[1]])
    }

    /// `step ∘ self`, with first-order covariance propagation (see the module docs).
    /// The covariance is unknown when either factor's is.
    pub fn then(&self, step: &Similarity, step_cov: Option<&Cov4>) -> Chain {
        self.then_carrying(step, step_cov).0
    }

    /// [`Chain::then`], and the Jacobian of the result with respect to `self`'s parameters:
    /// the result's error is `J · e_self` plus the step's, so its covariance with any other
    /// chain's error `e` is `J · Cov(e_self, e)`.
    pub fn then_carrying(&self, step: &Similarity, step_cov: Option<&Cov4>) -> (Chain, Matrix4) {
        let (j_step, j_self) = composition_jacobians(step, &self.transform);
        let covariance = match (step_cov, self.covariance.as_ref()) {
            (Some(sc), Some(cc)) => Some(add(
                &sandwich(&j_step, sc, &j_step),
                &sandwich(&j_self, cc, &j_self),
            )),
            _ => None,
        };
        let chain = Chain {
            transform: step.after(&self.transform),
            covariance,
            plate_scale_arcsec: self.plate_scale_arcsec,
        };
        (chain, j_self)
    }

    /// 1-σ of (scale, rotation_rad, dx, dy).
    pub fn sigmas(&self) -> Option<[f64; 4]> {
        self.covariance.as_ref().map(sigmas)
    }
}

/// Two estimates of one keyframe's chain, combined: through the last keyframe and through
/// the one before it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Combined {
    pub chain: Chain,
    /// `G`: the combination is `a + G (b − a)`, so its error is `e_a + G (e_b − e_a)`.
    pub gain: Matrix4,
    pub closure: Closure,
}

/// How far two estimates of one chain are apart (`b − a`, per parameter), and the σ of that
/// difference: a closure that holds stays within a few σ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Closure {
    pub difference: [f64; 4],
    pub sigma: [f64; 4],
}

impl Closure {
    /// `difference / sigma` per parameter (0 where a parameter's difference has no σ).
    pub fn z(&self) -> [f64; 4] {
        std::array::from_fn(|k| match self.sigma[k] > 0.0 {
            true => self.difference[k] / self.sigma[k],
            false => 0.0,
        })
    }
}

/// The best linear combination of two estimates `a` and `b` of one chain whose errors have
/// covariance `cross = Cov(e_a, e_b)`: `a + (Σ_a − Σ_ab) D⁻¹ (b − a)`, with
/// `D = Σ_a + Σ_b − Σ_ab − Σ_ba` the covariance of `b − a`, and the covariance
/// `Σ_a − (Σ_a − Σ_ab) D⁻¹ (Σ_a − Σ_ba)`. A parameter both ways know exactly (no variance in
/// `D`: nothing fitted it) keeps `a`'s value. `None` without both covariances, or when `D` is
/// singular otherwise.
pub fn combine(a: &Chain, b: &Chain, cross: &Cov4) -> Option<Combined> {
    use nalgebra::Matrix4 as M;
    let m = |c: &Cov4| M::from_fn(|r, s| c[r][s]);
    let (sa, sb, sab) = (
        m(a.covariance.as_ref()?),
        m(b.covariance.as_ref()?),
        m(cross),
    );
    let d = sa + sb - sab - sab.transpose();
    // D⁻¹ on the parameters that vary; zero elsewhere.
    let varies: [bool; 4] = std::array::from_fn(|k| d[(k, k)] > 0.0);
    let mut reduced = d;
    for k in 0..4 {
        if !varies[k] {
            for j in 0..4 {
                reduced[(k, j)] = 0.0;
                reduced[(j, k)] = 0.0;
            }
            reduced[(k, k)] = 1.0;
        }
    }
    let mut d_inv = reduced.try_inverse()?;
    for k in (0..4).filter(|&k| !varies[k]) {
        d_inv[(k, k)] = 0.0;
    }
    let gain = (sa - sab) * d_inv;
    let diff = nalgebra::Vector4::from(b.transform.params())
        - nalgebra::Vector4::from(a.transform.params());
    let p = nalgebra::Vector4::from(a.transform.params()) + gain * diff;
    let cov = sa - gain * (sa - sab.transpose());
    let cov = 0.5 * (cov + cov.transpose());
    let arr =
        |x: &M<f64>| -> Matrix4 { std::array::from_fn(|r| std::array::from_fn(|s| x[(r, s)])) };
    if !(p.iter().all(|v| v.is_finite()) && cov.iter().all(|v| v.is_finite())) {
        return None;
    }
    Some(Combined {
        chain: Chain {
            transform: Similarity::from_params(p.into(), a.transform.center),
            covariance: Some(arr(&cov)),
            plate_scale_arcsec: a.plate_scale_arcsec,
        },
        gain: arr(&gain),
        closure: Closure {
            difference: diff.into(),
            sigma: std::array::from_fn(|k| d[(k, k)].max(0.0).sqrt()),
        },
    })
}

/// `Cov(e, x)` for an error `e = e_a + G (e_b − e_a)` of a combination, from the covariances
/// of its two estimates' errors with `x`.
pub fn combined_cross(gain: &Matrix4, cov_a_x: &Cov4, cov_b_x: &Cov4) -> Cov4 {
    let one_minus: Matrix4 =
        std::array::from_fn(|r| std::array::from_fn(|s| IDENTITY[r][s] - gain[r][s]));
    add(
        &sandwich(&one_minus, cov_a_x, &IDENTITY),
        &sandwich(gain, cov_b_x, &IDENTITY),
    )
}

/// `J · C · Kᵀ`: the covariance of two carried errors `J e` and `K x`, from `C = Cov(e, x)`.
pub fn carried(j: &Matrix4, c: &Cov4, k: &Matrix4) -> Cov4 {
    sandwich(j, c, k)
}

/// The identity, the Jacobian of an error carried unchanged.
pub const IDENTITY: Matrix4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// Write `chain` into a message's chained fields (`None`: no chain).
pub fn set_chain(m: &mut FrameAlignment, chain: Option<&Chain>) {
    let sig = chain.and_then(|c| c.sigmas());
    let arcsec = chain.and_then(|c| c.shift_arcsec());
    let plate = chain.and_then(|c| c.plate_scale_arcsec);
    let sig_arcsec = sig
        .zip(plate)
        .map(|(s, p)| [s[2] * p[0].abs(), s[3] * p[1].abs()]);
    m.chained_dx_px = chain.map(|c| c.transform.dx);
    m.chained_dy_px = chain.map(|c| c.transform.dy);
    m.chained_dx_arcsec = arcsec.map(|a| a[0]);
    m.chained_dy_arcsec = arcsec.map(|a| a[1]);
    m.chained_rotation_arcsec = chain.map(|c| c.transform.rotation_arcsec());
    m.chained_scale = chain.map(|c| c.transform.scale);
    m.sigma_chained_dx_px = sig.map(|s| s[2]);
    m.sigma_chained_dy_px = sig.map(|s| s[3]);
    m.sigma_chained_dx_arcsec = sig_arcsec.map(|s| s[0]);
    m.sigma_chained_dy_arcsec = sig_arcsec.map(|s| s[1]);
    m.sigma_chained_rotation_arcsec = sig.map(|s| s[1] * ARCSEC_PER_RAD);
    m.sigma_chained_scale = sig.map(|s| s[0]);
}

/// The chain of a frame aligned by `outcome` to a reference whose chain is `ref_chain`.
/// A chain restored from a log that does not give its origin's plate scale takes the one the
/// alignment to its reference used (one instrument's series: the same, within the disk fit).
pub fn chain_after(ref_chain: Option<&Chain>, outcome: &AlignOutcome) -> Option<Chain> {
    chain_after_carrying(ref_chain, outcome).map(|(chain, _)| chain)
}

/// [`chain_after`], and the Jacobian of the chain with respect to `ref_chain`'s parameters
/// ([`Chain::then_carrying`]).
pub fn chain_after_carrying(
    ref_chain: Option<&Chain>,
    outcome: &AlignOutcome,
) -> Option<(Chain, Matrix4)> {
    let step = outcome.transform.as_ref()?;
    if outcome.result.status == Status::Failed {
        return None;
    }
    let (mut chain, j) = ref_chain?.then_carrying(step, outcome.covariance.as_ref());
    if chain.plate_scale_arcsec.is_none() {
        chain.plate_scale_arcsec = outcome.reference_geometry.map(|g| g.plate_scale_arcsec);
    }
    Some((chain, j))
}

/// The chain a message carries (diagonal covariance only: messages hold σ, not correlations).
pub fn chain_from_message(m: &FrameAlignment, center: Option<[f64; 2]>) -> Option<Chain> {
    let center = center?;
    let transform = Similarity {
        scale: m.chained_scale?,
        rotation_rad: m.chained_rotation_arcsec? / ARCSEC_PER_RAD,
        dx: m.chained_dx_px?,
        dy: m.chained_dy_px?,
        center,
    };
    let covariance = match (
        m.sigma_chained_scale,
        m.sigma_chained_rotation_arcsec,
        m.sigma_chained_dx_px,
        m.sigma_chained_dy_px,
    ) {
        (Some(s), Some(r), Some(x), Some(y)) => {
            let mut c = [[0.0; 4]; 4];
            c[0][0] = s * s;
            c[1][1] = (r / ARCSEC_PER_RAD).powi(2);
            c[2][2] = x * x;
            c[3][3] = y * y;
            Some(c)
        }
        _ => None,
    };
    // The message gives the plate scale as the ratio of its arcsec to its px values.
    let ratio = |pairs: [(Option<f64>, Option<f64>); 2]| {
        pairs.into_iter().find_map(|(a, p)| match (a?, p?) {
            (a, p) if p != 0.0 && (a / p).is_finite() => Some(a / p),
            _ => None,
        })
    };
    let plate_x = ratio([
        (m.chained_dx_arcsec, m.chained_dx_px),
        (m.sigma_chained_dx_arcsec, m.sigma_chained_dx_px),
    ]);
    let plate_y = ratio([
        (m.chained_dy_arcsec, m.chained_dy_px),
        (m.sigma_chained_dy_arcsec, m.sigma_chained_dy_px),
    ]);
    Some(Chain {
        transform,
        covariance,
        plate_scale_arcsec: plate_x.zip(plate_y).map(|(x, y)| [x, y]),
    })
}
