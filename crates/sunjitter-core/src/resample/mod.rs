//! Resampling a frame onto another pixel grid: `out[p] = frame(T(p))`, NaN outside.
//!
//! Interpolators:
//! - [`Interp::Spline3`] (default): cubic B-spline with the exact interpolating
//!   prefilter and whole-sample mirror boundaries — the same numbers as
//!   `scipy.ndimage.map_coordinates(order=3, mode='mirror')` inside the image.
//!   Positions are float (no 1/32 px quantisation as in OpenCV's warps).
//! - [`Interp::Keys`]: Keys (1981) cubic convolution, a = −0.5, on the raw samples.
//! - [`Interp::Linear`]: bilinear, for quick looks.
//! - [`HighOrderSpline`]: quintic, septic and degree-9 B-splines (same prefilter scheme and
//!   boundaries; the quintic one matches scipy's `order=5`), with value and gradient. The
//!   engine's flow warps and intensity refinement model the frame with the quintic one.
//!
//! Non-finite input pixels: the spline prefilter is recursive across whole rows and
//! columns, so a single NaN would poison them. NaNs are filled first with a smooth
//! local mean (push-pull pyramid), and every output whose interpolation support
//! (4×4 samples; 2×2 for bilinear) touches a non-finite input is NaN.
//!
//! Sample coordinates are f64: at 4096 px an f32 position resolves only 2.4e-4 px.

mod high_order;
mod prefilter;
#[cfg(target_arch = "x86_64")]
mod quintic_x86;

pub use high_order::{HighOrder, HighOrderSpline};
use prefilter::{dilate_support, fill_non_finite, non_finite_mask, prefilter, CUBIC_PREFILTER};

use crate::geometry::Similarity;
use ndarray::{Array2, ArrayView2, Axis, Zip};
use rayon::prelude::*;

/// Choice of interpolator.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Interp {
    /// Cubic B-spline with prefilter (order 3), the default.
    #[default]
    Spline3,
    /// Keys cubic convolution (a = −0.5).
    Keys,
    /// Bilinear.
    Linear,
}

/// Something that can be sampled at a float position of its own grid.
pub trait Sampler: Sync {
    fn width(&self) -> usize;
    fn height(&self) -> usize;
    /// Value at `(x, y)` (x = column), NaN outside `[0, W−1] × [0, H−1]` or where the
    /// support touches a non-finite input pixel.
    fn sample(&self, x: f64, y: f64) -> f32;
}

/// Index reflection about the first and last sample (whole-sample symmetric,
/// `d c b | a b c d | c b a`), as scipy's `mode='mirror'`.
#[inline]
fn mirror(i: isize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let period = 2 * (n as isize - 1);
    let i = i.rem_euclid(period);
    if i >= n as isize {
        (period - i) as usize
    } else {
        i as usize
    }
}

/// Integer position and fraction, `None` outside the sample hull.
#[inline(always)]
fn locate(v: f64, n: usize) -> Option<(usize, f64)> {
    // A hair of tolerance for round-off at the last sample.
    const TOL: f64 = 1e-9;
    let last = n as f64 - 1.0;
    if !(v >= -TOL && v <= last + TOL) {
        return None; // also catches NaN
    }
    let v = v.clamp(0.0, last);
    let i = (v.floor() as usize).min(n - 1);
    Some((i, v - i as f64))
}

/// Cubic B-spline weights of the samples at offsets −1, 0, 1, 2 from `floor(x)`, for the
/// fraction `t`.
#[inline(always)]
pub(crate) fn bspline3_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    let u = 1.0 - t;
    [
        u * u * u / 6.0,
        (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
        (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
        t3 / 6.0,
    ]
}

/// Derivatives of [`bspline3_weights`] with respect to `t` (they sum to zero).
#[inline(always)]
fn bspline3_derivative_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let u = 1.0 - t;
    [
        -u * u / 2.0,
        (3.0 * t2 - 4.0 * t) / 2.0,
        (-3.0 * t2 + 2.0 * t + 1.0) / 2.0,
        t2 / 2.0,
    ]
}

#[inline]
fn keys_weights(t: f64) -> [f64; 4] {
    const A: f64 = -0.5;
    let near = |s: f64| ((A + 2.0) * s - (A + 3.0)) * s * s + 1.0;
    let far = |s: f64| ((A * s - 5.0 * A) * s + 8.0 * A) * s - 4.0 * A;
    [far(1.0 + t), near(t), near(1.0 - t), far(2.0 - t)]
}

/// 4×4 weighted sum around `(ix, iy)` (offsets −1..=2), mirrored at the borders.
#[inline(always)]
fn sum4x4(data: &ArrayView2<f32>, ix: usize, iy: usize, wx: &[f64; 4], wy: &[f64; 4]) -> f64 {
    let (h, w) = data.dim();
    let mut acc = 0.0;
    if ix >= 1 && ix + 2 < w && iy >= 1 && iy + 2 < h {
        for (j, wyj) in wy.iter().enumerate() {
            let row = data.row(iy + j - 1);
            let mut r = 0.0;
            for (i, wxi) in wx.iter().enumerate() {
                r += wxi * row[ix + i - 1] as f64;
            }
            acc += wyj * r;
        }
    } else {
        let xs: [usize; 4] = std::array::from_fn(|i| mirror(ix as isize + i as isize - 1, w));
        for (j, wyj) in wy.iter().enumerate() {
            let row = data.row(mirror(iy as isize + j as isize - 1, h));
            let mut r = 0.0;
            for (i, wxi) in wx.iter().enumerate() {
                r += wxi * row[xs[i]] as f64;
            }
            acc += wyj * r;
        }
    }
    acc
}

/// A frame prepared for repeated cubic B-spline sampling (prefiltered once).
#[derive(Debug, Clone)]
pub struct SplineImage {
    coeffs: Array2<f32>,
    /// `true` where the 4×4 support of floor position `[y, x]` holds a non-finite input.
    support_bad: Option<Array2<bool>>,
}

