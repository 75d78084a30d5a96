//! Robust one-dimensional statistics for the inspected series (no I/O).

use serde::{Deserialize, Serialize};

/// Median (average of the middle two for an even count); reorders `v`. `None` when empty.
pub fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// Summary of one parameter's values; every number is `null` when there are none.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Samples used (frames with a value).
    pub n: usize,
    pub mean: Option<f64>,
    /// Root-mean-square deviation about the mean (the jitter amplitude, offset removed).
    pub rms: Option<f64>,
    pub min: Option<f64>,
    pub max: Option<f64>,
    pub peak_to_peak: Option<f64>,
    /// Median of the reported 1-σ errors (frames aligned to themselves, σ = 0, excluded).
    pub median_sigma: Option<f64>,
}

impl Stats {
    pub fn of(values: &[f64], sigmas: &[f64]) -> Stats {
        let n = values.len();
        let mut positive: Vec<f64> = sigmas.iter().copied().filter(|s| *s > 0.0).collect();
        let median_sigma = median(&mut positive);
        if n == 0 {
            return Stats {
                median_sigma,
                ..Stats::default()
            };
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let rms = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
        let min = values.iter().copied().fold(f64::INFINITY, f64::min);
        let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        Stats {
            n,
            mean: Some(mean),
            rms: Some(rms),
            min: Some(min),
            max: Some(max),
            peak_to_peak: Some(max - min),
            median_sigma,
        }
    }
}

/// A sample far from its neighbours.
#[derive(Debug, Clone, PartialEq)]
pub struct Deviation {
    pub index: usize,
    /// The neighbours' prediction for this sample.
    pub baseline: f64,
    /// The divisor: `max(σ_i, S) · √(1 + Σw²)` (see [`outliers`]).
    pub scale: f64,
    /// `(value − baseline) / scale`.
    pub z: f64,
}

/// Root-mean-square of `r` after iterated 3σ clipping: the typical scatter with a few wild
/// values ignored.
pub fn clipped_scatter(r: &[f64]) -> f64 {
    let mut limit = f64::INFINITY;
    let mut s = 0.0;
    for _ in 0..20 {
        let kept: Vec<f64> = r.iter().copied().filter(|v| v.abs() <= limit).collect();
        if kept.is_empty() {
            break;
        }
        let next = (kept.iter().map(|v| v * v).sum::<f64>() / kept.len() as f64).sqrt();
        if next == s {
            break;
        }
        s = next;
        limit = 3.0 * s;
    }
    s
}

/// Prediction at `ti` of a quadratic in time fitted to the samples `idx`, and its noise
/// amplification `Σw²` (white noise); `None` with fewer than 4 samples or a degenerate fit.
fn quadratic_at(t: &[f64], y: &[f64], idx: &[usize], ti: f64, unit: f64) -> Option<(f64, f64)> {
    if idx.len() < 4 {
        return None;
    }
    // Normal equations of y = a + b·u + c·u², u in cadences from ti.
    let mut m = [[0.0f64; 3]; 3];
    let mut v = [0.0f64; 3];
    for &j in idx {
        let u = (t[j] - ti) / unit;
        let x = [1.0, u, u * u];
        for r in 0..3 {
            v[r] += x[r] * y[j];
            for c in 0..3 {
                m[r][c] += x[r] * x[c];
            }
        }
    }
    let inv = invert3(m)?;
    let a: f64 = (0..3).map(|c| inv[0][c] * v[c]).sum();
    Some((a, inv[0][0]))
}

const NEIGHBOURS: usize = 6;

/// Leave-one-out predictions of sample `i` of the segment `lo..hi`: from its 6 nearest
/// neighbours (as balanced as the segment's ends allow), from the 6 before it, from the 6 after.
fn predictions(
    t: &[f64],
    y: &[f64],
    (lo, hi): (usize, usize),
    i: usize,
    unit: f64,
) -> [Option<(f64, f64)>; 3] {
    let before = (i - lo)
        .min(NEIGHBOURS / 2)
        .max(NEIGHBOURS.saturating_sub(hi - 1 - i));
    let start = i.saturating_sub(before).max(lo);
    let both: Vec<usize> = (start..hi).filter(|&j| j != i).take(NEIGHBOURS).collect();
    let left: Vec<usize> = (i.saturating_sub(NEIGHBOURS).max(lo)..i).collect();
    let right: Vec<usize> = (i + 1..hi.min(i + 1 + NEIGHBOURS)).collect();
    [
        quadratic_at(t, y, &both, t[i], unit),
        quadratic_at(t, y, &left, t[i], unit),
        quadratic_at(t, y, &right, t[i], unit),
    ]
}

fn invert3(m: [[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    let scale = m.iter().flatten().fold(0.0f64, |a, b| a.max(b.abs()));
    if det.is_nan() || det.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let c =
        |r0: usize, c0: usize, r1: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    Some([
        [
            c(1, 1, 2, 2) / det,
            -c(0, 1, 2, 2) / det,
            c(0, 1, 1, 2) / det,
        ],
        [
            -c(1, 0, 2, 2) / det,
            c(0, 0, 2, 2) / det,
            -c(0, 0, 1, 2) / det,
        ],
        [
            c(1, 0, 2, 1) / det,
            -c(0, 0, 2, 1) / det,
            c(0, 0, 1, 1) / det,
        ],
    ])
}

/// Outliers of the series `y(t)` with reported errors `sigma`.
///
/// The series is cut into segments at gaps longer than 3 median cadences; segments shorter
/// than 7 samples are not tested. Each sample gets leave-one-out predictions from quadratics in
/// time through 6 neighbours of its segment: the nearest on both sides (`B`), the 6 before
/// (`L`), the 6 after (`R`); quadratics follow real jitter down to periods of a few samples.
/// A residual `r` normalised by `√(1 + Σw²)` (`w` the prediction's weights) has the sample's σ
/// under white noise; `S_k` is the 3σ-clipped RMS of the normalised residuals of kind `k` over
/// the series: the typical scatter, including jitter too fast to follow (and, for `L`, `R`, the
/// larger errors of extrapolation). The primary prediction is `B` with `S_B`, except at a
/// segment's first (last) sample, where only `R` (`L`) exists, with its own `S`. Score:
/// `z = r / (max(σ_i, S) · √(1 + Σw²))`; `σ_i ≤ 0` (unknown, or a frame aligned to itself) uses
/// `S` alone. A sample with `|z| > threshold` is an outlier unless one of its one-sided
/// predictions, on the same scale, is within the threshold: a step agrees with its own side, a
/// glitch with neither. Sensitivity is lower at segment ends, where only extrapolation exists.
///
/// A glitch spoils its neighbours' predictions, so each flagged sample is confirmed by a second
/// test with the other flagged samples left out; confirmed ones are removed and the test
/// repeats on the rest (at most 20 rounds, at most a quarter of the samples).
pub fn outliers(t: &[f64], y: &[f64], sigma: &[f64], threshold: f64) -> Vec<Deviation> {
    let n = y.len();
    if n < 7 || t.len() != n || sigma.len() != n {
        return Vec::new();
    }
    let mut active = vec![true; n];
    let mut found: Vec<Deviation> = Vec::new();
    for _round in 0..20 {
        let flagged: Vec<usize> = scores(t, y, sigma, &active, threshold)
            .into_iter()
            .flatten()
            .map(|d| d.index)
            .collect();
        let mut confirmed = Vec::new();
        for &i in flagged.iter().take(500) {
            let mut alone = active.clone();
            for &j in &flagged {
                alone[j] = j == i;
            }
            if let Some(d) = scores(t, y, sigma, &alone, threshold)[i].take() {
                confirmed.push(d);
            }
        }
        if confirmed.is_empty() || found.len() + confirmed.len() > n / 4 {
            break;
        }
        for d in confirmed {
            active[d.index] = false;
            found.push(d);
        }
    }
    found.sort_by_key(|d| d.index);
    found
}

/// One pass of [`outliers`] over the `active` samples: the flagged ones, by index.
fn scores(
    t_all: &[f64],
    y_all: &[f64],
    sigma_all: &[f64],
    active: &[bool],
    threshold: f64,
) -> Vec<Option<Deviation>> {
    let mut out = vec![None; y_all.len()];
    let map: Vec<usize> = (0..y_all.len()).filter(|&i| active[i]).collect();
    let t: Vec<f64> = map.iter().map(|&i| t_all[i]).collect();
    let y: Vec<f64> = map.iter().map(|&i| y_all[i]).collect();
    let sigma: Vec<f64> = map.iter().map(|&i| sigma_all[i]).collect();
    let n = y.len();
    if n < 7 {
        return out;
    }
    let mut gaps: Vec<f64> = t
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .filter(|d| *d > 0.0)
        .collect();
    let unit = median(&mut gaps).unwrap_or(1.0);
    let mut segments = Vec::new();
    let mut start = 0;
    for i in 1..=n {
        if i == n || t[i] - t[i - 1] > 3.0 * unit {
            if i - start >= 7 {
                segments.push((start, i));
            }
            start = i;
        }
    }
    // (sample, segment, [B, L, R]); B counts as two-sided only with neighbours on both sides.
    let mut preds = Vec::new();
    for &(lo, hi) in &segments {
        for i in lo..hi {
            let mut p = predictions(&t, &y, (lo, hi), i, unit);
            if i == lo || i + 1 == hi {
                p[0] = None;
            }
            preds.push((i, p));
        }
    }
    let scatter: Vec<f64> = (0..3)
        .map(|k| {
            let normalised: Vec<f64> = preds
                .iter()
                .filter_map(|(i, p)| p[k].map(|(b, w2)| (y[*i] - b) / (1.0 + w2).sqrt()))
                .collect();
            clipped_scatter(&normalised)
        })
        .collect();
    let flagged = preds.iter().filter_map(|(i, p)| {
        let i = *i;
        let kind = (0..3).find(|&k| p[k].is_some())?;
        let (b, w2) = p[kind]?;
        let base = sigma[i].max(scatter[kind]);
        if base.is_nan() || base <= 0.0 {
            return None;
        }
        let s = base * (1.0 + w2).sqrt();
        let z = (y[i] - b) / s;
        let explained_by_one_side = p[1..]
            .iter()
            .flatten()
            .any(|&(bk, w2k)| ((y[i] - bk) / (base * (1.0 + w2k).sqrt())).abs() <= threshold);
        (z.abs() > threshold && !explained_by_one_side).then_some(Deviation {
            index: map[i],
            baseline: b,
            scale: s,
            z,
        })
    });
    for d in flagged {
        let i = d.index;
        out[i] = Some(d);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stats_of_a_known_series() {
        // 1, 2, 3, 4: mean 2.5, population rms about the mean √1.25, p-p 3.
        let s = Stats::of(&[1.0, 2.0, 3.0, 4.0], &[0.0, 0.2, 0.1, 0.3]);
        assert_eq!(s.n, 4);
        assert_eq!(s.mean, Some(2.5));
        assert!((s.rms.unwrap() - 1.25f64.sqrt()).abs() < 1e-15);
        assert_eq!(s.peak_to_peak, Some(3.0));
        // σ = 0 (a frame aligned to itself) does not count.
        assert_eq!(s.median_sigma, Some(0.2));
        let empty = Stats::of(&[], &[]);
        assert_eq!((empty.n, empty.rms), (0, None));
    }

    #[test]
    fn medians() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&mut []), None);
    }

    #[test]
    fn quadratic_predictions_are_exact_for_a_parabola() {
        // Uneven times; y = 2 − t + 0.5 t² is reproduced at every sample by every fit that
        // has enough points, interior and ends.
        let t = [0.0, 1.0, 2.5, 3.0, 4.0, 6.0, 7.0, 8.5, 9.0, 11.0];
        let y: Vec<f64> = t.iter().map(|t| 2.0 - t + 0.5 * t * t).collect();
        for i in 0..t.len() {
            let p = predictions(&t, &y, (0, t.len()), i, 1.0);
            assert!(p[0].is_some());
            for (b, w2) in p.iter().flatten() {
                assert!((b - y[i]).abs() < 1e-9, "{i}: {b} vs {}", y[i]);
                assert!(*w2 > 0.0);
            }
        }
        // Σw² of the symmetric interior fit (offsets ±1, ±2, ±3) is (XᵀX)⁻¹₀₀ = 0.5:
        // u=np.array([-3,-2,-1,1,2,3.]); X=np.c_[np.ones(6),u,u*u]; np.linalg.inv(X.T@X)[0,0]
        let t: Vec<f64> = (0..7).map(f64::from).collect();
        let y = vec![0.0; 7];
        let (_, w2) = predictions(&t, &y, (0, 7), 3, 1.0)[0].unwrap();
        assert!((w2 - 0.5).abs() < 1e-12, "{w2}");
    }

    #[test]
    fn clipped_scatter_ignores_a_wild_value() {
        // ±1 alternating (rms 1) plus one 100: the 100 is clipped, the rest kept.
        let mut r: Vec<f64> = (0..40)
            .map(|i| if i % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        r.push(100.0);
        assert!((clipped_scatter(&r) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn a_spike_is_an_outlier_but_clean_fast_jitter_is_not() {
        // A noise-free 0.3 px sinusoid of period 10 samples (strong, fast, real jitter) with
        // σ = 0.005, then with a 0.5 px glitch.
        let t: Vec<f64> = (0..80).map(|i| 12.0 * i as f64).collect();
        let mut y: Vec<f64> = t
            .iter()
            .map(|t| 0.3 * (2.0 * std::f64::consts::PI * t / 120.0).sin())
            .collect();
        let sigma = vec![0.005; y.len()];
        let clean = outliers(&t, &y, &sigma, 5.0);
        assert!(clean.is_empty(), "{clean:?}");
        y[17] += 0.5;
        let found = outliers(&t, &y, &sigma, 5.0);
        let idx: Vec<usize> = found.iter().map(|d| d.index).collect();
        assert_eq!(idx, [17], "{found:?}");
        // The baseline is near the clean value (a quadratic through 6 neighbours of a 10-sample
        // period sine misses its crest by ~0.05 px), and z is the deviation over the scale.
        let clean17 = 0.3 * (2.0 * std::f64::consts::PI * t[17] / 120.0).sin();
        assert!((found[0].baseline - clean17).abs() < 0.08);
        assert!((found[0].z - (y[17] - found[0].baseline) / found[0].scale).abs() < 1e-9);
    }

    #[test]
    fn glitches_at_the_ends_and_next_to_each_other_are_found() {
        // A slow sinusoid (period 40 samples) with a σ-sized deterministic wiggle; glitches at
        // the first sample, at the last, and two side by side in the middle.
        let t: Vec<f64> = (0..120).map(|i| 12.0 * i as f64).collect();
        let mut y: Vec<f64> = (0..120)
            .map(|i| {
                0.3 * (2.0 * std::f64::consts::PI * i as f64 / 40.0).sin()
                    + 0.005 * ((i * 37 % 11) as f64 - 5.0) / 5.0
            })
            .collect();
        let sigma = vec![0.005; y.len()];
        assert!(outliers(&t, &y, &sigma, 5.0).is_empty());
        y[0] += 0.3;
        y[119] -= 0.3;
        y[60] += 0.4;
        y[61] += 0.4;
        let idx: Vec<usize> = outliers(&t, &y, &sigma, 5.0)
            .iter()
            .map(|d| d.index)
            .collect();
        assert_eq!(idx, [0, 60, 61, 119]);
    }

    #[test]
    fn noise_within_sigma_gives_no_outliers_and_a_step_is_followed() {
        // Deterministic ±σ-sized wiggle with a 2 px step half way.
        let t: Vec<f64> = (0..100).map(|i| 12.0 * i as f64).collect();
        let y: Vec<f64> = (0..100)
            .map(|i| 0.01 * ((i * 37 % 11) as f64 - 5.0) / 5.0 + if i >= 50 { 2.0 } else { 0.0 })
            .collect();
        let sigma = vec![0.01; y.len()];
        let found = outliers(&t, &y, &sigma, 5.0);
        // Each side of the step agrees with its own side.
        assert!(found.is_empty(), "{found:?}");
    }
}
