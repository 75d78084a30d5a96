//! Polynomial expansion (Farnebäck 2003 §3; OpenCV `FarnebackPolyExp`): every pixel's
//! neighbourhood, weighted by a Gaussian applicability of radius `n` and σ `sigma`, is fitted
//! with `f(x) ≈ xᵀAx + bᵀx + c`. Output per pixel, 5 channels in OpenCV's order:
//! `[b_y, b_x, A_yy, A_xx, A_xy·2]` (the last is the xy coefficient, i.e. 2·A_xy).
//! Borders replicate the edge pixel, as OpenCV does. A pixel whose support touches missing
//! data (NaN) gets NaN in all five channels.

use super::simd;
use nalgebra::SMatrix;
use rayon::prelude::*;
use std::ops::Range;

/// Separable kernels and the entries of the inverse Gram matrix the expansion needs.
pub(crate) struct PolyKernel {
    pub n: usize,
    g: Vec<f32>,
    xg: Vec<f32>,
    xxg: Vec<f32>,
    ig11: f32,
    ig03: f32,
    ig33: f32,
    ig55: f32,
}

impl PolyKernel {
    pub fn new(n: usize, sigma: f64) -> Self {
        let sigma = if sigma < f32::EPSILON as f64 {
            n as f64 * 0.3
        } else {
            sigma
        };
        let ni = n as isize;
        let mut g: Vec<f64> = (-ni..=ni)
            .map(|x| (-((x * x) as f64) / (2.0 * sigma * sigma)).exp())
            .collect();
        let s: f64 = g.iter().sum();
        g.iter_mut().for_each(|v| *v /= s);
        // OpenCV keeps the kernels in f32 and builds the Gram matrix from those values.
        let g32: Vec<f32> = g.iter().map(|&v| v as f32).collect();
        let xg: Vec<f32> = (-ni..=ni).zip(&g32).map(|(x, &v)| x as f32 * v).collect();
        let xxg: Vec<f32> = (-ni..=ni)
            .zip(&g32)
            .map(|(x, &v)| (x * x) as f32 * v)
            .collect();
        let mut gm = SMatrix::<f64, 6, 6>::zeros();
        for y in -ni..=ni {
            for x in -ni..=ni {
                let gy = g32[(y + ni) as usize] as f64;
                let gx = g32[(x + ni) as usize] as f64;
                let (xf, yf) = (x as f64, y as f64);
                gm[(0, 0)] += gy * gx;
                gm[(1, 1)] += gy * gx * xf * xf;
                gm[(3, 3)] += gy * gx * xf * xf * xf * xf;
                gm[(5, 5)] += gy * gx * xf * xf * yf * yf;
            }
        }
        let g11 = gm[(1, 1)];
        gm[(2, 2)] = g11;
        gm[(0, 3)] = g11;
        gm[(0, 4)] = g11;
        gm[(3, 0)] = g11;
        gm[(4, 0)] = g11;
        gm[(4, 4)] = gm[(3, 3)];
        gm[(3, 4)] = gm[(5, 5)];
        gm[(4, 3)] = gm[(5, 5)];
        // The Gram matrix of a normalised positive kernel is positive definite.
        let inv = gm.try_inverse().unwrap_or_else(SMatrix::zeros);
        PolyKernel {
            n,
            g: g32[n..].to_vec(),
            xg: xg[n..].to_vec(),
            xxg: xxg[n..].to_vec(),
            ig11: inv[(1, 1)] as f32,
            ig03: inv[(0, 3)] as f32,
            ig33: inv[(3, 3)] as f32,
            ig55: inv[(5, 5)] as f32,
        }
    }
}

/// Rows of an image as the expansion reads them, a band at a time.
pub(crate) trait Rows: Sync {
    fn height(&self) -> usize;
    fn width(&self) -> usize;
    /// Rows `rows` into `out` (row-major); `scratch` is the source's own working space.
    fn fill(&self, rows: Range<usize>, out: &mut [f32], scratch: &mut Vec<f32>);
}

/// Rows each task expands; it makes them and the `n` rows on either side that their
/// neighbourhoods read.
const BAND_ROWS: usize = 32;

