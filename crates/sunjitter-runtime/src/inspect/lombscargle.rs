//! Generalised (floating-mean) Lomb–Scargle periodogram for unevenly sampled series
//! (Zechmeister & Kürster 2009), unweighted, in astropy's `standard` normalisation: the power
//! at `f` is the fraction of the variance about the mean that a sinusoid of frequency `f`
//! (with a free offset) explains, `1 − χ²(f)/χ²₀`, in [0, 1].
//!
//! Frequency grid: from `1/T` (T = time span) to the pseudo-Nyquist `1/(2·median Δt)`, in
//! steps of `1/(oversampling·T)`. The resolution — one frequency bin — is `1/T`; a peak is
//! located to better than a bin by parabolic refinement on the grid.

/// The frequencies a periodogram is evaluated at.
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyGrid {
    pub min_hz: f64,
    pub step_hz: f64,
    pub count: usize,
    /// Time span `T` of the samples, seconds.
    pub span_s: f64,
    /// Grid points per resolution bin `1/T`.
    pub oversampling: f64,
}

impl FrequencyGrid {
    /// `None` when there are fewer than 5 samples or no span; `max_count` caps the grid
    /// (the oversampling is lowered to fit, never below 1).
    pub fn for_times(t: &[f64], oversampling: f64, max_count: usize) -> Option<Self> {
        if t.len() < 5 {
            return None;
        }
        let span = t.last()? - t.first()?;
        let gaps: Vec<f64> = t
            .windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| *d > 0.0)
            .collect();
        if span.is_nan() || span <= 0.0 || gaps.is_empty() {
            return None;
        }
        let nyquist = 0.5 / super::stats::median(&gaps)?;
        let min_hz = 1.0 / span;
        if nyquist <= min_hz {
            return None;
        }
        let mut oversampling = oversampling.max(1.0);
        let bins = (nyquist - min_hz) * span;
        if bins * oversampling > max_count as f64 {
            oversampling = (max_count as f64 / bins).max(1.0);
        }
        let step_hz = 1.0 / (oversampling * span);
        let count = ((nyquist - min_hz) / step_hz).floor() as usize + 1;
        Some(FrequencyGrid {
            min_hz,
            step_hz,
            count,
            span_s: span,
            oversampling,
        })
    }

    pub fn frequency(&self, i: usize) -> f64 {
        self.min_hz + i as f64 * self.step_hz
    }

    pub fn max_hz(&self) -> f64 {
        self.frequency(self.count.saturating_sub(1))
    }

    /// One frequency bin, `1/T`.
    pub fn resolution_hz(&self) -> f64 {
        1.0 / self.span_s
    }
}

/// Sums of one frequency shared by every series on the same times.
struct TrigSums {
    c: f64,
    s: f64,
    cc: f64,
    ss: f64,
    cs: f64,
}

fn power_from(t: &TrigSums, yc: f64, ys: f64, yy: f64) -> f64 {
    let cc = t.cc - t.c * t.c;
    let ss = t.ss - t.s * t.s;
    let cs = t.cs - t.c * t.s;
    let d = cc * ss - cs * cs;
    if yy <= 0.0 || d <= 1e-12 * (cc * ss).max(f64::MIN_POSITIVE) {
        // Constant series, or a frequency where the sampling cannot tell sine from cosine.
        return 0.0;
    }
    ((ss * yc * yc + cc * ys * ys - 2.0 * cs * yc * ys) / (yy * d)).clamp(0.0, 1.0)
}

/// Centre `y` and return (centred, mean square).
fn centred(y: &[f64]) -> (Vec<f64>, f64) {
    let n = y.len() as f64;
    let mean = y.iter().sum::<f64>() / n;
    let c: Vec<f64> = y.iter().map(|v| v - mean).collect();
    let yy = c.iter().map(|v| v * v).sum::<f64>() / n;
    (c, yy)
}

