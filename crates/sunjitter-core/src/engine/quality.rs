//! How well two images match inside a mask: the paper's Bhattacharyya coefficient of the
//! intensity histograms, and a structural check (zero-mean normalised cross-correlation)
//! that histograms cannot give — a flipped copy has identical histograms.

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

/// Bhattacharyya coefficient of the intensity histograms of `a` and `b` inside `mask`.
///
/// Each image is normalised by its own mean inside the mask (so units and exposure do not
/// matter) and both are binned on the same range, from the lower to the upper 0.5 %
/// quantile of the pooled values, with a bin count that grows with the sample size.
pub fn bhattacharyya(
    a: ArrayView2<f32>,
    b: ArrayView2<f32>,
    mask: ArrayView2<bool>,
) -> Option<f64> {
    // Histograms of at most a few million values are as good as of all of them.
    let va = masked_values(a, mask, MAX_HISTOGRAM_VALUES);
    let vb = masked_values(b, mask, MAX_HISTOGRAM_VALUES);
    if va.len() < 16 || vb.len() < 16 {
        return None;
    }
    let na = normalise_by_mean(va)?;
    let nb = normalise_by_mean(vb)?;
    let pooled: Vec<f64> = na.iter().chain(nb.iter()).copied().collect();
    // The two order statistics by selection (same values as after a full sort).
    let (k_lo, k_hi) = (
        (pooled.len() as f64 * 0.005) as usize,
        ((pooled.len() as f64 * 0.995) as usize).min(pooled.len() - 1),
    );
    let (lo, hi) = rayon::join(
        || crate::stats::par_select(&pooled, k_lo),
        || crate::stats::par_select(&pooled, k_hi),
    );
    if hi <= lo {
        // Both constant and equal after normalisation: identical histograms.
        return Some(1.0);
    }
    let bins = ((na.len().min(nb.len()) as f64).sqrt() / 2.0).clamp(16.0, 256.0) as usize;
    let hist = |v: &[f64]| -> Vec<f64> {
        let mut h = vec![0.0; bins];
        for &x in v {
            let k = (((x - lo) / (hi - lo)) * bins as f64).floor();
            let k = (k.max(0.0) as usize).min(bins - 1);
            h[k] += 1.0;
        }
        let total = v.len() as f64;
        h.iter_mut().for_each(|c| *c /= total);
        h
    };
    let (ha, hb) = (hist(&na), hist(&nb));
    Some(ha.iter().zip(&hb).map(|(p, q)| (p * q).sqrt()).sum())
}

/// Zero-mean normalised cross-correlation of `a` and `b` over pixels inside `mask` where both
/// are finite. 1 for identical structure, about 0 for unrelated images.
pub fn normalised_cross_correlation(
    a: ArrayView2<f32>,
    b: ArrayView2<f32>,
    mask: ArrayView2<bool>,
) -> Option<f64> {
    let mut n = 0.0;
    let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for ((&x, &y), &m) in a.iter().zip(b.iter()).zip(mask.iter()) {
        if m && x.is_finite() && y.is_finite() {
            let (x, y) = (x as f64, y as f64);
            n += 1.0;
            sa += x;
            sb += y;
            saa += x * x;
            sbb += y * y;
            sab += x * y;
        }
    }
    if n < 16.0 {
        return None;
    }
    let cov = sab / n - (sa / n) * (sb / n);
    let var_a = saa / n - (sa / n).powi(2);
    let var_b = sbb / n - (sb / n).powi(2);
    if var_a <= 0.0 || var_b <= 0.0 {
        return None;
    }
    Some(cov / (var_a * var_b).sqrt())
}