/// Expand `src` into `out`, row by row with the 5 channels of a row one after the other
/// (`out[y·5w + c·w + x]`): each channel is contiguous along x, and everything the flow
/// update reads for a row sits together in memory. The source's rows are made band by band
/// as they are expanded.
pub(crate) fn expand(k: &PolyKernel, src: &impl Rows, out: &mut Vec<f32>) {
    let (h, w) = (src.height(), src.width());
    crate::pages::fill_vec(out, h * w * 5, 0.0);
    if h * w == 0 {
        return;
    }
    let n = k.n;
    out.par_chunks_mut(5 * w * BAND_ROWS)
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new(), vec![0f32; (w + 2 * n) * 3 + 6 * w]),
            |(band, scratch, buf), (b, chunk)| {
                let y0 = b * BAND_ROWS;
                let y1 = (y0 + BAND_ROWS).min(h);
                let (lo, hi) = (y0.saturating_sub(n), (y1 + n).min(h));
                band.resize((hi - lo) * w, 0.0);
                src.fill(lo..hi, band, scratch);
                let rows = Band {
                    rows: band,
                    lo,
                    h,
                    w,
                };
                for (y, row) in (y0..y1).zip(chunk.chunks_mut(5 * w)) {
                    let (d0, rest) = row.split_at_mut(w);
                    let (d1, rest) = rest.split_at_mut(w);
                    let (d2, rest) = rest.split_at_mut(w);
                    let (d3, d4) = rest.split_at_mut(w);
                    expand_row_mv(k, &rows, y, buf, [d0, d1, d2, d3, d4])
                }
            },
        );
}

/// Rows `lo..` of an image `h` rows high and `w` wide.
struct Band<'a> {
    rows: &'a [f32],
    lo: usize,
    h: usize,
    w: usize,
}

impl Band<'_> {
    #[inline(always)]
    fn row(&self, y: usize) -> &[f32] {
        &self.rows[(y - self.lo) * self.w..][..self.w]
    }
}

simd::multiversion!(fn expand_row_mv(
    k: &PolyKernel,
    img: &Band<'_>,
    y: usize,
    buf: &mut [f32],
    d: [&mut [f32]; 5],
) => expand_row);

