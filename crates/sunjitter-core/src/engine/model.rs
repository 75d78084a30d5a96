//! Which transform a pair determines: scale and roll are fitted only where the images measure
//! them better than the instrument holds them.
//!
//! A telescope's plate scale and roll do not change by a per cent in hours; on a small or
//! evolving field the images measure them far worse than that (an IRIS slit-jaw field binned
//! to 110 px: scale to 1e-3, roll to 200″), and a chained series built from such fits drifts
//! by per cents. Where the fit's σ exceeds the instrument's stability (`scale_stability`,
//! `roll_stability_arcsec`) and its value agrees with the headers' within
//! [`AGREEMENT_SIGMAS`], the parameter is set to the headers' prediction with the stability
//! as its σ, and the others are conditioned on it: for a least-squares fit this is the
//! constrained fit's answer (`p_t + Σ_tf Σ_ff⁻¹ (μ_f − p_f)`, covariance
//! `Σ_tt − Σ_tf Σ_ff⁻¹ Σ_ft` plus the prior's, carried through the same gain). A value that
//! disagrees with the headers beyond that is a measured change (a focus change, a derotator
//! error): it is kept and fitted. Scale is fixed before roll (`rigid`), both give
//! `translation`.

use crate::geometry::{Covariance4, Similarity, ARCSEC_PER_RAD};
pub use crate::record::Model;
use serde::{Deserialize, Serialize};

/// Which model to fit (`[engine] model`): `auto` chooses by the instrument's stability.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelChoice {
    #[default]
    Auto,
    Similarity,
    Rigid,
    Translation,
}

/// How well the instrument holds its plate scale and roll between two frames: the prior
/// a parameter falls back on when the images measure it worse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelPrior {
    pub model: ModelChoice,
    /// Relative plate-scale stability (1-σ).
    pub scale_stability: f64,
    /// Roll stability, arcsec (1-σ).
    pub roll_stability_arcsec: f64,
}

/// A space telescope's plate scale holds to 1e-5–1e-4 over a day (focus and thermal
/// changes); the apparent size of the Sun, which changes more, is in the headers. Roll is
/// held to arcseconds by a spacecraft's star trackers; a ground-based derotator to
/// arcminutes. The defaults are the looser ends.
pub const SCALE_STABILITY: f64 = 1e-4;
pub const ROLL_STABILITY_ARCSEC: f64 = 60.0;

impl Default for ModelPrior {
    fn default() -> Self {
        ModelPrior {
            model: ModelChoice::Auto,
            scale_stability: SCALE_STABILITY,
            roll_stability_arcsec: ROLL_STABILITY_ARCSEC,
        }
    }
}

/// A fitted value further than this many combined σ from the headers' is a measured change.
pub const AGREEMENT_SIGMAS: f64 = 4.0;

/// The model chosen for a fit `t` with covariance `cov`, the headers' prediction `headers`,
/// and why a smaller one was chosen (for the record's message).
pub fn choose(
    t: &Similarity,
    cov: &Covariance4,
    headers: &Similarity,
    prior: &ModelPrior,
) -> (Model, Option<String>) {
    let fixed = |choice| match choice {
        ModelChoice::Similarity => Model::Similarity,
        ModelChoice::Rigid => Model::Rigid,
        _ => Model::Translation,
    };
    if prior.model != ModelChoice::Auto {
        let model = fixed(prior.model);
        let why = (model != Model::Similarity)
            .then(|| format!("{} fitted as configured", model.as_str()));
        return (model, why);
    }
    let (sigma_scale, sigma_roll) = stabilities(headers, prior);
    let measured = [cov[0][0].max(0.0).sqrt(), cov[1][1].max(0.0).sqrt()];
    let off = [
        t.scale - headers.scale,
        t.rotation_rad - headers.rotation_rad,
    ];
    let agrees = |k: usize, prior_sigma: f64| {
        off[k].abs() <= AGREEMENT_SIGMAS * measured[k].hypot(prior_sigma)
    };
    // Scale first: its stability is the tighter one for any telescope.
    let scale_held = measured[0] > sigma_scale && agrees(0, sigma_scale);
    let roll_held = scale_held && measured[1] > sigma_roll && agrees(1, sigma_roll);
    let model = match (scale_held, roll_held) {
        (false, _) => Model::Similarity,
        (true, false) => Model::Rigid,
        (true, true) => Model::Translation,
    };
    let why = match model {
        Model::Similarity => None,
        Model::Rigid => Some(format!(
            "rigid fitted: the images measure scale to {:.1e}, the instrument holds it to {:.1e}",
            measured[0], prior.scale_stability
        )),
        Model::Translation => Some(format!(
            "translation fitted: the images measure scale to {:.1e} and roll to {:.0}″, the \
             instrument holds them to {:.1e} and {:.0}″",
            measured[0],
            measured[1] * ARCSEC_PER_RAD,
            prior.scale_stability,
            prior.roll_stability_arcsec
        )),
    };
    (model, why)
}