impl SplineImage {
    /// Prefilter `src` (NaN-safe). Cost: two recursive passes over the image.
    pub fn new(src: ArrayView2<f32>) -> Self {
        let bad = non_finite_mask(&src);
        let mut coeffs = Zip::from(&src).par_map_collect(|&v| v);
        if let Some(b) = &bad {
            fill_non_finite(&mut coeffs, b);
        }
        prefilter(&mut coeffs, CUBIC_PREFILTER);
        SplineImage {
            coeffs,
            support_bad: bad.map(|b| dilate_support(&b, 1, 2)),
        }
    }

    /// The B-spline coefficients (mirror boundary), e.g. to compare with scipy's
    /// `spline_filter(mode='mirror')`.
    pub fn coefficients(&self) -> ArrayView2<'_, f32> {
        self.coeffs.view()
    }

    pub fn warp_similarity(
        &self,
        t: &Similarity,
        out_width: usize,
        out_height: usize,
    ) -> Array2<f32> {
        self.warp_similarity_window(t, 0, 0, out_width, out_height)
    }

    /// The `out_width × out_height` window at column `x0`, row `y0` of
    /// [`SplineImage::warp_similarity`]'s output (same values, computed only there).
    pub fn warp_similarity_window(
        &self,
        t: &Similarity,
        x0: usize,
        y0: usize,
        out_width: usize,
        out_height: usize,
    ) -> Array2<f32> {
        let size = (out_width, out_height);
        warp_rows(self, t, (x0, y0), size, spline_similarity_row)
    }

    /// Value and gradient `[v, ∂v/∂x, ∂v/∂y]` of the spline at `(x, y)`: NaN outside the
    /// image or where the support holds a blank.
    #[inline]
    pub fn sample_with_gradient(&self, x: f64, y: f64) -> [f64; 3] {
        let (h, w) = self.coeffs.dim();
        let (Some((ix, tx)), Some((iy, ty))) = (locate(x, w), locate(y, h)) else {
            return [f64::NAN; 3];
        };
        if let Some(bad) = &self.support_bad {
            if bad[[iy, ix]] {
                return [f64::NAN; 3];
            }
        }
        let (wx, wy) = (bspline3_weights(tx), bspline3_weights(ty));
        let (dx, dy) = (
            bspline3_derivative_weights(tx),
            bspline3_derivative_weights(ty),
        );
        let c = self.coeffs.view();
        if ix >= 1 && ix + 2 < w && iy >= 1 && iy + 2 < h {
            // One pass over the 4×4 support for all three sums.
            let (mut v, mut gx, mut gy) = (0.0, 0.0, 0.0);
            for j in 0..4 {
                let row = c.row(iy + j - 1);
                let (mut r, mut rd) = (0.0, 0.0);
                for i in 0..4 {
                    let cv = row[ix + i - 1] as f64;
                    r += wx[i] * cv;
                    rd += dx[i] * cv;
                }
                v += wy[j] * r;
                gx += wy[j] * rd;
                gy += dy[j] * r;
            }
            [v, gx, gy]
        } else {
            [
                sum4x4(&c, ix, iy, &wx, &wy),
                sum4x4(&c, ix, iy, &dx, &wy),
                sum4x4(&c, ix, iy, &wx, &dy),
            ]
        }
    }

    /// [`Sampler::sample`], inlined into the row loops.
    #[inline(always)]
    fn sample_at(&self, x: f64, y: f64) -> f32 {
        let (h, w) = self.coeffs.dim();
        let (Some((ix, tx)), Some((iy, ty))) = (locate(x, w), locate(y, h)) else {
            return f32::NAN;
        };
        if let Some(bad) = &self.support_bad {
            if bad[[iy, ix]] {
                return f32::NAN;
            }
        }
        sum4x4(
            &self.coeffs.view(),
            ix,
            iy,
            &bspline3_weights(tx),
            &bspline3_weights(ty),
        ) as f32
    }
}

/// A similarity as `similarity_map` evaluates it, for output columns offset by `x0`.
struct RowMap {
    a: f64,
    b: f64,
    cx: f64,
    cy: f64,
    ox: f64,
    oy: f64,
    x0: f64,
}

impl RowMap {
    fn new(t: &Similarity, x0: usize) -> Self {
        let (a, b) = t.ab();
        let [cx, cy] = t.center;
        RowMap {
            a,
            b,
            cx,
            cy,
            ox: cx + t.dx,
            oy: cy + t.dy,
            x0: x0 as f64,
        }
    }

    /// `T(p + d)` for `p = (x + x0, y)`: the similarity's linear part carries the shift.
    #[inline(always)]
    fn shifted(&self, x: usize, y: f64, d: &[f32; 2]) -> (f64, f64) {
        let (sx, sy) = self.at(x, y);
        let (dx, dy) = (d[0] as f64, d[1] as f64);
        (
            sx + self.a * dx - self.b * dy,
            sy + self.b * dx + self.a * dy,
        )
    }

    /// Same arithmetic as `similarity_map` at `(x + x0, y)`, so results are bitwise equal.
    #[inline(always)]
    fn at(&self, x: usize, y: f64) -> (f64, f64) {
        let (u, v) = (x as f64 + self.x0 - self.cx, y - self.cy);
        (
            self.a * u - self.b * v + self.ox,
            self.b * u + self.a * v + self.oy,
        )
    }
}

/// A prefiltered spline that a warp samples point by point.
trait SplineSample: Sync {
    fn sample_at(&self, x: f64, y: f64) -> f32;
}

impl SplineSample for SplineImage {
    #[inline(always)]
    fn sample_at(&self, x: f64, y: f64) -> f32 {
        SplineImage::sample_at(self, x, y)
    }
}

impl SplineSample for HighOrderSpline {
    #[inline(always)]
    fn sample_at(&self, x: f64, y: f64) -> f32 {
        HighOrderSpline::sample_at(self, x, y)
    }
}

