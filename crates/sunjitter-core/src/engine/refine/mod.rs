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
//! method's systematic floor ([`self_test_floor`], once per reference, most of its cases
//! handed on from the previous reference along a chain) is added to it; the plain `σ²H⁻¹` is
//! kept as well.

mod accept;
mod apply;
mod blur_match;
mod checks;
mod covariance;
mod pixels;
mod reference;
mod robust;
mod self_test;
mod solve;
mod window;

pub use crate::engine::config::RefineMode;
pub use apply::{run_refinement, settle, FlowAnswer, RefineInputs, RefinementRun};
pub use pixels::{inlier_cell_pixels, CellGrid};
pub use reference::RefineReference;
pub use self_test::{
    self_test_floor, HandedOn, SelfTest, SelfTestCases, SelfTestKey, SelfTestStore,
    SELF_TEST_QUARTERS,
};
pub use solve::refine;
pub use window::FrameWindow;

use crate::geometry::{Covariance4, Similarity};
use crate::resample::HighOrder;
use serde::{Deserialize, Serialize};

/// Settings of one refinement.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
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
    /// misfit is least (see `covariance::noise_covariance`).
    pub flat_residual_sigma: Option<f64>,
    /// The covariance that residual noise of unit σ gives through the M-estimator's exact
    /// slope, when [`RefineSettings::noise_covariance`] asks for it.
    pub noise_covariance: Option<Covariance4>,
}

/// The refinement's model of the frame between its samples: a quintic B-spline. A real frame
/// is a new sampling of the sky, band-limited by the optics, and a spline moves structure near
/// the Nyquist frequency differently from it; a quintic spline errs several times less than a
/// cubic one (docs/validation.md#quintic-model). It costs 36 taps per sample against 16.
pub const MODEL: HighOrder = HighOrder::Quintic;

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
