//! Robust statistics of the refinement's residuals: Tukey's biweight, the MAD, and sums over
//! chunks that come out the same whatever the thread count.

use rayon::prelude::*;

/// `f` over consecutive chunks of `0..n` in parallel, combined in order with `add`: the same
/// sum whatever the thread count.
pub(super) fn sum_in_chunks<T: Send>(
    n: usize,
    f: impl Fn(std::ops::Range<usize>) -> T + Sync,
    add: impl Fn(T, T) -> T,
) -> T {
    const CHUNK: usize = 1 << 14;
    let parts: Vec<T> = (0..n.div_ceil(CHUNK).max(1))
        .into_par_iter()
        .map(|c| f(c * CHUNK..((c + 1) * CHUNK).min(n)))
        .collect();
    let mut parts = parts.into_iter();
    let first = parts.next().expect("at least one chunk");
    parts.fold(first, add)
}

/// Slope of Tukey's ψ(r) = r·w(r): (1 − u²)(1 − 5u²) with u = r/c, zero beyond c.
pub(super) fn tukey_psi_slope(r: f64, c: f64) -> f64 {
    let u2 = (r / c).powi(2);
    if !u2.is_finite() || u2 >= 1.0 {
        0.0
    } else {
        (1.0 - u2) * (1.0 - 5.0 * u2)
    }
}

pub(super) fn tukey_weight(r: f64, c: f64) -> f64 {
    if !r.is_finite() {
        return 0.0;
    }
    let u = r / c;
    if u.abs() >= 1.0 {
        0.0
    } else {
        (1.0 - u * u).powi(2)
    }
}

/// 1.4826 × median absolute deviation about the median, over the finite values.
pub(super) fn robust_sigma(values: &[f64]) -> Option<f64> {
    robust_sigma_where(values.len(), |i| Some(values[i]).filter(|v| v.is_finite()))
}

/// [`robust_sigma`] over the values `value(i)` that are `Some` (finite) for `i` in `0..len`,
/// without collecting them.
pub(super) fn robust_sigma_where(
    len: usize,
    value: impl Fn(usize) -> Option<f64> + Sync,
) -> Option<f64> {
    let n = (0..len)
        .into_par_iter()
        .filter(|&i| value(i).is_some())
        .count();
    if n == 0 {
        return None;
    }
    let mid = n / 2;
    let median = crate::stats::par_select_where(len, mid, &value)?;
    let mad = crate::stats::par_select_where(len, mid, |i| value(i).map(|v| (v - median).abs()))?;
    Some(1.482_602_218_505_602 * mad)
}
