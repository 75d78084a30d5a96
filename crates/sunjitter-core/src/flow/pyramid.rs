//! Pyramid levels the way OpenCV's `calcOpticalFlowFarneback` builds them: every level is made
//! from the full-resolution image (Gaussian blur with σ = (1/scale − 1)/2, kernel
//! `round(5σ)|1` ≥ 3, border reflect-101, then a bilinear resize with pixel-centre alignment).
//! Only the pixels of a level's domain are produced, and the blur is evaluated only on the
//! full-resolution rows and columns that the resize reads, so coarse levels cost little.
//! NaN (missing data) propagates through the blur and the resize on purpose: a level pixel is
//! missing when any pixel it was made from is missing.

use super::Rect;
use ndarray::{s, ArrayView2};

/// OpenCV's `cvRound` (round half to even).
pub(crate) fn cv_round(v: f64) -> i64 {
    v.round_ties_even() as i64
}

/// Blur kernel OpenCV uses for a level with scale `scale` (radius, taps).
fn level_kernel(scale: f64) -> Vec<f32> {
    let sigma = (1.0 / scale - 1.0) * 0.5;
    let size = ((cv_round(sigma * 5.0) | 1).max(3)) as usize;
    if sigma <= 0.0 && size == 3 {
        // getGaussianKernel's fixed table for ksize 3 when σ ≤ 0.
        return vec![0.25, 0.5, 0.25];
    }
    let half = (size as f64 - 1.0) * 0.5;
    let k: Vec<f64> = (0..size)
        .map(|i| {
            let x = i as f64 - half;
            (-0.5 / (sigma * sigma) * x * x).exp()
        })
        .collect();
    let sum: f64 = k.iter().sum();
    k.iter().map(|v| (v / sum) as f32).collect()
}

/// Reflect-101 index (OpenCV's default border for GaussianBlur).
#[inline]
fn reflect101(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let mut i = i;
    loop {
        if i < 0 {
            i = -i;
        } else if i >= n {
            i = 2 * n - 2 - i;
        } else {
            return i as usize;
        }
    }
}

/// One resize tap pair: source index `i0`, `i1` and weight of `i1`.
#[derive(Clone, Copy)]
struct Tap {
    i0: usize,
    i1: usize,
    w1: f32,
}

/// OpenCV INTER_LINEAR coefficients for destination index `d` (source size `src`, dest `dst`).
fn resize_tap(d: usize, src: usize, dst: usize) -> Tap {
    let scale = 1.0 / (dst as f64 / src as f64);
    let f = ((d as f64 + 0.5) * scale - 0.5) as f32;
    let mut s = f.floor() as isize;
    let mut w = f - s as f32;
    if s < 0 {
        s = 0;
        w = 0.0;
    }
    if s >= src as isize - 1 {
        s = src as isize - 1;
        w = 0.0;
    }
    let i0 = s as usize;
    Tap {
        i0,
        i1: (i0 + 1).min(src - 1),
        w1: w,
    }
}

/// Taps of the bilinear resize for every destination index in `range` (used for flow upsampling too).
pub(crate) fn resize_taps(
    range: std::ops::Range<usize>,
    src: usize,
    dst: usize,
) -> Vec<(usize, usize, f32)> {
    range
        .map(|d| {
            let t = resize_tap(d, src, dst);
            (t.i0, t.i1, t.w1)
        })
        .collect()
}

/// A full-resolution image as the pyramid reads it, `(v − offset)·gain` (NaN stays NaN): in
/// units where f32 keeps full precision whatever the data's offset and scale, normalised as
/// each pixel is read so that no normalised copy of the image is kept.
#[derive(Clone, Copy)]
pub(crate) struct Normalised<'a> {
    pub(crate) img: ArrayView2<'a, f32>,
    pub(crate) offset: f32,
    pub(crate) gain: f32,
}

/// What one blurred source row needs.
struct RowJob<'a, 'i> {
    img: Normalised<'i>,
    src_h: usize,
    src_w: usize,
    kernel: &'a [f32],
    vlo: usize,
    need_cols: &'a [usize],
}

super::simd::multiversion!(fn blur_row_mv(
    job: &RowJob<'_, '_>,
    sy: usize,
    vrow: &mut [f32],
    dst: &mut [f32],
) => blur_row);

