//! The figure's axes: UTC time ticks spaced so their labels never touch, 1-2-5 periods on a
//! log axis, and their labels.

/// Tick labels of a time axis: `YYYY-MM-DD HH:MM` on the first tick and wherever the UTC date
/// changes, `HH:MM` elsewhere (with seconds when ticks are less than a minute apart). An axis
/// within one UTC day (`one_day`) has its date in its title: `HH:MM` everywhere.
pub(super) fn time_labels(t0_ns: i64, ticks: &[f64], step: f64, one_day: bool) -> Vec<String> {
    let mut prev_day = None;
    ticks
        .iter()
        .map(|&x| {
            let iso = sunjitter_core::time::format_iso_utc(t0_ns + (x * 1e9).round() as i64);
            let clock = if step < 60.0 {
                &iso[11..19]
            } else {
                &iso[11..16]
            };
            let day = iso[..10].to_string();
            let dated = !one_day && prev_day.as_ref() != Some(&day);
            prev_day = Some(day);
            if dated {
                format!("{} {clock}", &iso[..10])
            } else {
                clock.to_string()
            }
        })
        .collect()
}

/// A human duration.
pub(super) fn duration(s: f64) -> String {
    if s < 120.0 {
        format!("{s:.0} s")
    } else if s < 7200.0 {
        format!("{:.1} min", s / 60.0)
    } else if s < 2.0 * 86_400.0 {
        format!("{:.1} h", s / 3600.0)
    } else {
        format!("{:.1} d", s / 86_400.0)
    }
}

/// An f64 axis (linear or log10) with the tick values we choose: round UTC clock times,
/// 1-2-5 periods (plotters' own f64 ticks are 1-2-5 multiples, e.g. 12:01:40).
#[derive(Debug, Clone)]
pub(super) struct TickedAxis {
    lo: f64,
    hi: f64,
    log: bool,
    ticks: Vec<f64>,
}

impl TickedAxis {
    pub(super) fn linear(lo: f64, hi: f64, ticks: Vec<f64>) -> Self {
        TickedAxis {
            lo,
            hi,
            log: false,
            ticks,
        }
    }

    pub(super) fn log(lo: f64, hi: f64, ticks: Vec<f64>) -> Self {
        TickedAxis {
            lo,
            hi,
            log: true,
            ticks,
        }
    }

    pub(super) fn to_unit(&self, v: f64) -> f64 {
        if self.log {
            (v.max(f64::MIN_POSITIVE).ln() - self.lo.ln()) / (self.hi.ln() - self.lo.ln())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        }
    }
}

impl plotters::coord::ranged1d::Ranged for TickedAxis {
    type FormatOption = plotters::coord::ranged1d::DefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let f = self.to_unit(*value);
        limit.0 + (f * (limit.1 - limit.0) as f64).round() as i32
    }

    fn key_points<Hint: plotters::coord::ranged1d::KeyPointHint>(&self, _hint: Hint) -> Vec<f64> {
        self.ticks.clone()
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.lo..self.hi
    }
}

/// Tick times (s from `t0_ns`) in `lo..=hi` on round UTC clock values, at most `max_ticks`;
/// also the step between them.
pub(super) fn time_ticks(t0_ns: i64, lo: f64, hi: f64, max_ticks: usize) -> (Vec<f64>, f64) {
    const STEPS: [f64; 24] = [
        1.0,
        2.0,
        5.0,
        10.0,
        15.0,
        30.0,
        60.0,
        120.0,
        300.0,
        600.0,
        900.0,
        1800.0,
        3600.0,
        7200.0,
        10800.0,
        21600.0,
        43200.0,
        86400.0,
        172_800.0,
        432_000.0,
        864_000.0,
        1_728_000.0,
        4_320_000.0,
        8_640_000.0,
    ];
    let span = hi - lo;
    let max_ticks = max_ticks.max(2) as f64;
    let step = STEPS
        .iter()
        .copied()
        .find(|s| span / s <= max_ticks)
        .unwrap_or(span / max_ticks);
    // First tick: the next multiple of `step` in absolute UTC seconds.
    let origin = t0_ns as f64 * 1e-9;
    let first = ((origin + lo) / step).ceil() * step - origin;
    let mut ticks: Vec<f64> = (0..)
        .map(|k| first + k as f64 * step)
        .take_while(|t| *t <= hi)
        .collect();
    if ticks.is_empty() {
        ticks.push(0.5 * (lo + hi));
    }
    (ticks, step)
}

/// A tick value with as many decimals as the axis range needs, and no "-0".
pub(super) fn tick_label(v: f64, range: f64) -> String {
    // About five ticks: one decimal more than the tick step's leading digit needs.
    let step = (range.abs() / 5.0).max(1e-12);
    let decimals = (-step.log10().floor()).clamp(0.0, 8.0) as usize;
    let s = format!("{v:.decimals$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        s.trim_start_matches('-').to_string()
    } else {
        s
    }
}

/// 1-2-5 ticks between two periods.
pub(super) fn period_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut decade = 10f64.powf(lo.max(1e-9).log10().floor());
    while decade <= hi {
        for m in [1.0, 2.0, 5.0] {
            let v = m * decade;
            if v >= lo && v <= hi {
                out.push(v);
            }
        }
        decade *= 10.0;
    }
    out
}
