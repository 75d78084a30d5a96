//! Smoothing and binning: NaN-aware Gaussians (full and trend), block means, bilinear reads.

use ndarray::{Array2, ArrayView2, ArrayViewMut1, Axis, Zip};
use rayon::prelude::*;

/// Separable Gaussian smoothing with σ in pixels, NaN-aware (normalised convolution:
/// non-finite pixels and the outside of the image carry no weight; they stay NaN).
/// The kernel is truncated at `round(4σ)` like `scipy.ndimage.gaussian_filter`, whose
/// numbers it reproduces away from NaNs and borders.
pub fn gaussian_smooth(img: ArrayView2<f32>, sigma_px: f64) -> Array2<f32> {
    gaussian_smooth_as(img, sigma_px, !crate::stats::all_finite(img))
}

/// [`gaussian_smooth`], normalised by the convolved weights (`has_nan`) or by the kernel's
/// sums: a window of an image with a NaN anywhere takes the former, and then has the same
/// values as the whole image's at least the kernel's reach (`round(4σ)` px) inside its edges
/// that are not the image's.
pub(crate) fn gaussian_smooth_as(
    img: ArrayView2<f32>,
    sigma_px: f64,
    has_nan: bool,
) -> Array2<f32> {
    if sigma_px.is_nan() || sigma_px <= 0.0 || !sigma_px.is_finite() {
        return img.to_owned();
    }
    let (_, kernel) = gaussian_kernel(sigma_px);
    let (h, w) = img.dim();
    if has_nan {
        let mut out = convolve_columns(
            &convolve_rows(img, &kernel, zero_blanks),
            &kernel,
            |_, _| {},
        );
        let den = convolve_columns(&convolve_rows(img, &kernel, weight), &kernel, |_, _| {});
        Zip::from(&mut out)
            .and(&den)
            .and(&img)
            .par_for_each(|o, &d, &v| {
                *o = if v.is_finite() && d > 0.0 {
                    *o / d
                } else {
                    f32::NAN
                };
            });
        out
    } else {
        // Without NaNs the weight plane is the outer product of the 1-D edge sums, divided out
        // as each row is made.
        let (wx, wy) = (edge_sums(&kernel, w), edge_sums(&kernel, h));
        convolve_columns(
            &convolve_rows(img, &kernel, zero_blanks),
            &kernel,
            |y, mut row| {
                for (o, &kx) in row.iter_mut().zip(&wx) {
                    *o /= kx * wy[y];
                }
            },
        )
    }
}

/// Blanks count as zeros in the sums of a normalised convolution; their weight is divided out.
fn zero_blanks(v: f32) -> f32 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// The weight a pixel carries in a normalised convolution: none for a blank.
fn weight(v: f32) -> f32 {
    if v.is_finite() {
        1.0
    } else {
        0.0
    }
}

/// The normalised Gaussian kernel of σ px truncated at `round(4σ)` (scipy's), and that radius.
fn gaussian_kernel(sigma_px: f64) -> (usize, Vec<f32>) {
    let radius = (4.0 * sigma_px + 0.5) as usize;
    let mut kernel: Vec<f32> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-0.5 * d * d / (sigma_px * sigma_px)).exp() as f32
        })
        .collect();
    let total: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    (radius, kernel)
}

/// The kernel's mass inside `0..n` about each index: a zero-padded convolution's weights.
fn edge_sums(kernel: &[f32], n: usize) -> Vec<f32> {
    let radius = kernel.len() / 2;
    (0..n)
        .map(|i| {
            let lo = radius.saturating_sub(i);
            let hi = (radius + n - 1 - i).min(2 * radius);
            kernel[lo..=hi].iter().sum()
        })
        .collect()
}

