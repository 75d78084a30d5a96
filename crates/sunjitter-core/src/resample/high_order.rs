//! B-splines of degree 5, 7 and 9: weights, the prefiltered image, its values and gradients.

use super::prefilter::{dilate_support, fill_non_finite, non_finite_mask, prefilter, Prefilter};
use super::{
    gradients_at, high_order_shifted_row, high_order_similarity_row, locate, mirror, warp_rows,
    RowMap,
};
use crate::geometry::Similarity;
use ndarray::{Array2, ArrayView2, Axis, Zip};
use rayon::prelude::*;

/// Quintic B-spline weights of the six samples at offsets −2..=3 from `floor(x)`, for the
/// fraction `t` (Thévenaz, Blu & Unser 2000).
#[inline(always)]
pub(super) fn bspline5_weights(t: f64) -> [f64; 6] {
    let t2 = t * t;
    let last = t * t2 * t2 / 120.0;
    let u2 = t2 - t;
    let u4 = u2 * u2;
    let m = t - 0.5;
    let v = u2 * (u2 - 3.0);
    let first = (0.2 + u2 + u4) / 24.0 - last;
    let (a0, a1) = ((u2 * (u2 - 5.0) + 46.0 / 5.0) / 24.0, -m * (v + 4.0) / 12.0);
    let (b0, b1) = ((9.0 / 5.0 - v) / 16.0, m * (u4 - u2 - 5.0) / 24.0);
    [first, b0 + b1, a0 + a1, a0 - a1, b0 - b1, last]
}

/// Most taps of a supported spline (degree 9).
const MAX_TAPS: usize = 10;

/// `M_d(t + k)` for `k = 0..=d`: the cardinal B-spline of degree `d` (support `[0, d + 1]`).
fn cardinal_bspline(d: usize, t: f64) -> [f64; MAX_TAPS] {
    // A constant degree lets the recurrence unroll (with a run-time degree it takes a tenth
    // of a refinement's time).
    match d {
        0 => cardinal_bspline_of::<0>(t),
        1 => cardinal_bspline_of::<1>(t),
        2 => cardinal_bspline_of::<2>(t),
        3 => cardinal_bspline_of::<3>(t),
        4 => cardinal_bspline_of::<4>(t),
        5 => cardinal_bspline_of::<5>(t),
        6 => cardinal_bspline_of::<6>(t),
        7 => cardinal_bspline_of::<7>(t),
        8 => cardinal_bspline_of::<8>(t),
        _ => cardinal_bspline_of::<9>(t),
    }
}

/// [`cardinal_bspline`] by the recurrence `M_d(x) = (x·M_{d−1}(x) + (d+1−x)·M_{d−1}(x−1)) / d`,
/// no powers, no divisions and no branches in the loop.
#[inline(always)]
fn cardinal_bspline_of<const D: usize>(t: f64) -> [f64; MAX_TAPS] {
    const INVERSE: [f64; MAX_TAPS] = [
        0.0,
        1.0,
        1.0 / 2.0,
        1.0 / 3.0,
        1.0 / 4.0,
        1.0 / 5.0,
        1.0 / 6.0,
        1.0 / 7.0,
        1.0 / 8.0,
        1.0 / 9.0,
    ];
    let mut v = [0.0; MAX_TAPS];
    v[0] = 1.0;
    for e in 1..=D {
        let inv = INVERSE[e];
        // Descending, so that v[k − 1] is still degree e − 1's.
        v[e] = (1.0 - t) * v[e - 1] * inv;
        for k in (1..e).rev() {
            let x = t + k as f64;
            v[k] = (x * v[k] + (e as f64 + 1.0 - x) * v[k - 1]) * inv;
        }
        v[0] = t * v[0] * inv;
    }
    v
}

/// `M_4(t + k)`, `k = 0..=4`, explicitly: the quintic spline's derivative weights need them
/// for every sample of the refinement.
#[inline(always)]
fn quartic_cardinal(t: f64) -> [f64; 5] {
    let (t2, u) = (t * t, 1.0 - t);
    let t4 = t2 * t2;
    let u2 = u * u;
    [
        t4 / 24.0,
        (((-4.0 * t + 4.0) * t + 6.0) * t + 4.0) * t / 24.0 + 1.0 / 24.0,
        (((6.0 * t - 12.0) * t - 6.0) * t + 12.0) * t / 24.0 + 11.0 / 24.0,
        (((-4.0 * t + 12.0) * t - 6.0) * t - 12.0) * t / 24.0 + 11.0 / 24.0,
        u2 * u2 / 24.0,
    ]
}

