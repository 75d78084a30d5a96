//! The fine stage: flow passes on crops of the reference grid, each fitted with a similarity
//! and composed into the estimate until the update is negligible.

use super::config::EngineConfig;
use super::region::{erode, gaussian_reach, mask_roi};
use super::workspace::Workspace;
use super::{derotate, refine, sigma, SigmaMethod};
use crate::fit::{fit_similarity, FitFailure, RansacParams, SimilarityFit};
use crate::flow::{Farneback, FarnebackParams, FlowOptions, Roi, RowLattice};
use crate::geometry::{compose_with_covariance, sigmas, Covariance4, Similarity};
use crate::preprocess;
use crate::resample::HighOrderSpline;
use crate::sampling::grid_median_sample;
use ndarray::{s, Array2, ArrayView2, Zip};
use std::ops::Range;
use std::time::Instant;

/// What the fine stage measured.
pub(super) struct FineResult {
    pub(super) transform: Similarity,
    pub(super) covariance: Covariance4,
    pub(super) uabjm_covariance: Covariance4,
    pub(super) fit: SimilarityFit,
    pub(super) points: usize,
    /// The frame resampled onto the reference grid through the final estimate, on `crop`
    /// only (the mask's box plus every later filter's reach).
    /// For a seed on binned copies, on the binned grid (and `crop` too).
    warped: Option<Array2<f32>>,
    crop: Crop,
    pub(super) passes: usize,
    pub(super) converged: bool,
    /// The last pass's motion (px at the mask's radius) when the passes ran out before it
    /// became negligible and it exceeded the answer's σ: the estimate was still moving.
    pub(super) unsettled_px: Option<f64>,
    /// `Some(level)` for a seed for the refinement measured on images binned to that pyramid
    /// level.
    pub(super) seed_level: Option<usize>,
    /// `Some(level)` for full-resolution passes that started from a seed measured on images
    /// binned to that pyramid level.
    pub(super) seeded_from: Option<usize>,
    /// What the refinement needs: the bounding box (x0, y0, x1, y1, inclusive, reference
    /// grid) of the sampling mask, over which the sampling grid's cells lie, and the inliers.
    pub(super) sample_box: Option<(usize, usize, usize, usize)>,
    pub(super) inliers: Vec<crate::sampling::Correspondence>,
}

impl FineResult {
    /// `warped` at reference-grid rows and columns (which must lie inside the crop).
    pub(super) fn warped_at(
        &self,
        rows: Range<usize>,
        cols: Range<usize>,
    ) -> Option<ArrayView2<'_, f32>> {
        let (y0, x0) = (self.crop.rows.start, self.crop.cols.start);
        let inside = rows.start >= y0
            && cols.start >= x0
            && rows.end <= self.crop.rows.end
            && cols.end <= self.crop.cols.end;
        let warped = self.warped.as_ref().filter(|_| inside)?;
        Some(warped.slice(s![
            rows.start - y0..rows.end - y0,
            cols.start - x0..cols.end - x0
        ]))
    }
}

/// Errors of the fine stage.
#[derive(Debug, thiserror::Error)]
pub(super) enum FineError {
    #[error("flow: {0}")]
    Flow(String),
    #[error("fit (pass {pass}): {source}")]
    Fit {
        pass: usize,
        #[source]
        source: FitFailure,
    },
}

/// Where the passes start.
#[derive(Clone, Copy, Debug)]
pub(super) enum PassStart {
    /// The coarse alignment: the first pass runs the flow's whole pyramid.
    Coarse(Similarity),
    /// A seed measured on binned copies, well within the full-resolution flow's reach: every
    /// pass at full resolution only, with the later passes' iterations.
    Seed(Similarity),
}

/// Where the fine stage measures: the mask, and optionally a circle (centre, radius px on the
/// reference grid) its sampled points must also lie in.
#[derive(Clone, Copy)]
pub(super) struct FlowRegion<'a> {
    pub(super) mask: &'a Array2<bool>,
    pub(super) sample_within: Option<([f64; 2], f64)>,
}

