//! The refinement of one pair: from the flow's answer to the answer reported, with its σ.

use super::accept::{accept, Evidence};
use super::blur_match::{blur_matching, BlurMatch};
use super::checks::{blur_check, interpolation_check, noise_factors, CHECK_MAX_SIDE};
use super::pixels::{central_pixels, inlier_cell_pixels, pixel_box, refinement_region, CellGrid};
use super::{
    refine, settings, FrameWindow, RefineFailure, RefineReference, RefineSettings, Refined,
    Rejected, SelfTest, MAX_PIXELS,
};
use crate::engine::derotate::Carried;
use crate::engine::region::gaussian_reach;
use crate::engine::{EngineConfig, SigmaMethod};
use crate::geometry::{Covariance4, Similarity};
use crate::sampling::Correspondence;
use ndarray::{Array2, ArrayView2};
use std::time::{Duration, Instant};

/// The flow stage's answer, which the refinement's replaces when it is taken.
pub struct FlowAnswer<'a> {
    pub transform: &'a mut Similarity,
    pub covariance: &'a mut Covariance4,
    /// Bounding box (x0, y0, x1, y1, inclusive) of the flow's sampling mask; `None` when empty.
    pub sample_box: Option<(usize, usize, usize, usize)>,
    /// The flow's RANSAC inliers: the refinement fits the cells that hold them.
    pub inliers: &'a [Correspondence],
    /// How far the flow's answer may be from its converged value, px (0 when it converged; a
    /// seed finished on a coarse level is further).
    pub slack_px: f64,
}

/// The pair as the refinement reads it.
pub struct RefineInputs<'a> {
    /// The reference as the flow stage saw it (resolution matched).
    pub reference: ArrayView2<'a, f32>,
    /// The same, as every refinement against it reads it.
    pub prepared: &'a RefineReference,
    pub frame: ArrayView2<'a, f32>,
    pub mask: &'a Array2<bool>,
    /// `mask`'s bounding box.
    pub mask_box: crate::flow::Roi,
    /// Gaussian σ that matches the frame's resolution to the reference's, px.
    pub frame_smoothing_px: f64,
    /// How much blurrier the frame is than the reference, when measured.
    pub blur: Option<crate::blur::BlurDifference>,
    /// The Sun's motion between the two times.
    pub carried: Option<&'a Carried>,
    pub cfg: &'a EngineConfig,
}

/// A refinement run from the flow's answer, before its σ: [`settle`] makes the answer
/// reported from it.
pub struct RefinementRun {
    setup: Setup,
    refined: Refined,
}

/// The refinement from the flow stage's answer, up to its σ (which needs the reference's
/// self-test: a caller may run that beside this); `Err` when the refinement is not possible.
pub fn run_refinement(
    flow: &FlowAnswer<'_>,
    pair: &RefineInputs<'_>,
) -> Result<RefinementRun, Rejected> {
    let setup = Setup::new(flow, pair)?;
    let refined = run(&setup, pair, flow)?;
    Ok(RefinementRun { setup, refined })
}

/// From a run made by [`run_refinement`] on the same flow answer and pair: refine the flow
/// stage's transform in place (and its covariance), or leave both as they are when the
/// refinement disagrees with the flow. `self_test` gives the method's systematic floor on
/// this reference (measured once per reference by the caller). Returns a note for the
/// result's message: `Ok` when the refinement's answer was taken, `Err` when the flow's
/// stands.
pub fn settle(
    run: RefinementRun,
    flow: FlowAnswer<'_>,
    pair: &RefineInputs<'_>,
    self_test: impl FnOnce(&RefineSettings) -> Option<SelfTest>,
) -> Result<String, Rejected> {
    let RefinementRun { setup, refined } = run;
    let sigma = match pair.cfg.sigma {
        SigmaMethod::Calibrated => calibrated_sigma(&setup, pair, &flow, &refined, self_test),
        SigmaMethod::Uabjm => Sigma {
            covariance: refined.plain_covariance,
            agreement: refined.plain_covariance,
            note: String::new(),
        },
    };
    let mut flow_covariance = *flow.covariance;
    crate::engine::sigma::add_floor(
        &mut flow_covariance,
        flow.inliers,
        flow.transform.center,
        flow.slack_px,
    );
    accept(&Evidence {
        flow: *flow.transform,
        flow_covariance,
        refined: refined.transform,
        refined_covariance: sigma.agreement,
        converged: refined.converged,
        iterations: refined.iterations,
    })?;
    *flow.transform = refined.transform;
    *flow.covariance = sigma.covariance;
    let matched = match (pair.blur, setup.blur_uncertainty) {
        (Some(b), Some(u)) => format!(
            ", blur matched (frame blurrier by {:.3} ± {u:.3} px²)",
            b.variance_px2 + setup.base_settings.frame_smoothing_px.powi(2),
        ),
        _ => String::new(),
    };
    Ok(format!(
        "intensity refinement on {} px in {} blocks, {} iterations{matched}{}",
        refined.pixels, refined.blocks, refined.iterations, sigma.note
    ))
}

