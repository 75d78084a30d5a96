//! Whether the refinement's answer replaces the flow's.

use super::Rejected;
use crate::geometry::{sigmas, Covariance4, Similarity};

/// What the decision weighs: both answers with their σ, and how the iterations ended.
#[derive(Debug, Clone)]
pub(super) struct Evidence {
    pub flow: Similarity,
    /// The flow's covariance, with its slack (how far it may be from converged) as a floor.
    pub flow_covariance: Covariance4,
    pub refined: Similarity,
    /// The refinement's covariance as agreement weighs it (see `apply::Sigma::agreement`).
    pub refined_covariance: Covariance4,
    pub converged: bool,
    pub iterations: usize,
}

/// `Ok` when the refinement's answer is taken; else why not. Pure: it reads only `e`.
pub(super) fn accept(e: &Evidence) -> Result<(), Rejected> {
    // Both answers measure the same motion; a large disagreement means the intensities do not
    // follow one similarity (changed scene, different channels): keep the flow's.
    let (a, b) = (e.flow.params(), e.refined.params());
    let (sa, sb) = (sigmas(&e.flow_covariance), sigmas(&e.refined_covariance));
    let worst = (0..4)
        .map(|k| (a[k] - b[k]).abs() / sa[k].hypot(sb[k]).max(f64::MIN_POSITIVE))
        .fold(0.0, f64::max);
    // A refinement that ran off (a brightening between the frames can send it to a wildly
    // wrong scale and turn) reports σ so large that it "agrees" with anything. Gauss–Newton on
    // intensities is a sub-pixel method: σ beyond a pixel say it is outside its basin
    // (docs/validation.md#a-refinement-that-ran-off-is-not-taken).
    let widest = sb[2].max(sb[3]);
    if widest.is_nan() || widest > MAX_REFINED_SIGMA_PX {
        return Err(Rejected::ran_off(format!(
            "intensity refinement rejected: its σ reach {widest:.2} px"
        )));
    }
    if worst.is_nan() || worst > MAX_DISAGREEMENT_SIGMA {
        return Err(Rejected {
            note: format!("intensity refinement rejected: {worst:.1}σ from the flow's answer"),
            disagreeing: (!worst.is_nan() && e.converged).then_some(e.refined),
            ran_off: false,
        });
    }
    if !e.converged {
        return Err(Rejected::skipped(format!(
            "intensity refinement rejected: not converged in {} iterations",
            e.iterations
        )));
    }
    Ok(())
}

/// Largest translation σ of a refinement whose answer is taken, px.
const MAX_REFINED_SIGMA_PX: f64 = 1.0;

/// Largest disagreement (in combined σ) between flow and refinement that keeps the refinement.
const MAX_DISAGREEMENT_SIGMA: f64 = 5.0;