/// How far a point's flow sees, px (a point that far inside the limb sees none of it): half the
/// window, the polynomial expansion's reach (`poly_n` px each side, as in OpenCV) and two
/// strides of the affine grid. A point's flow is interpolated from the nodes around it, one
/// stride; and each iteration of the solver reads the previous flow across the window, so the
/// dependence reaches further: with a margin of one stride, another channel's brighter limb
/// still pulls the scale (docs/validation.md#flow-reach-two-grid-strides).
pub(super) fn flow_reach_px(winsize: usize, poly_n: usize) -> f64 {
    (winsize / 2 + 2 * FlowOptions::affine_grid(winsize).grid_stride + poly_n) as f64
}

/// What every flow run of one alignment shares: the window, the frame's extra smoothing, the
/// Sun's rotation carried, the settings and the working memory.
#[derive(Clone, Copy)]
pub(super) struct FlowSetup<'a> {
    pub(super) winsize: usize,
    /// Gaussian σ that brings the frame to the reference's resolution, px.
    pub(super) frame_smoothing_px: f64,
    pub(super) carried: Option<&'a derotate::Carried>,
    pub(super) cfg: &'a EngineConfig,
    pub(super) workspace: &'a Workspace,
}

/// Flow passes from `start` until the update is negligible or `max_passes` have run.
pub(super) fn fine_alignment(
    reference: ArrayView2<f32>,
    frame: &Array2<f32>,
    region: FlowRegion,
    start: PassStart,
    max_passes: usize,
    setup: FlowSetup,
) -> Result<FineResult, FineError> {
    let FlowSetup {
        winsize,
        frame_smoothing_px,
        carried,
        cfg,
        workspace,
    } = setup;
    let (h, w) = reference.dim();
    let mask = region.mask;
    let center = Similarity::array_center(w, h);
    // The refinement's model, so that the two answers share no interpolation bias the other
    // lacks (with a lower-order spline here, the two disagree beyond their σ on band-limited
    // frames; docs/validation.md#passes-resample-with-the-refinements-model).
    let spline = HighOrderSpline::new(frame.view(), refine::MODEL);
    let roi = mask_roi(mask);
    let levels = cfg
        .pyramid_levels
        .unwrap_or_else(|| auto_levels(roi.width.min(roi.height)));
    let ransac = RansacParams {
        threshold_px: cfg.ransac_threshold_px,
        max_trials: cfg.ransac_max_trials,
        seed: cfg.seed,
        ..RansacParams::default()
    };
    let stride = (roi.width.min(roi.height) / cfg.sample.max(1) / 6).max(1);
    let radius = mask_extent_px(mask, roi);
    let crops = PassCrops {
        roi,
        winsize,
        poly_n: cfg.poly_n,
        quality_reach: gaussian_reach(winsize as f64 / 4.0),
        smoothing_reach: gaussian_reach(frame_smoothing_px),
        w,
        h,
    };

    // The Sun's motion over the later passes' crop, kept for each of them; the first pass's
    // larger crop reads it there and works out the rest row by row.
    let shifts = carried.map(|c| {
        let crop = crops.for_levels(0);
        let s = c.shifts(
            crop.cols.start,
            crop.rows.start,
            crop.cols.len(),
            crop.rows.len(),
        );
        (crop, s)
    });
    let (estimate, seeded) = match start {
        PassStart::Coarse(t) => (t.recentered(center), false),
        PassStart::Seed(t) => (t.recentered(center), true),
    };
    let mut state = PassState {
        pass: 0,
        estimate,
        solver: workspace.take(),
        last_moved: None,
        last_crop: None,
    };
    loop {
        state.pass += 1;
        let pass = state.pass;
        let pass_started = Instant::now();
        let whole_pyramid = pass == 1 && !seeded;
        let pass_levels = if whole_pyramid { levels } else { 0 };
        let crop = crops.for_levels(pass_levels);
        let (x0, y0) = (crop.cols.start, crop.rows.start);
        let (ch, cw) = (crop.rows.len(), crop.cols.len());
        let warped = warp_pass(
            &spline,
            &state.estimate,
            &crop,
            shifts.as_ref(),
            carried,
            frame_smoothing_px,
        );
        let ref_crop = reference.slice(s![crop.rows.clone(), crop.cols.clone()]);
        let mask_crop = mask.slice(s![crop.rows.clone(), crop.cols.clone()]);
        let roi_crop = Roi {
            x: roi.x - x0,
            y: roi.y - y0,
            ..roi
        };
        let params = FarnebackParams {
            pyr_scale: 0.5,
            levels: pass_levels,
            winsize,
            iterations: if whole_pyramid {
                cfg.iterations
            } else {
                cfg.iterations.min(4)
            },
            poly_n: cfg.poly_n,
            poly_sigma: cfg.poly_sigma,
            gaussian_window: false,
        };
        let options = FlowOptions {
            ..FlowOptions::affine_grid(winsize)
        };
        let sample_mask = sample_mask(
            &warped,
            ref_crop,
            mask_crop,
            winsize,
            region.sample_within,
            (x0, y0),
        );
        let mut s = configured_solver(state.solver.take(), &params, &options)?;
        // The same reference crop as the last pass's: its expansion is kept.
        if state.last_crop.as_ref() == Some(&crop) {
            s.next_prev_unchanged();
        }
        // The flow is read only on the sampling lattice's rows.
        s.next_rows(crate::sampling::mask_bounding_box(sample_mask.view()).map(
            |(_, first, _, _)| RowLattice {
                first,
                step: stride,
            },
        ));
        let warped_at = pass_started.elapsed();
        let flow = s
            .compute(ref_crop, warped.view(), Some(roi_crop), None)
            .map_err(|e| FineError::Flow(e.to_string()))?;
        state.solver = Some(s);
        state.last_crop = Some(crop.clone());
        let flow_at = pass_started.elapsed();

        let mut points = grid_median_sample(
            flow.u.view(),
            flow.v.view(),
            sample_mask.view(),
            stride,
            cfg.sample,
        );
        for p in &mut points {
            p.x += x0 as f64;
            p.y += y0 as f64;
        }
        let fit = fit_similarity(&points, center, &ransac)
            .map_err(|source| FineError::Fit { pass, source })?;
        tracing::debug!(pass, ?warped_at, ?flow_at, fitted_at = ?pass_started.elapsed(), crop = ?(cw, ch), "fine pass");
        let update = fit.transform;
        let previous = state.estimate;
        state.estimate = state.estimate.after(&update);
        // Converged when what is left is negligible, or lost in this pass's own noise.
        let moved = max_motion_px(&update, radius);
        let noise = sigmas(&fit.covariance)[2].hypot(sigmas(&fit.covariance)[3]);
        let left = left_after(moved, seeded.then_some(state.last_moved).flatten());
        let converged = left < cfg.convergence_px.max(0.1 * noise);
        state.last_moved = Some(moved);
        tracing::debug!(pass, moved, noise, estimate = ?state.estimate.params(), "fine pass estimate");
        if converged || pass >= max_passes.max(1) {
            if let Some(solver) = state.solver.take() {
                workspace.give(solver);
            }
            let step = PassStep {
                previous,
                update,
                moved,
                converged,
            };
            let measured = PassMeasurement {
                fit,
                points,
                warped,
                crop,
                sample_mask,
            };
            return Ok(FineResult::of_last_pass(
                &state, step, measured, center, winsize, cfg,
            ));
        }
    }
}