/// The prior's σ of (scale, rotation rad) about the headers' prediction.
fn stabilities(headers: &Similarity, prior: &ModelPrior) -> (f64, f64) {
    (
        prior.scale_stability * headers.scale.abs(),
        prior.roll_stability_arcsec / ARCSEC_PER_RAD,
    )
}

/// `t` and `cov` with the parameters `model` does not fit set to the headers' values, the
/// others conditioned on them.
pub fn constrain(
    t: &mut Similarity,
    cov: &mut Covariance4,
    model: Model,
    headers: &Similarity,
    prior: &ModelPrior,
) {
    let fixed: &[usize] = match model {
        Model::Similarity => return,
        Model::Rigid => &[0],
        Model::Translation => &[0, 1],
    };
    let (sigma_scale, sigma_roll) = stabilities(headers, prior);
    let mean = [headers.scale, headers.rotation_rad];
    let prior_var = [sigma_scale * sigma_scale, sigma_roll * sigma_roll];
    let free: Vec<usize> = (0..4).filter(|k| !fixed.contains(k)).collect();
    let nf = fixed.len();
    // Σ_ff⁻¹ (one or two parameters).
    let sff = |a: usize, b: usize| cov[fixed[a]][fixed[b]];
    let inv: [[f64; 2]; 2] = if nf == 1 {
        [[1.0 / sff(0, 0), 0.0], [0.0, 0.0]]
    } else {
        let det = sff(0, 0) * sff(1, 1) - sff(0, 1) * sff(1, 0);
        [
            [sff(1, 1) / det, -sff(0, 1) / det],
            [-sff(1, 0) / det, sff(0, 0) / det],
        ]
    };
    if !inv.iter().flatten().all(|v| v.is_finite()) {
        return;
    }
    // Gain K = Σ_tf Σ_ff⁻¹ (rows: free parameters; columns: fixed ones).
    let gain: Vec<[f64; 2]> = free
        .iter()
        .map(|&t_| {
            let mut k = [0.0; 2];
            for (b, kb) in k.iter_mut().enumerate().take(nf) {
                *kb = (0..nf).map(|a| cov[t_][fixed[a]] * inv[a][b]).sum();
            }
            k
        })
        .collect();
    let mut p = t.params();
    let shift: Vec<f64> = (0..nf).map(|a| mean[a] - p[fixed[a]]).collect();
    for (i, &t_) in free.iter().enumerate() {
        p[t_] += (0..nf).map(|a| gain[i][a] * shift[a]).sum::<f64>();
    }
    for (a, &f) in fixed.iter().enumerate() {
        p[f] = mean[a];
    }
    let mut out = [[0.0; 4]; 4];
    for (i, &r) in free.iter().enumerate() {
        for (j, &c) in free.iter().enumerate() {
            // Σ_tt − K Σ_ft + K P Kᵀ.
            let explained: f64 = (0..nf).map(|a| gain[i][a] * cov[fixed[a]][c]).sum();
            let prior: f64 = (0..nf)
                .map(|a| gain[i][a] * prior_var[a] * gain[j][a])
                .sum();
            out[r][c] = cov[r][c] - explained + prior;
        }
        for (a, &f) in fixed.iter().enumerate() {
            // Cov(free, fixed) = K P.
            out[r][f] = gain[i][a] * prior_var[a];
            out[f][r] = out[r][f];
        }
    }
    for (a, &f) in fixed.iter().enumerate() {
        out[f][f] = prior_var[a];
    }
    *t = Similarity::from_params(p, t.center);
    *cov = out;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::{least_squares, uabjm_detail};
    use crate::sampling::Correspondence;
    use crate::stats::SplitMix64;

    #[test]
    fn conditioning_on_the_headers_is_the_constrained_least_squares_fit() {
        // Points on one side of the centre, so that the shifts correlate with scale and
        // rotation; noisy displacements of a known similarity.
        let c = [50.0, 50.0];
        let truth = Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: 0.3,
            dy: -0.2,
            center: c,
        };
        let mut rng = SplitMix64::new(3);
        let points: Vec<Correspondence> = (0..200)
            .map(|_| {
                let p = [rng.uniform(60.0, 100.0), rng.uniform(0.0, 40.0)];
                let q = truth.apply(p);
                Correspondence {
                    x: p[0],
                    y: p[1],
                    u: q[0] - p[0] + 0.05 * rng.gaussian(),
                    v: q[1] - p[1] + 0.05 * rng.gaussian(),
                }
            })
            .collect();
        let full = least_squares(&points, None, c).expect("fit");
        let plain = uabjm_detail(&points, &full).expect("covariance");
        // Fixed exactly (a vanishing prior): the shifts that least squares gives with scale 1
        // and rotation 0 are the mean displacements, their variance σ²/n.
        let prior = ModelPrior {
            model: ModelChoice::Translation,
            scale_stability: 1e-15,
            roll_stability_arcsec: 1e-12,
        };
        let (mut got, mut cov) = (full, plain.covariance);
        constrain(
            &mut got,
            &mut cov,
            Model::Translation,
            &Similarity::identity(c),
            &prior,
        );
        // Linear in (s cos θ, s sin θ), not in (s, θ): the conditioning is the constrained fit
        // to first order in the scale and rotation it moves (here by ~1e-3).
        let n = points.len() as f64;
        let mean_u = points.iter().map(|p| p.u).sum::<f64>() / n;
        let mean_v = points.iter().map(|p| p.v).sum::<f64>() / n;
        assert!(
            (got.dx - mean_u).abs() < 1e-5,
            "dx {} against {mean_u}",
            got.dx
        );
        assert!(
            (got.dy - mean_v).abs() < 1e-5,
            "dy {} against {mean_v}",
            got.dy
        );
        assert_eq!((got.scale, got.rotation_rad), (1.0, 0.0));
        for k in [2, 3] {
            let want = plain.sigma2 / n;
            assert!(
                (cov[k][k] / want - 1.0).abs() < 1e-9,
                "{} against {want}",
                cov[k][k]
            );
        }
        assert!(cov[2][3].abs() < 1e-9 * cov[2][2]);
    }

    #[test]
    fn a_scale_the_images_measure_well_or_that_disagrees_with_the_headers_is_fitted() {
        let headers = Similarity::identity([0.0, 0.0]);
        let prior = ModelPrior::default();
        let arcsec = 1.0 / ARCSEC_PER_RAD;
        let case = |s: f64, r_arcsec: f64, sigma_s: f64, sigma_r_arcsec: f64| {
            let mut cov = [[0.0; 4]; 4];
            cov[0][0] = sigma_s * sigma_s;
            cov[1][1] = (sigma_r_arcsec * arcsec).powi(2);
            cov[2][2] = 1e-4;
            cov[3][3] = 1e-4;
            let t = Similarity {
                scale: s,
                rotation_rad: r_arcsec * arcsec,
                ..headers
            };
            choose(&t, &cov, &headers, &prior).0
        };
        // Measured better than the instrument holds it: fitted.
        assert_eq!(case(1.00001, 0.0, 1e-6, 1.0), Model::Similarity);
        // Measured worse, in agreement with the headers: held.
        assert_eq!(case(1.001, 0.0, 1e-3, 1.0), Model::Rigid);
        assert_eq!(case(1.001, 200.0, 1e-3, 300.0), Model::Translation);
        // A change six of its σ away from the headers: measured, kept.
        assert_eq!(case(1.006, 0.0, 1e-3, 300.0), Model::Similarity);
        assert_eq!(case(1.001, 2000.0, 1e-3, 300.0), Model::Rigid);
    }
}