/// [`gaussian_smooth`] at the rows `rows` of `img` only, one output row per entry in that
/// order: each is the column convolution over the kernel's reach, then the row convolution,
/// with the same normalisation. The same values up to rounding (the passes run in the other
/// order), at the cost of the rows asked for.
pub fn gaussian_smooth_rows(img: ArrayView2<f32>, sigma_px: f64, rows: &[usize]) -> Array2<f32> {
    let (h, w) = img.dim();
    if sigma_px.is_nan() || sigma_px <= 0.0 || !sigma_px.is_finite() {
        return ndarray::stack(
            Axis(0),
            &rows.iter().map(|&y| img.row(y)).collect::<Vec<_>>(),
        )
        .unwrap_or_else(|_| Array2::zeros((0, w)));
    }
    let (radius, kernel) = gaussian_kernel(sigma_px);
    let has_nan = !crate::stats::all_finite(img);
    let (wx, wy) = (edge_sums(&kernel, w), edge_sums(&kernel, h));
    let mut out = Array2::<f32>::zeros((rows.len(), w));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(rows.par_iter())
        .for_each(|(mut o, &y)| {
            // The column sums over the rows in reach, in row order; then along the row.
            let reach = y.saturating_sub(radius)..=(y + radius).min(h - 1);
            let column = |map: fn(f32) -> f32| {
                let mut sums = vec![0f32; w];
                let slices = (!has_nan).then(|| {
                    reach
                        .clone()
                        .map(|yy| Some((img.row(yy).to_slice()?, kernel[yy + radius - y])))
                        .collect::<Option<Vec<(&[f32], f32)>>>()
                });
                match slices.flatten() {
                    // All finite: `map` is the identity.
                    Some(rows) => sum_rows(&rows, &mut sums),
                    None => {
                        for yy in reach.clone() {
                            let k = kernel[yy + radius - y];
                            for (s, &v) in sums.iter_mut().zip(img.row(yy)) {
                                *s += k * map(v);
                            }
                        }
                    }
                }
                let mut along = vec![0f32; w];
                convolve_row(&sums, &kernel, &mut along);
                along
            };
            let num = column(zero_blanks);
            let own = img.row(y);
            if has_nan {
                let den = column(weight);
                for (x, o) in o.iter_mut().enumerate() {
                    *o = if own[x].is_finite() && den[x] > 0.0 {
                        num[x] / den[x]
                    } else {
                        f32::NAN
                    };
                }
            } else {
                for (x, o) in o.iter_mut().enumerate() {
                    *o = num[x] / (wx[x] * wy[y]);
                }
            }
        });
    out
}

/// A wide Gaussian blur (the large-scale trend) at a fraction of [`gaussian_smooth`]'s cost:
/// block means `f = ⌊σ/3⌋` px wide, the remaining blur on those, bilinear interpolation back.
/// A block mean is a box of variance `(f² − 1)/12` px², so the small image is blurred by
/// `√(σ² − (f² − 1)/12)/f` of its own pixels; what the interpolation misses is the
/// trend's curvature over `f` px, `~(f/σ)²/8` of its amplitude at the scale σ. NaN stays NaN;
/// below σ = 6 px this is `gaussian_smooth` itself.
pub fn gaussian_trend(img: ArrayView2<f32>, sigma_px: f64) -> Array2<f32> {
    let f = if sigma_px.is_finite() {
        (sigma_px / 3.0).floor() as usize
    } else {
        0
    };
    let (h, w) = img.dim();
    if f < 2 || h < 4 * f || w < 4 * f {
        return gaussian_smooth(img, sigma_px);
    }
    let blocks = bin_mean(img, f);
    let (bh, bw) = blocks.dim();
    let fb = f as f64;
    let sigma_blocks = (sigma_px * sigma_px - (fb * fb - 1.0) / 12.0)
        .max(0.0)
        .sqrt()
        / fb;
    let small = gaussian_smooth(blocks.view(), sigma_blocks);
    // Block `b` is centred on pixel `b·f + (f − 1)/2`.
    let taps = |n: usize, nb: usize| -> Vec<(usize, usize, f32)> {
        (0..n)
            .map(|i| {
                let t = ((i as f64 - (fb - 1.0) / 2.0) / fb).clamp(0.0, (nb - 1) as f64);
                let i0 = (t.floor() as usize).min(nb - 1);
                let i1 = (i0 + 1).min(nb - 1);
                (i0, i1, (t - i0 as f64) as f32)
            })
            .collect()
    };
    let (xt, yt) = (taps(w, bw), taps(h, bh));
    let mut out = crate::pages::filled(h, w, 0.0);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            let (y0, y1, wy) = yt[y];
            let (r0, r1) = (small.row(y0), small.row(y1));
            for (x, o) in row.iter_mut().enumerate() {
                let v = img[[y, x]];
                if !v.is_finite() {
                    *o = f32::NAN;
                    continue;
                }
                let (x0, x1, wx) = xt[x];
                let lerp = |a: f32, b: f32| {
                    // A NaN neighbour (a blank block) gives way to the other one.
                    if !a.is_finite() {
                        b
                    } else if !b.is_finite() {
                        a
                    } else {
                        a + wx * (b - a)
                    }
                };
                let (top, bot) = (lerp(r0[x0], r0[x1]), lerp(r1[x0], r1[x1]));
                *o = if !top.is_finite() {
                    bot
                } else if !bot.is_finite() {
                    top
                } else {
                    top + wy * (bot - top)
                };
            }
        });
    out
}

