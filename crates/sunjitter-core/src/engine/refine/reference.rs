//! The reference as the refinement reads it.

use super::RefineSettings;
use crate::engine::region::gaussian_reach;
use crate::preprocess::gaussian_smooth_as;
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

/// The reference as every refinement against it reads it, made once per reference: smoothed
/// by the refinement's `smoothing_px`, and the copy smoothed further whose gradient weighs
/// the residuals.
pub struct RefineReference {
    /// On `window` of the reference grid only.
    smoothed: Array2<f32>,
    /// `None` when no further smoothing is configured (the gradient is `smoothed`'s).
    weighting: Option<Array2<f32>>,
    smoothing_px: f64,
    /// Where `smoothed` lies on the reference grid: first column and row, and the grid's size.
    origin: (usize, usize),
    grid: (usize, usize),
}

impl RefineReference {
    pub fn new(reference: ArrayView2<f32>, settings: &RefineSettings) -> RefineReference {
        let (h, w) = reference.dim();
        RefineReference::within(reference, settings, (0, 0, w.max(1) - 1, h.max(1) - 1))
    }

    /// As [`RefineReference::new`] for pixels inside `bbox` (inclusive) only: the smoothing
    /// runs on the box and the reach of what reads around each pixel, with the same values
    /// there (a full-disk frame's disk is about half its pixels).
    pub fn within(
        reference: ArrayView2<f32>,
        settings: &RefineSettings,
        (x0, y0, x1, y1): (usize, usize, usize, usize),
    ) -> RefineReference {
        let (h, w) = reference.dim();
        // Around each pixel: its gain instrument's points, or its gradient on the weighting
        // copy and that copy's kernel; all on exact values, a kernel's reach from the edges.
        let around = gain_reach(settings.smoothing_px)
            .max(1 + gaussian_reach(settings.gradient_smoothing_px));
        let margin = around + gaussian_reach(settings.smoothing_px);
        let rows = y0.saturating_sub(margin)..(y1 + margin + 1).min(h);
        let cols = x0.saturating_sub(margin)..(x1 + margin + 1).min(w);
        let origin = (cols.start, rows.start);
        // Normalised as the whole reference would be, so the window's values are its values.
        let has_nan = !crate::stats::all_finite(reference);
        let window = reference.slice(ndarray::s![rows, cols]);
        let smoothed = gaussian_smooth_as(window, settings.smoothing_px, has_nan);
        let weighting = (settings.gradient_smoothing_px > 0.0)
            .then(|| gaussian_smooth_as(smoothed.view(), settings.gradient_smoothing_px, has_nan));
        RefineReference {
            smoothed,
            weighting,
            smoothing_px: settings.smoothing_px.max(0.0),
            origin,
            grid: (h, w),
        }
    }

    fn weighting(&self) -> ArrayView2<'_, f32> {
        self.weighting.as_ref().unwrap_or(&self.smoothed).view()
    }

    /// The fit's pixels among `pixels` (x, y, cell): those whose gain instrument lies on the
    /// grid and whose values and instruments are finite.
    pub(super) fn fit_pixels(&self, pixels: &[(usize, usize, usize)]) -> Vec<Pixel> {
        let (h, w) = self.grid;
        let (ox, oy) = self.origin;
        let (sh, sw) = self.smoothed.dim();
        let reach_gain = gain_reach(self.smoothing_px);
        let (smoothed, weighting) = (self.smoothed.view(), self.weighting());
        let pixel = |&(x, y, cell): &(usize, usize, usize)| {
            if x < reach_gain || y < reach_gain || x + reach_gain >= w || y + reach_gain >= h {
                return None;
            }
            // On the window's grid; a pixel whose reads leave the window is not the fit's.
            let (lx, ly) = (x.checked_sub(ox)?, y.checked_sub(oy)?);
            let d = reach_gain;
            if lx < d || ly < d || lx + d >= sw || ly + d >= sh {
                return None;
            }
            let value = smoothed[[ly, lx]] as f64;
            let (gx, gy) = gradient(&weighting, lx, ly);
            let neighbours = (smoothed[[ly, lx - d]] as f64
                + smoothed[[ly, lx + d]] as f64
                + smoothed[[ly - d, lx]] as f64
                + smoothed[[ly + d, lx]] as f64)
                / 4.0;
            let finite = [value, gx, gy, neighbours].iter().all(|v| v.is_finite());
            finite.then_some(Pixel {
                x,
                y,
                cell,
                value,
                gx,
                gy,
                slope: gx.hypot(gy),
                neighbours,
            })
        };
        // Blocks of pixels kept in buffers of their own size, put together once, in parallel:
        // collected straight, each thread's buffer would grow by doubling, copied at every
        // step.
        let blocks: Vec<Vec<Pixel>> = pixels
            .par_chunks(FIT_PIXEL_BLOCK)
            .map(|block| {
                let mut kept = Vec::with_capacity(block.len());
                kept.extend(block.iter().filter_map(pixel));
                kept
            })
            .collect();
        crate::pages::concat(&blocks)
    }
}