/// How far the estimate is still from where the passes converge, px, after a pass that moved
/// it by `moved`. From a seed the passes work in the flow's linear range, where each removes
/// the same fraction of what is left: with `q = moved / previous` (the previous pass's
/// motion), a contraction's error bound `moved · q / (1 − q)`. Otherwise, and when the
/// passes are not clearly contracting, the motion itself.
fn left_after(moved: f64, previous: Option<f64>) -> f64 {
    match previous {
        Some(p) if moved < 0.5 * p => {
            let q = moved / p;
            moved * q / (1.0 - q)
        }
        _ => moved,
    }
}

/// Rows and columns each pass works on: the mask's box plus what the flow's domain (at the
/// pass's coarsest level), its border taper, the frame's smoothing and the quality filters
/// after the last pass read around it. Inside the mask the results equal those of whole-frame
/// arrays; outside nothing is computed (the disk covers under half of a full-disk frame).
struct PassCrops {
    roi: Roi,
    winsize: usize,
    poly_n: usize,
    quality_reach: usize,
    smoothing_reach: usize,
    w: usize,
    h: usize,
}

impl PassCrops {
    fn for_levels(&self, levels: usize) -> Crop {
        // 2^16 px exceeds any image: more levels only clamp the crop to the whole image.
        let levels = levels.min(16);
        let flow = (self.winsize / 2 + self.poly_n + 3 + FLOW_TAPER_PX + 2) << levels;
        let blur = if levels > 0 {
            (5usize << levels) / 4 + 2
        } else {
            0
        };
        let margin = (flow + blur).max(self.quality_reach) + self.smoothing_reach;
        // Aligned so that every level's pixels and flow-grid nodes are those of the whole image.
        let grid_stride = FlowOptions::affine_grid(self.winsize).grid_stride;
        Crop::around(self.roi, margin, grid_stride << levels, self.w, self.h)
    }
}

