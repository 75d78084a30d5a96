//! `inspect --plot OUT.png|OUT.svg`: one figure read at a glance. A title with the time range,
//! a legend strip, then one panel per channel: a row of four subplots (dx and dy in px,
//! rotation in ″, scale in ppm from 1) against a shared UTC time axis whose tick labels carry
//! the date where it is needed. Each subplot shows the raw (frame → its reference) and, when
//! logged, the chained (to the first reference) series with their ±1σ bands; degraded frames
//! ringed in orange, failed frames as red crosses along the floor, outliers as black
//! triangles. Below, the Lomb–Scargle periodogram (power against period, dx solid, dy dashed)
//! with the strongest periods labelled and its legend beside the plot. Text uses the embedded
//! DejaVu Sans, so no system font is needed.

use super::{ChannelAnalysis, Param, SeriesKind, PARAMS};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;
use sunjitter_core::record::Status;
use sunjitter_core::{Error, Result};

use sunjitter_io::font::{self, FAMILY};
const WIDTH: u32 = 2000;
const TITLE_H: u32 = 50;
const LEGEND_H: u32 = 40;
/// One channel's panel: caption line plus the subplots.
const ROW_H: u32 = 340;
const CAPTION_H: u32 = 30;
const SPECTRUM_H: u32 = 400;
/// Width of the periodogram's legend column, right of its plot.
const SPECTRUM_LEGEND_W: u32 = 320;
const Y_LABEL_W: u32 = 88;
const RIGHT_MARGIN: u32 = 16;
/// Narrowest tick spacing (px) for `HH:MM` labels; wider when dated labels may be neighbours.
const TICK_SPACING_PX: f64 = 90.0;
const DATED_TICK_SPACING_PX: f64 = 130.0;

const CHANNEL_COLOURS: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(23, 190, 207),
    RGBColor(127, 127, 127),
];
const RAW: RGBColor = RGBColor(110, 110, 110);
const CHAINED: RGBColor = RGBColor(31, 119, 180);
const DEGRADED: RGBColor = RGBColor(255, 127, 14);
const FAILED: RGBColor = RGBColor(214, 39, 40);
const PANEL_FRAME: RGBColor = RGBColor(190, 190, 190);

/// Figure size for `channels` channels: fixed width, one row per channel.
pub fn figure_size(channels: usize) -> (u32, u32) {
    let rows = channels.max(1) as u32;
    (WIDTH, TITLE_H + LEGEND_H + rows * ROW_H + SPECTRUM_H + 10)
}