/// Zero-padded 1-D convolution along each row (symmetric kernel) of `a`'s values mapped by
/// `map` (mapped as each row is read: no mapped copy of the image).
fn convolve_rows(
    a: ArrayView2<f32>,
    kernel: &[f32],
    map: impl Fn(f32) -> f32 + Sync,
) -> Array2<f32> {
    let (h, w) = a.dim();
    let mut out = crate::pages::filled(h, w, 0.0);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(a.axis_iter(Axis(0)))
        .for_each_init(Vec::new, |buf, (mut o, row)| {
            buf.clear();
            buf.extend(row.iter().map(|&v| map(v))); // contiguous copy: one row, cheap
            match o.as_slice_mut() {
                Some(o) => convolve_row(buf, kernel, o),
                None => {
                    let mut tmp = vec![0f32; w];
                    convolve_row(buf, kernel, &mut tmp);
                    o.iter_mut().zip(&tmp).for_each(|(d, s)| *d = *s);
                }
            }
        });
    out
}

/// `out[x] = Σ_t kernel[t]·row[x + t − r]` over the taps inside the row, summed in tap order.
/// Interior pixels go tap-outer over contiguous slices (vectorised; same sums, same order).
fn convolve_row(row: &[f32], kernel: &[f32], out: &mut [f32]) {
    let r = kernel.len() / 2;
    let w = row.len();
    let direct = |x: usize| -> f32 {
        let lo = x.saturating_sub(r);
        let hi = (x + r).min(w - 1);
        row[lo..=hi]
            .iter()
            .zip(&kernel[lo + r - x..=hi + r - x])
            .map(|(v, k)| v * k)
            .sum()
    };
    if w <= 2 * r {
        for (x, o) in out.iter_mut().enumerate() {
            *o = direct(x);
        }
        return;
    }
    let n = w - 2 * r;
    convolve_interior(row, kernel, &mut out[r..r + n]);
    for x in (0..r).chain(r + n..w) {
        out[x] = direct(x);
    }
}

/// Outputs summed side by side in registers, each over the taps in order.
const CONVOLVE_BLOCK: usize = 32;

crate::flow::simd::multiversion!(fn convolve_interior(
    row: &[f32],
    kernel: &[f32],
    inner: &mut [f32],
) => convolve_interior_body);

/// `inner[x] = Σ_t kernel[t]·row[x + t]`, summed from 0 in tap order, block by block of
/// outputs (the sums stay in registers across the taps).
#[inline(always)]
fn convolve_interior_body(row: &[f32], kernel: &[f32], inner: &mut [f32]) {
    let n = inner.len();
    let mut blocks = inner.chunks_exact_mut(CONVOLVE_BLOCK);
    for (b, out) in (&mut blocks).enumerate() {
        let x = b * CONVOLVE_BLOCK;
        let mut acc = [0f32; CONVOLVE_BLOCK];
        for (t, &k) in kernel.iter().enumerate() {
            let src: &[f32; CONVOLVE_BLOCK] = row[x + t..x + t + CONVOLVE_BLOCK]
                .try_into()
                .expect("a block of the row");
            for (a, &v) in acc.iter_mut().zip(src) {
                *a += v * k;
            }
        }
        out.copy_from_slice(&acc);
    }
    let tail = blocks.into_remainder();
    let x0 = n - tail.len();
    tail.iter_mut().for_each(|o| *o = 0.0);
    for (t, &k) in kernel.iter().enumerate() {
        for (o, &v) in tail.iter_mut().zip(&row[x0 + t..]) {
            *o += v * k;
        }
    }
}