/// The `width × height` window at column `x0`, row `y0` of `sp` warped by `t`, rows in
/// parallel, each through `row` (a CPU-dispatched instance of [`similarity_row_body`]).
fn warp_rows<S: SplineSample>(
    sp: &S,
    t: &Similarity,
    (x0, y0): (usize, usize),
    (width, height): (usize, usize),
    row: fn(&S, &RowMap, f64, &mut [f32]),
) -> Array2<f32> {
    let map = RowMap::new(t, x0);
    let mut out = Array2::<f32>::zeros((height, width));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut line)| match line.as_slice_mut() {
            Some(r) => row(sp, &map, (y + y0) as f64, r),
            None => {
                for (x, v) in line.iter_mut().enumerate() {
                    let (sx, sy) = map.at(x, (y + y0) as f64);
                    *v = sp.sample_at(sx, sy);
                }
            }
        });
    out
}

crate::flow::simd::multiversion!(fn spline_similarity_row(
    sp: &SplineImage,
    map: &RowMap,
    y: f64,
    out: &mut [f32],
) => similarity_row_body::<SplineImage>);

/// [`HighOrderSpline::sample_with_gradient`] at each of `positions`: four at a time with AVX2
/// where the CPU has it and the spline is quintic (identical values).
fn gradients_at(sp: &HighOrderSpline, positions: &[[f64; 2]], out: &mut [[f64; 3]]) {
    #[cfg(target_arch = "x86_64")]
    if let (HighOrder::Quintic, Some(isa)) = (sp.order(), quintic_x86::Isa::detect()) {
        // SAFETY: the CPU has `isa`'s features and the spline is quintic.
        return unsafe { quintic_x86::gradients_at(isa, sp, positions, out) };
    }
    for (&[x, y], o) in positions.iter().zip(out) {
        *o = sp.sample_with_gradient(x, y);
    }
}

/// One output row of a warp whose pixels are moved by `shift` before the similarity: four
/// pixels at a time with AVX2 where the CPU has it and the spline is quintic (identical
/// values).
fn high_order_shifted_row(
    sp: &HighOrderSpline,
    map: &RowMap,
    y: f64,
    shift: &[[f32; 2]],
    out: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    if let (HighOrder::Quintic, Some(isa)) = (sp.order(), quintic_x86::Isa::detect()) {
        // SAFETY: the CPU has `isa`'s features and the spline is quintic.
        return unsafe { quintic_x86::values_at(isa, sp, |x| map.shifted(x, y, &shift[x]), out) };
    }
    shifted_row_portable(sp, map, y, shift, out)
}

crate::flow::simd::multiversion!(fn shifted_row_portable(
    sp: &HighOrderSpline,
    map: &RowMap,
    y: f64,
    shift: &[[f32; 2]],
    out: &mut [f32],
) => shifted_row_body);

/// One output row of a warp whose pixels are moved by `shift` before the similarity.
#[inline(always)]
fn shifted_row_body(
    sp: &HighOrderSpline,
    map: &RowMap,
    y: f64,
    shift: &[[f32; 2]],
    out: &mut [f32],
) {
    for (x, (v, d)) in out.iter_mut().zip(shift).enumerate() {
        let (sx, sy) = map.shifted(x, y, d);
        *v = sp.sample_at(sx, sy);
    }
}

/// One output row of a spline warp: four pixels at a time with AVX2 where the CPU has it and
/// the spline is quintic (identical values).
fn high_order_similarity_row(sp: &HighOrderSpline, map: &RowMap, y: f64, out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if let (HighOrder::Quintic, Some(isa)) = (sp.order(), quintic_x86::Isa::detect()) {
        // SAFETY: the CPU has `isa`'s features and the spline is quintic.
        return unsafe { quintic_x86::values_at(isa, sp, |x| map.at(x, y), out) };
    }
    similarity_row_portable(sp, map, y, out)
}

crate::flow::simd::multiversion!(fn similarity_row_portable(
    sp: &HighOrderSpline,
    map: &RowMap,
    y: f64,
    out: &mut [f32],
) => similarity_row_body::<HighOrderSpline>);

/// One output row of a spline warp (compiled for AVX2 when available: `floor` becomes one
/// instruction; no FMA contraction, so the values do not depend on the CPU).
#[inline(always)]
fn similarity_row_body<S: SplineSample>(sp: &S, map: &RowMap, y: f64, out: &mut [f32]) {
    for (x, v) in out.iter_mut().enumerate() {
        let (sx, sy) = map.at(x, y);
        *v = sp.sample_at(sx, sy);
    }
}

impl Sampler for SplineImage {
    fn width(&self) -> usize {
        self.coeffs.ncols()
    }
    fn height(&self) -> usize {
        self.coeffs.nrows()
    }
    #[inline]
    fn sample(&self, x: f64, y: f64) -> f32 {
        self.sample_at(x, y)
    }
}

/// Keys cubic convolution on the raw samples (NaN propagates through its support).
#[derive(Debug, Clone)]
pub struct KeysImage<'a> {
    data: ArrayView2<'a, f32>,
}

impl<'a> KeysImage<'a> {
    pub fn new(data: ArrayView2<'a, f32>) -> Self {
        KeysImage { data }
    }
}

impl Sampler for KeysImage<'_> {
    fn width(&self) -> usize {
        self.data.ncols()
    }
    fn height(&self) -> usize {
        self.data.nrows()
    }
    #[inline]
    fn sample(&self, x: f64, y: f64) -> f32 {
        let (h, w) = self.data.dim();
        let (Some((ix, tx)), Some((iy, ty))) = (locate(x, w), locate(y, h)) else {
            return f32::NAN;
        };
        sum4x4(&self.data, ix, iy, &keys_weights(tx), &keys_weights(ty)) as f32
    }
}

/// Bilinear interpolation on the raw samples.
#[derive(Debug, Clone)]
pub struct LinearImage<'a> {
    data: ArrayView2<'a, f32>,
}

impl<'a> LinearImage<'a> {
    pub fn new(data: ArrayView2<'a, f32>) -> Self {
        LinearImage { data }
    }
}