/// The power of `y(t)` at one frequency (direct evaluation).
pub fn power_at(t: &[f64], y: &[f64], f_hz: f64) -> f64 {
    let n = t.len() as f64;
    let (y, yy) = centred(y);
    let w = 2.0 * std::f64::consts::PI * f_hz;
    let mut sums = TrigSums {
        c: 0.0,
        s: 0.0,
        cc: 0.0,
        ss: 0.0,
        cs: 0.0,
    };
    let (mut yc, mut ys) = (0.0, 0.0);
    for (&ti, &yi) in t.iter().zip(&y) {
        let (s, c) = (w * ti).sin_cos();
        sums.c += c;
        sums.s += s;
        sums.cc += c * c;
        sums.ss += s * s;
        sums.cs += c * s;
        yc += yi * c;
        ys += yi * s;
    }
    for v in [
        &mut sums.c,
        &mut sums.s,
        &mut sums.cc,
        &mut sums.ss,
        &mut sums.cs,
    ] {
        *v /= n;
    }
    power_from(&sums, yc / n, ys / n, yy)
}

/// Powers of several series sampled at the same times `t`, on `grid`.
/// Trigonometric terms advance by rotation from one frequency to the next (exactly
/// re-evaluated every 256 steps), so the cost is a few multiplications per sample and frequency.
pub fn periodogram(t: &[f64], series: &[&[f64]], grid: &FrequencyGrid) -> Vec<Vec<f64>> {
    let n = t.len();
    let nf = n as f64;
    let two_pi = 2.0 * std::f64::consts::PI;
    // Times about their middle keep the phases small.
    let mid = 0.5 * (t[0] + t[n - 1]);
    let tc: Vec<f64> = t.iter().map(|v| v - mid).collect();
    let ys: Vec<(Vec<f64>, f64)> = series.iter().map(|y| centred(y)).collect();
    let step: Vec<(f64, f64)> = tc
        .iter()
        .map(|&ti| (two_pi * grid.step_hz * ti).sin_cos())
        .collect();
    let mut rot: Vec<(f64, f64)> = vec![(0.0, 1.0); n];
    let mut out = vec![Vec::with_capacity(grid.count); series.len()];
    let mut yc = vec![0.0; series.len()];
    let mut ysn = vec![0.0; series.len()];
    for j in 0..grid.count {
        if j % 256 == 0 {
            let w = two_pi * grid.frequency(j);
            for (r, &ti) in rot.iter_mut().zip(&tc) {
                *r = (w * ti).sin_cos();
            }
        }
        let mut sums = TrigSums {
            c: 0.0,
            s: 0.0,
            cc: 0.0,
            ss: 0.0,
            cs: 0.0,
        };
        yc.iter_mut().for_each(|v| *v = 0.0);
        ysn.iter_mut().for_each(|v| *v = 0.0);
        for (i, &(s, c)) in rot.iter().enumerate() {
            sums.c += c;
            sums.s += s;
            sums.cc += c * c;
            sums.ss += s * s;
            sums.cs += c * s;
            for (k, (y, _)) in ys.iter().enumerate() {
                yc[k] += y[i] * c;
                ysn[k] += y[i] * s;
            }
        }
        for v in [
            &mut sums.c,
            &mut sums.s,
            &mut sums.cc,
            &mut sums.ss,
            &mut sums.cs,
        ] {
            *v /= nf;
        }
        for (k, (_, yy)) in ys.iter().enumerate() {
            out[k].push(power_from(&sums, yc[k] / nf, ysn[k] / nf, *yy));
        }
        for (r, &(ds, dc)) in rot.iter_mut().zip(&step) {
            let (s, c) = *r;
            *r = (s * dc + c * ds, c * dc - s * ds);
        }
    }
    out
}

/// A periodogram peak.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Peak {
    pub period_s: f64,
    pub frequency_hz: f64,
    pub power: f64,
    /// Baluev (2008) false-alarm probability of a peak this high anywhere on the grid,
    /// for white noise (astropy's `method='baluev'`).
    pub false_alarm_probability: f64,
}

/// The strongest `max_peaks` local maxima of `power` (ends included), each at least one
/// resolution bin from a stronger one, refined by a parabola through the grid points.
pub fn peaks(
    t: &[f64],
    y: &[f64],
    grid: &FrequencyGrid,
    power: &[f64],
    max_peaks: usize,
) -> Vec<Peak> {
    select_peaks(t, y, grid, power, max_peaks, None)
}

/// [`peaks`] among the maxima at `min_hz` or above (on the grid and once refined) that are
/// maxima on both sides: a rise towards the grid's end is power leaking from lower
/// frequencies (a trend), not a period.
pub fn resolved_peaks(
    t: &[f64],
    y: &[f64],
    grid: &FrequencyGrid,
    power: &[f64],
    max_peaks: usize,
    min_hz: f64,
) -> Vec<Peak> {
    select_peaks(t, y, grid, power, max_peaks, Some(min_hz))
}