#[inline(always)]
fn expand_row(k: &PolyKernel, img: &Band<'_>, y: usize, buf: &mut [f32], d: [&mut [f32]; 5]) {
    let (n, h, w) = (k.n, img.h, img.w);
    let wp = w + 2 * n;
    let (r0, rest) = buf.split_at_mut(wp);
    let (r1, rest) = rest.split_at_mut(wp);
    let (r2, rest) = rest.split_at_mut(wp);
    let (acc, _) = rest.split_at_mut(6 * w);
    // Vertical pass: (Σg·f, Σ y·g·f, Σ y²·g·f) along the column, replicate border.
    let s0 = img.row(y);
    {
        let (q0, q1, q2) = (&mut r0[n..n + w], &mut r1[n..n + w], &mut r2[n..n + w]);
        let g0 = k.g[0];
        for x in 0..w {
            q0[x] = s0[x] * g0;
            q1[x] = 0.0;
            q2[x] = 0.0;
        }
        for t in 1..=n {
            let a = img.row(y.saturating_sub(t));
            let b = img.row((y + t).min(h - 1));
            let (g0, g1, g2) = (k.g[t], k.xg[t], k.xxg[t]);
            for x in 0..w {
                let p = a[x] + b[x];
                q0[x] += g0 * p;
                q1[x] += g1 * (b[x] - a[x]);
                q2[x] += g2 * p;
            }
        }
    }
    for r in [&mut *r0, &mut *r1, &mut *r2] {
        let (first, last) = (r[n], r[n + w - 1]);
        r[..n].iter_mut().for_each(|v| *v = first);
        r[n + w..].iter_mut().for_each(|v| *v = last);
    }
    // Horizontal pass, tap-outer so the inner loop runs along contiguous x.
    let (b1, rest) = acc.split_at_mut(w);
    let (b2, rest) = rest.split_at_mut(w);
    let (b3, rest) = rest.split_at_mut(w);
    let (b4, rest) = rest.split_at_mut(w);
    let (b5, b6) = rest.split_at_mut(w);
    let g0 = k.g[0];
    for x in 0..w {
        b1[x] = r0[n + x] * g0;
        b2[x] = 0.0;
        b3[x] = r1[n + x] * g0;
        b4[x] = 0.0;
        b5[x] = r2[n + x] * g0;
        b6[x] = 0.0;
    }
    for t in 1..=n {
        let (gt, xgt, xxgt) = (k.g[t], k.xg[t], k.xxg[t]);
        let (l0, h0) = (&r0[n - t..][..w], &r0[n + t..][..w]);
        let (l1, h1) = (&r1[n - t..][..w], &r1[n + t..][..w]);
        let (l2, h2) = (&r2[n - t..][..w], &r2[n + t..][..w]);
        for x in 0..w {
            let tg = h0[x] + l0[x];
            b1[x] += tg * gt;
            b4[x] += tg * xxgt;
            b2[x] += (h0[x] - l0[x]) * xgt;
            b3[x] += (h1[x] + l1[x]) * gt;
            b6[x] += (h1[x] - l1[x]) * xgt;
            b5[x] += (h2[x] + l2[x]) * gt;
        }
    }
    let [d0, d1, d2, d3, d4] = d;
    for x in 0..w {
        let v0 = b3[x] * k.ig11;
        let v1 = b2[x] * k.ig11;
        let v2 = b1[x] * k.ig03 + b5[x] * k.ig33;
        let v3 = b1[x] * k.ig03 + b4[x] * k.ig33;
        let v4 = b6[x] * k.ig55;
        // One NaN channel makes the pixel missing in all five.
        let bad = (v0 + v1 + v2 + v3 + v4).is_nan();
        let nan = f32::NAN;
        d0[x] = if bad { nan } else { v0 };
        d1[x] = if bad { nan } else { v1 };
        d2[x] = if bad { nan } else { v2 };
        d3[x] = if bad { nan } else { v3 };
        d4[x] = if bad { nan } else { v4 };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An image held whole.
    struct Whole<'a> {
        img: &'a [f32],
        h: usize,
        w: usize,
    }

    impl Rows for Whole<'_> {
        fn height(&self) -> usize {
            self.h
        }
        fn width(&self) -> usize {
            self.w
        }
        fn fill(&self, rows: Range<usize>, out: &mut [f32], _: &mut Vec<f32>) {
            out.copy_from_slice(&self.img[rows.start * self.w..rows.end * self.w]);
        }
    }

    /// A quadratic image is reproduced exactly by the expansion (away from borders):
    /// f = 3 + 0.5x − 0.25y + 0.1x² − 0.05y² + 0.02xy.
    #[test]
    fn recovers_quadratic_coefficients() {
        let (h, w) = (21, 23);
        let f =
            |x: f32, y: f32| 3.0 + 0.5 * x - 0.25 * y + 0.1 * x * x - 0.05 * y * y + 0.02 * x * y;
        let img: Vec<f32> = (0..h * w)
            .map(|i| f((i % w) as f32, (i / w) as f32))
            .collect();
        let k = PolyKernel::new(5, 1.1);
        let mut out = Vec::new();
        expand(&k, &Whole { img: &img, h, w }, &mut out);
        let (x, y) = (11usize, 10usize);
        let d: Vec<f32> = (0..5).map(|c| out[y * 5 * w + c * w + x]).collect();
        // Gradient at (x, y): b_y = −0.25 − 0.1y + 0.02x, b_x = 0.5 + 0.2x + 0.02y.
        let by = -0.25 - 0.1 * y as f32 + 0.02 * x as f32;
        let bx = 0.5 + 0.2 * x as f32 + 0.02 * y as f32;
        let want = [by, bx, -0.05, 0.1, 0.02];
        for (got, want) in d.iter().zip(want) {
            assert!((got - want).abs() < 2e-4, "{d:?} vs {want:?}");
        }
    }

    #[test]
    fn nan_poisons_only_its_support() {
        let (h, w) = (30, 30);
        let mut img: Vec<f32> = (0..h * w).map(|i| ((i * 7919) % 13) as f32).collect();
        img[15 * w + 15] = f32::NAN;
        let k = PolyKernel::new(5, 1.1);
        let mut out = Vec::new();
        expand(&k, &Whole { img: &img, h, w }, &mut out);
        assert!(out[15 * 5 * w + 20].is_nan());
        assert!(out[15 * 5 * w + 21].is_finite());
        assert!(out[9 * 5 * w + 15].is_finite());
    }
}
