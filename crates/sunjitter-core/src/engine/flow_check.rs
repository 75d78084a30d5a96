//! The flow's interpolation check, for pairs whose answer is the flow's (between channels,
//! or with the refinement off).
//!
//! A real frame is a new sampling of the sky, not the flow's quintic resampling of the
//! reference, and on undersampled images the two move structure differently. The flow's σ
//! (the scatter of its vectors) cannot see that: between channels, on known-truth pairs, the
//! flow's translation can be several σ off (docs/validation.md#flow-interpolation-check). So,
//! as the refinement does, every such frame is checked. A frame is made from the reference
//! through the measured transform, with its shift reduced to the fractional part, by a cubic
//! spline (one order below the flow's model; band-limited frames lie on the model's other
//! side, nearer). The flow then measures it, and the part of its error that its own σ do not
//! cover is this frame's interpolation term. It starts as far from the copy's answer as the
//! pair's flow started from its own: on undersampled images the flow settles within a band
//! around the answer, and where in it depends on the way in (from the exact answer the check
//! would see far less error than the pair's own).

use super::fine::{fine_alignment, flow_reach_px, FlowRegion, FlowSetup, PassStart, FLOW_TAPER_PX};
use super::region::mask_roi;
use super::seed::Binned;
use crate::geometry::Similarity;
use crate::resample::SplineImage;
use ndarray::{s, Array2, ArrayView2, Zip};

/// Side of the square the check measures on, px. On large images the check runs on the
/// central part of the sampled region only: less of the field means less averaging of the
/// error over sub-pixel positions when the frame turns or scales, so a larger term, not a
/// smaller one.
const CHECK_SIDE_PX: usize = 512;

/// Per parameter (scale, rotation rad, dx, dy), the error beyond the check's own σ (quadratic
/// excess) of the flow on a cubic-spline copy of `reference` moved by `transform`, started
/// where `start` (the pair's own start) was relative to it. Both about the reference array's
/// centre. With `binned`, the answer was measured on those binned copies, and so is the
/// check: the copy is moved at full resolution and then binned, as the pair's frame was
/// (binning a moved image is not moving a binned one); the term is in full-grid pixels.
/// `None` when the check cannot run.
/// `answer`: the transform measured and the start it was measured from; `setup`: the pair's
/// (its frame's smoothing and the Sun's rotation do not apply to the copy).
pub(super) fn flow_interpolation_check(
    reference: ArrayView2<f32>,
    binned: Option<&Binned>,
    region: FlowRegion,
    answer: (&Similarity, &Similarity),
    setup: FlowSetup,
) -> Option<[f64; 4]> {
    let (transform, start) = answer;
    let (winsize, cfg) = (setup.winsize, setup.cfg);
    let factor = binned.map_or(1, |b| 1usize << b.level());
    let on_grid = |t: &Similarity| binned.map_or(*t, |b| b.to_binned(t));
    // The grid the flow measures on: the reference's, or its binned copy.
    let grid = binned.map_or(reference, |b| b.reference.view());
    let (h, w) = grid.dim();
    // Same sub-pixel positions (on the full grid too), and the copy stays inside the
    // reference.
    let f = factor as f64;
    let local_full = Similarity {
        dx: transform.dx - f * (transform.dx / f).round(),
        dy: transform.dy - f * (transform.dy / f).round(),
        ..*transform
    };
    let local = on_grid(&local_full);
    // The square sampled: the centre of the mask's box.
    let roi = mask_roi(region.mask);
    let (side_x, side_y) = (roi.width.min(CHECK_SIDE_PX), roi.height.min(CHECK_SIDE_PX));
    let inner = (
        roi.x + (roi.width - side_x) / 2,
        roi.y + (roi.height - side_y) / 2,
        side_x,
        side_y,
    );
    // The sub-image around it holds the flow's whole reach from every sampled point (and,
    // binned, whole blocks of the full grid).
    let reach = flow_reach_px(winsize, cfg.poly_n).ceil() as usize + FLOW_TAPER_PX + 2;
    let (full_h, full_w) = reference.dim();
    let (sx0, sx1) = grow(inner.0, inner.2, reach, w.min(full_w / factor));
    let (sy0, sy1) = grow(inner.1, inner.3, reach, h.min(full_h / factor));
    let (sw, sh) = (sx1 - sx0, sy1 - sy0);
    let copy = moved_copy(
        reference,
        &local_full,
        (factor * sx0, factor * sy0),
        (factor * sw, factor * sh),
    )?;
    let copy = match binned {
        Some(binned) => binned.bin(copy.view(), None),
        None => copy,
    };
    let offset = [sx0 as f64, sy0 as f64];
    let in_sub = |t: &Similarity| Similarity {
        center: [t.center[0] - offset[0], t.center[1] - offset[1]],
        ..*t
    };
    let (transform, start) = (on_grid(transform), on_grid(start));
    let reference = grid;

    let sub_reference = reference.slice(s![sy0..sy1, sx0..sx1]);
    let mut sub_mask: Array2<bool> = region.mask.slice(s![sy0..sy1, sx0..sx1]).to_owned();
    Zip::indexed(&mut sub_mask).for_each(|(y, x), m| {
        let (gx, gy) = (x + sx0, y + sy0);
        *m = *m
            && (inner.0..inner.0 + inner.2).contains(&gx)
            && (inner.1..inner.1 + inner.3).contains(&gy);
    });
    let sub_region = FlowRegion {
        mask: &sub_mask,
        sample_within: region
            .sample_within
            .map(|([cx, cy], r)| ([cx - offset[0], cy - offset[1]], r)),
    };
    // The pair's start error, `transform⁻¹ ∘ start` in reference coordinates, from the copy's
    // answer.
    let start_error = transform
        .inverse()
        .after(&start.recentered(transform.center));
    let measured = fine_alignment(
        sub_reference,
        &copy,
        sub_region,
        PassStart::Coarse(in_sub(&local.after(&start_error))),
        cfg.max_passes,
        FlowSetup {
            frame_smoothing_px: 0.0,
            carried: None,
            ..setup
        },
    )
    .ok()?;
    let truth = in_sub(&local)
        .recentered(measured.transform.center)
        .params();
    let got = measured.transform.params();
    let term: [f64; 4] = std::array::from_fn(|k| {
        let bias = got[k] - truth[k];
        (bias * bias - measured.covariance[k][k]).max(0.0).sqrt()
    });
    tracing::debug!(?term, bias = ?std::array::from_fn::<f64, 4, _>(|k| got[k] - truth[k]), factor, "flow interpolation check");
    let term = [term[0], term[1], term[2] * f, term[3] * f];
    term.iter().all(|v| v.is_finite()).then_some(term)
}

