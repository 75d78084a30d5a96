//! Hot pixels and cosmic-ray hits: a 3×3 median test with a noise guard and a lone-pixel rule.

use ndarray::{Array2, ArrayView2, Axis};
use rayon::prelude::*;

use super::quantile_in_place;

/// Noise guard of [`remove_hot_pixels`], in robust standard deviations: a pixel must
/// also stand out from the noise, estimated both over the image and among its own 8
/// neighbours. Where the median is near zero (sky) or the signal is photon-noisy or
/// finely structured (UV slit-jaws, rebinned EUV), a fraction of the median alone is
/// within the noise, and noise is not a hot pixel.
pub const HOT_PIXEL_NOISE_SIGMAS: f32 = 5.0;

/// Replace pixels deviating from their 3×3 median by more than `threshold_fraction` of
/// that median (and by more than [`HOT_PIXEL_NOISE_SIGMAS`] of the noise), and standing alone
/// by [`HOT_PIXEL_LONE_FACTOR`], with the median. Non-finite pixels are left alone and
/// ignored by the medians. Returns the number of pixels replaced.
pub fn remove_hot_pixels(img: &mut Array2<f32>, threshold_fraction: f32) -> usize {
    remove_hot_pixels_with(
        img,
        threshold_fraction,
        HOT_PIXEL_NOISE_SIGMAS,
        HOT_PIXEL_LONE_FACTOR,
    )
}

/// [`remove_hot_pixels`] without the test that the pixel stands alone: every suspect goes,
/// real compact features included. For a scene that is to be warped into synthetic frames
/// (`simulate`): a detector defect warped along with the Sun would be a feature no real pair
/// has, and what this removes of real structure it removes from both images alike.
pub fn remove_spikes_from_scene(img: &mut Array2<f32>, threshold_fraction: f32) -> usize {
    remove_hot_pixels_with(img, threshold_fraction, HOT_PIXEL_NOISE_SIGMAS, 0.0)
}

/// [`remove_hot_pixels`] with an explicit noise guard (0 disables it: the paper's test) and
/// lone factor (0: every suspect stands alone).
pub fn remove_hot_pixels_with(
    img: &mut Array2<f32>,
    threshold_fraction: f32,
    noise_sigmas: f32,
    lone_factor: f32,
) -> usize {
    let medians = median3x3(&img.view());
    // Image-wide robust noise of the residual: 1.4826 × median |v − m|, from at most
    // about a million pixels (plenty for a median).
    let stride = (img.len() / (1 << 20)).max(1);
    let residual = |(v, m): (&f32, &f32)| (v.is_finite() && m.is_finite()).then(|| (v - m).abs());
    let mut residuals: Vec<f32> = match (img.as_slice(), medians.as_slice()) {
        // Slices step in O(1); ndarray's element iterators walk every element.
        (Some(a), Some(b)) => a
            .iter()
            .zip(b)
            .step_by(stride)
            .filter_map(residual)
            .collect(),
        _ => img
            .iter()
            .zip(medians.iter())
            .step_by(stride)
            .filter_map(residual)
            .collect(),
    };
    let sigma = if residuals.is_empty() {
        0.0
    } else {
        1.4826 * quantile_in_place(&mut residuals, 0.5)
    };
    drop(residuals);
    // Decide on the unmodified image, then replace.
    let (h, w) = img.dim();
    let view = img.view();
    let hits: Vec<(usize, usize, f32)> = (0..h)
        .into_par_iter()
        .flat_map_iter(|y| {
            let (view, medians) = (&view, &medians);
            let (row, med_row) = (view.row(y), medians.row(y));
            (0..w).filter_map(move |x| {
                let (v, m) = (row[x], med_row[x]);
                let dev = (v - m).abs();
                // Cheap tests first (false for NaN): most pixels end here.
                let suspect = dev > threshold_fraction * m.abs() && dev > noise_sigmas * sigma;
                // The local spread is needed only for the few suspects.
                let is_suspect = |yy: usize, xx: usize| {
                    let (v, m) = (view[[yy, xx]], medians[[yy, xx]]);
                    let dev = (v - m).abs();
                    dev > threshold_fraction * m.abs() && dev > noise_sigmas * sigma
                };
                (suspect
                    && dev > noise_sigmas * neighbour_spread(view, y, x, m)
                    && stands_alone(view, medians, (y, x), lone_factor, is_suspect))
                .then_some((y, x, m))
            })
        })
        .collect();
    for &(y, x, m) in &hits {
        img[[y, x]] = m;
    }
    hits.len()
}