/// The frame resampled onto `crop` of the reference grid through `estimate` (and the Sun's
/// motion when carried), smoothed to the reference's resolution.
fn warp_pass(
    spline: &HighOrderSpline,
    estimate: &Similarity,
    crop: &Crop,
    shifts: Option<&(Crop, Array2<[f32; 2]>)>,
    carried: Option<&derotate::Carried>,
    frame_smoothing_px: f64,
) -> Array2<f32> {
    let (x0, y0) = (crop.cols.start, crop.rows.start);
    let (ch, cw) = (crop.rows.len(), crop.cols.len());
    let warped = match (shifts, carried) {
        (Some((kept, s)), _) if kept.contains(crop) => {
            let (ox, oy) = (x0 - kept.cols.start, y0 - kept.rows.start);
            let window = s.slice(s![oy..oy + ch, ox..ox + cw]);
            spline.warp_similarity_window_shifted(estimate, x0, y0, window)
        }
        (kept, Some(c)) => {
            let kept = kept.filter(|(k, _)| crop.contains(k));
            spline.warp_similarity_window_shifted_by(estimate, (x0, y0), (cw, ch), |y, row| {
                let y = y + y0;
                match kept {
                    Some((k, s)) if k.rows.contains(&y) => {
                        let (a, b) = (k.cols.start - x0, k.cols.end - x0);
                        c.shifts_row(x0, y, &mut row[..a]);
                        for (r, v) in row[a..b].iter_mut().zip(s.row(y - k.rows.start)) {
                            *r = *v;
                        }
                        c.shifts_row(k.cols.end, y, &mut row[b..]);
                    }
                    _ => c.shifts_row(x0, y, row),
                }
            })
        }
        _ => spline.warp_similarity_window(estimate, x0, y0, cw, ch),
    };
    if frame_smoothing_px > 0.0 {
        preprocess::gaussian_smooth(warped.view(), frame_smoothing_px)
    } else {
        warped
    }
}

/// The flow solver for one pass: the one kept (its buffers reused between passes and frames),
/// reconfigured if need be, or a new one.
fn configured_solver(
    kept: Option<Farneback>,
    params: &FarnebackParams,
    options: &FlowOptions,
) -> Result<Farneback, FineError> {
    match kept {
        Some(mut s) => {
            if s.params() != params || s.options() != options {
                s.reconfigure(params.clone(), options.clone())
                    .map_err(|e| FineError::Flow(e.to_string()))?;
            }
            Ok(s)
        }
        None => Farneback::new(params.clone())
            .and_then(|f| f.with_options(options.clone()))
            .map_err(|e| FineError::Flow(e.to_string())),
    }
}

/// Where a pass samples its flow, on the crop at `origin` of the reference grid.
fn sample_mask(
    warped: &Array2<f32>,
    ref_crop: ArrayView2<f32>,
    mask_crop: ArrayView2<bool>,
    winsize: usize,
    sample_within: Option<([f64; 2], f64)>,
    (x0, y0): (usize, usize),
) -> Array2<bool> {
    // Only where the whole window saw data: a window cut by the frame's edge (or a blank
    // region) measures a biased motion. The crop's own edge is further than the window from
    // the mask unless it is the image's edge, which erosion treats alike.
    let valid = Zip::from(warped)
        .and(&ref_crop)
        .par_map_collect(|w, v| w.is_finite() && v.is_finite());
    let mut sample_mask = erode(&valid, winsize / 2);
    Zip::from(&mut sample_mask)
        .and(&mask_crop)
        .par_for_each(|a, b| *a = *a && *b);
    if let Some(([cx, cy], r)) = sample_within {
        let r2 = if r > 0.0 { r * r } else { -1.0 };
        Zip::indexed(&mut sample_mask).par_for_each(|(y, x), m| {
            let (dx, dy) = ((x + x0) as f64 - cx, (y + y0) as f64 - cy);
            *m = *m && dx * dx + dy * dy <= r2;
        });
    }
    sample_mask
}

