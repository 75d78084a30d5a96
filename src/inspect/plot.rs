//! `inspect --plot OUT.png|OUT.svg`: one figure read at a glance. Four stacked panels of the
//! pointing series against UTC time — dx, dy (px), rotation (″), scale (ppm from 1) — each with
//! its ±1σ band, degraded frames ringed in orange, failed frames as red crosses along the panel
//! floor, outliers as black triangles; below, the Lomb–Scargle periodogram (power against period,
//! dx solid, dy dashed) with the strongest period labelled. Text uses the embedded DejaVu Sans,
//! so no system font is needed.

use super::{ChannelAnalysis, Param, PARAMS};
use crate::record::Status;
use crate::{Error, Result};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::Path;

static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";
const WIDTH: u32 = 1600;
const HEIGHT: u32 = 1500;

const CHANNEL_COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(23, 190, 207),
    RGBColor(127, 127, 127),
];
const DEGRADED: RGBColor = RGBColor(255, 127, 14);
const FAILED: RGBColor = RGBColor(214, 39, 40);

fn register_font() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        if register_font_bytes().is_err() {
            tracing::warn!("embedded font could not be registered; plot text may be missing");
        }
    });
}

fn register_font_bytes() -> std::result::Result<(), ()> {
    plotters::style::register_font(FAMILY, FontStyle::Normal, FONT).map_err(|_| ())
}

/// Draw the figure to `path`; the extension (`.png` or `.svg`) picks the format.
pub fn write_plot(analyses: &[ChannelAnalysis], path: &Path) -> Result<()> {
    register_font();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let fail = |e: String| Error::output(path, e);
    match ext.as_deref() {
        Some("png") => {
            let root = BitMapBackend::new(path, (WIDTH, HEIGHT)).into_drawing_area();
            draw(&root, analyses).map_err(fail)?;
            root.present().map_err(|e| fail(e.to_string()))
        }
        Some("svg") => {
            let root = SVGBackend::new(path, (WIDTH, HEIGHT)).into_drawing_area();
            draw(&root, analyses).map_err(fail)?;
            root.present().map_err(|e| fail(e.to_string()))
        }
        _ => Err(Error::Usage(format!(
            "--plot {}: the file name must end in .png or .svg",
            path.display()
        ))),
    }
}

/// One plotted sample: time (s from the figure's origin), value, σ, status, outlier flag.
struct Sample {
    t: f64,
    v: f64,
    sigma: f64,
    status: Status,
    outlier: bool,
}

fn to_plot_units(p: Param, v: f64) -> f64 {
    match p {
        Param::Scale => (v - 1.0) * 1e6,
        _ => v,
    }
}

fn sigma_units(p: Param, s: f64) -> f64 {
    match p {
        Param::Scale => s * 1e6,
        _ => s,
    }
}

fn label(p: Param) -> &'static str {
    match p {
        Param::Dx => "dx [px]",
        Param::Dy => "dy [px]",
        Param::Rotation => "rotation [arcsec]",
        Param::Scale => "scale - 1 [ppm]",
    }
}

fn samples(a: &ChannelAnalysis, p: Param, t0: i64) -> (Vec<Sample>, Vec<f64>) {
    let kind = a.report.series;
    let mut out = Vec::new();
    let mut failed = Vec::new();
    for f in &a.frames {
        let t = (f.log_time_ns - t0) as f64 * 1e-9;
        let (v, s) = p.get(&f.record, kind);
        match v.filter(|x| x.is_finite()) {
            Some(v) => out.push(Sample {
                t,
                v: to_plot_units(p, v),
                sigma: sigma_units(p, s.filter(|x| x.is_finite()).unwrap_or(0.0)),
                status: f.record.align.status,
                outlier: a.report.outliers.iter().any(|o| {
                    o.sequence == f.record.sequence
                        && o.log_time_ns == f.log_time_ns
                        && o.parameter == p.name()
                }),
            }),
            None => failed.push(t),
        }
    }
    (out, failed)
}

/// Split at failed frames and at gaps longer than 2.5 cadences, so lines and bands do not
/// bridge missing data.
fn runs(s: &[Sample], failed: &[f64], cadence: f64) -> Vec<std::ops::Range<usize>> {
    let mut out = Vec::new();
    let mut start = 0;
    for i in 1..=s.len() {
        let broken = i == s.len()
            || s[i].t - s[i - 1].t > 2.5 * cadence
            || failed.iter().any(|&t| t > s[i - 1].t && t < s[i].t);
        if broken {
            out.push(start..i);
            start = i;
        }
    }
    out
}