/// Zero-padded 1-D convolution along each column, row-wise for cache locality; `finish`
/// runs on each output row once it is summed (while it is still in cache).
fn convolve_columns(
    a: &Array2<f32>,
    kernel: &[f32],
    finish: impl Fn(usize, ArrayViewMut1<f32>) + Sync,
) -> Array2<f32> {
    let r = kernel.len() / 2;
    let (h, w) = a.dim();
    let mut out = crate::pages::filled(h, w, 0.0);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut o)| {
            let taps = y.saturating_sub(r)..=(y + r).min(h - 1);
            match (o.as_slice_mut(), a.as_slice()) {
                (Some(out), Some(a)) => {
                    let rows: Vec<(&[f32], f32)> = taps
                        .map(|yy| (&a[yy * w..(yy + 1) * w], kernel[yy + r - y]))
                        .collect();
                    sum_rows(&rows, out);
                }
                _ => {
                    for yy in taps {
                        let k = kernel[yy + r - y];
                        o.zip_mut_with(&a.row(yy), |ov, &v| *ov += k * v);
                    }
                }
            }
            finish(y, o);
        });
    out
}

crate::flow::simd::multiversion!(fn sum_rows(rows: &[(&[f32], f32)], out: &mut [f32]) => sum_rows_body);

/// `out[x] += Σ k·row[x]` over `rows` in order, block by block of columns (the sums stay in
/// registers across the rows).
#[inline(always)]
fn sum_rows_body(rows: &[(&[f32], f32)], out: &mut [f32]) {
    let mut x = 0;
    for out in out.chunks_mut(CONVOLVE_BLOCK) {
        let len = out.len();
        if len == CONVOLVE_BLOCK {
            let acc: &mut [f32; CONVOLVE_BLOCK] = out.try_into().expect("a block");
            let mut sums = *acc;
            for &(row, k) in rows {
                let src: &[f32; CONVOLVE_BLOCK] = row[x..x + CONVOLVE_BLOCK]
                    .try_into()
                    .expect("a block of the row");
                for (s, &v) in sums.iter_mut().zip(src) {
                    *s += k * v;
                }
            }
            *acc = sums;
        } else {
            for &(row, k) in rows {
                for (o, &v) in out.iter_mut().zip(&row[x..x + len]) {
                    *o += k * v;
                }
            }
        }
        x += len;
    }
}

/// Block means by `bin` of the image smoothed by a Gaussian of σ px: what
/// `bin_mean(&gaussian_smooth(img, σ), bin)` gives, in one pass over the image and without its
/// two full-size intermediates. Each output is a weighted sum of the pixels its block's
/// smoothed values read (the Gaussian convolved with the block, `2·round(4σ) + bin` taps per
/// axis), with the same edge normalisation. Images with blanks take the two steps.
pub fn smooth_bin(img: ArrayView2<f32>, bin: usize, sigma_px: f64) -> Array2<f32> {
    if bin <= 1 || !(sigma_px > 0.0 && sigma_px.is_finite()) || !crate::stats::all_finite(img) {
        return bin_mean(gaussian_smooth(img, sigma_px).view(), bin);
    }
    let radius = (4.0 * sigma_px + 0.5) as usize;
    let kernel: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-0.5 * d * d / (sigma_px * sigma_px)).exp()
        })
        .collect();
    let total: f64 = kernel.iter().sum();
    let kernel: Vec<f64> = kernel.iter().map(|k| k / total).collect();
    // Per block along an axis of `n` pixels: its first source pixel and the weights of the
    // pixels from there. A pixel's smoothed value is its kernel sum over the pixels inside,
    // divided by the kernel's weight inside; a block's value is the mean of its pixels'.
    let taps = |n: usize| -> Vec<(usize, Vec<f32>)> {
        (0..n.div_ceil(bin))
            .map(|b| {
                let (x0, x1) = (b * bin, ((b + 1) * bin).min(n));
                let lo = x0.saturating_sub(radius);
                let hi = (x1 - 1 + radius).min(n - 1);
                let mut weights = vec![0f64; hi - lo + 1];
                for x in x0..x1 {
                    let (a, z) = (x.saturating_sub(radius), (x + radius).min(n - 1));
                    let inside: f64 = (a..=z).map(|u| kernel[u + radius - x]).sum();
                    for u in a..=z {
                        weights[u - lo] += kernel[u + radius - x] / inside / (x1 - x0) as f64;
                    }
                }
                (lo, weights.iter().map(|&v| v as f32).collect())
            })
            .collect()
    };
    let (h, w) = img.dim();
    let (xt, yt) = (taps(w), taps(h));
    let (bh, bw) = (yt.len(), xt.len());
    let mut out = Array2::<f32>::zeros((bh, bw));
    // Per output row: the weighted sum of its source rows (whole rows, in vector lanes),
    // then the weighted sums along it.
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(&yt)
        .for_each_init(
            || vec![0f32; w],
            |column_sums, (mut orow, (lo, wts))| {
                column_sums.iter_mut().for_each(|v| *v = 0.0);
                for (i, &wt) in wts.iter().enumerate() {
                    let row = img.row(lo + i);
                    match row.as_slice() {
                        Some(r) => column_sums
                            .iter_mut()
                            .zip(r)
                            .for_each(|(o, &v)| *o += wt * v),
                        None => column_sums
                            .iter_mut()
                            .zip(row.iter())
                            .for_each(|(o, &v)| *o += wt * v),
                    }
                }
                for (o, (lo, wts)) in orow.iter_mut().zip(&xt) {
                    *o = wts
                        .iter()
                        .zip(&column_sums[*lo..])
                        .map(|(&wt, &v)| wt * v)
                        .sum();
                }
            },
        );
    out
}