/// Weights of the `n + 1` samples at offsets `−(n−1)/2 ..= (n+1)/2` from `floor(x)` for the
/// fraction `t`, for odd degree `n ≤ 9`.
#[inline(always)]
pub(super) fn bspline_weights(n: usize, t: f64) -> [f64; MAX_TAPS] {
    let v = cardinal_bspline(n, t);
    // Tap i sits at centred argument t − (i − (n−1)/2), i.e. M_n at t + (n − i).
    std::array::from_fn(|i| if i <= n { v[n - i] } else { 0.0 })
}

/// Derivatives of [`bspline_weights`] with respect to `t`: `M_n′(x) = M_{n−1}(x) − M_{n−1}(x−1)`.
#[inline(always)]
pub(super) fn bspline_derivative_weights(n: usize, t: f64) -> [f64; MAX_TAPS] {
    let v = if n == 5 {
        let q = quartic_cardinal(t);
        std::array::from_fn(|k| if k < 5 { q[k] } else { 0.0 })
    } else {
        cardinal_bspline(n - 1, t)
    };
    let at = |k: usize| if k < n { v[k] } else { 0.0 };
    std::array::from_fn(|i| {
        if i > n {
            0.0
        } else if i == n {
            at(0)
        } else {
            at(n - i) - at(n - i - 1)
        }
    })
}

/// Odd spline degrees above the cubic one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HighOrder {
    Quintic,
    Septic,
    Nonic,
}

impl HighOrder {
    fn degree(self) -> usize {
        match self {
            HighOrder::Quintic => 5,
            HighOrder::Septic => 7,
            HighOrder::Nonic => 9,
        }
    }

    /// Prefilter poles (Unser 1999) with the samples after which their powers are below f64
    /// precision, and the gain `Π (1 − z)(1 − 1/z)`.
    fn prefilter(self) -> Prefilter {
        match self {
            HighOrder::Quintic => Prefilter {
                poles: &[
                    (-0.430_575_347_099_973_8, 45),
                    (-0.043_096_288_203_264_65, 12),
                ],
                gain: 120.0,
            },
            HighOrder::Septic => Prefilter {
                poles: &[
                    (-0.535_280_430_796_438_2, 60),
                    (-0.122_554_615_192_326_7, 18),
                    (-0.009_148_694_809_608_277, 8),
                ],
                gain: 5040.0,
            },
            HighOrder::Nonic => Prefilter {
                poles: &[
                    (-0.607_997_389_168_625_7, 75),
                    (-0.201_750_520_193_153_3, 24),
                    (-0.043_222_608_540_481_76, 12),
                    (-0.002_121_306_903_180_816, 6),
                ],
                gain: 362_880.0,
            },
        }
    }
}

/// An image prepared for quintic, septic or degree-9 B-spline sampling: closer to band-limited
/// than the cubic one. The refinement models the frame with the quintic spline (and the flow
/// stage warps with it); `simulate` makes its frames with the degree-9 one.
#[derive(Debug, Clone)]
pub struct HighOrderSpline {
    order: HighOrder,
    coeffs: Array2<f32>,
    support_bad: Option<Array2<bool>>,
}

impl HighOrderSpline {
    /// Prefilter `src` (NaN-safe, as [`SplineImage::new`](super::SplineImage::new)).
    pub fn new(src: ArrayView2<f32>, order: HighOrder) -> Self {
        let bad = non_finite_mask(&src);
        let mut coeffs = Zip::from(&src).par_map_collect(|&v| v);
        if let Some(b) = &bad {
            fill_non_finite(&mut coeffs, b);
        }
        prefilter(&mut coeffs, order.prefilter());
        if !coeffs.is_standard_layout() {
            coeffs = coeffs.as_standard_layout().into_owned();
        }
        let reach = (order.degree() as isize - 1) / 2;
        HighOrderSpline {
            order,
            coeffs,
            support_bad: bad.map(|b| dilate_support(&b, reach, reach + 1)),
        }
    }