/// What a pair's refinement works on: its cells, settings (with any blur difference matched),
/// pixels, and the window of the frame they map into.
struct Setup {
    grid: CellGrid,
    /// The configured settings, before blur matching.
    base_settings: RefineSettings,
    settings: RefineSettings,
    /// The reference blurred to a blurrier frame's resolution (`None`: the shared one serves).
    blurred_reference: Option<RefineReference>,
    /// 1-σ error of the matched blur difference, px² (`None`: nothing matched).
    blur_uncertainty: Option<f64>,
    pixels: Vec<(usize, usize, usize)>,
    /// Bounding box of `pixels`.
    bbox: (usize, usize, usize, usize),
    window: FrameWindow,
    started: Instant,
    window_at: Duration,
}

impl Setup {
    fn new(flow: &FlowAnswer, pair: &RefineInputs) -> Result<Setup, Rejected> {
        let Some(sample_box) = flow.sample_box else {
            return Err(Rejected::skipped(
                "intensity refinement skipped: empty sampling mask",
            ));
        };
        let grid = CellGrid::over_box(sample_box, pair.cfg.sample);
        let base_settings = settings(pair.cfg, pair.frame_smoothing_px);
        // A blur difference the model cannot absorb: the sharper image is blurred to the other's.
        let BlurMatch {
            reference_extra,
            frame_smoothing_px,
            uncertainty_px2: blur_uncertainty,
        } = blur_matching(
            pair.blur,
            pair.frame_smoothing_px,
            base_settings.smoothing_px,
        );
        let (blurred_reference, settings) = if reference_extra > 0.0 {
            let settings = RefineSettings {
                smoothing_px: base_settings.smoothing_px.hypot(reference_extra),
                ..base_settings
            };
            (
                Some(RefineReference::new(pair.reference, &settings)),
                settings,
            )
        } else {
            (None, base_settings)
        };
        let frame_sigma = base_settings.smoothing_px.hypot(frame_smoothing_px);
        let margin = gaussian_reach(frame_sigma.max(settings.smoothing_px)) + 3;
        let region = refinement_region(
            pair.mask,
            pair.mask_box,
            pair.reference,
            pair.frame,
            flow.transform,
            pair.carried,
            margin,
        );
        let pixels = inlier_cell_pixels(
            pair.reference.dim(),
            |x, y| region.usable(x, y),
            &grid,
            flow.inliers,
            MAX_PIXELS,
        );
        drop(region);
        let Some(bbox) = pixel_box(&pixels) else {
            return Err(Rejected::skipped(
                "intensity refinement skipped: no pixels in the inlier cells",
            ));
        };
        let started = Instant::now();
        let Some(window) =
            FrameWindow::new(pair.frame, bbox, flow.transform, frame_sigma, pair.carried)
        else {
            return Err(Rejected::skipped(
                "intensity refinement skipped: the pixels map outside the frame",
            ));
        };
        Ok(Setup {
            grid,
            base_settings,
            settings,
            blurred_reference,
            blur_uncertainty,
            pixels,
            bbox,
            window,
            started,
            window_at: started.elapsed(),
        })
    }

    /// The reference as this pair's refinement reads it.
    fn reference<'s>(&'s self, pair: &'s RefineInputs) -> &'s RefineReference {
        self.blurred_reference.as_ref().unwrap_or(pair.prepared)
    }
}

