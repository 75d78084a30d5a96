//! The contract's geometry convention, in one place.
//!
//! A [`Similarity`] says where reference content appears in the frame:
//! `p_frame = s · R(θ) · (p_ref − c) + c + (dx, dy)`, with `c` the centre of the
//! reference array `((W−1)/2, (H−1)/2)` and `R(θ)` counter-clockwise in the
//! (x right, y up) plane, i.e. `[[cos, −sin], [sin, cos]]` acting on (x, y) pixel
//! coordinates (x = column = FITS axis 1, y = row = FITS axis 2, 0-based).

use serde::{Deserialize, Serialize};

pub const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// A 4-parameter similarity transform about a fixed centre.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Similarity {
    pub scale: f64,
    /// θ in radians (counter-clockwise, x right / y up).
    pub rotation_rad: f64,
    pub dx: f64,
    pub dy: f64,
    /// The centre `c` about which scale and rotation act (reference array centre).
    pub center: [f64; 2],
}

impl Similarity {
    pub fn identity(center: [f64; 2]) -> Self {
        Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: 0.0,
            dy: 0.0,
            center,
        }
    }

    /// Centre of an array of `width × height` pixels, `((W−1)/2, (H−1)/2)`.
    pub fn array_center(width: usize, height: usize) -> [f64; 2] {
        [(width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0]
    }

    /// Linear part `a = s cos θ`, `b = s sin θ`.
    pub fn ab(&self) -> (f64, f64) {
        (
            self.scale * self.rotation_rad.cos(),
            self.scale * self.rotation_rad.sin(),
        )
    }

    /// Map a reference-grid point to the frame grid.
    pub fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        let (a, b) = self.ab();
        let (x, y) = (p[0] - self.center[0], p[1] - self.center[1]);
        [
            a * x - b * y + self.center[0] + self.dx,
            b * x + a * y + self.center[1] + self.dy,
        ]
    }

    /// The inverse mapping (frame grid to reference grid), expressed about the same centre.
    pub fn inverse(&self) -> Self {
        // p_ref - c = (1/s) R(-θ) (p_frame - c - d)
        let inv_s = 1.0 / self.scale;
        let (c, s) = (self.rotation_rad.cos(), self.rotation_rad.sin());
        // translation term: -(1/s) R(-θ) d
        let tx = -inv_s * (c * self.dx + s * self.dy);
        let ty = -inv_s * (-s * self.dx + c * self.dy);
        Similarity {
            scale: inv_s,
            rotation_rad: -self.rotation_rad,
            dx: tx,
            dy: ty,
            center: self.center,
        }
    }

    /// `self ∘ first`: apply `first`, then `self`. The result uses `first`'s centre.
    pub fn after(&self, first: &Similarity) -> Self {
        let c = first.center;
        let scale = self.scale * first.scale;
        let rotation_rad = self.rotation_rad + first.rotation_rad;
        // Translation: where the centre goes, minus the centre.
        let q = self.apply(first.apply(c));
        Similarity {
            scale,
            rotation_rad,
            dx: q[0] - c[0],
            dy: q[1] - c[1],
            center: c,
        }
    }

    /// The same mapping expressed about another centre.
    pub fn recentered(&self, center: [f64; 2]) -> Self {
        let q = self.apply(center);
        Similarity {
            dx: q[0] - center[0],
            dy: q[1] - center[1],
            center,
            ..*self
        }
    }

    pub fn rotation_arcsec(&self) -> f64 {
        self.rotation_rad * ARCSEC_PER_RAD
    }
}

/// Covariance of the parameters `(scale, rotation_rad, dx, dy)`.
pub type Covariance4 = [[f64; 4]; 4];

impl Similarity {
    /// Parameters as a vector `(scale, rotation_rad, dx, dy)`.
    pub fn params(&self) -> [f64; 4] {
        [self.scale, self.rotation_rad, self.dx, self.dy]
    }

    /// Rebuild from `(scale, rotation_rad, dx, dy)` about `center`.
    pub fn from_params(p: [f64; 4], center: [f64; 2]) -> Self {
        Similarity {
            scale: p[0],
            rotation_rad: p[1],
            dx: p[2],
            dy: p[3],
            center,
        }
    }
}

/// `outer ∘ inner` with first-order propagation of independent parameter covariances:
/// `Cov = J_o Cov_o J_oᵀ + J_i Cov_i J_iᵀ` ([`composition_jacobians`]).
pub fn compose_with_covariance(
    outer: &Similarity,
    outer_cov: &Covariance4,
    inner: &Similarity,
    inner_cov: &Covariance4,
) -> (Similarity, Covariance4) {
    let composed = outer.after(inner);
    let (jo, ji) = composition_jacobians(outer, inner);
    let co = sandwich(&jo, outer_cov, &jo);
    let ci = sandwich(&ji, inner_cov, &ji);
    (composed, add(&co, &ci))
}

/// A 4 × 4 matrix.
pub type Matrix4 = [[f64; 4]; 4];

