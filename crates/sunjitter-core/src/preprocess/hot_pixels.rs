//! Hot pixels and cosmic-ray hits: a 3×3 median test with a noise guard and a lone-pixel rule.

use ndarray::{Array2, ArrayView2, Axis};
use rayon::prelude::*;

use super::quantile;

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
    let test = HotPixelTest::new(img.view(), threshold_fraction, noise_sigmas, lone_factor);
    let h = img.nrows();
    let hits: Vec<(usize, usize, f32)> = (0..h.div_ceil(BAND))
        .into_par_iter()
        .flat_map_iter(|band| {
            let mut hits = Vec::new();
            test.band(
                img.view(),
                band * BAND..((band + 1) * BAND).min(h),
                |y, row| {
                    hits.extend(row.iter().map(|&(x, m)| (y, x, m)));
                },
            );
            hits
        })
        .collect();
    for &(y, x, m) in &hits {
        img[[y, x]] = m;
    }
    hits.len()
}

/// `img` cleaned as [`remove_hot_pixels`] cleans it, into a new array: each row is copied
/// with its replacements as it is decided, and the medians are never stored whole.
pub fn hot_pixels_removed(img: ArrayView2<f32>, threshold_fraction: f32) -> Array2<f32> {
    let test = HotPixelTest::new(
        img,
        threshold_fraction,
        HOT_PIXEL_NOISE_SIGMAS,
        HOT_PIXEL_LONE_FACTOR,
    );
    let (h, w) = img.dim();
    let mut out = Array2::<f32>::uninit((h, w));
    out.axis_chunks_iter_mut(Axis(0), BAND)
        .into_par_iter()
        .enumerate()
        .for_each(|(band, mut rows)| {
            let y0 = band * BAND;
            test.band(img, y0..y0 + rows.nrows(), |y, hits| {
                let mut row = rows.row_mut(y - y0);
                for (o, &v) in row.iter_mut().zip(img.row(y)) {
                    o.write(v);
                }
                for &(x, m) in hits {
                    row[x].write(m);
                }
            });
        });
    // SAFETY: every row of every band was written above.
    unsafe { out.assume_init() }
}

/// Rows decided together: each band computes its rows' medians (and one more on either
/// side) in turn, while they are in cache.
const BAND: usize = 32;

/// The hot-pixel test on one image: its thresholds and the image-wide noise.
struct HotPixelTest {
    threshold_fraction: f32,
    noise_sigmas: f32,
    lone_factor: f32,
    /// Image-wide robust noise of the residual from the 3×3 median.
    sigma: f32,
}

impl HotPixelTest {
    fn new(
        img: ArrayView2<f32>,
        threshold_fraction: f32,
        noise_sigmas: f32,
        lone_factor: f32,
    ) -> HotPixelTest {
        HotPixelTest {
            threshold_fraction,
            noise_sigmas,
            lone_factor,
            sigma: residual_noise(img),
        }
    }

    /// The hits of rows `rows` (pixel, median), decided on `img` as it is, row by row in
    /// order through `row_hits`.
    fn band(
        &self,
        img: ArrayView2<f32>,
        rows: std::ops::Range<usize>,
        mut row_hits: impl FnMut(usize, &[(usize, f32)]),
    ) {
        let (h, w) = img.dim();
        let mut scratch = RowScratch::new(w);
        // Medians of rows y − 1, y and y + 1 (a suspect's partner lies within them).
        let mut medians = [vec![0f32; w], vec![0f32; w], vec![0f32; w]];
        let slot = |yy: usize| (yy + 1 - rows.start) % 3;
        for yy in rows.start.saturating_sub(1)..(rows.start + 2).min(h) {
            median_row(&img, yy, &mut scratch, &mut medians[slot(yy)]);
        }
        let (mut hits, mut flags) = (Vec::new(), vec![false; w]);
        for y in rows.clone() {
            if y > rows.start && y + 1 < h {
                median_row(&img, y + 1, &mut scratch, &mut medians[slot(y + 1)]);
            }
            let at = |yy: usize| &medians[slot(yy)];
            let median = |yy: usize, xx: usize| at(yy)[xx];
            let (row, med_row) = (img.row(y), at(y));
            let sigma = self.noise_sigmas * self.sigma;
            let suspect = |v: f32, m: f32| is_suspect(v, m, self.threshold_fraction, sigma);
            hits.clear();
            // Cheap tests first, over the whole row (false for NaN): most pixels end here.
            // The local spread is needed only for the few suspects.
            match row.as_slice() {
                Some(row) => {
                    suspects_in_row(row, med_row, &mut flags, self.threshold_fraction, sigma)
                }
                None => {
                    for ((f, &v), &m) in flags.iter_mut().zip(row).zip(med_row) {
                        *f = suspect(v, m);
                    }
                }
            }
            for x in flagged(&flags) {
                let (v, m) = (row[x], med_row[x]);
                if (v - m).abs() > self.noise_sigmas * neighbour_spread(&img, y, x, m)
                    && stands_alone(&img, median, (y, x), self.lone_factor, |yy, xx| {
                        suspect(img[[yy, xx]], median(yy, xx))
                    })
                {
                    hits.push((x, m));
                }
            }
            row_hits(y, &hits);
        }
    }
}