/// Spearman rank correlation of `a` and `b` over pixels inside `mask` where both are finite
/// (at most `MAX_RANK_PAIRS` of them, evenly strided). Unlike the Pearson correlation it is
/// not dominated by a few bright pixels, such as a brightening in one exposure of a low-count
/// pair (docs/validation.md#rank-correlation-for-the-structure-check); unrelated and flipped
/// images still give about 0.
pub fn rank_correlation(
    a: ArrayView2<f32>,
    b: ArrayView2<f32>,
    mask: ArrayView2<bool>,
) -> Option<f64> {
    let usable = |x: &f32, y: &f32, m: &bool| *m && x.is_finite() && y.is_finite();
    // Every `stride`-th usable pair, counted first so that only the chosen ones are kept.
    let n_usable = ndarray::Zip::from(&a).and(&b).and(&mask).par_fold(
        || 0usize,
        |n, x, y, m| n + usize::from(usable(x, y, m)),
        |p, q| p + q,
    );
    let stride = n_usable.div_ceil(MAX_RANK_PAIRS).max(1);
    let mut pairs: Vec<(f32, f32)> = Vec::with_capacity(n_usable.div_ceil(stride));
    let mut k = 0usize;
    for ((x, y), m) in a.iter().zip(b.iter()).zip(mask.iter()) {
        if usable(x, y, m) {
            if k.is_multiple_of(stride) {
                pairs.push((*x, *y));
            }
            k += 1;
        }
    }
    if pairs.len() < 16 {
        return None;
    }
    let (ra, rb) = rayon::join(
        || ranks(pairs.iter().map(|p| p.0).collect()),
        || ranks(pairs.iter().map(|p| p.1).collect()),
    );
    let n = ra.len() as f64;
    let mean = (n - 1.0) / 2.0;
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        let (x, y) = (x - mean, y - mean);
        sab += x * y;
        saa += x * x;
        sbb += y * y;
    }
    (saa > 0.0 && sbb > 0.0).then(|| sab / (saa * sbb).sqrt())
}

/// Most pixel pairs the rank correlation sorts.
const MAX_RANK_PAIRS: usize = 1 << 18;

/// 0-based ranks, ties given their mean rank.
fn ranks(values: Vec<f32>) -> Vec<f64> {
    // Sorted as integers: each value's bits in f32 total order above its index.
    let key = |v: f32| {
        let b = v.to_bits();
        if b >> 31 == 1 {
            !b
        } else {
            b | 1 << 31
        }
    };
    let mut order: Vec<u64> = values
        .par_iter()
        .enumerate()
        .map(|(i, &v)| (u64::from(key(v)) << 32) | i as u64)
        .collect();
    order.par_sort_unstable();
    let index = |k: u64| (k & u64::from(u32::MAX)) as usize;
    let mut out = vec![0.0; values.len()];
    let mut start = 0;
    while start < order.len() {
        let first = values[index(order[start])];
        let mut end = start + 1;
        while end < order.len() && values[index(order[end])] == first {
            end += 1;
        }
        let rank = (start + end - 1) as f64 / 2.0;
        for &k in &order[start..end] {
            out[index(k)] = rank;
        }
        start = end;
    }
    out
}

/// `img` minus its Gaussian blur at `sigma_px`: the structure without the large-scale trend.
pub fn high_pass(img: ArrayView2<f32>, sigma_px: f64) -> Array2<f32> {
    let trend = crate::preprocess::gaussian_trend(img, sigma_px);
    ndarray::Zip::from(img)
        .and(&trend)
        .par_map_collect(|&v, &t| v - t)
}

/// Most values one histogram of [`bhattacharyya`] takes (evenly strided beyond that).
const MAX_HISTOGRAM_VALUES: usize = 1 << 21;

/// The finite values of `img` inside `mask`, every `k`-th of them so that at most `max`.
fn masked_values(img: ArrayView2<f32>, mask: ArrayView2<bool>, max: usize) -> Vec<f64> {
    let inside = crate::stats::count_set(mask);
    let stride = inside.div_ceil(max.max(1)).max(1);
    img.iter()
        .zip(mask.iter())
        .filter(|(_, m)| **m)
        .step_by(stride)
        .filter(|(v, _)| v.is_finite())
        .map(|(v, _)| *v as f64)
        .collect()
}

