//! Robust one-dimensional statistics for the inspected series (no I/O).

use serde::{Deserialize, Serialize};

pub use sunjitter_core::stats::median;

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
        let positive: Vec<f64> = sigmas.iter().copied().filter(|s| *s > 0.0).collect();
        let median_sigma = median(&positive);
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

/// Neighbours of sample `i` in the segment `lo..hi`: its 6 nearest (as balanced as the
/// segment's ends allow), the 6 before it, the 6 after it.
fn neighbour_sets(i: usize, (lo, hi): (usize, usize)) -> [Vec<usize>; 3] {
    let before = (i - lo)
        .min(NEIGHBOURS / 2)
        .max(NEIGHBOURS.saturating_sub(hi - 1 - i));
    let start = i.saturating_sub(before).max(lo);
    [
        (start..hi).filter(|&j| j != i).take(NEIGHBOURS).collect(),
        (i.saturating_sub(NEIGHBOURS).max(lo)..i).collect(),
        (i + 1..hi.min(i + 1 + NEIGHBOURS)).collect(),
    ]
}

/// Leave-one-out predictions of sample `i` of the segment `lo..hi` from each of its
/// [`neighbour_sets`]: (prediction, Σw²).
#[cfg(test)]
fn predictions(
    t: &[f64],
    y: &[f64],
    segment: (usize, usize),
    i: usize,
    unit: f64,
) -> [Option<(f64, f64)>; 3] {
    neighbour_sets(i, segment).map(|set| quadratic_at(t, y, &set, t[i], unit))
}