    /// Tap weights for the fraction `t` (the explicit quintic form: fewer operations than
    /// the recurrence).
    #[inline(always)]
    fn weights(&self, t: f64) -> [f64; MAX_TAPS] {
        match self.order {
            HighOrder::Quintic => {
                let w = bspline5_weights(t);
                std::array::from_fn(|i| if i < 6 { w[i] } else { 0.0 })
            }
            order => bspline_weights(order.degree(), t),
        }
    }

    /// The spline's degree.
    #[inline(always)]
    pub fn order(&self) -> HighOrder {
        self.order
    }

    /// The prefiltered coefficients.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(super) fn coeffs(&self) -> &Array2<f32> {
        &self.coeffs
    }

    /// Integer position and fraction on both axes, `None` outside the image or where the
    /// support holds a blank.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(super) fn locate_at(&self, x: f64, y: f64) -> Option<((usize, f64), (usize, f64))> {
        self.locate(x, y)
    }

    /// Integer position and fraction on both axes, `None` outside the image or where the
    /// support holds a blank.
    #[inline(always)]
    fn locate(&self, x: f64, y: f64) -> Option<((usize, f64), (usize, f64))> {
        let (h, w) = self.coeffs.dim();
        let (Some((ix, tx)), Some((iy, ty))) = (locate(x, w), locate(y, h)) else {
            return None;
        };
        if self.support_bad.as_ref().is_some_and(|bad| bad[[iy, ix]]) {
            return None;
        }
        Some(((ix, tx), (iy, ty)))
    }

    /// Per support row `j`, `Σ_i wx[k][i] c[iy − reach + j, ix − reach + i]` for each of the
    /// `K` column weight sets, for `TAPS = degree + 1` (a constant, so that the loops unroll;
    /// mirrored at the borders).
    #[inline(always)]
    fn row_sums<const TAPS: usize, const K: usize>(
        &self,
        (ix, iy): (usize, usize),
        wxs: [&[f64; MAX_TAPS]; K],
    ) -> [[f64; K]; TAPS] {
        let (h, w) = self.coeffs.dim();
        let reach = (TAPS - 2) / 2;
        let mut sums = [[0.0; K]; TAPS];
        if ix >= reach && iy >= reach && ix + TAPS <= w + reach && iy + TAPS <= h + reach {
            let data = self.coeffs.as_slice().expect("standard layout");
            for (j, r) in sums.iter_mut().enumerate() {
                let start = (iy + j - reach) * w + ix - reach;
                let row: &[f32; TAPS] = data[start..start + TAPS].try_into().expect("TAPS");
                for (i, &c) in row.iter().enumerate() {
                    for k in 0..K {
                        r[k] += wxs[k][i] * c as f64;
                    }
                }
            }
        } else {
            for (j, r) in sums.iter_mut().enumerate() {
                let row = self
                    .coeffs
                    .row(mirror((iy + j) as isize - reach as isize, h));
                for i in 0..TAPS {
                    let c = row[mirror((ix + i) as isize - reach as isize, w)] as f64;
                    for k in 0..K {
                        r[k] += wxs[k][i] * c;
                    }
                }
            }
        }
        sums
    }

    #[inline(always)]
    fn value_n<const TAPS: usize>(&self, at: (usize, usize), t: (f64, f64)) -> f64 {
        let rows = self.row_sums::<TAPS, 1>(at, [&self.weights(t.0)]);
        let wy = self.weights(t.1);
        rows.iter().zip(&wy).map(|(r, w)| w * r[0]).sum()
    }

    #[inline(always)]
    pub(super) fn sample_at(&self, x: f64, y: f64) -> f32 {
        let Some(((ix, tx), (iy, ty))) = self.locate(x, y) else {
            return f32::NAN;
        };
        let (at, t) = ((ix, iy), (tx, ty));
        (match self.order {
            HighOrder::Quintic => self.value_n::<6>(at, t),
            HighOrder::Septic => self.value_n::<8>(at, t),
            HighOrder::Nonic => self.value_n::<10>(at, t),
        }) as f32
    }

    #[inline(always)]
    fn gradient_n<const TAPS: usize>(&self, at: (usize, usize), (tx, ty): (f64, f64)) -> [f64; 3] {
        let n = TAPS - 1;
        let rows =
            self.row_sums::<TAPS, 2>(at, [&self.weights(tx), &bspline_derivative_weights(n, tx)]);
        let (wy, dy) = (self.weights(ty), bspline_derivative_weights(n, ty));
        let mut out = [0.0; 3];
        for (j, [r, rd]) in rows.iter().enumerate() {
            out[0] += wy[j] * r;
            out[1] += wy[j] * rd;
            out[2] += dy[j] * r;
        }
        out
    }

    /// [`HighOrderSpline::sample_with_gradient`] at each of `positions` (compiled for AVX2
    /// when the CPU has it: the refinement spends most of its time here).
    pub fn sample_with_gradient_at(&self, positions: &[[f64; 2]], out: &mut [[f64; 3]]) {
        gradients_at(self, positions, out);
    }

    /// Value and gradient `[v, ∂v/∂x, ∂v/∂y]` at `(x, y)`, as
    /// [`SplineImage::sample_with_gradient`](super::SplineImage::sample_with_gradient): one pass over the support.
    #[inline(always)]
    pub fn sample_with_gradient(&self, x: f64, y: f64) -> [f64; 3] {
        let Some(((ix, tx), (iy, ty))) = self.locate(x, y) else {
            return [f64::NAN; 3];
        };
        let (at, t) = ((ix, iy), (tx, ty));
        match self.order {
            HighOrder::Quintic => self.gradient_n::<6>(at, t),
            HighOrder::Septic => self.gradient_n::<8>(at, t),
            HighOrder::Nonic => self.gradient_n::<10>(at, t),
        }
    }

    /// The `out_width × out_height` window at column `x0`, row `y0` of the image warped by
    /// `t` (`out[p] = image(T(p))`, NaN outside), as [`SplineImage::warp_similarity_window`](super::SplineImage::warp_similarity_window).
    pub fn warp_similarity_window(
        &self,
        t: &Similarity,
        x0: usize,
        y0: usize,
        out_width: usize,
        out_height: usize,
    ) -> Array2<f32> {
        let size = (out_width, out_height);
        warp_rows(self, t, (x0, y0), size, high_order_similarity_row)
    }

    pub fn warp_similarity(
        &self,
        t: &Similarity,
        out_width: usize,
        out_height: usize,
    ) -> Array2<f32> {
        self.warp_similarity_window(t, 0, 0, out_width, out_height)
    }

    /// As [`Self::warp_similarity_window`], each output pixel moved by `shift` first:
    /// `out[p] = image(T(p + shift[p]))`, with `shift` the window's shape (NaN: no value).
    pub fn warp_similarity_window_shifted(
        &self,
        t: &Similarity,
        x0: usize,
        y0: usize,
        shift: ArrayView2<[f32; 2]>,
    ) -> Array2<f32> {
        let (height, width) = shift.dim();
        self.warp_similarity_window_shifted_by(t, (x0, y0), (width, height), |y, row| {
            for (r, s) in row.iter_mut().zip(shift.row(y)) {
                *r = *s;
            }
        })
    }

    /// As [`Self::warp_similarity_window_shifted`], the shifts of each of the window's rows
    /// (`y` from 0) written by `shift_row` as they are needed, so that none is stored whole.
    pub fn warp_similarity_window_shifted_by(
        &self,
        t: &Similarity,
        (x0, y0): (usize, usize),
        (width, height): (usize, usize),
        shift_row: impl Fn(usize, &mut [[f32; 2]]) + Sync,
    ) -> Array2<f32> {
        let map = RowMap::new(t, x0);
        let mut out = Array2::<f32>::zeros((height, width));
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each_init(
                || vec![[0f32; 2]; width],
                |shifts, (y, mut line)| {
                    shift_row(y, shifts);
                    let y = (y + y0) as f64;
                    match line.as_slice_mut() {
                        Some(r) => high_order_shifted_row(self, &map, y, shifts, r),
                        None => {
                            for (x, (v, d)) in line.iter_mut().zip(shifts.iter()).enumerate() {
                                let (sx, sy) = map.shifted(x, y, d);
                                *v = self.sample_at(sx, sy);
                            }
                        }
                    }
                },
            );
        out
    }
}
