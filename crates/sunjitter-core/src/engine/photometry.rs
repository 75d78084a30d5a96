//! The frame brought to the reference's intensity scale before any flow is measured.
//!
//! Dense flow assumes the brightness of a feature does not change between the images: a frame
//! taken with ten times the exposure (automatic exposure control during a flare) otherwise
//! reads as motion everywhere. A constant gain and offset are estimated from the intensity
//! distributions of the same part of the Sun in both images (through the coarse transform,
//! which is pixels off at most) and removed. The distributions' spread and centre do not
//! depend on small misalignments, unlike a pixel-by-pixel fit, which a misalignment biases
//! towards zero gain. The refinement fits gain and offset again, exactly, on aligned pixels.

use crate::geometry::Similarity;
use ndarray::{Array2, ArrayView2};

/// Samples taken from each image (evenly strided over the mask).
const SAMPLES: usize = 200_000;
/// The spread compared: between these quantiles (robust to flares and cosmic rays).
const LOW_QUANTILE: f64 = 0.1;
const HIGH_QUANTILE: f64 = 0.9;

/// `frame ≈ gain × reference + offset` over the region both images show.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Photometry {
    pub gain: f64,
    pub offset: f64,
}

impl Photometry {
    /// Estimated from the reference inside `mask` and the frame at the coarse transform's
    /// image of the same pixels (`coarse` maps reference pixels to frame pixels). `None` when
    /// either image is flat there or too few pixels are shared.
    pub fn estimate(
        reference: ArrayView2<f32>,
        mask: &Array2<bool>,
        frame: ArrayView2<f32>,
        coarse: &Similarity,
    ) -> Option<Photometry> {
        let (h, w) = reference.dim();
        let (fh, fw) = frame.dim();
        let n_mask = crate::stats::count_set(mask.view());
        let stride = ((n_mask as f64 / SAMPLES as f64).sqrt().ceil() as usize).max(1);
        let mut ref_values = Vec::with_capacity(n_mask / (stride * stride) + 1);
        let mut frame_values = Vec::with_capacity(ref_values.capacity());
        for y in (0..h).step_by(stride) {
            for x in (0..w).step_by(stride) {
                if !mask[[y, x]] {
                    continue;
                }
                let r = reference[[y, x]];
                let [fx, fy] = coarse.apply([x as f64, y as f64]);
                let (fx, fy) = (fx.round(), fy.round());
                if !r.is_finite() || fx < 0.0 || fy < 0.0 || fx >= fw as f64 || fy >= fh as f64 {
                    continue;
                }
                let f = frame[[fy as usize, fx as usize]];
                if f.is_finite() {
                    ref_values.push(r);
                    frame_values.push(f);
                }
            }
        }
        if ref_values.len() < 64 {
            return None;
        }
        let (r_lo, r_mid, r_hi) = quantiles(&mut ref_values);
        let (f_lo, f_mid, f_hi) = quantiles(&mut frame_values);
        let (r_spread, f_spread) = (r_hi - r_lo, f_hi - f_lo);
        if !(r_spread > 0.0 && f_spread > 0.0) {
            return None;
        }
        let gain = f_spread / r_spread;
        let offset = f_mid - gain * r_mid;
        (gain.is_finite() && offset.is_finite()).then_some(Photometry { gain, offset })
    }

    /// The frame in the reference's intensity units: `(frame − offset) / gain`.
    /// Whether removing it changes no value.
    pub fn is_identity(&self) -> bool {
        self.gain == 1.0 && self.offset == 0.0
    }

    pub fn remove(&self, frame: &mut Array2<f32>) {
        let (scale, shift) = (1.0 / self.gain, -self.offset / self.gain);
        frame.mapv_inplace(|v| (v as f64 * scale + shift) as f32);
    }
}

fn quantiles(values: &mut [f32]) -> (f64, f64, f64) {
    let mut at = |q: f64| {
        let k = ((values.len() - 1) as f64 * q).round() as usize;
        *values.select_nth_unstable_by(k, f32::total_cmp).1 as f64
    };
    (at(LOW_QUANTILE), at(0.5), at(HIGH_QUANTILE))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(w: usize, h: usize) -> Array2<f32> {
        Array2::from_shape_fn((h, w), |(y, x)| {
            let (x, y) = (x as f32, y as f32);
            100.0 + 40.0 * (x / 7.0).sin() * (y / 11.0).cos() + 0.3 * x
        })
    }

    #[test]
    fn a_constant_gain_and_offset_are_recovered_and_removed() {
        let reference = scene(200, 160);
        let mask = Array2::from_elem(reference.dim(), true);
        let mut frame = reference.mapv(|v| 37.5 * v - 812.0);
        let identity = Similarity::identity(Similarity::array_center(200, 160));
        let p = Photometry::estimate(reference.view(), &mask, frame.view(), &identity).unwrap();
        assert!((p.gain - 37.5).abs() < 1e-4 * 37.5, "{p:?}");
        assert!((p.offset + 812.0).abs() < 1e-2, "{p:?}");
        p.remove(&mut frame);
        let worst = (&frame - &reference)
            .mapv(f32::abs)
            .fold(0f32, |a, &b| a.max(b));
        assert!(worst < 1e-3, "largest difference after removal {worst}");
    }

    #[test]
    fn the_frame_is_read_where_the_coarse_transform_puts_the_reference() {
        // The frame is the reference moved by (+30, −20) px and darkened 100×: where the
        // mask's pixels land, its distribution is the reference's.
        let big = scene(400, 300);
        let reference = big.slice(ndarray::s![50..250, 50..350]).to_owned();
        let frame = big.slice(ndarray::s![30..230, 80..380]).mapv(|v| 0.01 * v);
        let mut mask = Array2::from_elem(reference.dim(), false);
        mask.slice_mut(ndarray::s![40..160, 60..240]).fill(true);
        let mut moved = Similarity::identity(Similarity::array_center(300, 200));
        moved.dx = -30.0;
        moved.dy = 20.0;
        let p = Photometry::estimate(reference.view(), &mask, frame.view(), &moved).unwrap();
        assert!((p.gain - 0.01).abs() < 1e-6, "{p:?}");
        assert!(p.offset.abs() < 1e-4, "{p:?}");
    }

    #[test]
    fn a_flat_frame_has_no_photometry() {
        let reference = scene(64, 64);
        let mask = Array2::from_elem(reference.dim(), true);
        let flat = Array2::from_elem((64, 64), 5.0f32);
        let identity = Similarity::identity(Similarity::array_center(64, 64));
        assert_eq!(
            Photometry::estimate(reference.view(), &mask, flat.view(), &identity),
            None
        );
    }
}