/// The refinement from the flow's answer, its failures turned into rejections.
fn run(setup: &Setup, pair: &RefineInputs, flow: &FlowAnswer) -> Result<Refined, Rejected> {
    let pair_settings = RefineSettings {
        noise_covariance: true,
        ..setup.settings
    };
    let refined = match refine(
        setup.reference(pair),
        &setup.window,
        &setup.pixels,
        &setup.grid,
        *flow.transform,
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
        flow = ?flow.transform.params(),
        refined = ?refined.transform.params(),
        flow_sigma = ?crate::geometry::sigmas(flow.covariance),
        robust_sigma = ?crate::geometry::sigmas(&refined.covariance),
        plain_sigma = ?crate::geometry::sigmas(&refined.plain_covariance),
        refined.blocks, refined.pixels, refined.iterations, refined.converged, refined.gain,
        refined.residual_sigma,
        window_at = ?setup.window_at,
        refined_at = ?setup.started.elapsed(),
        "intensity refinement"
    );
    Ok(refined)
}

/// The covariance a refinement reports, and the one its agreement with the flow is weighed
/// by; with the note that says how they were made.
struct Sigma {
    covariance: Covariance4,
    /// With the floor but not the interpolation check. The check bounds how far the model may
    /// be from frames made otherwise; taken as agreement, it would let a refinement further
    /// off replace a closer flow
    /// (docs/validation.md#agreement-weighed-without-the-interpolation-check).
    agreement: Covariance4,
    note: String,
}

/// The calibrated σ: the cluster-robust covariance raised to the residual noise's, with the
/// blur check's term, and the larger of the method's systematic floor (the self-test's, else
/// the configured one) and the interpolation check.
fn calibrated_sigma(
    setup: &Setup,
    pair: &RefineInputs,
    flow: &FlowAnswer,
    refined: &Refined,
    self_test: impl FnOnce(&RefineSettings) -> Option<SelfTest>,
) -> Sigma {
    let prepared = setup.reference(pair);
    let mut agreement_cov = refined.covariance;
    // The method's systematic floor for this reference, measured once per reference;
    // without it, the configured floor.
    let self_tested = self_test(&setup.base_settings);
    let floor = self_tested.map(|t| t.floor);
    tracing::debug!(self_tested_at = ?setup.started.elapsed(), "refinement self-test");
    if let Some(factors) = noise_factors(refined, self_tested, &agreement_cov) {
        tracing::debug!(?factors, "σ raised to the residual noise's");
        for i in 0..4 {
            for j in 0..4 {
                agreement_cov[i][j] *= factors[i] * factors[j];
            }
        }
    }
    let check_pixels = central_pixels(&setup.pixels, setup.bbox, CHECK_MAX_SIDE);
    let check = interpolation_check(
        pair.reference,
        prepared,
        &check_pixels,
        &setup.grid,
        &refined.transform,
        &setup.settings,
    );
    let blur_term = setup.blur_uncertainty.and_then(|mismatch| {
        blur_check(
            pair.reference,
            prepared,
            &check_pixels,
            &setup.grid,
            &refined.transform,
            &setup.settings,
            mismatch,
        )
    });
    if let Some(b) = blur_term {
        for (k, bk) in b.iter().enumerate() {
            agreement_cov[k][k] += bk * bk;
        }
    }
    // Both measure the interpolation error beyond the σ: the floor as a typical frame's,
    // this frame's transform as it is. Summed, they count it twice and overstate the σ; the
    // larger stands (docs/validation.md#floor-or-check-the-larger).
    match floor {
        Some(f) => {
            for (k, b) in f.iter().enumerate() {
                agreement_cov[k][k] += b * b;
            }
        }
        None => crate::engine::sigma::add_floor(
            &mut agreement_cov,
            flow.inliers,
            flow.transform.center,
            pair.cfg.systematic_floor_px,
        ),
    }
    let mut cov = agreement_cov;
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
    let note = format!(
        ", self-test floor {}, interpolation check {}{}",
        show(floor, "failed (configured floor)"),
        show(check, "failed"),
        blur_term.map_or(String::new(), |b| format!(
            ", blur check {}",
            show(Some(b), "")
        ))
    );
    tracing::debug!(checked_at = ?setup.started.elapsed(), "interpolation check");
    Sigma {
        covariance: cov,
        agreement: agreement_cov,
        note,
    }
}