/// A hot pixel (or a cosmic ray's hit) stands alone: it rises above the floor of its 8
/// neighbours by more than this many times the brightest of them does. A real feature,
/// however compact, spills into a neighbour (the optics' PSF, the pixel's own footprint): a
/// point source with a PSF of FWHM 1 px, centred on a pixel, rises 7.4× as high as its
/// brightest neighbour, and less at any other phase. The bright cores of real structure on
/// undersampled disks stand well below this factor, and a rule that cleaned them would do so
/// by sub-pixel phase, so differently in two images of the same Sun; detector spikes stand
/// far above it (docs/validation.md#hot-pixels-stand-alone).
pub const HOT_PIXEL_LONE_FACTOR: f32 = 10.0;

/// Whether the pixel at `at` stands alone: its rise above the floor of its 8 neighbours is
/// more than `lone_factor` times the brightest neighbour's (mirrored for a dark pixel). Or it
/// stands alone together with that neighbour, when that one is a `suspect` too and the pair
/// does among the rest of their neighbours: a cosmic ray's hit of two pixels.
fn stands_alone(
    img: &ArrayView2<f32>,
    medians: &Array2<f32>,
    at: (usize, usize),
    lone_factor: f32,
    suspect: impl Fn(usize, usize) -> bool,
) -> bool {
    let above = img[[at.0, at.1]] > medians[[at.0, at.1]];
    let Some(alone) = rise_over_neighbours(img, at, above, None) else {
        return true;
    };
    if alone.ratio > lone_factor {
        return true;
    }
    let partner = alone.brightest;
    let pair_alone = |of: (usize, usize), but: (usize, usize)| {
        rise_over_neighbours(img, of, above, Some(but)).is_none_or(|r| r.ratio > lone_factor)
    };
    suspect(partner.0, partner.1) && pair_alone(at, partner) && pair_alone(partner, at)
}

/// How a pixel rises above its neighbours (but `skip`), on its side (`above`, or mirrored).
struct Rise {
    /// The pixel's rise above the neighbours' floor over the brightest neighbour's.
    ratio: f32,
    brightest: (usize, usize),
}

fn rise_over_neighbours(
    img: &ArrayView2<f32>,
    (y, x): (usize, usize),
    above: bool,
    skip: Option<(usize, usize)>,
) -> Option<Rise> {
    let (h, w) = img.dim();
    let signed = |v: f32| if above { v } else { -v };
    let (mut floor, mut top) = (f32::INFINITY, f32::NEG_INFINITY);
    let mut brightest = (y, x);
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let n = img[[yy, xx]];
            if (yy, xx) == (y, x) || Some((yy, xx)) == skip || !n.is_finite() {
                continue;
            }
            let n = signed(n);
            floor = floor.min(n);
            if n > top {
                top = n;
                brightest = (yy, xx);
            }
        }
    }
    if !top.is_finite() {
        return None;
    }
    let rise = signed(img[[y, x]]) - floor;
    let spread = top - floor;
    Some(Rise {
        ratio: if spread > 0.0 {
            rise / spread
        } else {
            f32::INFINITY
        },
        brightest,
    })
}

/// Robust σ of the 8 neighbours about `median`: 1.4826 × median |n − median|.
fn neighbour_spread(img: &ArrayView2<f32>, y: usize, x: usize, median: f32) -> f32 {
    let (h, w) = img.dim();
    let mut dev = [0f32; 8];
    let mut k = 0;
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let v = img[[yy, xx]];
            if (yy, xx) != (y, x) && v.is_finite() {
                dev[k] = (v - median).abs();
                k += 1;
            }
        }
    }
    if k == 0 {
        0.0
    } else {
        1.4826 * median_of(&mut dev[..k])
    }
}