crate::flow::simd::multiversion!(fn suspects_in_row(
    row: &[f32],
    medians: &[f32],
    flags: &mut [bool],
    threshold_fraction: f32,
    sigma: f32,
) => suspects_in_row_body);

/// `flags[x]`: whether pixel `x` of a row is a suspect ([`is_suspect`]).
#[inline(always)]
fn suspects_in_row_body(
    row: &[f32],
    medians: &[f32],
    flags: &mut [bool],
    threshold_fraction: f32,
    sigma: f32,
) {
    for ((f, &v), &m) in flags.iter_mut().zip(row).zip(medians) {
        *f = is_suspect(v, m, threshold_fraction, sigma);
    }
}

/// Whether `v` deviates from its median `m` by more than `threshold_fraction` of it and by
/// more than `sigma` (false for NaN).
#[inline(always)]
fn is_suspect(v: f32, m: f32, threshold_fraction: f32, sigma: f32) -> bool {
    let dev = (v - m).abs();
    (dev > threshold_fraction * m.abs()) & (dev > sigma)
}

/// The indices of the set flags, in order, passing over eight clear flags at a time.
fn flagged(flags: &[bool]) -> impl Iterator<Item = usize> + '_ {
    flags
        .chunks(8)
        .enumerate()
        .filter(|(_, chunk)| chunk.iter().fold(false, |a, &f| a | f))
        .flat_map(|(k, chunk)| {
            chunk
                .iter()
                .enumerate()
                .filter(|&(_, &f)| f)
                .map(move |(i, _)| 8 * k + i)
        })
}