/// Vertical blur of source row `sy` over `vrow`'s columns, then the horizontal blur at the
/// needed columns into `dst`.
#[inline(always)]
fn blur_row(job: &RowJob<'_, '_>, sy: usize, vrow: &mut [f32], dst: &mut [f32]) {
    let (kernel, vlo) = (job.kernel, job.vlo);
    let r = kernel.len() / 2;
    let vw = vrow.len();
    vrow.iter_mut().for_each(|v| *v = 0.0);
    let Normalised { img, offset, gain } = job.img;
    for (t, &kw) in kernel.iter().enumerate() {
        let yy = reflect101(sy as isize + t as isize - r as isize, job.src_h);
        let row = img.slice(s![yy, vlo..vlo + vw]);
        match row.as_slice() {
            Some(row) => {
                for (acc, &v) in vrow.iter_mut().zip(row) {
                    *acc += kw * ((v - offset) * gain);
                }
            }
            None => {
                for (acc, &v) in vrow.iter_mut().zip(row.iter()) {
                    *acc += kw * ((v - offset) * gain);
                }
            }
        }
    }
    let cols = job.need_cols;
    let n = cols.len();
    let contiguous = n > 0 && cols[n - 1] - cols[0] + 1 == n;
    // Contiguous needed columns (levels 0 and 1): tap-outer loops over the interior span,
    // which vectorise; reflected edges one by one.
    let (mut a, mut b) = (0, 0);
    if contiguous {
        a = r.saturating_sub(cols[0]).min(n);
        b = (job.src_w.saturating_sub(r + cols[0])).clamp(a, n);
        if b > a {
            let span = &mut dst[a..b];
            span.iter_mut().for_each(|d| *d = 0.0);
            let start = cols[a] - r - vlo;
            for (t, &kw) in kernel.iter().enumerate() {
                let src = &vrow[start + t..][..b - a];
                for (d, &v) in span.iter_mut().zip(src) {
                    *d += kw * v;
                }
            }
        }
    }
    for (i, (d, &cx)) in dst.iter_mut().zip(cols).enumerate() {
        if i >= a && i < b {
            continue;
        }
        let mut s = 0f32;
        if cx >= r && cx + r < job.src_w {
            // Interior: contiguous taps, no reflection.
            let taps = &vrow[cx - r - vlo..][..kernel.len()];
            for (&kw, &v) in kernel.iter().zip(taps) {
                s += kw * v;
            }
        } else {
            for (t, &kw) in kernel.iter().enumerate() {
                let xx = reflect101(cx as isize + t as isize - r as isize, job.src_w);
                s += kw * vrow[xx - vlo];
            }
        }
        *d = s;
    }
}

/// A pyramid level's pixels over a domain, made a band of rows at a time as the polynomial
/// expansion reads them: no level-sized copy of an image is kept, only its expansion.
pub(crate) struct LevelRows<'a> {
    img: Normalised<'a>,
    src_h: usize,
    src_w: usize,
    kernel: Vec<f32>,
    /// Resize taps of every domain row.
    ytaps: Vec<Tap>,
    /// Source columns the resize reads, and where each domain column finds its two.
    need_cols: Vec<usize>,
    col_pos: Vec<(usize, usize, f32)>,
    /// Columns the horizontal blur reads (reflections stay inside this span, see reflect101).
    vlo: usize,
    vw: usize,
}

impl<'a> LevelRows<'a> {
    /// The level of `img` with scale `scale`, `level_size` = (height, width) of the whole level,
    /// over `dom`.
    pub(crate) fn new(
        img: Normalised<'a>,
        scale: f64,
        level_size: (usize, usize),
        dom: Rect,
    ) -> LevelRows<'a> {
        let kernel = level_kernel(scale);
        let r = kernel.len() / 2;
        let (lh, lw) = level_size;
        let (src_h, src_w) = img.img.dim();
        let tap = |d: usize, src: usize, level: usize| {
            if level == src {
                Tap {
                    i0: d,
                    i1: d,
                    w1: 0.0,
                }
            } else {
                resize_tap(d, src, level)
            }
        };
        let ytaps: Vec<Tap> = (dom.y0..dom.y1).map(|d| tap(d, src_h, lh)).collect();
        let xtaps: Vec<Tap> = (dom.x0..dom.x1).map(|d| tap(d, src_w, lw)).collect();
        let col_lo = xtaps.iter().map(|t| t.i0).min().unwrap_or(0);
        let col_hi = xtaps.iter().map(|t| t.i1).max().unwrap_or(0);
        let vlo = col_lo.saturating_sub(r);
        let vhi = (col_hi + r).min(src_w - 1);
        let mut need_cols: Vec<usize> = xtaps.iter().flat_map(|t| [t.i0, t.i1]).collect();
        need_cols.sort_unstable();
        need_cols.dedup();
        let col_pos = xtaps
            .iter()
            .map(|t| {
                (
                    need_cols.binary_search(&t.i0).unwrap_or(0),
                    need_cols.binary_search(&t.i1).unwrap_or(0),
                    t.w1,
                )
            })
            .collect();
        LevelRows {
            img,
            src_h,
            src_w,
            kernel,
            ytaps,
            need_cols,
            col_pos,
            vlo,
            vw: vhi - vlo + 1,
        }
    }
}