/// `reference` moved by `local` (about the reference's centre) by a cubic spline, on the
/// `size` (width, height) sub-image at `origin` (x, y): sub-image pixel q is the reference at
/// `local⁻¹(q + origin)`, read from a window around it. `None` for a non-finite motion.
fn moved_copy(
    reference: ArrayView2<f32>,
    local: &Similarity,
    (sx0, sy0): (usize, usize),
    (sw, sh): (usize, usize),
) -> Option<Array2<f32>> {
    let (h, w) = reference.dim();
    let (sx1, sy1) = (sx0 + sw, sy0 + sh);
    // Where the copy's pixels come from: the sub-image moved back by the transform.
    let inverse = local.inverse();
    let corners = [
        [sx0 as f64, sy0 as f64],
        [sx1 as f64 - 1.0, sy0 as f64],
        [sx0 as f64, sy1 as f64 - 1.0],
        [sx1 as f64 - 1.0, sy1 as f64 - 1.0],
    ];
    let motion = corners
        .iter()
        .map(|p| {
            let q = inverse.apply(*p);
            (q[0] - p[0]).abs().max((q[1] - p[1]).abs())
        })
        .fold(0.0f64, f64::max);
    if !motion.is_finite() {
        return None;
    }
    // The cubic spline's support and its prefilter's border transient.
    let source_margin = motion.ceil() as usize + 8;
    let (ux0, ux1) = grow(sx0, sw, source_margin, w);
    let (uy0, uy1) = grow(sy0, sh, source_margin, h);
    let to_source = Similarity {
        dx: inverse.dx + (sx0 as f64 - ux0 as f64),
        dy: inverse.dy + (sy0 as f64 - uy0 as f64),
        center: [
            inverse.center[0] - sx0 as f64,
            inverse.center[1] - sy0 as f64,
        ],
        ..inverse
    };
    let source = reference.slice(s![uy0..uy1, ux0..ux1]);
    Some(SplineImage::new(source).warp_similarity(&to_source, sw, sh))
}

/// The span `lo … lo + len` grown by `by` each side, within `0 … n`.
fn grow(lo: usize, len: usize, by: usize, n: usize) -> (usize, usize) {
    (lo.saturating_sub(by), (lo + len + by).min(n))
}