/// NaN-aware block mean by an integer factor.
/// Means of `bin × bin` blocks (the last ones partial), ignoring NaN; NaN for an all-NaN block.
pub fn bin_mean(img: ArrayView2<f32>, bin: usize) -> Array2<f32> {
    if bin <= 1 {
        return img.to_owned();
    }
    let (h, w) = img.dim();
    let (bh, bw) = (h.div_ceil(bin), w.div_ceil(bin));
    let mut out = Array2::<f32>::zeros((bh, bw));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(by, mut row)| {
            let mut sum = vec![0f64; bw];
            let mut n = vec![0u32; bw];
            for y in by * bin..((by + 1) * bin).min(h) {
                let row = img.row(y);
                match row.as_slice() {
                    Some(r) => add_binned_row(r, bin, &mut sum, &mut n),
                    None => row.iter().enumerate().for_each(|(x, &v)| {
                        if v.is_finite() {
                            sum[x / bin] += v as f64;
                            n[x / bin] += 1;
                        }
                    }),
                }
            }
            for ((o, s), c) in row.iter_mut().zip(&sum).zip(&n) {
                *o = if *c > 0 {
                    (*s / *c as f64) as f32
                } else {
                    f32::NAN
                };
            }
        });
    out
}

/// Adds each run of `bin` pixels of `row` to its block's sum and count (finite pixels only),
/// in order. Four blocks at a time with AVX2 where the CPU has it: a pixel that is not finite
/// adds +0.0, which leaves the sum as it is (a sum of finite values from +0.0 is never −0.0),
/// so the sums are the same bit for bit.
fn add_binned_row(row: &[f32], bin: usize, sum: &mut [f64], n: &mut [u32]) {
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if crate::flow::simd::has_avx2_fma() && row.len() < i32::MAX as usize {
        // SAFETY: the CPU has AVX2.
        done = unsafe { add_binned_row_x86(row, bin, sum, n) };
    }
    for (bx, c) in row.chunks(bin).enumerate().skip(done) {
        for &v in c {
            if v.is_finite() {
                sum[bx] += v as f64;
                n[bx] += 1;
            }
        }
    }
}

/// [`add_binned_row`] on the groups of four whole blocks; returns the blocks done.
///
/// # Safety
/// The CPU must have AVX2, and `row.len()` must fit in an `i32` (the gathers' indices).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn add_binned_row_x86(row: &[f32], bin: usize, sum: &mut [f64], n: &mut [u32]) -> usize {
    use std::arch::x86_64::*;
    let groups = row.len() / (4 * bin);
    let b = bin as i32;
    let lanes = _mm_setr_epi32(0, b, 2 * b, 3 * b);
    for g in 0..groups {
        let (first, bx) = (g * 4 * bin, 4 * g);
        // The blocks' sums so far, to which this row's pixels are added one by one.
        let mut s = _mm256_loadu_pd(sum[bx..bx + 4].as_ptr());
        let mut c = _mm_loadu_si128(n[bx..bx + 4].as_ptr().cast());
        // Each block's pixels in order, as the one-block loop adds them.
        for k in 0..bin {
            let at = _mm_add_epi32(lanes, _mm_set1_epi32((first + k) as i32));
            let v = _mm_i32gather_ps::<4>(row.as_ptr(), at);
            let finite = _mm_cmpeq_ps(_mm_sub_ps(v, v), _mm_setzero_ps());
            s = _mm256_add_pd(s, _mm256_cvtps_pd(_mm_and_ps(v, finite)));
            c = _mm_sub_epi32(c, _mm_castps_si128(finite));
        }
        _mm256_storeu_pd(sum[bx..bx + 4].as_mut_ptr(), s);
        _mm_storeu_si128(n[bx..bx + 4].as_mut_ptr().cast(), c);
    }
    4 * groups
}