fn hhmmss(t0_ns: i64, x: f64, with_date: bool) -> String {
    let iso = crate::time::format_iso_utc(t0_ns + (x * 1e9).round() as i64);
    // YYYY-MM-DDTHH:MM:SS.sss
    if with_date {
        format!("{} {}", &iso[5..10], &iso[11..16])
    } else {
        iso[11..19].to_string()
    }
}

/// An f64 axis (linear or log10) with the tick values we choose: round UTC clock times,
/// 1-2-5 periods (plotters' own f64 ticks are 1-2-5 multiples, e.g. 12:01:40).
struct TickedAxis {
    lo: f64,
    hi: f64,
    log: bool,
    ticks: Vec<f64>,
}

impl TickedAxis {
    fn linear(lo: f64, hi: f64, ticks: Vec<f64>) -> Self {
        TickedAxis {
            lo,
            hi,
            log: false,
            ticks,
        }
    }

    fn log(lo: f64, hi: f64, ticks: Vec<f64>) -> Self {
        TickedAxis {
            lo,
            hi,
            log: true,
            ticks,
        }
    }

    fn to_unit(&self, v: f64) -> f64 {
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

/// Tick times (s from `t0_ns`) on round UTC clock values, at most about 10 of them.
fn time_ticks(t0_ns: i64, span: f64) -> Vec<f64> {
    const STEPS: [f64; 19] = [
        1.0, 2.0, 5.0, 10.0, 15.0, 30.0, 60.0, 120.0, 300.0, 600.0, 900.0, 1800.0, 3600.0, 7200.0,
        10800.0, 21600.0, 43200.0, 86400.0, 172_800.0,
    ];
    let step = STEPS
        .iter()
        .copied()
        .find(|s| span / s <= 10.0)
        .unwrap_or(span / 10.0);
    // First tick: the next multiple of `step` in absolute UTC seconds.
    let t0 = t0_ns as f64 * 1e-9;
    let first = (t0 / step).ceil() * step - t0;
    (0..)
        .map(|k| first + k as f64 * step)
        .take_while(|t| *t <= span)
        .collect()
}

/// A tick value with as many decimals as the axis range needs, and no "-0".
fn tick_label(v: f64, range: f64) -> String {
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
fn period_ticks(lo: f64, hi: f64) -> Vec<f64> {
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

type DrawResult = std::result::Result<(), String>;
/// Frequencies and the powers of each parameter.
type Spectrum = (Vec<f64>, Vec<Vec<f64>>);

fn draw<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    analyses: &[ChannelAnalysis],
) -> DrawResult
where
    DB::ErrorType: 'static,
{
    let e = |err: DrawingAreaErrorKind<DB::ErrorType>| err.to_string();
    root.fill(&WHITE).map_err(e)?;
    let t0 = analyses
        .iter()
        .filter_map(|a| a.frames.first())
        .map(|f| f.log_time_ns)
        .min();
    let t_end = analyses
        .iter()
        .filter_map(|a| a.frames.last())
        .map(|f| f.log_time_ns)
        .max();
    let (Some(t0), Some(t_end)) = (t0, t_end) else {
        root.draw(&Text::new("no /jitter messages", (40, 40), (FAMILY, 32)))
            .map_err(e)?;
        return Ok(());
    };
    let span = ((t_end - t0) as f64 * 1e-9).max(1.0);
    let with_date = span > 86_400.0;
    let series_names: Vec<String> = analyses
        .iter()
        .map(|a| {
            format!(
                "{} ({})",
                a.report.channel,
                if a.report.series == super::SeriesKind::Chained {
                    "chained"
                } else {
                    "raw"
                }
            )
        })
        .collect();
    let title = format!(
        "sunjitter inspect: {} from {} UTC, {:.0} s",
        series_names.join(", "),
        &crate::time::format_iso_utc(t0)[..19].replace('T', " "),
        span
    );
    let body = root.titled(&title, (FAMILY, 30)).map_err(e)?;
    let (series_area, spectrum_area) = body.split_vertically(HEIGHT as i32 * 66 / 100);
    let panels = series_area.split_evenly((4, 1));
    let x_pad = span * 0.01;
    let date = crate::time::format_iso_utc(t0)[..10].to_string();
    for (k, (panel, p)) in panels.iter().zip(PARAMS).enumerate() {
        let per_channel: Vec<(Vec<Sample>, Vec<f64>)> =
            analyses.iter().map(|a| samples(a, p, t0)).collect();
        let (lo, hi) = y_range(per_channel.iter().flat_map(|(s, _)| s.iter()));
        let mut chart = ChartBuilder::on(panel)
            .margin_left(10)
            .margin_right(30)
            .margin_top(8)
            .x_label_area_size(if k == 3 { 56 } else { 28 })
            .y_label_area_size(95)
            .build_cartesian_2d(
                TickedAxis::linear(-x_pad, span + x_pad, time_ticks(t0, span)),
                lo..hi,
            )
            .map_err(e)?;
        let fmt_x = |x: &f64| hhmmss(t0, *x, with_date);
        let fmt_y = |y: &f64| tick_label(*y, hi - lo);
        let mut mesh = chart.configure_mesh();
        mesh.y_labels(5)
            .x_label_formatter(&fmt_x)
            .y_label_formatter(&fmt_y)
            .y_desc(label(p))
            .label_style((FAMILY, 18))
            .axis_desc_style((FAMILY, 20))
            .light_line_style(RGBColor(235, 235, 235));
        if k == 3 {
            mesh.x_desc(format!("UTC time ({date})"));
        }
        mesh.draw().map_err(e)?;
        let floor = lo + 0.04 * (hi - lo);
        let mut any_degraded = false;
        let mut any_failed = false;
        let mut any_outlier = false;
        for (ci, ((s, failed), a)) in per_channel.iter().zip(analyses).enumerate() {
            let colour = CHANNEL_COLOURS[ci % CHANNEL_COLOURS.len()];
            let cadence = a.report.median_cadence_s.unwrap_or(span);
            for r in runs(s, failed, cadence) {
                let run = &s[r];
                if run.iter().any(|x| x.sigma > 0.0) {
                    let band: Vec<(f64, f64)> = run
                        .iter()
                        .map(|x| (x.t, x.v + x.sigma))
                        .chain(run.iter().rev().map(|x| (x.t, x.v - x.sigma)))
                        .collect();
                    chart
                        .draw_series(std::iter::once(Polygon::new(
                            band,
                            colour.mix(0.22).filled(),
                        )))
                        .map_err(e)?;
                }
                let line = chart
                    .draw_series(LineSeries::new(
                        run.iter().map(|x| (x.t, x.v)),
                        colour.stroke_width(2),
                    ))
                    .map_err(e)?;
                if k == 0 && run.as_ptr() == s.as_ptr() {
                    line.label(a.report.channel.clone()).legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
                    });
                }
            }
            chart
                .draw_series(
                    s.iter()
                        .map(|x| Circle::new((x.t, x.v), 2, colour.filled())),
                )
                .map_err(e)?;
            let degraded: Vec<&Sample> =
                s.iter().filter(|x| x.status == Status::Degraded).collect();
            any_degraded |= !degraded.is_empty();
            chart
                .draw_series(
                    degraded
                        .iter()
                        .map(|x| Circle::new((x.t, x.v), 7, DEGRADED.stroke_width(3))),
                )
                .map_err(e)?;
            any_failed |= !failed.is_empty();
            chart
                .draw_series(
                    failed
                        .iter()
                        .map(|&t| Cross::new((t, floor), 7, FAILED.stroke_width(3))),
                )
                .map_err(e)?;
            let outl: Vec<&Sample> = s.iter().filter(|x| x.outlier).collect();
            any_outlier |= !outl.is_empty();
            chart
                .draw_series(
                    outl.iter()
                        .map(|x| TriangleMarker::new((x.t, x.v), 9, BLACK.filled())),
                )
                .map_err(e)?;
        }
        if k == 0 {
            // Legend entries for the markers (the series themselves draw nothing).
            let off = (0.0, lo);
            if any_degraded {
                chart
                    .draw_series(std::iter::once(EmptyElement::at(off)))
                    .map_err(e)?
                    .label("degraded")
                    .legend(|(x, y)| Circle::new((x + 12, y), 6, DEGRADED.stroke_width(3)));
            }
            if any_failed {
                chart
                    .draw_series(std::iter::once(EmptyElement::at(off)))
                    .map_err(e)?
                    .label("failed")
                    .legend(|(x, y)| Cross::new((x + 12, y), 6, FAILED.stroke_width(3)));
            }
            if any_outlier {
                chart
                    .draw_series(std::iter::once(EmptyElement::at(off)))
                    .map_err(e)?
                    .label("outlier > 5σ")
                    .legend(|(x, y)| TriangleMarker::new((x + 12, y), 8, BLACK.filled()));
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperRight)
                .label_font((FAMILY, 18))
                .background_style(WHITE.mix(0.85))
                .border_style(RGBColor(180, 180, 180))
                .draw()
                .map_err(e)?;
        }
    }
    draw_spectrum(&spectrum_area, analyses).map_err(e)
}

/// Value range with room for the ±σ bands (σ capped at 3× the median so one wild σ does not
/// flatten the rest), padded by 8 %.
fn y_range<'a>(samples: impl Iterator<Item = &'a Sample>) -> (f64, f64) {
    let s: Vec<&Sample> = samples.collect();
    let mut sig: Vec<f64> = s.iter().map(|x| x.sigma).filter(|v| *v > 0.0).collect();
    let cap = 3.0 * super::stats::median(&mut sig).unwrap_or(0.0);
    let lo = s
        .iter()
        .map(|x| x.v - x.sigma.min(cap))
        .fold(f64::INFINITY, f64::min);
    let hi = s
        .iter()
        .map(|x| x.v + x.sigma.min(cap))
        .fold(f64::NEG_INFINITY, f64::max);
    if !(lo.is_finite() && hi.is_finite()) {
        return (-1.0, 1.0);
    }
    let pad = ((hi - lo) * 0.08)
        .max(1e-9 * hi.abs().max(1.0))
        .max(if hi > lo { 0.0 } else { 0.5 });
    (lo - pad, hi + pad)
}