/// Draw the figure to `path`; the extension (`.png` or `.svg`) picks the format.
pub fn write_plot(analyses: &[ChannelAnalysis], path: &Path) -> Result<()> {
    font::register();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let fail = |e: String| Error::output(path, e);
    let size = figure_size(analyses.len());
    match ext.as_deref() {
        Some("png") => {
            let root = BitMapBackend::new(path, size).into_drawing_area();
            draw(&root, analyses).map_err(fail)?;
            root.present().map_err(|e| fail(e.to_string()))
        }
        Some("svg") => {
            let root = SVGBackend::new(path, size).into_drawing_area();
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
        Param::Rotation => "rotation [″]",
        Param::Scale => "scale - 1 [ppm]",
    }
}

/// The values of `p` in series `kind`, and the times of frames without one.
fn samples(a: &ChannelAnalysis, p: Param, kind: SeriesKind, t0: i64) -> (Vec<Sample>, Vec<f64>) {
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
                    o.series == kind
                        && o.sequence == f.record.sequence
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

/// Tick labels of a time axis: `YYYY-MM-DD HH:MM` on the first tick and wherever the UTC date
/// changes, `HH:MM` elsewhere (with seconds when ticks are less than a minute apart).
fn time_labels(t0_ns: i64, ticks: &[f64], step: f64) -> Vec<String> {
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
            let dated = prev_day.as_ref() != Some(&day);
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
fn duration(s: f64) -> String {
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

/// `text` cut (with "…") to fit `max_w` px in `style` on `area`.
fn fit_text<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    text: &str,
    style: &TextStyle,
    max_w: u32,
) -> String {
    let fits = |s: &str| {
        area.estimate_text_size(s, style)
            .map_or(true, |(w, _)| w <= max_w)
    };
    if fits(text) {
        return text.to_string();
    }
    let chars: Vec<char> = text.chars().collect();
    for n in (0..chars.len()).rev() {
        let cut: String = chars[..n].iter().collect::<String>() + "…";
        if fits(&cut) {
            return cut;
        }
    }
    String::new()
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

/// Tick times (s from `t0_ns`) in `lo..=hi` on round UTC clock values, at most `max_ticks`;
/// also the step between them.
fn time_ticks(t0_ns: i64, lo: f64, hi: f64, max_ticks: usize) -> (Vec<f64>, f64) {
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

/// What a legend entry shows beside its text.
#[derive(Clone, Copy)]
enum Mark {
    Line(RGBColor, u32),
    Dashed(RGBColor),
    Band(RGBColor),
    Ring,
    Cross,
    Triangle,
}

fn draw_mark<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    mark: Mark,
    (x, y): (i32, i32),
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    match mark {
        Mark::Line(c, w) => area.draw(&PathElement::new(
            vec![(x, y), (x + 30, y)],
            c.stroke_width(w),
        )),
        Mark::Dashed(c) => {
            area.draw(&PathElement::new(
                vec![(x, y), (x + 10, y)],
                c.stroke_width(2),
            ))?;
            area.draw(&PathElement::new(
                vec![(x + 18, y), (x + 30, y)],
                c.stroke_width(2),
            ))
        }
        Mark::Band(c) => area.draw(&Rectangle::new(
            [(x, y - 7), (x + 30, y + 7)],
            c.mix(0.22).filled(),
        )),
        Mark::Ring => area.draw(&Circle::new((x + 15, y), 6, DEGRADED.stroke_width(3))),
        Mark::Cross => area.draw(&Cross::new((x + 15, y), 6, FAILED.stroke_width(3))),
        Mark::Triangle => area.draw(&TriangleMarker::new((x + 15, y), 8, BLACK.filled())),
    }
}

/// Legend entries in a row (`vertical` false) or a column, starting at `at`.
fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[(Mark, String)],
    at: (i32, i32),
    vertical: bool,
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    let style = TextStyle::from((FAMILY, 17).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let (mut x, mut y) = at;
    for (mark, text) in entries {
        draw_mark(area, *mark, (x, y))?;
        area.draw_text(text, &style, (x + 38, y))?;
        if vertical {
            y += 26;
        } else {
            let w = area.estimate_text_size(text, &style)?.0 as i32;
            x += 38 + w + 34;
        }
    }
    Ok(())
}

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
    let span = (t_end - t0) as f64 * 1e-9;
    // A short or single-frame log still gets a minute of axis, centred on its data.
    let x_range = if span < 60.0 {
        (0.5 * span - 30.0, 0.5 * span + 30.0)
    } else {
        (-0.01 * span, 1.01 * span)
    };
    let (width, _) = root.dim_in_pixel();

    let (title_area, rest) = root.split_vertically(TITLE_H);
    let (legend_area, rest) = rest.split_vertically(LEGEND_H);
    let rows_h = (analyses.len() as u32 * ROW_H) as i32;
    let (rows_area, spectrum_area) = rest.split_vertically(rows_h);

    let iso = |ns: i64| sunjitter_core::time::format_iso_utc(ns)[..19].replace('T', " ");
    let title = format!(
        "sunjitter inspect: {} channel{}, {} to {} UTC ({})",
        analyses.len(),
        if analyses.len() == 1 { "" } else { "s" },
        iso(t0),
        iso(t_end),
        duration(span)
    );
    let title_style =
        TextStyle::from((FAMILY, 26).into_font()).pos(Pos::new(HPos::Center, VPos::Center));
    let title = fit_text(&title_area, &title, &title_style, width - 40);
    title_area
        .draw_text(&title, &title_style, (width as i32 / 2, TITLE_H as i32 / 2))
        .map_err(e)?;

    let mut legend = vec![(
        Mark::Line(RAW, 1),
        "raw (frame → its reference)".to_string(),
    )];
    if analyses.iter().any(|a| a.report.chained.is_some()) {
        legend.push((
            Mark::Line(CHAINED, 3),
            "chained (to the first reference)".to_string(),
        ));
    }
    legend.push((Mark::Band(CHAINED), "±1σ".to_string()));
    if analyses.iter().any(|a| a.report.degraded > 0) {
        legend.push((Mark::Ring, "degraded".to_string()));
    }
    if analyses.iter().any(|a| a.report.failed > 0) {
        legend.push((Mark::Cross, "failed (no value)".to_string()));
    }
    if analyses.iter().any(|a| !a.report.outliers.is_empty()) {
        legend.push((Mark::Triangle, "outlier > 5σ".to_string()));
    }
    draw_legend(&legend_area, &legend, (30, LEGEND_H as i32 / 2), false).map_err(e)?;

    if !analyses.is_empty() {
        let rows = rows_area.split_evenly((analyses.len(), 1));
        for (ci, (row, a)) in rows.iter().zip(analyses).enumerate() {
            draw_channel(row, a, ci, t0, x_range).map_err(e)?;
        }
    }
    draw_spectrum(&spectrum_area, analyses).map_err(e)
}

/// One channel's panel: a caption line, then dx, dy, rotation and scale side by side.
fn draw_channel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    a: &ChannelAnalysis,
    ci: usize,
    t0: i64,
    (x_lo, x_hi): (f64, f64),
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB::ErrorType: 'static,
{
    let (w, h) = area.dim_in_pixel();
    area.draw(&Rectangle::new(
        [(6, 2), (w as i32 - 7, h as i32 - 5)],
        PANEL_FRAME.stroke_width(1),
    ))?;
    let inner = area.margin(4, 8, 10, 10);
    let (caption_area, plots) = inner.split_vertically(CAPTION_H);
    let colour = CHANNEL_COLOURS[ci % CHANNEL_COLOURS.len()];
    caption_area.draw(&Rectangle::new([(4, 6), (20, 22)], colour.filled()))?;
    let r = &a.report;
    // The end's date only when it differs from the start's.
    let start = r.start.get(..19).unwrap_or(&r.start).replace('T', " ");
    let end = r.end.get(..19).unwrap_or(&r.end).replace('T', " ");
    let end = if end.get(..10) == start.get(..10) {
        end.get(11..).unwrap_or(&end).to_string()
    } else {
        end
    };
    let caption = format!(
        "{}: {} frame{} ({} ok, {} degraded, {} failed), {start} to {end} UTC{}",
        r.channel,
        r.frames,
        if r.frames == 1 { "" } else { "s" },
        r.ok,
        r.degraded,
        r.failed,
        r.median_cadence_s
            .map_or(String::new(), |c| format!(", cadence {}", duration(c))),
    );
    let style = TextStyle::from((FAMILY, 19).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let caption = fit_text(&caption_area, &caption, &style, w.saturating_sub(60));
    caption_area.draw_text(&caption, &style, (30, 14))?;

    let kinds: Vec<SeriesKind> = if r.chained.is_some() {
        vec![SeriesKind::Raw, SeriesKind::Chained]
    } else {
        vec![SeriesKind::Raw]
    };
    let cadence = r.median_cadence_s.unwrap_or(x_hi - x_lo);
    let day =
        |x: f64| sunjitter_core::time::format_iso_utc(t0 + (x * 1e9) as i64)[..10].to_string();
    let spacing = if day(x_lo) == day(x_hi) {
        TICK_SPACING_PX
    } else {
        DATED_TICK_SPACING_PX
    };
    for (panel, p) in plots.split_evenly((1, 4)).iter().zip(PARAMS) {
        let series: Vec<(SeriesKind, Vec<Sample>, Vec<f64>)> = kinds
            .iter()
            .map(|&k| {
                let (s, missing) = samples(a, p, k, t0);
                (k, s, missing)
            })
            .collect();
        let (lo, hi) = y_range(series.iter().flat_map(|(_, s, _)| s.iter()));
        let plot_w = panel
            .dim_in_pixel()
            .0
            .saturating_sub(Y_LABEL_W + RIGHT_MARGIN) as f64;
        let (ticks, step) = time_ticks(t0, x_lo, x_hi, (plot_w / spacing) as usize);
        let labels = time_labels(t0, &ticks, step);
        let mut chart = ChartBuilder::on(panel)
            .margin_right(RIGHT_MARGIN)
            .margin_top(6)
            .x_label_area_size(50)
            .y_label_area_size(Y_LABEL_W)
            .build_cartesian_2d(TickedAxis::linear(x_lo, x_hi, ticks.clone()), lo..hi)?;
        let fmt_x = |x: &f64| {
            ticks
                .iter()
                .position(|t| (t - x).abs() < 1e-6 * step.max(1.0))
                .map_or(String::new(), |i| labels[i].clone())
        };
        let fmt_y = |y: &f64| tick_label(*y, hi - lo);
        chart
            .configure_mesh()
            .y_labels(5)
            .x_label_formatter(&fmt_x)
            .y_label_formatter(&fmt_y)
            .y_desc(label(p))
            .x_desc("time (UTC)")
            .label_style((FAMILY, 15))
            .axis_desc_style((FAMILY, 17))
            .light_line_style(RGBColor(238, 238, 238))
            .bold_line_style(RGBColor(215, 215, 215))
            .axis_style(BLACK)
            .draw()?;
        let floor = lo + 0.04 * (hi - lo);
        for (kind, s, missing) in &series {
            let (colour, width, radius) = match kind {
                SeriesKind::Raw => (RAW, 1, 2),
                SeriesKind::Chained => (CHAINED, 2, 3),
            };
            for run in runs(s, missing, cadence) {
                let run = &s[run];
                if run.len() == 1 {
                    // A lone sample: an error bar, not a zero-width band.
                    let x = &run[0];
                    chart.draw_series(std::iter::once(PathElement::new(
                        vec![(x.t, x.v - x.sigma), (x.t, x.v + x.sigma)],
                        colour.mix(0.45).stroke_width(1),
                    )))?;
                } else if run.iter().any(|x| x.sigma > 0.0) {
                    let band: Vec<(f64, f64)> = run
                        .iter()
                        .map(|x| (x.t, x.v + x.sigma))
                        .chain(run.iter().rev().map(|x| (x.t, x.v - x.sigma)))
                        .collect();
                    chart.draw_series(std::iter::once(Polygon::new(
                        band,
                        colour.mix(0.18).filled(),
                    )))?;
                }
                chart.draw_series(LineSeries::new(
                    run.iter().map(|x| (x.t, x.v)),
                    colour.stroke_width(width),
                ))?;
            }
            chart.draw_series(
                s.iter()
                    .map(|x| Circle::new((x.t, x.v), radius, colour.filled())),
            )?;
        }
        // Status and outlier marks on the series the analysis used.
        if let Some((_, s, _)) = series.iter().find(|(k, _, _)| *k == r.series) {
            chart.draw_series(
                s.iter()
                    .filter(|x| x.status == Status::Degraded)
                    .map(|x| Circle::new((x.t, x.v), 7, DEGRADED.stroke_width(2))),
            )?;
            chart.draw_series(
                s.iter()
                    .filter(|x| x.outlier)
                    .map(|x| TriangleMarker::new((x.t, x.v), 9, BLACK.filled())),
            )?;
        }
        let failed = a
            .frames
            .iter()
            .filter(|f| f.record.align.status == Status::Failed)
            .map(|f| (f.log_time_ns - t0) as f64 * 1e-9);
        chart.draw_series(failed.map(|t| Cross::new((t, floor), 6, FAILED.stroke_width(2))))?;
    }
    Ok(())
}

/// Value range with room for the ±σ bands (σ capped at 3× the median so one wild σ does not
/// flatten the rest), padded by 8 %.
fn y_range<'a>(samples: impl Iterator<Item = &'a Sample>) -> (f64, f64) {
    let s: Vec<&Sample> = samples.collect();
    let sig: Vec<f64> = s.iter().map(|x| x.sigma).filter(|v| *v > 0.0).collect();
    let cap = 3.0 * super::stats::median(&sig).unwrap_or(0.0);
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
    let (w, _) = area.dim_in_pixel();
    let (plot_area, legend_area) = area.split_horizontally(w.saturating_sub(SPECTRUM_LEGEND_W));
    let f_max = with_spectrum
        .iter()
        .filter_map(|(_, _, s)| s.0.last())
        .fold(0.0f64, |a, b| a.max(*b));
    let f_min = with_spectrum
        .iter()
        .filter_map(|(_, _, s)| s.0.first())
        .fold(f64::INFINITY, |a, b| a.min(*b));
    let (p_lo, p_hi) = (1.0 / f_max, 1.0 / f_min);
    let mut chart = ChartBuilder::on(&plot_area)
        .margin_left(10)
        .margin_right(RIGHT_MARGIN)
        .margin_top(10)
        .x_label_area_size(56)
        .y_label_area_size(Y_LABEL_W)
        .caption(
            "Lomb-Scargle periodogram of each channel's analysed series (straight-line trend removed)",
            (FAMILY, 21),
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
        .label_style((FAMILY, 16))
        .axis_desc_style((FAMILY, 18))
        .light_line_style(RGBColor(238, 238, 238))
        .draw()?;
    let mut legend = Vec::new();
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
        chart.draw_series(LineSeries::new(pts(0), colour.stroke_width(2)))?;
        chart.draw_series(DashedLineSeries::new(pts(1), 8, 5, colour.stroke_width(2)))?;
        let series = match a.report.series {
            SeriesKind::Chained => "chained",
            SeriesKind::Raw => "raw",
        };
        legend.push((
            Mark::Line(colour, 2),
            format!("{} dx ({series})", a.report.channel),
        ));
        legend.push((
            Mark::Dashed(colour),
            format!("{} dy ({series})", a.report.channel),
        ));
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
                    (FAMILY, 18).into_font().color(&colour),
                )))?;
            }
        }
    }
    // Long channel names are cut to the legend column.
    let style = TextStyle::from((FAMILY, 17).into_font());
    let max_w = SPECTRUM_LEGEND_W.saturating_sub(60);
    let legend: Vec<(Mark, String)> = legend
        .into_iter()
        .map(|(m, t)| (m, fit_text(&legend_area, &t, &style, max_w)))
        .collect();
    draw_legend(&legend_area, &legend, (10, 60), true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inspect::testdata::frame;
    use crate::inspect::{analyse, InspectOptions, LoggedFrame};

    /// Two channels from 2024-05-01 12:00 UTC for 15 h at 15-min cadence (so the series
    /// crosses midnight into 2024-05-02), and a one-frame channel.
    fn three_channels() -> Vec<ChannelAnalysis> {
        let mut frames: Vec<LoggedFrame> = Vec::new();
        for k in 0..60u64 {
            let t = 900.0 * k as f64;
            let w = (t / 3600.0).sin();
            frames.push(frame("AIA_171", k, t, 0.3 * w, -0.2 * w, Status::Ok));
            frames.push(frame("AIA_304", k, t, 0.1 * w, 0.4 * w, Status::Ok));
        }
        frames.push(frame("LONE", 0, 1800.0, 0.0, 0.0, Status::Ok));
        analyse(&frames, &InspectOptions::default())
    }

    fn render_svg(a: &[ChannelAnalysis]) -> String {
        font::register();
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, figure_size(a.len())).into_drawing_area();
            draw(&root, a).unwrap();
            root.present().unwrap();
        }
        svg
    }

    #[test]
    fn time_axis_labels_carry_the_date_at_the_start_and_across_midnight() {
        let svg = render_svg(&three_channels());
        for name in ["AIA_171", "AIA_304", "LONE"] {
            assert!(svg.contains(name), "SVG lacks {name}");
        }
        // The log starts 2024-05-01 12:00 UTC and ends 2024-05-02 02:45 UTC.
        assert!(svg.contains("2024-05-01 12:00"), "no dated first tick");
        assert!(
            svg.contains("2024-05-02 00:00"),
            "no dated tick at midnight"
        );
        for unit in ["dx [px]", "dy [px]", "rotation [″]", "scale - 1 [ppm]"] {
            assert!(svg.contains(unit), "SVG lacks {unit:?}");
        }
    }

    #[test]
    fn every_channel_gets_its_own_row_of_four_subplots() {
        font::register();
        let a = three_channels();
        let (w, h) = figure_size(a.len());
        let mut buf = vec![0u8; (w * h * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
            draw(&root, &a).unwrap();
            root.present().unwrap();
        }
        // A subplot's time axis is a long black horizontal line; a channel's row has four
        // of them at one height, the periodogram one.
        let dark = |x: u32, y: u32| {
            let i = 3 * (y * w + x) as usize;
            buf[i] < 60 && buf[i + 1] < 60 && buf[i + 2] < 60
        };
        let mut rows_of_four = Vec::new();
        for y in 0..h {
            let (mut runs, mut len) = (0, 0);
            for x in 0..w {
                if dark(x, y) {
                    len += 1;
                } else {
                    runs += usize::from(len >= 150);
                    len = 0;
                }
            }
            runs += usize::from(len >= 150);
            if runs == 4 && rows_of_four.last().is_none_or(|&last: &u32| y > last + 1) {
                rows_of_four.push(y);
            }
        }
        assert_eq!(rows_of_four.len(), 3, "axis rows at {rows_of_four:?}");
    }

    #[test]
    fn ticks_fall_on_round_utc_times_within_the_range() {
        // 2024-05-01 12:00:00 UTC plus 100 s; a 3.7-h range allows 4 ticks: hourly.
        let t0 = 1_714_564_800_000_000_000 + 100_000_000_000;
        let (ticks, step) = time_ticks(t0, 0.0, 13_320.0, 4);
        assert_eq!(step, 3600.0);
        let labels = time_labels(t0, &ticks, step);
        assert_eq!(labels, ["2024-05-01 13:00", "14:00", "15:00"]);
    }
}