/// The prediction of sample `i` from `set` that one bad neighbour cannot spoil: of the fit
/// through all of `set` and the fits leaving out one member each, the one that agrees best
/// with `y[i]` relative to its own noise amplification. (prediction, Σw²).
fn robust_prediction(
    t: &[f64],
    y: &[f64],
    set: &[usize],
    i: usize,
    unit: f64,
) -> Option<(f64, f64)> {
    let full = quadratic_at(t, y, set, t[i], unit);
    let reduced = (0..set.len()).filter_map(|k| {
        let subset: Vec<usize> = set
            .iter()
            .enumerate()
            .filter(|(m, _)| *m != k)
            .map(|(_, &j)| j)
            .collect();
        quadratic_at(t, y, &subset, t[i], unit)
    });
    full.into_iter().chain(reduced).min_by(|a, b| {
        ((y[i] - a.0).abs() / (1.0 + a.1).sqrt())
            .total_cmp(&((y[i] - b.0).abs() / (1.0 + b.1).sqrt()))
    })
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
/// than 7 samples are not tested. Each sample is predicted, leaving it out, by quadratics in
/// time through 6 neighbours of its segment, which follow real jitter down to periods of a few
/// samples: the primary prediction uses its nearest neighbours on both sides (`B`; at a segment's
/// first or last sample only the 6 after (`R`) or before (`L`) exist), and is made robust to one
/// bad neighbour by also fitting with each neighbour left out and keeping the fit that agrees
/// best. A residual `r` normalised by `√(1 + Σw²)` (`w` the prediction's weights) has the
/// sample's σ under white noise. `S_B` is the 3σ-clipped RMS of the normalised residuals of plain
/// (all-neighbour) two-sided fits over the series, `S_L`, `S_R` those of plain one-sided fits at
/// every sample: the typical scatter, including jitter too fast to follow and the larger errors
/// of extrapolation.
/// Score: `z = r / (max(σ_i, S) · √(1 + Σw²))` with the primary's `S`; `σ_i ≤ 0` (unknown, or a
/// frame aligned to itself) uses `S` alone. A sample with `|z| > threshold` is an outlier unless
/// its plain one-sided prediction, on the same scale, is within the threshold: a step agrees with
/// its own side, a glitch with neither. Each round removes the flagged samples that are the worst
/// within ±3 samples and the test repeats on the rest (at most 50 rounds, at most a quarter of
/// the samples). Sensitivity is lower at segment ends, where only extrapolation exists.
pub fn outliers(t: &[f64], y: &[f64], sigma: &[f64], threshold: f64) -> Vec<Deviation> {
    let n = y.len();
    if n < 7 || t.len() != n || sigma.len() != n {
        return Vec::new();
    }
    let mut active: Vec<usize> = (0..n).collect();
    let mut found: Vec<Deviation> = Vec::new();
    for _round in 0..50 {
        let ta: Vec<f64> = active.iter().map(|&i| t[i]).collect();
        let ya: Vec<f64> = active.iter().map(|&i| y[i]).collect();
        let sa: Vec<f64> = active.iter().map(|&i| sigma[i]).collect();
        let all = one_pass(&ta, &ya, &sa, threshold);
        // Only the worst within ±3 samples: a neighbour flagged beside it is re-tested without it.
        let flagged: Vec<Deviation> = all
            .iter()
            .filter(|d| {
                all.iter()
                    .all(|o| o.index.abs_diff(d.index) > 3 || o.z.abs() <= d.z.abs())
            })
            .cloned()
            .collect();
        if flagged.is_empty() || found.len() + flagged.len() > n / 4 {
            break;
        }
        let removed: Vec<usize> = flagged.iter().map(|d| active[d.index]).collect();
        found.extend(flagged.into_iter().map(|d| Deviation {
            index: active[d.index],
            ..d
        }));
        active.retain(|i| !removed.contains(i));
    }
    found.sort_by_key(|d| d.index);
    found
}

/// One pass of [`outliers`] (indices into the given arrays).
fn one_pass(t: &[f64], y: &[f64], sigma: &[f64], threshold: f64) -> Vec<Deviation> {
    let n = y.len();
    let gaps: Vec<f64> = t
        .windows(2)
        .map(|w| (w[1] - w[0]).abs())
        .filter(|d| *d > 0.0)
        .collect();
    let unit = median(&gaps).unwrap_or(1.0);
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
    // Per sample: primary kind (0 = B, 1 = L, 2 = R), robust primary, plain B, L and R.
    struct Sample {
        i: usize,
        kind: usize,
        primary: Option<(f64, f64)>,
        plain: [Option<(f64, f64)>; 3],
    }
    let mut samples = Vec::new();
    for &seg in &segments {
        for i in seg.0..seg.1 {
            let sets = neighbour_sets(i, seg);
            let kind = if i == seg.0 {
                2
            } else if i + 1 == seg.1 {
                1
            } else {
                0
            };
            samples.push(Sample {
                i,
                kind,
                primary: robust_prediction(t, y, &sets[kind], i, unit),
                plain: sets.map(|set| quadratic_at(t, y, &set, t[i], unit)),
            });
        }
    }
    let normalised =
        |p: Option<(f64, f64)>, i: usize| p.map(|(b, w2)| (y[i] - b) / (1.0 + w2).sqrt());
    // Scatter of plain predictions (B only where it is two-sided): unbiased for clean data.
    let scatter = [0, 1, 2].map(|k| {
        let r: Vec<f64> = samples
            .iter()
            .filter(|s| k != 0 || s.kind == 0)
            .filter_map(|s| normalised(s.plain[k], s.i))
            .collect();
        clipped_scatter(&r)
    });
    samples
        .iter()
        .filter_map(|s| {
            let i = s.i;
            let (b, w2) = s.primary?;
            let base = sigma[i].max(scatter[s.kind]);
            if base.is_nan() || base <= 0.0 {
                return None;
            }
            let scale = base * (1.0 + w2).sqrt();
            let z = (y[i] - b) / scale;
            let explained_by_one_side = s.plain[1..]
                .iter()
                .flatten()
                .any(|&(bk, w2k)| ((y[i] - bk) / (base * (1.0 + w2k).sqrt())).abs() <= threshold);
            (z.abs() > threshold && !explained_by_one_side).then_some(Deviation {
                index: i,
                baseline: b,
                scale,
                z,
            })
        })
        .collect()
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
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&[]), None);
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
    fn finds_scattered_glitches_among_fast_jitter() {
        // 1200 samples of a 0.3 px sine (period 10 samples) with ±0.017 px uniform noise
        // (σ 0.01), and 1 px glitches at random 5 % of the samples, some side by side.
        let mut state = 7u64;
        let mut uniform = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let t: Vec<f64> = (0..1200).map(|i| 12.0 * i as f64).collect();
        let mut bad = vec![false; t.len()];
        let y: Vec<f64> = t
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let mut v = 0.3 * (2.0 * std::f64::consts::PI * t / 120.0).sin()
                    + 0.034 * (uniform() - 0.5);
                if uniform() < 0.05 {
                    v += 1.0;
                    bad[i] = true;
                }
                v
            })
            .collect();
        let found = outliers(&t, &y, &vec![0.01; t.len()], 5.0);
        let glitches = bad.iter().filter(|b| **b).count();
        let hits = found.iter().filter(|d| bad[d.index]).count();
        let false_alarms = found.len() - hits;
        assert!(
            hits as f64 >= 0.95 * glitches as f64,
            "{hits} of {glitches}"
        );
        assert!(
            false_alarms as f64 <= 0.1 * glitches as f64,
            "{false_alarms} false of {glitches}"
        );
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