impl super::poly::Rows for LevelRows<'_> {
    fn height(&self) -> usize {
        self.ytaps.len()
    }

    fn width(&self) -> usize {
        self.col_pos.len()
    }

    /// Domain rows `rows`: the vertical blur of the source rows they read over the blur's
    /// columns, the horizontal blur at the resize's columns only, then the bilinear
    /// combination. `scratch` holds the blurred rows.
    fn fill(&self, rows: std::ops::Range<usize>, out: &mut [f32], scratch: &mut Vec<f32>) {
        let taps = &self.ytaps[rows];
        let mut need_rows: Vec<usize> = taps.iter().flat_map(|t| [t.i0, t.i1]).collect();
        need_rows.sort_unstable();
        need_rows.dedup();
        let ncols = self.need_cols.len();
        scratch.resize(need_rows.len() * ncols + self.vw, 0.0);
        let (blurred, vrow) = scratch.split_at_mut(need_rows.len() * ncols);
        let job = RowJob {
            img: self.img,
            src_h: self.src_h,
            src_w: self.src_w,
            kernel: &self.kernel,
            vlo: self.vlo,
            need_cols: &self.need_cols,
        };
        for (dst, &sy) in blurred.chunks_mut(ncols.max(1)).zip(&need_rows) {
            blur_row_mv(&job, sy, vrow, dst);
        }
        let blurred: &[f32] = blurred;
        let row_pos = |sy: usize| need_rows.binary_search(&sy).unwrap_or(0);
        let dw = self.width();
        for (orow, ty) in out.chunks_mut(dw.max(1)).zip(taps) {
            let a = &blurred[row_pos(ty.i0) * ncols..][..ncols];
            let b = &blurred[row_pos(ty.i1) * ncols..][..ncols];
            let wy = ty.w1;
            for (o, &(c0, c1, wx)) in orow.iter_mut().zip(&self.col_pos) {
                let top = a[c0] + wx * (a[c1] - a[c0]);
                let bot = b[c0] + wx * (b[c1] - b[c0]);
                *o = if wy == 0.0 {
                    top
                } else {
                    top + wy * (bot - top)
                };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_match_opencv_sizes() {
        // cv2.getGaussianKernel sizes used by optflowgf.cpp for scales 1, 1/2, 1/4, 1/8, 1/16:
        // round(5σ)|1 with σ = 0, 0.5, 1.5, 3.5, 7.5 → 3 (fixed table), 3, 9, 19, 39.
        let sizes: Vec<usize> = [1.0, 0.5, 0.25, 0.125, 0.0625]
            .iter()
            .map(|&s| level_kernel(s).len())
            .collect();
        assert_eq!(sizes, vec![3, 3, 9, 19, 39]);
        assert_eq!(level_kernel(1.0), vec![0.25, 0.5, 0.25]);
        // cv2.getGaussianKernel(3, 0.5) = [0.10650698, 0.78698604, 0.10650698]
        let k = level_kernel(0.5);
        assert!((k[0] - 0.106_506_98).abs() < 1e-7 && (k[1] - 0.786_986_04).abs() < 1e-7);
    }

    #[test]
    fn resize_taps_match_opencv_half_scale() {
        // Halving: destination d reads source 2d and 2d+1 with equal weights (cv2.resize INTER_LINEAR).
        let t = resize_tap(3, 16, 8);
        assert_eq!((t.i0, t.i1, t.w1), (6, 7, 0.5));
        // Doubling: d = 0 clamps to source 0; d = 1 reads 0 and 1 at 0.25.
        let t = resize_tap(0, 8, 16);
        assert_eq!((t.i0, t.w1), (0, 0.0));
        let t = resize_tap(1, 8, 16);
        assert_eq!((t.i0, t.i1, t.w1), (0, 1, 0.25));
    }
}