fn draw_spectrum<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    analyses: &[ChannelAnalysis],
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB::ErrorType: 'static,
{
    let with_spectrum: Vec<(usize, &ChannelAnalysis, &Spectrum)> = analyses
        .iter()
        .enumerate()
        .filter_map(|(i, a)| a.spectrum.as_ref().map(|s| (i, a, s)))
        .collect();
    let area = area.margin(10, 0, 0, 0);
    if with_spectrum.is_empty() {
        area.draw(&Text::new(
            "periodogram: too few samples",
            (140, 60),
            (FAMILY, 24),
        ))?;
        return Ok(());
    }
    let f_max = with_spectrum
        .iter()
        .filter_map(|(_, _, s)| s.0.last())
        .fold(0.0f64, |a, b| a.max(*b));
    let f_min = with_spectrum
        .iter()
        .filter_map(|(_, _, s)| s.0.first())
        .fold(f64::INFINITY, |a, b| a.min(*b));
    let (p_lo, p_hi) = (1.0 / f_max, 1.0 / f_min);
    let mut chart = ChartBuilder::on(&area)
        .margin_left(10)
        .margin_right(30)
        .margin_top(10)
        .x_label_area_size(56)
        .y_label_area_size(95)
        .caption(
            "Lomb-Scargle periodogram (dx solid, dy dashed; straight-line trend removed)",
            (FAMILY, 22),
        )
        .build_cartesian_2d(
            TickedAxis::log(
                p_lo * 0.95,
                p_hi * 1.05,
                period_ticks(p_lo * 0.95, p_hi * 1.05),
            ),
            0.0..1.05,
        )?;
    chart
        .configure_mesh()
        .x_desc("period [s]")
        .y_desc("power (fraction of variance)")
        .x_label_formatter(&|v: &f64| format!("{v:.0}"))
        .label_style((FAMILY, 18))
        .axis_desc_style((FAMILY, 20))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (ci, a, (freqs, power)) in with_spectrum {
        let colour = CHANNEL_COLOURS[ci % CHANNEL_COLOURS.len()];
        let pts = |k: usize| -> Vec<(f64, f64)> {
            let mut v: Vec<(f64, f64)> = freqs
                .iter()
                .zip(&power[k])
                .map(|(f, p)| (1.0 / f, *p))
                .collect();
            v.reverse();
            v
        };
        chart
            .draw_series(LineSeries::new(pts(0), colour.stroke_width(2)))?
            .label(format!("{} dx", a.report.channel))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
            });
        chart
            .draw_series(DashedLineSeries::new(pts(1), 8, 5, colour.stroke_width(2)))?
            .label(format!("{} dy", a.report.channel))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 8, y)], colour.stroke_width(3))
            });
        if let Some(p) = &a.report.periodogram {
            for peak in p
                .peaks
                .dx_px
                .iter()
                .take(1)
                .chain(p.peaks.dy_px.iter().take(1))
            {
                chart.draw_series(std::iter::once(Circle::new(
                    (peak.period_s, peak.power),
                    5,
                    colour.filled(),
                )))?;
                chart.draw_series(std::iter::once(Text::new(
                    format!("{:.1} s", peak.period_s),
                    (peak.period_s * 1.03, (peak.power + 0.02).min(1.0)),
                    (FAMILY, 20).into_font().color(&colour),
                )))?;
            }
        }
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .label_font((FAMILY, 18))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(180, 180, 180))
        .draw()?;
    Ok(())
}