impl Sampler for LinearImage<'_> {
    fn width(&self) -> usize {
        self.data.ncols()
    }
    fn height(&self) -> usize {
        self.data.nrows()
    }
    #[inline]
    fn sample(&self, x: f64, y: f64) -> f32 {
        let (h, w) = self.data.dim();
        let (Some((ix, tx)), Some((iy, ty))) = (locate(x, w), locate(y, h)) else {
            return f32::NAN;
        };
        let (x1, y1) = ((ix + 1).min(w - 1), (iy + 1).min(h - 1));
        let d = &self.data;
        let top = d[[iy, ix]] as f64 * (1.0 - tx) + d[[iy, x1]] as f64 * tx;
        let bottom = d[[y1, ix]] as f64 * (1.0 - tx) + d[[y1, x1]] as f64 * tx;
        (top * (1.0 - ty) + bottom * ty) as f32
    }
}

/// The coordinate map of a similarity, reference grid → frame grid.
pub fn similarity_map(t: &Similarity) -> impl Fn(f64, f64) -> (f64, f64) + Sync {
    // Same arithmetic as `Similarity::apply`, with cos/sin hoisted out of the pixel loop.
    let (a, b) = t.ab();
    let [cx, cy] = t.center;
    let (ox, oy) = (cx + t.dx, cy + t.dy);
    move |x, y| {
        let (u, v) = (x - cx, y - cy);
        (a * u - b * v + ox, b * u + a * v + oy)
    }
}

/// `out[y, x] = sampler(map(x, y))` for an `out_height × out_width` grid, parallel over rows.
pub fn warp_sampler<S, F>(sampler: &S, out_width: usize, out_height: usize, map: F) -> Array2<f32>
where
    S: Sampler + ?Sized,
    F: Fn(f64, f64) -> (f64, f64) + Sync,
{
    let mut out = Array2::<f32>::zeros((out_height, out_width));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for (x, v) in row.iter_mut().enumerate() {
                let (sx, sy) = map(x as f64, y as f64);
                *v = sampler.sample(sx, sy);
            }
        });
    out
}

/// Resample `src` onto an `out_width × out_height` grid through a similarity:
/// `out[p] = src(t.apply(p))`, NaN outside `src`.
pub fn warp_similarity(
    src: ArrayView2<f32>,
    t: &Similarity,
    out_width: usize,
    out_height: usize,
    interp: Interp,
) -> Array2<f32> {
    warp_with(src, out_width, out_height, interp, similarity_map(t))
}

/// Resample `src` through any coordinate map `(x, y) → (x', y')` of the output grid.
pub fn warp_with<F>(
    src: ArrayView2<f32>,
    out_width: usize,
    out_height: usize,
    interp: Interp,
    map: F,
) -> Array2<f32>
where
    F: Fn(f64, f64) -> (f64, f64) + Sync,
{
    match interp {
        Interp::Spline3 => warp_sampler(&SplineImage::new(src), out_width, out_height, map),
        Interp::Keys => warp_sampler(&KeysImage::new(src), out_width, out_height, map),
        Interp::Linear => warp_sampler(&LinearImage::new(src), out_width, out_height, map),
    }
}

#[cfg(test)]
mod tests {
    use super::high_order::{bspline5_weights, bspline_derivative_weights, bspline_weights};
    use super::*;
    use crate::test_data::read_real;
    use ndarray::s;

    /// The 6×7 test array `a[y, x] = ((7·y + 3·x) mod 11) − 2·y + 0.25·x·y` (float32).
    fn small() -> Array2<f32> {
        Array2::from_shape_fn((6, 7), |(y, x)| {
            ((7 * y + 3 * x) % 11) as f32 - 2.0 * y as f32 + 0.25 * (x * y) as f32
        })
    }

    #[test]
    fn prefilter_matches_scipy_spline_filter_mirror() {
        // python3 -c "import numpy as np, scipy.ndimage as nd
        // y,x=np.mgrid[0:6,0:7]; a=((7*y+3*x)%11-2*y+0.25*x*y).astype(float)
        // c=nd.spline_filter(a,3,mode='mirror'); print(c[0,0],c[2,3],c[5,6],c[3,0],c[0,4])"
        let c = SplineImage::new(small().view());
        let got = c.coefficients();
        let truth = [
            ([0, 0], -5.539_777_327_935_224),
            ([2, 3], -13.186_842_105_263_162),
            ([5, 6], 22.0),
            ([3, 0], 20.291_902_834_008_106),
            ([0, 4], -13.937_348_178_137_654),
        ];
        for ([y, x], want) in truth {
            let v = got[[y, x]] as f64;
            assert!((v - want).abs() < 1e-5, "c[{y},{x}] = {v}, scipy {want}");
        }
    }

    #[test]
    fn spline_samples_match_scipy_map_coordinates_mirror() {
        // python3 -c "import numpy as np, scipy.ndimage as nd
        // y,x=np.mgrid[0:6,0:7]; a=((7*y+3*x)%11-2*y+0.25*x*y).astype(float)
        // pts=[(0.3,0.0),(2.71,3.15),(5.0,6.0),(4.9,0.05),(0.5,5.5),(3.0,2.0)]  # (y, x)
        // print(nd.map_coordinates(a, np.array(pts).T, order=3, mode='mirror'))"
        let s = SplineImage::new(small().view());
        let truth = [
            ((0.3, 0.0), 1.109_842_105_263_158_9),
            ((2.71, 3.15), 1.955_013_961_444_383_6),
            ((5.0, 6.0), 6.5),
            ((4.9, 0.05), -7.902_538_302_808_706),
            ((0.5, 5.5), 3.351_717_484_817_813),
            ((3.0, 2.0), 0.5),
        ];
        for ((y, x), want) in truth {
            let v = s.sample(x, y) as f64;
            assert!((v - want).abs() < 2e-6, "({x}, {y}) = {v}, scipy {want}");
        }
        assert!(s.sample(-0.01, 2.0).is_nan() && s.sample(3.0, 5.01).is_nan());
    }