fn median_of(vals: &mut [f32]) -> f32 {
    let n = vals.len();
    vals.sort_unstable_by(f32::total_cmp);
    if n % 2 == 1 {
        vals[n / 2]
    } else {
        0.5 * (vals[n / 2 - 1] + vals[n / 2])
    }
}

/// 3×3 median of the finite pixels (window clipped at the borders), NaN if none.
///
/// Interior pixels with nine finite values use the column-sort identity: with each column's
/// three values sorted into (lo, mid, hi), the median of the nine is
/// `med3(max(lo), med3(mid), min(hi))` — exact, and each column sort is shared by three
/// outputs, in straight-line min/max loops the compiler vectorises. Other pixels fall back
/// to sorting their finite neighbours.
pub(super) fn median3x3(img: &ArrayView2<f32>) -> Array2<f32> {
    let (h, w) = img.dim();
    let mut out = super::filters::zeroed(h, w);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each_init(
            || (vec![0f32; w], vec![0f32; w], vec![0f32; w], vec![false; w]),
            |(lo, mid, hi, finite), (y, mut row)| {
                let mut fast_ok = false;
                if y >= 1 && y + 1 < h && w >= 3 {
                    if let (Some(a), Some(b), Some(c)) = (
                        img.row(y - 1).to_slice(),
                        img.row(y).to_slice(),
                        img.row(y + 1).to_slice(),
                    ) {
                        sort_columns(a, b, c, lo, mid, hi, finite);
                        if let Some(o) = row.as_slice_mut() {
                            median_of_sorted_columns(lo, mid, hi, o);
                            fast_ok = true;
                        }
                    }
                }
                for x in 0..w {
                    let interior = fast_ok && x >= 1 && x + 1 < w;
                    if interior && finite[x - 1] && finite[x] && finite[x + 1] {
                        continue;
                    }
                    row[x] = median3x3_at(img, y, x);
                }
            },
        );
    out
}

/// Each column `x` of rows `a`, `b`, `c` sorted into `lo ≤ mid ≤ hi`; `finite[x]` when all
/// three values are finite (otherwise the sorted values are meaningless).
fn sort_columns(
    a: &[f32],
    b: &[f32],
    c: &[f32],
    lo: &mut [f32],
    mid: &mut [f32],
    hi: &mut [f32],
    finite: &mut [bool],
) {
    for x in 0..a.len() {
        let (p, q, r) = (a[x], b[x], c[x]);
        let (l1, h1) = (p.min(q), p.max(q));
        lo[x] = l1.min(r);
        let m = l1.max(r);
        mid[x] = m.min(h1);
        hi[x] = m.max(h1);
        finite[x] = p.is_finite() & q.is_finite() & r.is_finite();
    }
}

/// `out[x] = med3(max(lo[x-1..=x+1]), med3(mid[x-1..=x+1]), min(hi[x-1..=x+1]))` for the
/// interior columns.
fn median_of_sorted_columns(lo: &[f32], mid: &[f32], hi: &[f32], out: &mut [f32]) {
    #[inline(always)]
    fn med3(a: f32, b: f32, c: f32) -> f32 {
        a.min(b).max(a.max(b).min(c))
    }
    let w = out.len();
    for x in 1..w - 1 {
        let l = lo[x - 1].max(lo[x]).max(lo[x + 1]);
        let m = med3(mid[x - 1], mid[x], mid[x + 1]);
        let u = hi[x - 1].min(hi[x]).min(hi[x + 1]);
        out[x] = med3(l, m, u);
    }
}

/// Median of the finite pixels of the 3×3 window at `(y, x)`, clipped at the borders.
fn median3x3_at(img: &ArrayView2<f32>, y: usize, x: usize) -> f32 {
    let (h, w) = img.dim();
    let mut buf = [0f32; 9];
    let mut n = 0;
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let v = img[[yy, xx]];
            if v.is_finite() {
                buf[n] = v;
                n += 1;
            }
        }
    }
    if n == 0 {
        f32::NAN
    } else {
        median_of(&mut buf[..n])
    }
}
