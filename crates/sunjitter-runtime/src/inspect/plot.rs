//! `inspect --plot OUT.png|OUT.svg`: one figure read at a glance. A title with the time range,
//! a legend strip, then one panel per channel, each on its own UTC time axis whose tick labels
//! carry the date where it is needed: a row of four subplots, dx and dy in px with arcsec on
//! a second axis at the channel's plate scale, rotation in ″, ′ or ° as its size asks, scale
//! in ppm from 1. Each subplot shows the raw (frame → its reference) and, when logged, the
//! chained (to the first reference) series with their ±1σ bands; dashed violet lines where a
//! frame starts a reference (a new keyframe), degraded frames ringed in orange, failed frames
//! as red crosses along the floor, outliers as black triangles. Below, the Lomb–Scargle
//! periodogram of the periods `inspect` searches (at least three cycles in the span; power
//! against period, dx solid, dy dashed), the strongest listed periods labelled where no
//! label covers another, its legend beside the plot. Time ticks are spaced so that their
//! labels never touch. Text uses the embedded DejaVu Sans, so no system font is needed.

use super::{ChannelAnalysis, Param, SeriesKind, PARAMS};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use std::path::Path;
use sunjitter_core::record::{ReferenceKind, Status};
use sunjitter_core::{Error, Result};

use sunjitter_io::font::{self, FAMILY};

mod axes;

use axes::{duration, period_ticks, tick_label, time_labels, time_ticks, TickedAxis};

const WIDTH: u32 = 2000;
const TITLE_H: u32 = 50;
const LEGEND_H: u32 = 40;
/// One channel's panel: caption line plus the subplots.
const ROW_H: u32 = 340;
const CAPTION_H: u32 = 30;
const SPECTRUM_H: u32 = 400;
const NO_SPECTRUM_H: u32 = 60;
/// Width of the periodogram's legend column, right of its plot.
const SPECTRUM_LEGEND_W: u32 = 320;
const Y_LABEL_W: u32 = 88;
/// The arcsec axis right of the dx and dy subplots (kept on all four, so they line up).
const RIGHT_LABEL_W: u32 = 76;
const RIGHT_MARGIN: u32 = 16;
/// Room (px) between neighbouring time tick labels.
const TICK_GAP_PX: f64 = 14.0;
/// Time tick labels: size of their font.
const TICK_FONT: u32 = 15;

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
const NEW_REFERENCE: RGBColor = RGBColor(148, 103, 189);
const PANEL_FRAME: RGBColor = RGBColor(190, 190, 190);

/// The figure's size: fixed width, one row per channel, and the periodogram (one line saying
/// why there is none, where no channel has one).
pub fn figure_size(analyses: &[ChannelAnalysis]) -> (u32, u32) {
    let rows = analyses.len().max(1) as u32;
    let spectrum = if analyses.iter().any(|a| a.spectrum.is_some()) {
        SPECTRUM_H
    } else {
        NO_SPECTRUM_H
    };
    (WIDTH, TITLE_H + LEGEND_H + rows * ROW_H + spectrum + 10)
}