/// Pixels of [`RefineReference::fit_pixels`] made together.
const FIT_PIXEL_BLOCK: usize = 4096;

/// The gain's instrument reads the reference at four points this far from the pixel, far
/// enough for the smoothed noise to be uncorrelated with the pixel's own
/// (ρ = e^{−d²/4σ²} < 2 % at d = 4σ).
fn gain_reach(smoothing_px: f64) -> usize {
    ((4.0 * smoothing_px).ceil() as usize).max(1)
}

/// One pixel of the fit: position, cell, reference value, and the reference's weighting
/// gradient and neighbour mean (the instruments of the geometric and gain equations).
#[derive(Clone, Copy)]
pub(super) struct Pixel {
    pub(super) x: usize,
    pub(super) y: usize,
    pub(super) cell: usize,
    pub(super) value: f64,
    pub(super) gx: f64,
    pub(super) gy: f64,
    /// The gradient's length, which ranks the pixels by flatness (every refinement of the
    /// same pixels, a self-test's cases, reads it).
    pub(super) slope: f64,
    pub(super) neighbours: f64,
}

/// Central-difference gradient of `img` at `(x, y)` (interior points only).
fn gradient(img: &ArrayView2<f32>, x: usize, y: usize) -> (f64, f64) {
    (
        (img[[y, x + 1]] as f64 - img[[y, x - 1]] as f64) / 2.0,
        (img[[y + 1, x]] as f64 - img[[y - 1, x]] as f64) / 2.0,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_reads_what_the_whole_reference_reads() {
        // The definition is the whole reference smoothed; a window around the pixels must give
        // the same fit, bit for bit, with and without the weighting copy, and with a NaN far
        // outside the window (it switches the normalisation of the whole image).
        let mut image = crate::test_data::read_real("trace_171_19980519T222143_1024.fits");
        image[[5, 1000]] = f32::NAN;
        let (x0, y0, x1, y1) = (300, 400, 520, 610);
        let pixels: Vec<_> = (y0..=y1)
            .step_by(3)
            .flat_map(|y| (x0..=x1).step_by(2).map(move |x| (x, y, 0)))
            .collect();
        for gradient_smoothing_px in [0.0, 1.3] {
            let settings = RefineSettings {
                smoothing_px: 0.7,
                gradient_smoothing_px,
                ..RefineSettings::default()
            };
            let whole = RefineReference::new(image.view(), &settings).fit_pixels(&pixels);
            let window = RefineReference::within(image.view(), &settings, (x0, y0, x1, y1));
            assert!(window.smoothed.len() < image.len() / 8);
            let windowed = window.fit_pixels(&pixels);
            assert_eq!(whole.len(), pixels.len());
            assert_eq!(whole.len(), windowed.len());
            for (a, b) in whole.iter().zip(&windowed) {
                let same = |u: f64, v: f64| u.to_bits() == v.to_bits();
                assert!(
                    (a.x, a.y) == (b.x, b.y)
                        && same(a.value, b.value)
                        && same(a.gx, b.gx)
                        && same(a.gy, b.gy)
                        && same(a.neighbours, b.neighbours),
                    "({}, {}) with gradient smoothing {gradient_smoothing_px}",
                    a.x,
                    a.y
                );
            }
        }
    }
}
