//! The reference as the refinement reads it.

use super::RefineSettings;
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

/// The reference as every refinement against it reads it, made once per reference: smoothed
/// by the refinement's `smoothing_px`, and the copy smoothed further whose gradient weighs
/// the residuals.
pub struct RefineReference {
    smoothed: Array2<f32>,
    /// `None` when no further smoothing is configured (the gradient is `smoothed`'s).
    weighting: Option<Array2<f32>>,
    smoothing_px: f64,
}

impl RefineReference {
    pub fn new(reference: ArrayView2<f32>, settings: &RefineSettings) -> RefineReference {
        let smoothed = crate::preprocess::gaussian_smooth(reference, settings.smoothing_px);
        let weighting = (settings.gradient_smoothing_px > 0.0).then(|| {
            crate::preprocess::gaussian_smooth(smoothed.view(), settings.gradient_smoothing_px)
        });
        RefineReference {
            smoothed,
            weighting,
            smoothing_px: settings.smoothing_px.max(0.0),
        }
    }

    fn weighting(&self) -> ArrayView2<'_, f32> {
        self.weighting.as_ref().unwrap_or(&self.smoothed).view()
    }

    /// The fit's pixels among `pixels` (x, y, cell): those whose gain instrument lies on the
    /// grid and whose values and instruments are finite.
    pub(super) fn fit_pixels(&self, pixels: &[(usize, usize, usize)]) -> Vec<Pixel> {
        let (h, w) = self.smoothed.dim();
        // The gain's instrument: the reference at four points far enough for the smoothed noise
        // to be uncorrelated with this pixel's (ρ = e^{−d²/4σ²} < 2 % at d = 4σ).
        let reach_gain = ((4.0 * self.smoothing_px).ceil() as usize).max(1);
        let (smoothed, weighting) = (self.smoothed.view(), self.weighting());
        pixels
            .par_iter()
            .filter_map(|&(x, y, cell)| {
                if x < reach_gain || y < reach_gain || x + reach_gain >= w || y + reach_gain >= h {
                    return None;
                }
                let value = smoothed[[y, x]] as f64;
                let (gx, gy) = gradient(&weighting, x, y);
                let d = reach_gain;
                let neighbours = (smoothed[[y, x - d]] as f64
                    + smoothed[[y, x + d]] as f64
                    + smoothed[[y - d, x]] as f64
                    + smoothed[[y + d, x]] as f64)
                    / 4.0;
                let finite = [value, gx, gy, neighbours].iter().all(|v| v.is_finite());
                finite.then_some(Pixel {
                    x,
                    y,
                    cell,
                    value,
                    gx,
                    gy,
                    neighbours,
                })
            })
            .collect()
    }
}

/// One pixel of the fit: position, cell, reference value, and the reference's weighting
/// gradient and neighbour mean (the instruments of the geometric and gain equations).
pub(super) struct Pixel {
    pub(super) x: usize,
    pub(super) y: usize,
    pub(super) cell: usize,
    pub(super) value: f64,
    pub(super) gx: f64,
    pub(super) gy: f64,
    pub(super) neighbours: f64,
}

/// Central-difference gradient of `img` at `(x, y)` (interior points only).
fn gradient(img: &ArrayView2<f32>, x: usize, y: usize) -> (f64, f64) {
    (
        (img[[y, x + 1]] as f64 - img[[y, x - 1]] as f64) / 2.0,
        (img[[y + 1, x]] as f64 - img[[y - 1, x]] as f64) / 2.0,
    )
}