/// The Jacobians of `outer ∘ inner`'s parameters with respect to `outer`'s and to `inner`'s,
/// by central differences (the composition is smooth and cheap, so this avoids error-prone
/// hand derivatives).
pub fn composition_jacobians(outer: &Similarity, inner: &Similarity) -> (Matrix4, Matrix4) {
    let jac = |which_outer: bool| -> Matrix4 {
        let base = if which_outer {
            outer.params()
        } else {
            inner.params()
        };
        let mut j = [[0.0; 4]; 4];
        for k in 0..4 {
            let h = 1e-6 * base[k].abs().max(1e-3);
            let mut plus = base;
            let mut minus = base;
            plus[k] += h;
            minus[k] -= h;
            let eval = |p: [f64; 4]| -> [f64; 4] {
                if which_outer {
                    Similarity::from_params(p, outer.center)
                        .after(inner)
                        .params()
                } else {
                    outer
                        .after(&Similarity::from_params(p, inner.center))
                        .params()
                }
            };
            let (fp, fm) = (eval(plus), eval(minus));
            for r in 0..4 {
                j[r][k] = (fp[r] - fm[r]) / (2.0 * h);
            }
        }
        j
    };
    (jac(true), jac(false))
}

/// `A · C · Bᵀ`.
pub fn sandwich(a: &Matrix4, c: &Matrix4, b: &Matrix4) -> Matrix4 {
    let mut out = [[0.0; 4]; 4];
    for r in 0..4 {
        for s in 0..4 {
            let mut acc = 0.0;
            for i in 0..4 {
                for k in 0..4 {
                    acc += a[r][i] * c[i][k] * b[s][k];
                }
            }
            out[r][s] = acc;
        }
    }
    out
}

/// `a + b`.
pub fn add(a: &Matrix4, b: &Matrix4) -> Matrix4 {
    std::array::from_fn(|r| std::array::from_fn(|s| a[r][s] + b[r][s]))
}

/// The transpose of `a`.
pub fn transpose(a: &Matrix4) -> Matrix4 {
    std::array::from_fn(|r| std::array::from_fn(|s| a[s][r]))
}

/// Standard errors (square roots of the diagonal).
pub fn sigmas(cov: &Covariance4) -> [f64; 4] {
    [0, 1, 2, 3].map(|k| cov[k][k].max(0.0).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: [f64; 2], b: [f64; 2]) -> bool {
        (a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9
    }

    #[test]
    fn quarter_turn_is_counter_clockwise_in_x_right_y_up() {
        // +x axis rotated by +90° counter-clockwise lands on +y.
        let t = Similarity {
            scale: 1.0,
            rotation_rad: std::f64::consts::FRAC_PI_2,
            dx: 0.0,
            dy: 0.0,
            center: [0.0, 0.0],
        };
        assert!(close(t.apply([1.0, 0.0]), [0.0, 1.0]));
    }

    #[test]
    fn inverse_and_composition_round_trip() {
        let t = Similarity {
            scale: 1.003,
            rotation_rad: 0.007,
            dx: 2.5,
            dy: -1.25,
            center: [511.5, 511.5],
        };
        let p = [100.0, 900.0];
        assert!(close(t.inverse().apply(t.apply(p)), p));
        let id = t.inverse().after(&t);
        assert!((id.scale - 1.0).abs() < 1e-12 && id.rotation_rad.abs() < 1e-12);
        assert!(id.dx.abs() < 1e-9 && id.dy.abs() < 1e-9);
        let moved = t.recentered([0.0, 0.0]);
        assert!(close(moved.apply(p), t.apply(p)));
    }

    #[test]
    fn composition_covariance_matches_monte_carlo_of_known_errors() {
        // Truth: perturb `inner` by known Gaussian errors, compose, measure the spread.
        let outer = Similarity {
            scale: 1.01,
            rotation_rad: 0.3,
            dx: 4.0,
            dy: -2.0,
            center: [50.0, 40.0],
        };
        let inner = Similarity {
            scale: 0.999,
            rotation_rad: -0.01,
            dx: 1.0,
            dy: 0.5,
            center: [50.0, 40.0],
        };
        let sd = [1e-4, 2e-4, 0.05, 0.03];
        let mut cov_i = [[0.0; 4]; 4];
        for k in 0..4 {
            cov_i[k][k] = sd[k] * sd[k];
        }
        let zero = [[0.0; 4]; 4];
        let (_, cov) = compose_with_covariance(&outer, &zero, &inner, &cov_i);
        // Deterministic pseudo-normal draws (Box-Muller on a fixed LCG).
        let mut state: u64 = 12345;
        let mut uniform = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let n = 20000;
        let mut sum = [0.0; 4];
        let mut sum2 = [0.0; 4];
        for _ in 0..n {
            let mut p = inner.params();
            for k in 0..4 {
                let z =
                    (-2.0 * uniform().ln()).sqrt() * (2.0 * std::f64::consts::PI * uniform()).cos();
                p[k] += sd[k] * z;
            }
            let c = outer
                .after(&Similarity::from_params(p, inner.center))
                .params();
            for k in 0..4 {
                sum[k] += c[k];
                sum2[k] += c[k] * c[k];
            }
        }
        let predicted = sigmas(&cov);
        for k in 0..4 {
            let mean = sum[k] / n as f64;
            let sample_sd = (sum2[k] / n as f64 - mean * mean).sqrt();
            assert!(
                (sample_sd / predicted[k] - 1.0).abs() < 0.03,
                "param {k}: {sample_sd} vs {}",
                predicted[k]
            );
        }
    }
}