#[inline(always)]
pub(super) fn bilinear(img: ArrayView2<f32>, x: f64, y: f64) -> Option<f64> {
    let (h, w) = img.dim();
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = (x - x0 as f64, y - y0 as f64);
    let top = img[[y0, x0]] as f64 * (1.0 - tx) + img[[y0, x1]] as f64 * tx;
    let bottom = img[[y1, x0]] as f64 * (1.0 - tx) + img[[y1, x1]] as f64 * tx;
    Some(top * (1.0 - ty) + bottom * ty)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows added to block sums give, bit for bit, the f64 sums the textbook loop makes:
    /// each block's finite pixels added one by one in order to what earlier rows left.
    /// Magnitudes spread over 30 decades make the order of the additions show; blanks and
    /// infinities are skipped; rows of every length around the groups of four blocks.
    #[test]
    fn binned_rows_add_each_pixel_in_order() {
        let mut next = crate::test_data::uniform(3);
        for bin in 1..=5usize {
            for len in [1, 7, 4 * bin - 1, 4 * bin, 4 * bin + 1, 37 * bin + 3] {
                let blocks = len.div_ceil(bin);
                let (mut sum, mut n) = (vec![0f64; blocks], vec![0u32; blocks]);
                let (mut want_sum, mut want_n) = (sum.clone(), n.clone());
                for _ in 0..3 {
                    let row: Vec<f32> = (0..len)
                        .map(|_| match (next() * 20.0) as u32 {
                            0 => f32::NAN,
                            1 => f32::INFINITY,
                            _ => ((next() - 0.3) * 10f64.powi((next() * 30.0) as i32 - 15)) as f32,
                        })
                        .collect();
                    add_binned_row(&row, bin, &mut sum, &mut n);
                    for (x, &v) in row.iter().enumerate() {
                        if v.is_finite() {
                            want_sum[x / bin] += v as f64;
                            want_n[x / bin] += 1;
                        }
                    }
                }
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&sum), bits(&want_sum), "bin {bin}, length {len}");
                assert_eq!(n, want_n, "bin {bin}, length {len}");
            }
        }
    }

    #[test]
    fn convolutions_sum_each_output_over_its_taps_in_order() {
        // The definition: out[x] = Σ_t k[t]·v[x + t − r] over the taps inside the image, summed
        // from zero in tap order (rows), and the same down each column (rows in order). Row
        // lengths around the 32-output blocks, kernels short and long.
        let mut state = 5u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1);
            ((state >> 40) as f32 / (1u64 << 24) as f32) * 100.0 - 30.0
        };
        for (h, w, taps) in [(9, 31, 7), (40, 77, 7), (70, 64, 65), (41, 203, 17)] {
            let kernel: Vec<f32> = (0..taps).map(|_| next().abs() / 50.0).collect();
            let r = taps / 2;
            let img = Array2::from_shape_fn((h, w), |_| next());
            let rows = convolve_rows(img.view(), &kernel, |v| v);
            let cols = convolve_columns(&img, &kernel, |_, _| {});
            for y in 0..h {
                for x in 0..w {
                    let mut along = 0f32;
                    for (t, &k) in kernel.iter().enumerate() {
                        if let Some(xx) = (x + t).checked_sub(r).filter(|&xx| xx < w) {
                            along += img[[y, xx]] * k;
                        }
                    }
                    let mut down = 0f32;
                    for (t, &k) in kernel.iter().enumerate() {
                        if let Some(yy) = (y + t).checked_sub(r).filter(|&yy| yy < h) {
                            down += k * img[[yy, x]];
                        }
                    }
                    assert_eq!(
                        rows[[y, x]].to_bits(),
                        along.to_bits(),
                        "row sum at ({x}, {y})"
                    );
                    assert_eq!(
                        cols[[y, x]].to_bits(),
                        down.to_bits(),
                        "column sum at ({x}, {y})"
                    );
                }
            }
        }
    }
}