/// The fine passes' state from one pass to the next: where the estimate is, the solver (its
/// buffers, and its expansion of the reference crop), and what the last pass moved and read.
struct PassState {
    pass: usize,
    estimate: Similarity,
    solver: Option<Farneback>,
    last_moved: Option<f64>,
    last_crop: Option<Crop>,
}

/// A pass's step: the estimate it started from, the update it measured, the update's largest
/// motion within the mask (px), and whether the passes converged with it.
struct PassStep {
    previous: Similarity,
    update: Similarity,
    moved: f64,
    converged: bool,
}

/// What a pass measured: the fit to its sampled vectors, the frame warped onto its crop and
/// where it sampled.
struct PassMeasurement {
    fit: SimilarityFit,
    points: Vec<crate::sampling::Correspondence>,
    warped: Array2<f32>,
    crop: Crop,
    sample_mask: Array2<bool>,
}

impl FineResult {
    /// The fine stage's answer from its last pass: the step's covariance composed into the
    /// estimate's, widened by the step when the passes did not converge.
    fn of_last_pass(
        state: &PassState,
        step: PassStep,
        measured: PassMeasurement,
        center: [f64; 2],
        winsize: usize,
        cfg: &EngineConfig,
    ) -> FineResult {
        let PassStep {
            previous,
            update,
            moved,
            converged,
        } = step;
        let PassMeasurement {
            fit,
            points,
            warped,
            crop,
            sample_mask,
        } = measured;
        let (x0, y0) = (crop.cols.start, crop.rows.start);
        let inliers = fit.inlier_points(&points);
        let uabjm = fit.covariance;
        let mut calibrated = sigma::calibrated_covariance(cfg.sigma, &inliers, &fit, winsize);
        if cfg.sigma == SigmaMethod::Calibrated {
            sigma::add_floor(&mut calibrated, &inliers, center, cfg.systematic_floor_px);
        }
        let zero = [[0.0; 4]; 4];
        let (_, mut cov) = compose_with_covariance(&previous, &zero, &update, &calibrated);
        // Still moving when the passes ran out: the last step is a measure of how far
        // from settled the answer is (with little structure it can wander by pixels;
        // docs/validation.md#an-unsettled-flow-reports-its-last-step).
        let sigma_xy = sigmas(&cov)[2].hypot(sigmas(&cov)[3]);
        let unsettled_px = (!converged && moved > sigma_xy).then_some(moved);
        if !converged {
            let step = update.params();
            for (k, d) in [step[0] - 1.0, step[1], step[2], step[3]]
                .iter()
                .enumerate()
            {
                cov[k][k] += d * d;
            }
        }
        let (_, ucov) = compose_with_covariance(&previous, &zero, &update, &uabjm);
        let sample_box = crate::sampling::mask_bounding_box(sample_mask.view())
            .map(|(a, b, c, d)| (a + x0, b + y0, c + x0, d + y0));
        FineResult {
            transform: state.estimate,
            covariance: cov,
            uabjm_covariance: ucov,
            points: points.len(),
            fit,
            warped: Some(warped),
            crop,
            passes: state.pass,
            converged,
            unsettled_px,
            seed_level: None,
            seeded_from: None,
            sample_box,
            inliers,
        }
    }
}

/// How many times `max_passes` the fine passes may run in all when the flow is still moving
/// by more than its σ and the refinement did not take its answer.
pub(super) const UNSETTLED_PASS_FACTOR: usize = 3;

/// Outermost pixels of a level that OpenCV's border taper weighs down.
pub(super) const FLOW_TAPER_PX: usize = 5;

/// Rows and columns of the reference grid one pass works on.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Crop {
    pub(super) rows: Range<usize>,
    pub(super) cols: Range<usize>,
}