fn normalise_by_mean(mut v: Vec<f64>) -> Option<Vec<f64>> {
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    if !mean.is_finite() || mean.abs() < f64::MIN_POSITIVE {
        return None;
    }
    v.iter_mut().for_each(|x| *x /= mean);
    Some(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_histograms_give_one_and_disjoint_give_zero() {
        let a = Array2::from_shape_fn((64, 64), |(y, x)| 1.0 + ((x * 7 + y * 3) % 50) as f32);
        let mask = Array2::from_elem((64, 64), true);
        let same = bhattacharyya(a.view(), a.view(), mask.view()).unwrap();
        assert!((same - 1.0).abs() < 1e-12);
        // Gaussian histograms with known overlap: BC of N(0,1) and N(d,1) is exp(-d²/8).
        // Use two uniform distributions instead, exactly disjoint after mean normalisation.
        let lo = Array2::from_shape_fn((64, 64), |(y, x)| 1.0 + 0.1 * ((x + y) % 2) as f32);
        let hi = Array2::from_shape_fn((64, 64), |(y, x)| if (x + y) % 2 == 0 { 0.2 } else { 1.8 });
        let disjoint = bhattacharyya(lo.view(), hi.view(), mask.view()).unwrap();
        assert!(disjoint < 1e-12, "{disjoint}");
    }

    #[test]
    fn ranks_are_the_count_below_plus_half_the_ties() {
        // The definition of mid-ranks, on negatives, both zeros (equal) and repeated values.
        let values: Vec<f32> = (0..500)
            .map(|i| ((i * 37) % 41) as f32 - 20.0)
            .chain([0.0, -0.0, -0.0, f32::MAX, f32::MIN, 1e-40, -1e-40])
            .collect();
        let got = ranks(values.clone());
        for (v, r) in values.iter().zip(&got) {
            let below = values.iter().filter(|w| *w < v).count() as f64;
            let equal = values.iter().filter(|w| *w == v).count() as f64;
            assert_eq!(*r, below + (equal - 1.0) / 2.0, "value {v}");
        }
    }

    #[test]
    fn rank_correlation_of_a_monotone_map_is_one_and_of_a_reversal_minus_one() {
        // Spearman's ρ is 1 for any increasing function of the data and −1 for a decreasing
        // one (definition), whatever a few extreme values do to Pearson's r.
        let a = Array2::from_shape_fn((32, 32), |(y, x)| ((x * 7 + y * 13) % 31) as f32);
        let mask = Array2::from_elem((32, 32), true);
        let bright = a.mapv(|v| if v > 29.0 { 1e6 } else { v });
        let reversed = a.mapv(|v| -v * v);
        let r = rank_correlation(a.view(), bright.view(), mask.view()).unwrap();
        assert!((r - 1.0).abs() < 1e-12, "{r}");
        let r = rank_correlation(a.view(), reversed.view(), mask.view()).unwrap();
        assert!((r + 1.0).abs() < 1e-12, "{r}");
    }

    #[test]
    fn cross_correlation_sees_structure_histograms_cannot() {
        let a = Array2::from_shape_fn((64, 64), |(y, x)| {
            ((x as f32) * 0.3).sin() + (y as f32) * 0.05
        });
        let flipped = Array2::from_shape_fn((64, 64), |(y, x)| a[[63 - y, 63 - x]]);
        let mask = Array2::from_elem((64, 64), true);
        let bc = bhattacharyya(a.view(), flipped.view(), mask.view()).unwrap();
        assert!((bc - 1.0).abs() < 1e-12, "same values, same histogram");
        let ncc_same = normalised_cross_correlation(a.view(), a.view(), mask.view()).unwrap();
        let ncc_flip = normalised_cross_correlation(a.view(), flipped.view(), mask.view()).unwrap();
        assert!((ncc_same - 1.0).abs() < 1e-9);
        assert!(ncc_flip < 0.0, "{ncc_flip}");
    }
}