/// Draw the figure to `path`; the extension (`.png` or `.svg`) picks the format.
pub fn write_plot(analyses: &[ChannelAnalysis], path: &Path) -> Result<()> {
    font::register();
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let fail = |e: String| Error::output(path, e);
    let size = figure_size(analyses);
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

/// How a channel's values are drawn: the rotation's unit, and the plate scale for the
/// arcsec axis of dx and dy.
#[derive(Debug, Clone, Copy)]
struct Units {
    /// Arcsec per unit of the rotation axis (1, 60 or 3600) and its symbol.
    rotation: (f64, &'static str),
    /// Arcsec per px of the reference grid, where the log says (`dx_arcsec` / `dx_px`).
    plate_scale: Option<f64>,
}

impl Units {
    fn of(a: &ChannelAnalysis) -> Units {
        let largest = a
            .frames
            .iter()
            .flat_map(|f| {
                [SeriesKind::Raw, SeriesKind::Chained]
                    .map(|k| Param::Rotation.get(&f.record, k).0.unwrap_or(0.0).abs())
            })
            .filter(|v| v.is_finite())
            .fold(0.0f64, f64::max);
        // Arcsec up to 2′, arcmin up to 2°, then degrees: tick labels of a few digits.
        let rotation = if largest < 120.0 {
            (1.0, "″")
        } else if largest < 7200.0 {
            (60.0, "′")
        } else {
            (3600.0, "°")
        };
        Units {
            rotation,
            plate_scale: plate_scale(a),
        }
    }

    fn value(&self, p: Param, v: f64) -> f64 {
        match p {
            Param::Scale => (v - 1.0) * 1e6,
            Param::Rotation => v / self.rotation.0,
            _ => v,
        }
    }

    fn sigma(&self, p: Param, s: f64) -> f64 {
        match p {
            Param::Scale => s * 1e6,
            Param::Rotation => s / self.rotation.0,
            _ => s,
        }
    }

    fn label(&self, p: Param) -> String {
        match p {
            Param::Dx => "dx [px]".into(),
            Param::Dy => "dy [px]".into(),
            Param::Rotation => format!("rotation [{}]", self.rotation.1),
            Param::Scale => "scale - 1 [ppm]".into(),
        }
    }
}

/// The channel's plate scale (arcsec/px) as its records used it: the median of
/// `dx_arcsec / dx_px` and `dy_arcsec / dy_px` over frames with a shift.
fn plate_scale(a: &ChannelAnalysis) -> Option<f64> {
    let mut ratios: Vec<f64> = Vec::new();
    for f in &a.frames {
        let r = &f.record;
        let pairs = [
            (r.align.dx_arcsec, r.align.dx_px),
            (r.align.dy_arcsec, r.align.dy_px),
            (r.chained_dx_arcsec, r.chained_dx_px),
            (r.chained_dy_arcsec, r.chained_dy_px),
        ];
        for (arcsec, px) in pairs {
            if let (Some(arcsec), Some(px)) = (arcsec, px) {
                let ratio = (arcsec / px).abs();
                if px.abs() > 1e-9 && ratio.is_finite() && ratio > 0.0 {
                    ratios.push(ratio);
                }
            }
        }
    }
    super::stats::median(&ratios)
}

/// The values of `p` in series `kind`, and the times of frames without one.
fn samples(
    a: &ChannelAnalysis,
    p: Param,
    kind: SeriesKind,
    t0: i64,
    units: &Units,
) -> (Vec<Sample>, Vec<f64>) {
    let mut out = Vec::new();
    let mut failed = Vec::new();
    for f in &a.frames {
        let t = (f.log_time_ns - t0) as f64 * 1e-9;
        let (v, s) = p.get(&f.record, kind);
        match v.filter(|x| x.is_finite()) {
            Some(v) => out.push(Sample {
                t,
                v: units.value(p, v),
                sigma: units.sigma(p, s.filter(|x| x.is_finite()).unwrap_or(0.0)),
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
    Vertical,
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
        Mark::Vertical => {
            for (a, b) in [(-9, -4), (-1, 3), (6, 9)] {
                area.draw(&PathElement::new(
                    vec![(x + 15, y + a), (x + 15, y + b)],
                    NEW_REFERENCE.stroke_width(2),
                ))?;
            }
            Ok(())
        }
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
    if analyses.iter().any(|a| !new_references(a, 0).is_empty()) {
        legend.push((Mark::Vertical, "new reference (keyframe)".to_string()));
    }
    draw_legend(&legend_area, &legend, (30, LEGEND_H as i32 / 2), false).map_err(e)?;

    if !analyses.is_empty() {
        let rows = rows_area.split_evenly((analyses.len(), 1));
        for (ci, (row, a)) in rows.iter().zip(analyses).enumerate() {
            draw_channel(row, a, ci).map_err(e)?;
        }
    }
    draw_spectrum(&spectrum_area, analyses).map_err(e)
}

/// Times (s from `t0`) of the frames that start a reference after the channel's first frame.
fn new_references(a: &ChannelAnalysis, t0: i64) -> Vec<f64> {
    let first = a.frames.first().map(|f| f.log_time_ns);
    a.frames
        .iter()
        .filter(|f| {
            f.record.reference_kind == ReferenceKind::Itself
                && f.record.align.status != Status::Failed
                && Some(f.log_time_ns) != first
        })
        .map(|f| (f.log_time_ns - t0) as f64 * 1e-9)
        .collect()
}

/// A channel's time axis: its own span (a short or single-frame log gets a minute, centred
/// on its data), and ticks on round UTC times whose labels, in `style`, never touch.
struct TimeAxis {
    lo: f64,
    hi: f64,
    ticks: Vec<f64>,
    labels: Vec<String>,
    step: f64,
    /// `time (UTC)`, with the date when the axis lies within one UTC day.
    title: String,
}

fn time_axis<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    t0: i64,
    span: f64,
    plot_w: f64,
    style: &TextStyle,
) -> TimeAxis {
    let (lo, hi) = if span < 60.0 {
        (0.5 * span - 30.0, 0.5 * span + 30.0)
    } else {
        (-0.01 * span, 1.01 * span)
    };
    let day = |x: f64| {
        sunjitter_core::time::format_iso_utc(t0 + (x * 1e9).round() as i64)[..10].to_string()
    };
    let one_day = day(lo) == day(hi);
    let title = if one_day {
        format!("time (UTC), {}", day(lo))
    } else {
        "time (UTC)".to_string()
    };
    let width = |t: &str| {
        area.estimate_text_size(t, style)
            .map_or(8.0 * t.len() as f64, |(w, _)| w as f64)
    };
    let mut max_ticks = (plot_w / 60.0).max(1.0) as usize;
    loop {
        let (ticks, step) = time_ticks(t0, lo, hi, max_ticks);
        let labels = time_labels(t0, &ticks, step, one_day);
        let px = |t: f64| (t - lo) / (hi - lo) * plot_w;
        let apart = ticks
            .windows(2)
            .zip(labels.windows(2))
            .all(|(t, l)| px(t[1]) - px(t[0]) >= 0.5 * (width(&l[0]) + width(&l[1])) + TICK_GAP_PX);
        // The end labels must not run off the plot either.
        let inside = match (ticks.first(), ticks.last(), labels.first(), labels.last()) {
            (Some(&a), Some(&b), Some(la), Some(lb)) => {
                px(a) + Y_LABEL_W as f64 >= 0.5 * width(la)
                    && plot_w - px(b) + RIGHT_LABEL_W as f64 >= 0.5 * width(lb)
            }
            _ => true,
        };
        if (apart && inside) || max_ticks <= 1 {
            return TimeAxis {
                lo,
                hi,
                ticks,
                labels,
                step,
                title,
            };
        }
        max_ticks -= 1;
    }
}

/// One channel's panel: a caption line, then dx, dy, rotation and scale side by side, on the
/// channel's own time axis.
fn draw_channel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    a: &ChannelAnalysis,
    ci: usize,
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
    let units = Units::of(a);
    // The end's date only when it differs from the start's.
    let start = r.start.get(..19).unwrap_or(&r.start).replace('T', " ");
    let end = r.end.get(..19).unwrap_or(&r.end).replace('T', " ");
    let end = if end.get(..10) == start.get(..10) {
        end.get(11..).unwrap_or(&end).to_string()
    } else {
        end
    };
    let caption = format!(
        "{}: {} frame{} ({} ok, {} degraded, {} failed), {start} to {end} UTC{}{}",
        r.channel,
        r.frames,
        if r.frames == 1 { "" } else { "s" },
        r.ok,
        r.degraded,
        r.failed,
        r.median_cadence_s
            .map_or(String::new(), |c| format!(", cadence {}", duration(c))),
        units
            .plate_scale
            .map_or(String::new(), |p| format!(", {} ″/px", significant(p, 4))),
    );
    let style = TextStyle::from((FAMILY, 19).into_font()).pos(Pos::new(HPos::Left, VPos::Center));
    let caption = fit_text(&caption_area, &caption, &style, w.saturating_sub(60));
    caption_area.draw_text(&caption, &style, (30, 14))?;

    let kinds: Vec<SeriesKind> = if r.chained.is_some() {
        vec![SeriesKind::Raw, SeriesKind::Chained]
    } else {
        vec![SeriesKind::Raw]
    };
    let Some(t0) = a.frames.first().map(|f| f.log_time_ns) else {
        return Ok(());
    };
    let span = a
        .frames
        .last()
        .map_or(0.0, |f| (f.log_time_ns - t0) as f64 * 1e-9);
    let cadence = r.median_cadence_s.unwrap_or(span.max(60.0));
    let restarts = new_references(a, t0);
    let tick_style = TextStyle::from((FAMILY, TICK_FONT).into_font());
    for (panel, p) in plots.split_evenly((1, 4)).iter().zip(PARAMS) {
        let series: Vec<(SeriesKind, Vec<Sample>, Vec<f64>)> = kinds
            .iter()
            .map(|&k| {
                let (s, missing) = samples(a, p, k, t0, &units);
                (k, s, missing)
            })
            .collect();
        let (lo, hi) = y_range(series.iter().flat_map(|(_, s, _)| s.iter()));
        let plot_w = panel
            .dim_in_pixel()
            .0
            .saturating_sub(Y_LABEL_W + RIGHT_LABEL_W + RIGHT_MARGIN) as f64;
        let TimeAxis {
            lo: x_lo,
            hi: x_hi,
            ticks,
            labels,
            step,
            title,
        } = time_axis(panel, t0, span, plot_w, &tick_style);
        let x_axis = TickedAxis::linear(x_lo, x_hi, ticks.clone());
        let arcsec = units
            .plate_scale
            .filter(|_| matches!(p, Param::Dx | Param::Dy));
        let mut builder = ChartBuilder::on(panel);
        builder
            .margin_top(6)
            .x_label_area_size(50)
            .y_label_area_size(Y_LABEL_W);
        // The same plot width with or without the arcsec axis: the subplots line up.
        match arcsec {
            Some(_) => builder
                .margin_right(RIGHT_MARGIN)
                .right_y_label_area_size(RIGHT_LABEL_W),
            None => builder.margin_right(RIGHT_MARGIN + RIGHT_LABEL_W),
        };
        let chart = builder.build_cartesian_2d(x_axis.clone(), lo..hi)?;
        let fmt_x = |x: &f64| {
            ticks
                .iter()
                .position(|t| (t - x).abs() < 1e-6 * step.max(1.0))
                .map_or(String::new(), |i| labels[i].clone())
        };
        let fmt_y = |y: &f64| tick_label(*y, hi - lo);
        let mesh = |chart: &mut Chart<'_, DB>| {
            chart
                .configure_mesh()
                .y_labels(5)
                .x_label_formatter(&fmt_x)
                .y_label_formatter(&fmt_y)
                .y_desc(units.label(p))
                .x_desc(title.as_str())
                .label_style((FAMILY, TICK_FONT))
                .axis_desc_style((FAMILY, 17))
                .light_line_style(RGBColor(238, 238, 238))
                .bold_line_style(RGBColor(215, 215, 215))
                .axis_style(BLACK)
                .draw()
        };
        match arcsec {
            Some(scale) => {
                // The secondary axis takes the right label area before the mesh is drawn, so
                // the px labels stay on the left.
                let mut dual = chart.set_secondary_coord(x_axis, lo * scale..hi * scale);
                mesh(&mut dual)?;
                let fmt = |y: &f64| tick_label(*y, (hi - lo) * scale);
                let name = if p == Param::Dx {
                    "dx [″]"
                } else {
                    "dy [″]"
                };
                dual.configure_secondary_axes()
                    .y_labels(5)
                    .y_label_formatter(&fmt)
                    .label_style((FAMILY, TICK_FONT))
                    .axis_style(BLACK)
                    .draw()?;
                // Its title reads upwards, as the left one does (plotters turns it downwards).
                let (_, rows) = dual.plotting_area().get_pixel_range();
                let (base_x, base_y) = panel.get_base_pixel();
                let (w, _) = panel.dim_in_pixel();
                let style = TextStyle::from((FAMILY, 17).into_font())
                    .transform(FontTransform::Rotate270)
                    .pos(Pos::new(HPos::Center, VPos::Top));
                let x = base_x + w as i32 - RIGHT_MARGIN as i32 - 22;
                let y = (rows.start + rows.end) / 2;
                panel.draw_text(name, &style, (x - base_x, y - base_y))?;
                draw_series(&mut dual, a, &series, &restarts, t0, (lo, hi), cadence)?;
            }
            None => {
                let mut chart = chart;
                mesh(&mut chart)?;
                draw_series(&mut chart, a, &series, &restarts, t0, (lo, hi), cadence)?
            }
        }
    }
    Ok(())
}

/// `v` with at most `digits` significant digits (no trailing zeros).
fn significant(v: f64, digits: i32) -> String {
    let decimals = (digits - 1 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

type Chart<'a, DB> = ChartContext<'a, DB, Cartesian2d<TickedAxis, RangedCoordf64>>;

/// One subplot's content: new-reference lines, the series with their σ bands, the status
/// and outlier marks, the failed frames along the floor.
fn draw_series<DB: DrawingBackend>(
    chart: &mut Chart<'_, DB>,
    a: &ChannelAnalysis,
    series: &[(SeriesKind, Vec<Sample>, Vec<f64>)],
    restarts: &[f64],
    t0: i64,
    (lo, hi): (f64, f64),
    cadence: f64,
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB::ErrorType: 'static,
{
    let r = &a.report;
    for &t in restarts {
        chart.draw_series(DashedLineSeries::new(
            [(t, lo), (t, hi)],
            6,
            4,
            NEW_REFERENCE.stroke_width(1),
        ))?;
    }
    let floor = lo + 0.04 * (hi - lo);
    for (kind, s, missing) in series {
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
            format!(
                "periodogram: none (a period needs {} samples and {:.0} cycles in the span)",
                super::MIN_PERIOD_SAMPLES,
                super::MIN_CYCLES
            ),
            (140, 16),
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
    // Room above strong peaks for their labels.
    let strongest = with_spectrum
        .iter()
        .flat_map(|(_, _, s)| s.1.iter().take(2).flatten())
        .fold(0.0f64, |a, b| a.max(*b));
    let top = if strongest > 0.75 { 1.3 } else { 1.05 };
    let mut chart = ChartBuilder::on(&plot_area)
        .margin_left(10)
        .margin_right(RIGHT_MARGIN)
        .margin_top(10)
        .x_label_area_size(56)
        .y_label_area_size(Y_LABEL_W)
        .caption(
            "Lomb-Scargle periodogram of each channel's analysed series less its trend \
             (periods with at least 3 cycles in the span)",
            (FAMILY, 21),
        )
        .build_cartesian_2d(
            TickedAxis::log(
                p_lo * 0.95,
                p_hi * 1.05,
                period_ticks(p_lo * 0.95, p_hi * 1.05),
            ),
            0.0..top,
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
    let mut to_label: Vec<(RGBColor, &str, super::lombscargle::Peak)> = Vec::new();
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
            let strongest = [("dx", &p.peaks.dx_px), ("dy", &p.peaks.dy_px)];
            for (name, peaks) in strongest {
                if let Some(peak) = peaks.first() {
                    to_label.push((colour, name, peak.clone()));
                }
            }
        }
    }
    label_peaks(&mut chart, &plot_area, to_label)?;
    // Long channel names are cut to the legend column.
    let style = TextStyle::from((FAMILY, 17).into_font());
    let max_w = SPECTRUM_LEGEND_W.saturating_sub(60);
    let legend: Vec<(Mark, String)> = legend
        .into_iter()
        .map(|(m, t)| (m, fit_text(&legend_area, &t, &style, max_w)))
        .collect();
    draw_legend(&legend_area, &legend, (10, 60), true)
}

/// A box in backend pixels: left, top, right, bottom.
type PixelBox = (i32, i32, i32, i32);

fn overlaps(a: PixelBox, b: PixelBox) -> bool {
    a.0 < b.2 && b.0 < a.2 && a.1 < b.3 && b.1 < a.3
}

/// Mark each peak and label it (`dx 4349 s, FAP 0.28`, `dy 119.7 s, FAP 1.2e-9`) beside it, strongest first, where the
/// label covers no other label or mark and stays inside the plot: right or left of the peak,
/// then stepped upwards (with a leader line). A label with no such place is left out (the
/// text summary lists every period).
fn label_peaks<DB: DrawingBackend>(
    chart: &mut Chart<'_, DB>,
    area: &DrawingArea<DB, Shift>,
    mut peaks: Vec<(RGBColor, &str, super::lombscargle::Peak)>,
) -> std::result::Result<(), DrawingAreaErrorKind<DB::ErrorType>>
where
    DB::ErrorType: 'static,
{
    peaks.sort_by(|a, b| b.2.power.total_cmp(&a.2.power));
    let (xr, yr) = chart.plotting_area().get_pixel_range();
    let mut taken: Vec<PixelBox> = peaks
        .iter()
        .map(|(_, _, pk)| {
            let (x, y) = chart.backend_coord(&(pk.period_s, pk.power));
            (x - 7, y - 7, x + 7, y + 7)
        })
        .collect();
    for (colour, _, pk) in &peaks {
        chart.draw_series(std::iter::once(Circle::new(
            (pk.period_s, pk.power),
            5,
            colour.filled(),
        )))?;
    }
    for (colour, name, pk) in &peaks {
        // Four significant digits: 119.7 s, 4349 s.
        let decimals = (3 - pk.period_s.abs().log10().floor() as i32).clamp(0, 3) as usize;
        let text = format!(
            "{name} {:.decimals$} s, FAP {}",
            pk.period_s,
            super::probability(pk.false_alarm_probability)
        );
        let style = TextStyle::from((FAMILY, 17).into_font()).color(colour);
        let (w, h) = area.estimate_text_size(&text, &style)?;
        let (w, h) = (w as i32, h as i32);
        let (ax, ay) = chart.backend_coord(&(pk.period_s, pk.power));
        let mut candidates = Vec::new();
        for step in 0..12 {
            let up = -h - 6 - step * (h + 4);
            candidates.push((10, up, step));
            candidates.push((-w - 10, up, step));
        }
        for step in 0..12 {
            let down = 6 + step * (h + 4);
            candidates.push((10, down, step));
            candidates.push((-w - 10, down, step));
        }
        let place = candidates.into_iter().find(|&(dx, dy, _)| {
            let b = (ax + dx, ay + dy, ax + dx + w, ay + dy + h);
            b.0 >= xr.start
                && b.2 <= xr.end
                && b.1 >= yr.start
                && b.3 <= yr.end
                && !taken.iter().any(|t| overlaps(*t, b))
        });
        let Some((dx, dy, step)) = place else {
            continue;
        };
        taken.push((ax + dx, ay + dy, ax + dx + w, ay + dy + h));
        let at = (pk.period_s, pk.power);
        if step > 0 {
            let end = (if dx > 0 { dx } else { dx + w }, dy + h);
            chart.draw_series(std::iter::once(
                EmptyElement::at(at)
                    + PathElement::new(vec![(0, 0), end], colour.mix(0.6).stroke_width(1)),
            ))?;
        }
        chart.draw_series(std::iter::once(
            EmptyElement::at(at) + Text::new(text, (dx, dy), style),
        ))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inspect::testdata::frame;
    use crate::inspect::{analyse, InspectOptions, LoggedFrame};

    /// Two channels from 2024-05-01 12:00 UTC for 15 h at 15-min cadence (so the series
    /// crosses midnight into 2024-05-02), and a one-frame channel.
    fn three_channels() -> Vec<ChannelAnalysis> {
        analyse(&three_channels_frames(), &InspectOptions::default())
    }

    fn three_channels_frames() -> Vec<LoggedFrame> {
        let mut frames: Vec<LoggedFrame> = Vec::new();
        for k in 0..60u64 {
            let t = 900.0 * k as f64;
            let w = (t / 3600.0).sin();
            frames.push(frame("AIA_171", k, t, 0.3 * w, -0.2 * w, Status::Ok));
            frames.push(frame("AIA_304", k, t, 0.1 * w, 0.4 * w, Status::Ok));
        }
        frames.push(frame("LONE", 0, 1800.0, 0.0, 0.0, Status::Ok));
        frames
    }

    fn render_svg(a: &[ChannelAnalysis]) -> String {
        font::register();
        let mut svg = String::new();
        {
            let root = SVGBackend::with_string(&mut svg, figure_size(a)).into_drawing_area();
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
        let (w, h) = figure_size(&a);
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

    /// A backend that records the box of every horizontal text drawn, from the embedded
    /// font's own layout (rotated axis titles are left out).
    struct TextBoxes {
        size: (u32, u32),
        boxes: std::rc::Rc<std::cell::RefCell<Vec<(String, PixelBox)>>>,
    }

    impl DrawingBackend for TextBoxes {
        type ErrorType = std::io::Error;
        fn get_size(&self) -> (u32, u32) {
            self.size
        }
        fn ensure_prepared(
            &mut self,
        ) -> std::result::Result<(), plotters_backend::DrawingErrorKind<std::io::Error>> {
            Ok(())
        }
        fn present(
            &mut self,
        ) -> std::result::Result<(), plotters_backend::DrawingErrorKind<std::io::Error>> {
            Ok(())
        }
        fn draw_pixel(
            &mut self,
            _: plotters_backend::BackendCoord,
            _: plotters_backend::BackendColor,
        ) -> std::result::Result<(), plotters_backend::DrawingErrorKind<std::io::Error>> {
            Ok(())
        }
        fn draw_text<S: plotters_backend::BackendTextStyle>(
            &mut self,
            text: &str,
            style: &S,
            pos: plotters_backend::BackendCoord,
        ) -> std::result::Result<(), plotters_backend::DrawingErrorKind<std::io::Error>> {
            if !matches!(style.transform(), plotters_backend::FontTransform::None) {
                return Ok(());
            }
            let ((x0, y0), (x1, y1)) = style
                .layout_box(text)
                .map_err(|e| plotters_backend::DrawingErrorKind::FontError(Box::new(e)))?;
            let (w, h) = (x1 - x0, y1 - y0);
            let x = match style.anchor().h_pos {
                plotters_backend::text_anchor::HPos::Left => pos.0,
                plotters_backend::text_anchor::HPos::Center => pos.0 - w / 2,
                plotters_backend::text_anchor::HPos::Right => pos.0 - w,
            };
            let y = match style.anchor().v_pos {
                plotters_backend::text_anchor::VPos::Top => pos.1,
                plotters_backend::text_anchor::VPos::Center => pos.1 - h / 2,
                plotters_backend::text_anchor::VPos::Bottom => pos.1 - h,
            };
            self.boxes
                .borrow_mut()
                .push((text.to_string(), (x, y, x + w, y + h)));
            Ok(())
        }
    }

    /// Every text drawn for `a`, and the pairs that cover each other.
    fn text_overlaps(a: &[ChannelAnalysis]) -> (Vec<String>, Vec<(String, String)>) {
        font::register();
        let boxes = std::rc::Rc::new(std::cell::RefCell::new(Vec::new()));
        let backend = TextBoxes {
            size: figure_size(a),
            boxes: boxes.clone(),
        };
        draw(&backend.into_drawing_area(), a).unwrap();
        let boxes = boxes.borrow();
        let boxes: Vec<&(String, PixelBox)> =
            boxes.iter().filter(|(t, _)| !t.trim().is_empty()).collect();
        let mut clashes = Vec::new();
        for (i, (ta, ba)) in boxes.iter().enumerate() {
            for (tb, bb) in &boxes[i + 1..] {
                if overlaps(*ba, *bb) {
                    clashes.push((ta.clone(), tb.clone()));
                }
            }
        }
        (boxes.iter().map(|(t, _)| t.clone()).collect(), clashes)
    }

    #[test]
    fn no_label_covers_another_with_close_periods_or_frames_that_share_one_time() {
        let tau = 2.0 * std::f64::consts::PI;
        // Two channels over 3.6 h at 250 s with periods 10 % apart at equal power (their peak
        // labels want the same place), and a channel of five frames at one time.
        let mut frames: Vec<LoggedFrame> = Vec::new();
        for k in 0..53u64 {
            let t = 250.0 * k as f64;
            let a = (tau * t / 2600.0).sin();
            let b = (tau * t / 2860.0).sin();
            frames.push(frame("SJI_1400", k, t, 0.3 * a, 0.3 * a, Status::Ok));
            frames.push(frame("SJI_2796", k, t + 10.0, 0.3 * b, 0.3 * b, Status::Ok));
        }
        for k in 0..5u64 {
            frames.push(frame("STILL", k, 600.0, 0.01 * k as f64, 0.0, Status::Ok));
        }
        let a = analyse(&frames, &InspectOptions::default());
        let (texts, clashes) = text_overlaps(&a);
        assert!(clashes.is_empty(), "overlapping labels: {clashes:?}");
        let labels: Vec<&String> = texts.iter().filter(|t| t.contains("FAP")).collect();
        assert_eq!(
            labels.len(),
            4,
            "every strongest period labelled: {texts:?}"
        );
        // The one-time channel's axis: a minute about it, its date in the axis title.
        assert!(texts.iter().any(|t| t == "12:10:00"), "{texts:?}");
        assert!(
            texts.iter().any(|t| t == "time (UTC), 2024-05-01"),
            "{texts:?}"
        );

        let (_, clashes) = text_overlaps(&three_channels());
        assert!(clashes.is_empty(), "overlapping labels: {clashes:?}");
    }

    #[test]
    fn units_follow_the_data_arcsec_beside_px_and_rotation_by_its_size() {
        let mut frames: Vec<LoggedFrame> = Vec::new();
        for k in 0..30u64 {
            let mut f = frame("BIG", k, 60.0 * k as f64, 0.1, 0.2, Status::Ok);
            // A roll of up to 29 arcmin, and every 10th frame a new keyframe.
            f.record.chained_rotation_arcsec = Some(60.0 * k as f64);
            if k % 10 == 0 {
                f.record.reference_kind = ReferenceKind::Itself;
            }
            frames.push(f);
        }
        let a = analyse(&frames, &InspectOptions::default());
        let units = Units::of(&a[0]);
        assert_eq!(units.rotation.1, "′");
        assert_eq!(units.plate_scale, Some(0.6));
        assert_eq!(units.value(Param::Rotation, 1740.0), 29.0);
        assert_eq!(
            new_references(&a[0], a[0].frames[0].log_time_ns),
            [600.0, 1200.0]
        );
        let svg = render_svg(&a);
        for text in [
            "rotation [′]",
            "dx [″]",
            "dy [″]",
            "0.6 ″/px",
            "new reference (keyframe)",
        ] {
            assert!(svg.contains(text), "SVG lacks {text:?}");
        }
        let small = analyse(&three_channels_frames(), &InspectOptions::default());
        assert_eq!(Units::of(&small[0]).rotation.1, "″");
    }

    #[test]
    fn ticks_fall_on_round_utc_times_within_the_range() {
        // 2024-05-01 12:00:00 UTC plus 100 s; a 3.7-h range allows 4 ticks: hourly.
        let t0 = 1_714_564_800_000_000_000 + 100_000_000_000;
        let (ticks, step) = time_ticks(t0, 0.0, 13_320.0, 4);
        assert_eq!(step, 3600.0);
        let labels = time_labels(t0, &ticks, step, false);
        assert_eq!(labels, ["2024-05-01 13:00", "14:00", "15:00"]);
        let labels = time_labels(t0, &ticks, step, true);
        assert_eq!(labels, ["13:00", "14:00", "15:00"]);
    }
}