    #[test]
    fn quintic_samples_match_scipy_map_coordinates_mirror() {
        // python3 -c "import numpy as np, scipy.ndimage as nd
        // y,x=np.mgrid[0:6,0:7]; a=((7*y+3*x)%11-2*y+0.25*x*y).astype(float)
        // pts=[(0.3,0.0),(2.71,3.15),(5.0,6.0),(4.9,0.05),(0.5,5.5),(3.0,2.0),(1.37,4.62)]
        // print(nd.map_coordinates(a, np.array(pts).T, order=5, mode='mirror'))"
        // and the same formula on a 40×45 grid (rows longer than the first pole's horizon) at
        // (20.3, 17.8), (0.2, 44.0), (38.5, 0.7).
        let q = HighOrderSpline::new(small().view(), HighOrder::Quintic);
        let truth = [
            ((0.3, 0.0), 1.037_611_665_360_909_3),
            ((2.71, 3.15), 1.663_202_693_557_032_3),
            ((5.0, 6.0), 6.5),
            ((4.9, 0.05), -7.924_560_053_172_756_5),
            ((0.5, 5.5), 3.589_837_468_674_489),
            ((3.0, 2.0), 0.5),
            ((1.37, 4.62), 3.262_378_062_081_978),
        ];
        let sample = |q: &HighOrderSpline, x: f64, y: f64| {
            let t = Similarity::identity([0.0, 0.0]);
            let moved = Similarity { dx: x, dy: y, ..t };
            q.warp_similarity_window(&moved, 0, 0, 1, 1)[[0, 0]] as f64
        };
        for ((y, x), want) in truth {
            let v = sample(&q, x, y);
            assert!((v - want).abs() < 2e-5, "({x}, {y}) = {v}, scipy {want}");
        }
        let big = Array2::from_shape_fn((40, 45), |(y, x)| {
            ((7 * y + 3 * x) % 11) as f32 - 2.0 * y as f32 + 0.25 * (x * y) as f32
        });
        let q = HighOrderSpline::new(big.view(), HighOrder::Quintic);
        for ((y, x), want) in [
            ((20.3, 17.8), 54.669_184_236_706_41),
            ((0.2, 44.0), 1.108_591_534_222_591_4),
            ((38.5, 0.7), -68.629_977_391_725_89),
        ] {
            let v = sample(&q, x, y);
            assert!((v - want).abs() < 1e-4, "({x}, {y}) = {v}, scipy {want}");
        }
        assert!(sample(&q, -0.01, 2.0).is_nan());
    }

    #[test]
    fn quintic_samples_in_blocks_reproduce_a_quartic_and_its_gradient() {
        // A quintic B-spline reproduces polynomials up to degree 4; away from the mirrored
        // border (its influence decays as 0.43^distance) the samples are the polynomial's and
        // the gradients its derivative. Runs of positions go through the four-lane kernel
        // where the CPU has it; each must equal the one-at-a-time path bit for bit, blanks
        // and positions outside included.
        let f = |x: f64, y: f64| 1e-4 * x.powi(4) - 2e-4 * x * x * y * y + 0.03 * x * y + 0.5 * y;
        let fx = |x: f64, y: f64| 4e-4 * x.powi(3) - 4e-4 * x * y * y + 0.03 * y;
        let fy = |x: f64, y: f64| -4e-4 * x * x * y + 0.03 * x + 0.5;
        let mut img = Array2::from_shape_fn((64, 72), |(y, x)| f(x as f64, y as f64) as f32);
        let q = HighOrderSpline::new(img.view(), HighOrder::Quintic);
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let inner: Vec<[f64; 2]> = (0..203)
            .map(|_| [22.0 + 28.0 * next(), 22.0 + 20.0 * next()])
            .collect();
        let mut out = vec![[0.0; 3]; inner.len()];
        q.sample_with_gradient_at(&inner, &mut out);
        for (&[x, y], &[v, gx, gy]) in inner.iter().zip(&out) {
            assert!(
                (v - f(x, y)).abs() < 2e-4,
                "value at ({x}, {y}): {v} vs {}",
                f(x, y)
            );
            assert!(
                (gx - fx(x, y)).abs() < 2e-4,
                "∂x at ({x}, {y}): {gx} vs {}",
                fx(x, y)
            );
            assert!(
                (gy - fy(x, y)).abs() < 2e-4,
                "∂y at ({x}, {y}): {gy} vs {}",
                fy(x, y)
            );
        }
        // Near the edges, outside, and around a blank.
        img[[30, 40]] = f32::NAN;
        let q = HighOrderSpline::new(img.view(), HighOrder::Quintic);
        let mut mixed: Vec<[f64; 2]> = (0..401)
            .map(|_| [-2.0 + 76.0 * next(), -2.0 + 68.0 * next()])
            .collect();
        for k in 0..64 {
            mixed.push([38.0 + 4.0 * next(), 28.0 + 4.0 * next() + (k % 2) as f64]);
        }
        let mut out = vec![[0.0; 3]; mixed.len()];
        q.sample_with_gradient_at(&mixed, &mut out);
        let bits = |v: &[f64; 3]| v.map(f64::to_bits);
        for (&[x, y], got) in mixed.iter().zip(&out) {
            assert_eq!(
                bits(got),
                bits(&q.sample_with_gradient(x, y)),
                "at ({x}, {y})"
            );
        }
        // Each instruction set this CPU has, called directly (the dispatch above takes one):
        // the quartic where it is reproduced, the one-at-a-time path bit for bit everywhere.
        #[cfg(target_arch = "x86_64")]
        let q_plain = HighOrderSpline::new(
            Array2::from_shape_fn((64, 72), |(y, x)| f(x as f64, y as f64) as f32).view(),
            HighOrder::Quintic,
        );
        #[cfg(target_arch = "x86_64")]
        for isa in quintic_x86::Isa::available() {
            let mut got = vec![[0.0; 3]; inner.len()];
            // SAFETY: the CPU has `isa`'s features; the spline is quintic.
            unsafe { quintic_x86::gradients_at(isa, &q_plain, &inner, &mut got) };
            for (&[x, y], &[v, gx, gy]) in inner.iter().zip(&got) {
                let err = [v - f(x, y), gx - fx(x, y), gy - fy(x, y)];
                assert!(err.iter().all(|e| e.abs() < 2e-4), "{isa:?} at ({x}, {y})");
            }
            let mut got = vec![[0.0; 3]; mixed.len()];
            let mut values = vec![0.0f32; mixed.len()];
            // SAFETY: as above.
            unsafe {
                quintic_x86::gradients_at(isa, &q, &mixed, &mut got);
                quintic_x86::values_at(isa, &q, |k| (mixed[k][0], mixed[k][1]), &mut values);
            }
            for ((&[x, y], g), v) in mixed.iter().zip(&got).zip(&values) {
                let one = q.sample_with_gradient(x, y);
                assert_eq!(bits(g), bits(&one), "{isa:?} at ({x}, {y})");
                let value = q.sample_at(x, y);
                assert_eq!(v.to_bits(), value.to_bits(), "{isa:?} value at ({x}, {y})");
            }
        }
        // Warps, row by row: the same values as sampling each pixel.
        let t = Similarity {
            scale: 1.003,
            rotation_rad: 0.02,
            dx: 0.37,
            dy: -1.61,
            center: [35.5, 31.5],
        };
        let warped = q.warp_similarity_window(&t, 0, 0, 72, 64);
        let map = similarity_map(&t);
        for ((y, x), &v) in warped.indexed_iter() {
            let (sx, sy) = map(x as f64, y as f64);
            assert_eq!(
                v.to_bits(),
                q.sample_at(sx, sy).to_bits(),
                "pixel ({x}, {y})"
            );
            if (20..52).contains(&x) && (20..44).contains(&y) && (sx - 40.0).hypot(sy - 30.0) > 14.0
            {
                assert!((v as f64 - f(sx, sy)).abs() < 2e-4, "pixel ({x}, {y})");
            }
        }
    }