fn select_peaks(
    t: &[f64],
    y: &[f64],
    grid: &FrequencyGrid,
    power: &[f64],
    max_peaks: usize,
    interior_from_hz: Option<f64>,
) -> Vec<Peak> {
    let n = power.len();
    let mut candidates: Vec<usize> = (0..n)
        .filter(|&j| {
            if let Some(min_hz) = interior_from_hz {
                if j == 0 || j + 1 == n || grid.frequency(j) < min_hz {
                    return false;
                }
            }
            let left = j == 0 || power[j] > power[j - 1];
            let right = j + 1 == n || power[j] >= power[j + 1];
            left && right && power[j] > 0.0
        })
        .collect();
    candidates.sort_by(|&a, &b| power[b].total_cmp(&power[a]));
    let mut chosen: Vec<Peak> = Vec::new();
    for j in candidates {
        if chosen.len() >= max_peaks {
            break;
        }
        let mut f = grid.frequency(j);
        let mut p = power[j];
        if j > 0 && j + 1 < n {
            let (a, b, c) = (power[j - 1], power[j], power[j + 1]);
            let denom = a - 2.0 * b + c;
            if denom < 0.0 {
                let delta = (0.5 * (a - c) / denom).clamp(-0.5, 0.5);
                let f_ref = f + delta * grid.step_hz;
                let p_ref = power_at(t, y, f_ref);
                if p_ref >= p {
                    f = f_ref;
                    p = p_ref;
                }
            }
        }
        // Refined below the lowest frequency allowed: not a period the span holds that often.
        if interior_from_hz.is_some_and(|min_hz| f < min_hz)
            || chosen
                .iter()
                .any(|c| (c.frequency_hz - f).abs() < grid.resolution_hz())
        {
            continue;
        }
        chosen.push(Peak {
            period_s: 1.0 / f,
            frequency_hz: f,
            power: p,
            false_alarm_probability: false_alarm_baluev(p, grid.max_hz(), t),
        });
    }
    chosen
}

/// Baluev (2008) false-alarm probability for `standard` power `z` on a grid up to `f_max`,
/// as astropy computes it (`_statistics.fap_baluev`, unweighted).
pub fn false_alarm_baluev(z: f64, f_max: f64, t: &[f64]) -> f64 {
    let n = t.len() as f64;
    if n < 5.0 || !(0.0..1.0).contains(&z) {
        return if z >= 1.0 { 0.0 } else { 1.0 };
    }
    let (nh, nk) = (n - 1.0, n - 3.0);
    let mean = t.iter().sum::<f64>() / n;
    let var_t = t.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let w = f_max * (4.0 * std::f64::consts::PI * var_t).sqrt();
    let gamma = (2.0 / nh).sqrt() * (ln_gamma(nh / 2.0) - ln_gamma((nh - 1.0) / 2.0)).exp();
    let fap_single = (1.0 - z).powf(0.5 * nk);
    let tau = gamma * w * (1.0 - z).powf(0.5 * (nk - 1.0)) * (0.5 * nh * z).sqrt();
    (-(-tau).exp_m1() + fap_single * (-tau).exp()).clamp(0.0, 1.0)
}