/// Image-wide robust noise of the residual from the 3×3 median: 1.4826 × median |v − m|,
/// from every `stride`-th pixel in row-major order (at most about a million: plenty for a
/// median).
fn residual_noise(img: ArrayView2<f32>) -> f32 {
    let (h, w) = img.dim();
    let stride = (h * w / (1 << 20)).max(1);
    let residuals: Vec<f32> = (0..h)
        .into_par_iter()
        .fold(
            || (RowScratch::new(w), vec![0f32; w], Vec::new()),
            |(mut scratch, mut medians, mut out), y| {
                // The first pixel of row y on the stride's grid of the flattened image.
                let x0 = (stride - (y * w) % stride) % stride;
                if stride < 4 {
                    // Most of the row: its medians all at once.
                    median_row(&img, y, &mut scratch, &mut medians);
                } else {
                    sampled_medians(&img, y, (x0..w).step_by(stride), &mut medians);
                }
                let row = img.row(y);
                out.extend((x0..w).step_by(stride).filter_map(|x| {
                    let (v, m) = (row[x], medians[x]);
                    (v.is_finite() && m.is_finite()).then(|| (v - m).abs())
                }));
                (scratch, medians, out)
            },
        )
        .map(|(_, _, out)| out)
        .reduce(Vec::new, |mut a, mut b| {
            a.append(&mut b);
            a
        });
    if residuals.is_empty() {
        0.0
    } else {
        1.4826 * quantile(&residuals, 0.5)
    }
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
    median: impl Fn(usize, usize) -> f32,
    at: (usize, usize),
    lone_factor: f32,
    suspect: impl Fn(usize, usize) -> bool,
) -> bool {
    let above = img[[at.0, at.1]] > median(at.0, at.1);
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

/// 3×3 median of the finite pixels (window clipped at the borders), NaN if none: every
/// [`median_row`] of the image.
#[cfg(test)]
pub(super) fn median3x3(img: &ArrayView2<f32>) -> Array2<f32> {
    let (h, w) = img.dim();
    let mut out = Array2::<f32>::zeros((h, w));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each_init(
            || (RowScratch::new(w), vec![0f32; w]),
            |(scratch, medians), (y, mut row)| {
                median_row(img, y, scratch, medians);
                row.iter_mut()
                    .zip(medians.iter())
                    .for_each(|(o, &m)| *o = m);
            },
        );
    out
}

/// Working rows of [`median_row`].
struct RowScratch {
    lo: Vec<f32>,
    mid: Vec<f32>,
    hi: Vec<f32>,
    finite: Vec<bool>,
}

impl RowScratch {
    fn new(w: usize) -> RowScratch {
        RowScratch {
            lo: vec![0.0; w],
            mid: vec![0.0; w],
            hi: vec![0.0; w],
            finite: vec![false; w],
        }
    }
}

/// Row `y` of the 3×3 median of the finite pixels (window clipped at the borders, NaN if
/// none) into `out`.
///
/// Interior pixels with nine finite values use the column-sort identity: with each column's
/// three values sorted into (lo, mid, hi), the median of the nine is
/// `med3(max(lo), med3(mid), min(hi))` — exact, and each column sort is shared by three
/// outputs, in straight-line min/max loops the compiler vectorises. Other pixels fall back
/// to sorting their finite neighbours.
fn median_row(img: &ArrayView2<f32>, y: usize, s: &mut RowScratch, out: &mut [f32]) {
    let (h, w) = img.dim();
    let mut fast_ok = false;
    if y >= 1 && y + 1 < h && w >= 3 {
        if let (Some(a), Some(b), Some(c)) = (
            img.row(y - 1).to_slice(),
            img.row(y).to_slice(),
            img.row(y + 1).to_slice(),
        ) {
            let all_finite = sort_columns(a, b, c, &mut s.lo, &mut s.mid, &mut s.hi, &mut s.finite);
            median_of_sorted_columns(&s.lo, &s.mid, &s.hi, out);
            if all_finite {
                // Only the border columns' windows are clipped.
                out[0] = median3x3_at(img, y, 0);
                out[w - 1] = median3x3_at(img, y, w - 1);
                return;
            }
            fast_ok = true;
        }
    }
    for (x, o) in out.iter_mut().enumerate() {
        let interior = fast_ok && x >= 1 && x + 1 < w;
        if interior && s.finite[x - 1] && s.finite[x] && s.finite[x + 1] {
            continue;
        }
        *o = median3x3_at(img, y, x);
    }
}

crate::flow::simd::multiversion!(fn sort_columns(
    a: &[f32],
    b: &[f32],
    c: &[f32],
    lo: &mut [f32],
    mid: &mut [f32],
    hi: &mut [f32],
    finite: &mut [bool],
) -> bool => sort_columns_body);

/// Each column `x` of rows `a`, `b`, `c` sorted into `lo ≤ mid ≤ hi`; `finite[x]` when all
/// three values are finite (otherwise the sorted values are meaningless). Whether every
/// column is.
#[inline(always)]
fn sort_columns_body(
    a: &[f32],
    b: &[f32],
    c: &[f32],
    lo: &mut [f32],
    mid: &mut [f32],
    hi: &mut [f32],
    finite: &mut [bool],
) -> bool {
    let mut all = true;
    for x in 0..a.len() {
        let (p, q, r) = (a[x], b[x], c[x]);
        let (l1, h1) = (p.min(q), p.max(q));
        lo[x] = l1.min(r);
        let m = l1.max(r);
        mid[x] = m.min(h1);
        hi[x] = m.max(h1);
        let f = p.is_finite() & q.is_finite() & r.is_finite();
        finite[x] = f;
        all &= f;
    }
    all
}

crate::flow::simd::multiversion!(fn median_of_sorted_columns(
    lo: &[f32],
    mid: &[f32],
    hi: &[f32],
    out: &mut [f32],
) => median_of_sorted_columns_body);

/// `out[x] = med3(max(lo[x-1..=x+1]), med3(mid[x-1..=x+1]), min(hi[x-1..=x+1]))` for the
/// interior columns.
#[inline(always)]
fn median_of_sorted_columns_body(lo: &[f32], mid: &[f32], hi: &[f32], out: &mut [f32]) {
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

/// [`median_row`]'s value at `(y, x)`, on its own: an interior window of nine finite values
/// by a sorting network (its median is theirs, the sign of a zero aside), else as the row's
/// fallback does.
pub(super) fn median3x3_of(img: &ArrayView2<f32>, y: usize, x: usize) -> f32 {
    let (h, w) = img.dim();
    if y >= 1 && y + 1 < h && x >= 1 && x + 1 < w {
        let mut v = [0f32; 9];
        for (k, yy) in (y - 1..=y + 1).enumerate() {
            for (j, xx) in (x - 1..=x + 1).enumerate() {
                v[3 * k + j] = img[[yy, xx]];
            }
        }
        if v.iter().all(|v| v.is_finite()) {
            return median9(v);
        }
    }
    median3x3_at(img, y, x)
}

/// The 19 exchanges of Paeth's median-of-nine network: after them, the fifth value is the
/// median.
const MEDIAN9_NETWORK: [(usize, usize); 19] = [
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 1),
    (3, 4),
    (6, 7),
    (1, 2),
    (4, 5),
    (7, 8),
    (0, 3),
    (5, 8),
    (4, 7),
    (3, 6),
    (1, 4),
    (2, 5),
    (4, 7),
    (4, 2),
    (6, 4),
    (4, 2),
];

/// Median of nine values by [`MEDIAN9_NETWORK`].
fn median9(mut p: [f32; 9]) -> f32 {
    for (a, b) in MEDIAN9_NETWORK {
        let (lo, hi) = (p[a].min(p[b]), p[a].max(p[b]));
        (p[a], p[b]) = (lo, hi);
    }
    p[4]
}

/// [`median3x3_of`] at the pixels `columns` of row `y`, into `medians` at those columns. The
/// interior windows go through [`MEDIAN9_NETWORK`] eight at a time, one window per vector
/// lane; those with a value not finite, and the border's, as [`median3x3_of`] takes them.
fn sampled_medians(
    img: &ArrayView2<f32>,
    y: usize,
    columns: impl Iterator<Item = usize>,
    medians: &mut [f32],
) {
    let (h, w) = img.dim();
    let rows = (y >= 1 && y + 1 < h).then(|| {
        let row = |yy: usize| img.row(yy).to_slice();
        (row(y - 1), row(y), row(y + 1))
    });
    let Some((Some(a), Some(b), Some(c))) = rows else {
        columns.for_each(|x| medians[x] = median3x3_of(img, y, x));
        return;
    };
    let mut block = [0usize; LANES];
    let mut n = 0;
    let flush = |block: &[usize], medians: &mut [f32]| {
        // Windows value by value: `p[k][l]` is the `k`-th value of lane `l`'s window.
        let mut p = [[0f32; LANES]; 9];
        let mut whole = [false; LANES];
        for (l, &x) in block.iter().enumerate() {
            if x >= 1 && x + 1 < w {
                let v = [
                    a[x - 1],
                    a[x],
                    a[x + 1],
                    b[x - 1],
                    b[x],
                    b[x + 1],
                    c[x - 1],
                    c[x],
                    c[x + 1],
                ];
                for (lanes, v) in p.iter_mut().zip(v) {
                    lanes[l] = v;
                }
                whole[l] = v.iter().all(|v| v.is_finite());
            }
        }
        medians9(&mut p);
        for (l, &x) in block.iter().enumerate() {
            medians[x] = match whole[l] {
                true => p[4][l],
                false => median3x3_of(img, y, x),
            };
        }
    };
    for x in columns {
        block[n] = x;
        n += 1;
        if n == LANES {
            flush(&block, medians);
            n = 0;
        }
    }
    flush(&block[..n], medians);
}

/// Windows [`sampled_medians`] takes side by side, one per vector lane.
const LANES: usize = 8;

/// The medians [`sampled_medians`] makes at every `step`-th pixel of each row from `first`;
/// NaN elsewhere.
#[cfg(test)]
pub(super) fn median3x3_sampled(img: &ArrayView2<f32>, first: usize, step: usize) -> Array2<f32> {
    let (h, w) = img.dim();
    let mut out = Array2::from_elem((h, w), f32::NAN);
    for y in 0..h {
        let mut medians = vec![f32::NAN; w];
        sampled_medians(img, y, (first..w).step_by(step), &mut medians);
        out.row_mut(y).assign(&ndarray::ArrayView1::from(&medians));
    }
    out
}

crate::flow::simd::multiversion!(fn medians9(p: &mut [[f32; LANES]; 9]) => medians9_body);

/// [`MEDIAN9_NETWORK`] on [`LANES`] windows at once: after it, `p[4]` holds their medians.
#[inline(always)]
fn medians9_body(p: &mut [[f32; LANES]; 9]) {
    for (a, b) in MEDIAN9_NETWORK {
        let (pa, pb) = (p[a], p[b]);
        p[a] = std::array::from_fn(|l| pa[l].min(pb[l]));
        p[b] = std::array::from_fn(|l| pa[l].max(pb[l]));
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