impl Crop {
    fn contains(&self, other: &Crop) -> bool {
        self.rows.start <= other.rows.start
            && self.cols.start <= other.cols.start
            && self.rows.end >= other.rows.end
            && self.cols.end >= other.cols.end
    }

    /// `roi` grown by `margin`, its start rounded down and its end up to multiples of `align`,
    /// clamped to the `w × h` image.
    fn around(roi: Roi, margin: usize, align: usize, w: usize, h: usize) -> Crop {
        let span = |lo: usize, len: usize, n: usize| -> Range<usize> {
            let a = lo.saturating_sub(margin) / align * align;
            let b = (lo + len + margin).div_ceil(align) * align;
            a..b.min(n)
        };
        Crop {
            rows: span(roi.y, roi.height, h),
            cols: span(roi.x, roi.width, w),
        }
    }
}

/// Largest displacement the transform causes within `radius` of its centre.
pub(super) fn max_motion_px(t: &Similarity, radius: f64) -> f64 {
    let (a, b) = t.ab();
    let linear = ((a - 1.0).powi(2) + b * b).sqrt() * radius;
    (t.dx * t.dx + t.dy * t.dy).sqrt() + linear
}

/// Largest distance of a mask pixel from the array centre (`roi`: the mask's bounding box).
fn mask_extent_px(mask: &Array2<bool>, roi: Roi) -> f64 {
    let (h, w) = mask.dim();
    let c = Similarity::array_center(w, h);
    let mut r2: f64 = 0.0;
    let boxed = mask.slice(s![roi.y..roi.y + roi.height, roi.x..roi.x + roi.width]);
    for ((y, x), &m) in boxed.indexed_iter() {
        if m {
            let (x, y) = ((x + roi.x) as f64, (y + roi.y) as f64);
            r2 = r2.max((x - c[0]).powi(2) + (y - c[1]).powi(2));
        }
    }
    r2.sqrt()
}

/// Pyramid levels that keep the coarsest level at least 64 px across (at most 4).
pub(super) fn auto_levels(extent_px: usize) -> usize {
    let mut levels = 0;
    let mut size = extent_px as f64;
    while levels < 4 && size / 2.0 >= 64.0 {
        size /= 2.0;
        levels += 1;
    }
    levels
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn what_is_left_of_a_contraction_is_the_rest_of_its_geometric_series() {
        // Passes that each remove the same fraction 1 − q: their later motions sum to the
        // estimate's remaining distance from where they converge.
        for (first, q) in [(0.0044f64, 0.068f64), (0.19, 0.3), (1e-3, 0.49)] {
            let motions: Vec<f64> = (0..60).map(|k| first * q.powi(k)).collect();
            for k in 1..6 {
                let rest: f64 = motions[k + 1..].iter().sum();
                let left = left_after(motions[k], Some(motions[k - 1]));
                assert!(
                    (left - rest).abs() <= 1e-12 * first,
                    "q {q}, pass {k}: {left} vs {rest}"
                );
            }
        }
        // Not contracting by half or more, or no previous pass: the motion itself.
        assert_eq!(left_after(0.3, Some(0.5)), 0.3);
        assert_eq!(left_after(0.3, None), 0.3);
    }

    #[test]
    fn erosion_keeps_exactly_the_pixels_whose_whole_neighbourhood_is_valid() {
        // The definition, pixel by pixel, on masks with scattered holes and a blank block.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut kept = 0;
        for (h, w, r) in [
            (40, 57, 3),
            (33, 31, 5),
            (11, 11, 5),
            (9, 30, 5),
            (64, 300, 16),
        ] {
            let valid = Array2::from_shape_fn((h, w), |(y, x)| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                let hole = state.is_multiple_of(211);
                let blank = y > h / 2 && x < w / 4;
                !(hole || blank)
            });
            let eroded = erode(&valid, r);
            for ((y, x), &e) in eroded.indexed_iter() {
                let inside = y >= r && y + r < h && x >= r && x + r < w;
                let all =
                    inside && (y - r..=y + r).all(|yy| (x - r..=x + r).all(|xx| valid[[yy, xx]]));
                assert_eq!(e, all, "{h}×{w}, r {r}: pixel ({x}, {y})");
            }
            kept += eroded.iter().filter(|&&e| e).count();
        }
        assert!(kept > 1000, "{kept} pixels kept in all");
    }
}