/// ln Γ(x) for x > 0 (Lanczos, g = 7; relative error ~1e-15).
fn ln_gamma(x: f64) -> f64 {
    const G: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection.
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = G[0];
    let t = x + 7.5;
    for (i, g) in G.iter().enumerate().skip(1) {
        a += g / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uneven times with gaps: 12 s cadence ±2 s wobble, frames 20–27 and 55–59 missing.
    fn sample() -> (Vec<f64>, Vec<f64>) {
        let mut t = Vec::new();
        let mut y = Vec::new();
        for i in 0..100 {
            if (20..28).contains(&i) || (55..60).contains(&i) {
                continue;
            }
            let fi = i as f64;
            let ti = 12.0 * fi + 2.0 * (0.7 * fi).sin();
            t.push(ti);
            y.push(
                0.3 * (2.0 * std::f64::consts::PI * ti / 120.0).sin() + 0.1 * (1.3 * fi * fi).sin(),
            );
        }
        (t, y)
    }

    #[test]
    fn agrees_with_astropy_standard_power() {
        // python3 -c "
        // import numpy as np; from astropy.timeseries import LombScargle
        // i=np.array([k for k in range(100) if not (20<=k<28 or 55<=k<60)],float)
        // t=12*i+2*np.sin(0.7*i); y=0.3*np.sin(2*np.pi*t/120)+0.1*np.sin(1.3*i*i)
        // ls=LombScargle(t,y); print(ls.power([1/120,1/300,0.02,0.035]))
        // from astropy.timeseries.periodograms.lombscargle._statistics import fap_baluev
        // print(fap_baluev(np.array([0.15,0.3]),1/24,t-t.min(),y,None))"
        // → [0.8987888680630307, 0.04338071771963879, 0.00702745160820943, 0.00297743359948337]
        //   [1.45784691e-01, 7.04023457e-05]
        // (fap_baluev is what LombScargle.false_alarm_probability(method='baluev') calls, with
        // f_max the top of its own grid; here f_max = 1/24 Hz exactly.)
        let (t, y) = sample();
        let want = [
            (1.0 / 120.0, ASTROPY_POWER[0]),
            (1.0 / 300.0, ASTROPY_POWER[1]),
            (0.02, ASTROPY_POWER[2]),
            (0.035, ASTROPY_POWER[3]),
        ];
        for (f, p) in want {
            let got = power_at(&t, &y, f);
            assert!((got - p).abs() < 1e-9, "f = {f}: {got} vs astropy {p}");
        }
        for (z, want) in [(0.15, 1.457_846_91e-1), (0.3, 7.040_234_57e-5)] {
            let fap = false_alarm_baluev(z, 1.0 / 24.0, &t);
            assert!(
                (fap / want - 1.0).abs() < 1e-6,
                "z = {z}: {fap} vs astropy {want}"
            );
        }
    }

    const ASTROPY_POWER: [f64; 4] = [
        0.898_788_868_063_030_7,
        0.043_380_717_719_638_79,
        0.007_027_451_608_209_43,
        0.002_977_433_599_483_37,
    ];

    #[test]
    fn grid_recurrence_matches_direct_evaluation() {
        let (t, y) = sample();
        // Oversampled 10× so the grid crosses the every-256-steps re-evaluation.
        let grid = FrequencyGrid::for_times(&t, 10.0, 100_000).unwrap();
        let p = periodogram(&t, &[&y], &grid);
        assert!(grid.count > 300, "{}", grid.count);
        for j in [0, 1, 255, 256, 300, grid.count - 1] {
            let direct = power_at(&t, &y, grid.frequency(j));
            assert!((p[0][j] - direct).abs() < 1e-9, "bin {j}");
        }
    }

    #[test]
    fn recovers_injected_period_within_one_bin_despite_gaps() {
        let (t, y) = sample();
        let grid = FrequencyGrid::for_times(&t, 5.0, 100_000).unwrap();
        // Span ≈ 1188 s; median Δt = 12 s gives the pseudo-Nyquist 1/24 Hz.
        assert!((grid.max_hz() - 1.0 / 24.0).abs() <= grid.step_hz);
        let power = periodogram(&t, &[&y], &grid);
        let found = peaks(&t, &y, &grid, &power[0], 3);
        assert!((found[0].frequency_hz - 1.0 / 120.0).abs() < grid.resolution_hz());
        assert!(found[0].false_alarm_probability < 1e-6);
        // Peaks are at least one bin apart.
        for w in found.windows(2) {
            assert!((w[0].frequency_hz - w[1].frequency_hz).abs() >= grid.resolution_hz());
        }
    }

    #[test]
    fn ln_gamma_matches_factorials() {
        // Γ(n) = (n−1)!; Γ(1/2) = √π.
        assert!((ln_gamma(10.0) - 362_880f64.ln()).abs() < 1e-12);
        assert!((ln_gamma(0.5) - std::f64::consts::PI.sqrt().ln()).abs() < 1e-12);
        // scipy.special.gammaln(50.5) = 146.51925549072064
        assert!((ln_gamma(50.5) - 146.519_255_490_720_64).abs() < 1e-9);
    }

    #[test]
    fn too_few_samples_give_no_grid() {
        assert!(FrequencyGrid::for_times(&[0.0, 1.0, 2.0, 3.0], 5.0, 1000).is_none());
        assert!(FrequencyGrid::for_times(&[5.0; 8], 5.0, 1000).is_none());
    }
}