    /// Centred B-spline of odd degree `n` at `x` (de Boor's explicit sum of truncated powers,
    /// taken on the negative side, where fewer terms cancel: the spline is even).
    fn bspline(n: usize, x: f64) -> f64 {
        let x = -x.abs();
        let half = (n + 1) as f64 / 2.0;
        if x.abs() >= half {
            return 0.0;
        }
        let (mut acc, mut binomial, mut factorial) = (0.0, 1.0, 1.0);
        for k in 0..=n + 1 {
            let u = x + half - k as f64;
            if u > 0.0 {
                let term = binomial * u.powi(n as i32);
                acc += if k % 2 == 0 { term } else { -term };
            }
            binomial = binomial * (n + 1 - k) as f64 / (k + 1) as f64;
        }
        for i in 2..=n {
            factorial *= i as f64;
        }
        acc / factorial
    }

    #[test]
    fn quintic_septic_and_nonic_weights_are_the_b_spline() {
        for t in [0.0, 0.13, 0.5, 0.77, 0.999] {
            let explicit = bspline5_weights(t);
            for (n, w) in [
                (5, [&explicit[..], &[0.0; 4]].concat()),
                (5, bspline_weights(5, t).to_vec()),
                (7, bspline_weights(7, t).to_vec()),
                (9, bspline_weights(9, t).to_vec()),
            ] {
                let reach = (n as f64 - 1.0) / 2.0;
                for (i, wi) in w.iter().enumerate().take(n + 1) {
                    let want = bspline(n, t - (i as f64 - reach));
                    assert!(
                        (wi - want).abs() < 1e-12,
                        "n {n}, t {t}, tap {i}: {wi} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn derivative_weights_are_the_b_spline_slope() {
        // Central difference of de Boor's sum: its error is h²/6 · M‴, below 1e-9 at h = 1e-5.
        let h = 1e-5;
        for n in [3, 5, 7, 9] {
            for t in [0.0, 0.13, 0.5, 0.77, 0.999] {
                let d = bspline_derivative_weights(n, t);
                let reach = (n as f64 - 1.0) / 2.0;
                for (i, di) in d.iter().enumerate() {
                    let x = t - (i as f64 - reach);
                    let want = if i <= n {
                        (bspline(n, x + h) - bspline(n, x - h)) / (2.0 * h)
                    } else {
                        0.0
                    };
                    assert!(
                        (di - want).abs() < 1e-7,
                        "n {n}, t {t}, tap {i}: {di} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn septic_spline_interpolates_and_reproduces_cubics_in_the_interior() {
        // B-spline interpolation of degree n passes through the samples and reproduces
        // polynomials of degree ≤ n exactly; the mirror boundary's effect decays as
        // 0.535^d, below f32 precision 40 px inside.
        let p = |x: f64, y: f64| {
            1e-3 * (x - 50.0).powi(3) - 2e-2 * (y - 50.0).powi(2) + 0.5 * x - 3e-4 * x * y * y
        };
        let img = Array2::from_shape_fn((100, 100), |(y, x)| p(x as f64, y as f64) as f32);
        for order in [HighOrder::Septic, HighOrder::Nonic] {
            let spline = HighOrderSpline::new(img.view(), order);
            let at = |x: f64, y: f64| {
                let moved = Similarity {
                    dx: x,
                    dy: y,
                    ..Similarity::identity([0.0, 0.0])
                };
                spline.warp_similarity_window(&moved, 0, 0, 1, 1)[[0, 0]] as f64
            };
            for (x, y) in [(0.0, 0.0), (99.0, 17.0), (41.0, 58.0)] {
                let want = img[[y as usize, x as usize]] as f64;
                assert!(
                    (at(x, y) - want).abs() < 1e-3,
                    "sample ({x}, {y}): {} vs {want}",
                    at(x, y)
                );
            }
            for (x, y) in [(45.3, 52.71), (50.5, 49.5), (58.91, 41.07)] {
                let want = p(x, y);
                assert!(
                    (at(x, y) - want).abs() < 1e-3,
                    "{order:?} ({x}, {y}): {} vs {want}",
                    at(x, y)
                );
            }
        }
    }

    #[test]
    fn quintic_gradient_is_the_derivative_of_a_reproduced_quartic() {
        // Quintic B-splines reproduce polynomials of degree ≤ 5; away from the mirrored border
        // (0.43^distance) value and gradient must be the polynomial's own. Blanks make NaN.
        let f = |x: f64, y: f64| 1e-5 * (x - 30.0).powi(4) - 0.01 * x * y + 2e-4 * y.powi(3);
        let df = |x: f64, y: f64| {
            (
                4e-5 * (x - 30.0).powi(3) - 0.01 * y,
                -0.01 * x + 6e-4 * y * y,
            )
        };
        let mut img = Array2::from_shape_fn((64, 64), |(y, x)| f(x as f64, y as f64) as f32);
        let s = HighOrderSpline::new(img.view(), HighOrder::Quintic);
        for (x, y) in [(30.0, 31.0), (27.37, 33.81), (36.5, 28.25)] {
            let [v, gx, gy] = s.sample_with_gradient(x, y);
            let (wx, wy) = df(x, y);
            assert!((v - f(x, y)).abs() < 1e-4, "value {v} vs {}", f(x, y));
            assert!((gx - wx).abs() < 1e-4, "∂x {gx} vs {wx}");
            assert!((gy - wy).abs() < 1e-4, "∂y {gy} vs {wy}");
        }
        assert!(s.sample_with_gradient(63.5, 3.0)[0].is_nan());
        img[[30, 40]] = f32::NAN;
        let s = HighOrderSpline::new(img.view(), HighOrder::Quintic);
        assert!(s
            .sample_with_gradient(38.2, 29.5)
            .iter()
            .all(|v| v.is_nan()));
        assert!(s
            .sample_with_gradient(30.0, 31.0)
            .iter()
            .all(|v| v.is_finite()));
    }

    #[test]
    fn spline_gradient_is_the_derivative_of_a_reproduced_quadratic() {
        // Cubic B-splines reproduce quadratics; away from the mirrored border the gradient
        // must be the polynomial's own (the border's influence decays as 0.268^distance).
        let f = |x: f64, y: f64| 0.02 * x * x - 0.01 * x * y + 0.5 * y + 3.0;
        let img = Array2::from_shape_fn((48, 48), |(y, x)| f(x as f64, y as f64) as f32);
        let s = SplineImage::new(img.view());
        for (x, y) in [(20.0, 21.0), (23.37, 19.81), (26.5, 28.25)] {
            let [v, gx, gy] = s.sample_with_gradient(x, y);
            assert!((v - f(x, y)).abs() < 2e-4, "value {v} vs {}", f(x, y));
            assert!((gx - (0.04 * x - 0.01 * y)).abs() < 2e-4, "∂x {gx}");
            assert!((gy - (-0.01 * x + 0.5)).abs() < 2e-4, "∂y {gy}");
        }
        assert!(s.sample_with_gradient(-0.5, 3.0)[0].is_nan());
    }

    #[test]
    fn keys_matches_the_cubic_convolution_kernel() {
        // Keys (1981), a = −0.5, reproduces quadratics exactly in the interior.
        let q = Array2::from_shape_fn((8, 8), |(y, x)| {
            let (x, y) = (x as f32, y as f32);
            0.5 * x * x - 0.3 * x * y + 2.0 * y + 1.0
        });
        let k = KeysImage::new(q.view());
        let (x, y) = (3.37, 4.81);
        let want = 0.5 * x * x - 0.3 * x * y + 2.0 * y + 1.0;
        assert!((k.sample(x, y) as f64 - want).abs() < 1e-4);
    }

    #[test]
    fn shifted_trace_crop_matches_scipy() {
        // A real TRACE 171 crop shifted by (+0.37, −1.62) px:
        // python3 -c "import numpy as np, scipy.ndimage as nd; from astropy.io import fits
        // a=fits.getdata('data/real/trace_171_19980519T222143_1024.fits').astype(float)[400:440,500:540]
        // y,x=np.mgrid[0:40,0:40].astype(float)
        // o=nd.map_coordinates(a,[y-1.62,x+0.37],order=3,mode='mirror')
        // print([o[j,i] for j,i in [(2,0),(10,10),(20,31),(39,39),(25,5)]])"
        // Agreement is f32 rounding: ≤ 1.3e-5 on values near 200.
        let full = read_real("trace_171_19980519T222143_1024.fits");
        let crop = full.slice(s![400..440, 500..540]).to_owned();
        let t = Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: 0.37,
            dy: -1.62,
            center: Similarity::array_center(40, 40),
        };
        let out = warp_similarity(crop.view(), &t, 40, 40, Interp::Spline3);
        let truth = [
            ([2, 0], 178.340_996_735_971_2),
            ([10, 10], 185.072_521_583_694_3),
            ([20, 31], 186.116_070_665_049_08),
            ([25, 5], 209.794_896_156_004_85),
        ];
        for ([y, x], want) in truth {
            let v = out[[y, x]] as f64;
            assert!((v - want).abs() < 1e-4, "out[{y},{x}] = {v}, scipy {want}");
        }
        // Row 0 maps to y = −1.62 and column 39 to x = 39.37: outside the frame.
        assert!(out[[0, 5]].is_nan() && out[[39, 39]].is_nan());

        // The same crop through a rotation and scale (coordinates from the contract's
        // formula, c = 19.5): X = A(x−c) − B(y−c) + c + 0.37, Y = B(x−c) + A(y−c) + c − 1.62,
        // A = 1.003 cos 0.01, B = 1.003 sin 0.01;
        // nd.map_coordinates(a, [Y, X], order=3, mode='mirror') at (3,1), (17,23), (36,30).
        let t = Similarity {
            scale: 1.003,
            rotation_rad: 0.01,
            ..t
        };
        let out = warp_similarity(crop.view(), &t, 40, 40, Interp::Spline3);
        let truth = [
            ([3, 1], 173.425_866_421_311_04),
            ([17, 23], 199.092_298_361_948_82),
            ([36, 30], 157.965_060_017_594_7),
        ];
        for ([y, x], want) in truth {
            let v = out[[y, x]] as f64;
            assert!((v - want).abs() < 1e-4, "out[{y},{x}] = {v}, scipy {want}");
        }
    }

    /// Separable Gaussian blur of `a` (σ = 2 px, mirrored edges): a band-limited test image.
    fn band_limited(a: &Array2<f32>) -> Array2<f32> {
        let k: Vec<f64> = (-8..=8).map(|i| (-(i * i) as f64 / 8.0).exp()).collect();
        let norm: f64 = k.iter().sum();
        let (h, w) = a.dim();
        let pass = |a: &Array2<f32>, along_x: bool| {
            Array2::from_shape_fn((h, w), |(y, x)| {
                let mut acc = 0.0;
                for (i, kv) in k.iter().enumerate() {
                    let d = i as isize - 8;
                    acc += kv
                        * if along_x {
                            a[[y, mirror(x as isize + d, w)]]
                        } else {
                            a[[mirror(y as isize + d, h), x]]
                        } as f64;
                }
                (acc / norm) as f32
            })
        };
        pass(&pass(a, true), false)
    }

    #[test]
    fn sub_pixel_shift_and_back_recovers_a_band_limited_real_image() {
        let full = read_real("trace_171_19980519T222143_1024.fits");
        let img = band_limited(&full.slice(s![300..428, 400..528]).to_owned());
        let t = Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: 0.37,
            dy: -0.81,
            center: Similarity::array_center(128, 128),
        };
        let there = warp_similarity(img.view(), &t, 128, 128, Interp::Spline3);
        let back = warp_similarity(there.view(), &t.inverse(), 128, 128, Interp::Spline3);
        // Away from the NaN border and its fill, the round trip is the interpolation error
        // of a σ = 2 px image twice over: 4.3e-5 of the image's range (Keys 3.0e-4).
        let inner = s![8..120, 8..120];
        let range = img.slice(inner).fold(0.0f32, |m, v| m.max(*v))
            - img.slice(inner).fold(f32::MAX, |m, v| m.min(*v));
        let worst = ndarray::Zip::from(img.slice(inner))
            .and(back.slice(inner))
            .fold(0.0f32, |m, a, b| m.max((a - b).abs()));
        assert!(worst < 1e-4 * range, "worst {worst}, range {range}");
        // Keys is a lower-order interpolator: looser, but the same ballpark.
        let there = warp_similarity(img.view(), &t, 128, 128, Interp::Keys);
        let back = warp_similarity(there.view(), &t.inverse(), 128, 128, Interp::Keys);
        let worst_keys = ndarray::Zip::from(img.slice(inner))
            .and(back.slice(inner))
            .fold(0.0f32, |m, a, b| m.max((a - b).abs()));
        assert!(
            worst_keys > worst && worst_keys < 1e-3 * range,
            "keys {worst_keys}"
        );
    }

    #[test]
    fn a_nan_hole_masks_only_outputs_whose_support_touches_it() {
        let full = read_real("trace_171_19980519T222143_1024.fits");
        let clean = full.slice(s![500..564, 500..564]).to_owned();
        let mut holed = clean.clone();
        holed.slice_mut(s![30..33, 20..22]).fill(f32::NAN);
        let t = Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: 0.25,
            dy: 0.5,
            center: Similarity::array_center(64, 64),
        };
        let a = warp_similarity(clean.view(), &t, 64, 64, Interp::Spline3);
        let b = warp_similarity(holed.view(), &t, 64, 64, Interp::Spline3);
        // Output (x, y) samples (x + 0.25, y + 0.5): support columns x−1..x+2, rows y−1..y+2.
        // It touches columns 20..=21 iff x ∈ 18..=22, rows 30..=32 iff y ∈ 28..=33.
        for ((y, x), v) in b.indexed_iter() {
            let touches = (18..=22).contains(&x) && (28..=33).contains(&y);
            if y == 63 || x == 63 {
                continue; // maps outside the frame
            }
            assert_eq!(v.is_nan(), touches, "({x}, {y})");
            let far = !((14..=26).contains(&x) && (24..=36).contains(&y));
            if far {
                // The smooth fill leaks through the IIR prefilter, decaying as 0.27^d: ≤ 1.4e-5
                // relative at 4 px and beyond.
                let rel = (v - a[[y, x]]).abs() / a[[y, x]].abs();
                assert!(rel < 1e-4, "({x}, {y}): {v} vs {}", a[[y, x]]);
            }
        }
        // Keys and bilinear have no prefilter: NaN spreads over exactly their support.
        let k = warp_similarity(holed.view(), &t, 64, 64, Interp::Keys);
        assert!(k[[30, 20]].is_nan() && !k[[30, 17]].is_nan() && !k[[27, 20]].is_nan());
        // An image with no finite pixel gives no finite output, without panicking.
        let empty = Array2::from_elem((5, 6), f32::NAN);
        assert!(warp_similarity(
            empty.view(),
            &Similarity::identity([2.5, 2.0]),
            6,
            5,
            Interp::Spline3
        )
        .iter()
        .all(|v| v.is_nan()));
    }

    #[test]
    #[ignore = "timing report, run with --release --ignored --nocapture"]
    fn time_4096_square_warp() {
        let n = 4096;
        let img = Array2::from_shape_fn((n, n), |(y, x)| ((x * 7 + y * 13) % 97) as f32);
        let t = Similarity {
            scale: 1.0002,
            rotation_rad: 1e-3,
            dx: 0.3,
            dy: -0.2,
            center: Similarity::array_center(n, n),
        };
        let start = std::time::Instant::now();
        let spline = SplineImage::new(img.view());
        let prefiltered = start.elapsed();
        let out = spline.warp_similarity(&t, n, n);
        let total = start.elapsed();
        let start = std::time::Instant::now();
        let keys = warp_similarity(img.view(), &t, n, n, Interp::Keys);
        let keys_time = start.elapsed();
        println!(
            "4096² on {} threads: spline prefilter {prefiltered:?}, prefilter+warp {total:?}; keys warp {keys_time:?}",
            rayon::current_num_threads()
        );
        assert!(out[[n / 2, n / 2]].is_finite() && keys[[n / 2, n / 2]].is_finite());
    }
}
