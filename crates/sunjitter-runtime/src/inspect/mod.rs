//! Offline inspection of logged alignments: per-channel statistics, periodogram, outliers,
//! CSV and plots. Analysis works on an in-memory series ([`LoggedFrame`]), read from the logs
//! by [`logs`].
//!
//! Definitions (also the `inspect --json` schema, see [`Report`]):
//! - Frames are grouped by `channel` and ordered by `log_time` (then `sequence`).
//! - `raw` statistics use the frame-to-reference values (`dx_px`, …), `chained` the
//!   `chained_*` values when any frame has them. Failed frames have no values.
//! - `rms` is about the mean; `median_sigma` ignores σ = 0 (frames aligned to themselves).
//! - The *pointing series* used for the periodogram, the outliers and the plot is `chained`
//!   when at least half the frames with a raw value also have a chained one, else `raw`.
//! - Trend: the least-squares straight line of each parameter of the pointing series, its
//!   slope per hour with a 1σ from the scatter about the line ([`Trend`]). A drift is
//!   reported as a trend, never as a period.
//! - Periodogram: [`lombscargle`] on the pointing series of the frames where all four
//!   parameters are present, after removing that line (drift is not jitter). A period is
//!   listed only when the series holds at least [`MIN_PERIOD_SAMPLES`] samples, spans at least
//!   [`MIN_CYCLES`] of its cycles (frequency ≥ `MIN_CYCLES / T`, T the span; a 3.7-hour
//!   series lists nothing longer than 1.2 hours) and is a maximum on both sides (a rise
//!   towards long periods is what is left of a trend, not a period).
//! - Outliers: [`stats::outliers`] (leave-one-out local quadratic baseline) beyond 5σ.

pub mod consistency;
pub mod csv;
pub mod logs;
pub mod lombscargle;
pub mod plot;
pub mod stats;

pub use logs::{log_files, read_frames, read_frames_and_references};
use lombscargle::{FrequencyGrid, Peak};
use serde::{Deserialize, Serialize};
use stats::Stats;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use sunjitter_core::record::{FrameAlignment, Status};

/// One `/jitter/<channel>` message with its MCAP `log_time`.
#[derive(Debug, Clone, PartialEq)]
pub struct LoggedFrame {
    /// Observation time, ns since the Unix epoch (UTC).
    pub log_time_ns: i64,
    pub record: FrameAlignment,
}

/// The four similarity parameters, in the contract's units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Param {
    Dx,
    Dy,
    Rotation,
    Scale,
}

pub const PARAMS: [Param; 4] = [Param::Dx, Param::Dy, Param::Rotation, Param::Scale];

/// Which values of a record a series is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SeriesKind {
    /// Frame-to-reference (`dx_px`, …).
    Raw,
    /// Chained to the first reference (`chained_dx_px`, …).
    Chained,
}

impl Param {
    /// The contract's field name.
    pub fn name(self) -> &'static str {
        match self {
            Param::Dx => "dx_px",
            Param::Dy => "dy_px",
            Param::Rotation => "rotation_arcsec",
            Param::Scale => "scale",
        }
    }

    /// (value, σ) of this parameter in `kind`; `None` value for failed frames.
    pub fn get(self, r: &FrameAlignment, kind: SeriesKind) -> (Option<f64>, Option<f64>) {
        if r.align.status == Status::Failed {
            return (None, None);
        }
        let a = &r.align;
        match (kind, self) {
            (SeriesKind::Raw, Param::Dx) => (a.dx_px, a.sigma_dx_px),
            (SeriesKind::Raw, Param::Dy) => (a.dy_px, a.sigma_dy_px),
            (SeriesKind::Raw, Param::Rotation) => (a.rotation_arcsec, a.sigma_rotation_arcsec),
            (SeriesKind::Raw, Param::Scale) => (a.scale, a.sigma_scale),
            (SeriesKind::Chained, Param::Dx) => (r.chained_dx_px, r.sigma_chained_dx_px),
            (SeriesKind::Chained, Param::Dy) => (r.chained_dy_px, r.sigma_chained_dy_px),
            (SeriesKind::Chained, Param::Rotation) => {
                (r.chained_rotation_arcsec, r.sigma_chained_rotation_arcsec)
            }
            (SeriesKind::Chained, Param::Scale) => (r.chained_scale, r.sigma_chained_scale),
        }
    }
}

/// A period is listed only when the series spans at least this many of its cycles: fewer
/// cannot tell a period from a trend or a single excursion.
pub const MIN_CYCLES: f64 = 3.0;
/// ... and holds at least this many samples (a sinusoid on a straight line has five
/// parameters; a false-alarm probability from fewer samples than four per parameter is not
/// to be trusted).
pub const MIN_PERIOD_SAMPLES: usize = 20;

/// Analysis settings (defaults are the documented ones).
#[derive(Debug, Clone, PartialEq)]
pub struct InspectOptions {
    pub oversampling: f64,
    pub max_frequencies: usize,
    pub max_peaks: usize,
    pub outlier_threshold: f64,
}

impl Default for InspectOptions {
    fn default() -> Self {
        InspectOptions {
            oversampling: 5.0,
            max_frequencies: 200_000,
            max_peaks: 3,
            outlier_threshold: 5.0,
        }
    }
}

/// `inspect --json`: one document for all logs read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// The MCAP files read, in the order read.
    pub files: Vec<String>,
    pub channels: Vec<ChannelReport>,
    /// What `/log` says; frames that never reached a channel are only there.
    pub log: LogSummary,
    /// Fitted models, keyframe closures, disagreements with the headers and between
    /// channels of one instrument ([`consistency::consistency`]).
    #[serde(default)]
    pub consistency: consistency::Consistency,
}

/// The `/log` topic in numbers.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LogSummary {
    pub warnings: usize,
    pub errors: usize,
    /// Input files logged as errors that have no `/jitter` message (e.g. unreadable files),
    /// so they appear in no channel's count; in log order.
    pub unaligned: Vec<UnalignedFrame>,
}

/// An input logged as an error, with no alignment message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnalignedFrame {
    pub file: String,
    pub message: String,
}

/// Tallies `/log` entries as (level, file, message): foxglove.Log levels 3 = warning, ≥ 4 =
/// error. An error entry is `unaligned` when no frame in `frames` names its file.
pub fn summarise_log<'a>(
    entries: impl IntoIterator<Item = (u8, &'a str, &'a str)>,
    frames: &[LoggedFrame],
) -> LogSummary {
    let aligned: std::collections::HashSet<&str> = frames
        .iter()
        .map(|f| f.record.align.frame.as_str())
        .collect();
    let mut summary = LogSummary::default();
    let mut seen = std::collections::HashSet::new();
    for (level, file, message) in entries {
        match level {
            3 => summary.warnings += 1,
            l if l >= 4 => {
                summary.errors += 1;
                if !file.is_empty() && !aligned.contains(file) && seen.insert(file.to_string()) {
                    summary.unaligned.push(UnalignedFrame {
                        file: file.to_string(),
                        message: message.to_string(),
                    });
                }
            }
            _ => {}
        }
    }
    summary
}

/// Statistics of the four parameters of one series.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamStats {
    pub dx_px: Stats,
    pub dy_px: Stats,
    pub rotation_arcsec: Stats,
    pub scale: Stats,
}

/// Dominant periods of the four parameters (strongest first).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamPeaks {
    pub dx_px: Vec<Peak>,
    pub dy_px: Vec<Peak>,
    pub rotation_arcsec: Vec<Peak>,
    pub scale: Vec<Peak>,
}

/// A straight-line trend of one parameter: slope per hour, in the parameter's units (scale:
/// per hour, unitless), with its 1σ from the scatter about the line (`sqrt(Σr²/(n−2) /
/// Σ(t−t̄)²)`; jitter correlated in time makes it an underestimate).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Trend {
    pub per_hour: f64,
    pub sigma_per_hour: f64,
    /// Samples in the fit.
    pub samples: usize,
}

/// The trends of the four parameters of the pointing series (`null` with fewer than 3 samples).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ParamTrends {
    pub series: SeriesKind,
    pub dx_px: Option<Trend>,
    pub dy_px: Option<Trend>,
    pub rotation_arcsec: Option<Trend>,
    pub scale: Option<Trend>,
}

/// The periodogram's grid and peaks. "Within one frequency bin" means within
/// `frequency_resolution_hz` = 1/`span_s`; the grid is `oversampling` times finer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PeriodogramReport {
    pub series: SeriesKind,
    /// Samples used: non-failed frames with all four parameters.
    pub samples: usize,
    pub span_s: f64,
    /// The lowest frequency searched for periods, [`MIN_CYCLES`] / `span_s` (the grid itself
    /// starts at 1 / `span_s`).
    pub frequency_min_hz: f64,
    /// Pseudo-Nyquist, 1/(2 · median Δt).
    pub frequency_max_hz: f64,
    pub frequency_step_hz: f64,
    pub frequency_resolution_hz: f64,
    pub oversampling: f64,
    pub frequencies: usize,
    pub peaks: ParamPeaks,
}

/// A frame whose value lies beyond the threshold from what its neighbours predict.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Outlier {
    pub sequence: u64,
    pub obs_time: String,
    pub log_time_ns: i64,
    pub frame: String,
    pub parameter: String,
    pub series: SeriesKind,
    pub value: f64,
    pub baseline: f64,
    /// `value − baseline`.
    pub deviation: f64,
    /// The divisor (see [`stats::outliers`]).
    pub sigma: f64,
    /// `deviation / sigma`.
    pub z: f64,
}

/// Everything `inspect` says about one channel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelReport {
    pub channel: String,
    pub frames: usize,
    pub ok: usize,
    pub degraded: usize,
    pub failed: usize,
    /// Count per `reference_kind` (`self`, `previous`, `keyframe`, …).
    pub reference_kinds: BTreeMap<String, usize>,
    /// First and last `log_time` as ISO 8601 UTC.
    pub start: String,
    pub end: String,
    pub span_s: f64,
    /// Median interval between consecutive frames (all statuses), `null` for one frame.
    pub median_cadence_s: Option<f64>,
    pub raw: ParamStats,
    /// `null` when no frame has chained values.
    pub chained: Option<ParamStats>,
    /// The series the trend, periodogram, outliers and plot use.
    pub series: SeriesKind,
    pub trend: ParamTrends,
    /// `null` with fewer than [`MIN_PERIOD_SAMPLES`] usable samples, or a span shorter than
    /// [`MIN_CYCLES`] of the shortest period the cadence resolves.
    pub periodogram: Option<PeriodogramReport>,
    pub outliers: Vec<Outlier>,
}

/// A channel's report plus what the plot needs.
#[derive(Debug, Clone)]
pub struct ChannelAnalysis {
    pub report: ChannelReport,
    /// The channel's frames in time order.
    pub frames: Vec<LoggedFrame>,
    /// Frequencies and the power of each of [`PARAMS`], when a periodogram exists.
    pub spectrum: Option<(Vec<f64>, Vec<Vec<f64>>)>,
}

/// Group by channel (sorted by name), order each by time, and analyse.
pub fn analyse(frames: &[LoggedFrame], opts: &InspectOptions) -> Vec<ChannelAnalysis> {
    let mut by_channel: BTreeMap<&str, Vec<LoggedFrame>> = BTreeMap::new();
    for f in frames {
        by_channel
            .entry(f.record.channel.as_str())
            .or_default()
            .push(f.clone());
    }
    by_channel
        .into_iter()
        .map(|(name, mut frames)| {
            frames.sort_by_key(|f| (f.log_time_ns, f.record.sequence));
            analyse_channel(name, frames, opts)
        })
        .collect()
}

/// The JSON report of [`analyse`]'s results.
pub fn report(files: &[String], analyses: &[ChannelAnalysis], log: LogSummary) -> Report {
    Report {
        files: files.to_vec(),
        channels: analyses.iter().map(|a| a.report.clone()).collect(),
        log,
        consistency: Default::default(),
    }
}

fn values(frames: &[LoggedFrame], p: Param, kind: SeriesKind) -> (Vec<f64>, Vec<f64>) {
    let mut v = Vec::new();
    let mut s = Vec::new();
    for f in frames {
        let (value, sigma) = p.get(&f.record, kind);
        if let Some(value) = value.filter(|x| x.is_finite()) {
            v.push(value);
        }
        if let Some(sigma) = sigma.filter(|x| x.is_finite()) {
            s.push(sigma);
        }
    }
    (v, s)
}

fn param_stats(frames: &[LoggedFrame], kind: SeriesKind) -> ParamStats {
    let st = |p| {
        let (v, s) = values(frames, p, kind);
        Stats::of(&v, &s)
    };
    ParamStats {
        dx_px: st(Param::Dx),
        dy_px: st(Param::Dy),
        rotation_arcsec: st(Param::Rotation),
        scale: st(Param::Scale),
    }
}

fn analyse_channel(name: &str, frames: Vec<LoggedFrame>, opts: &InspectOptions) -> ChannelAnalysis {
    let count = |s: Status| frames.iter().filter(|f| f.record.align.status == s).count();
    let mut reference_kinds = BTreeMap::new();
    for f in &frames {
        *reference_kinds
            .entry(f.record.reference_kind.to_string())
            .or_insert(0) += 1;
    }
    let t0 = frames.first().map_or(0, |f| f.log_time_ns);
    let t1 = frames.last().map_or(0, |f| f.log_time_ns);
    let gaps: Vec<f64> = frames
        .windows(2)
        .map(|w| (w[1].log_time_ns - w[0].log_time_ns) as f64 * 1e-9)
        .collect();
    let raw = param_stats(&frames, SeriesKind::Raw);
    let has_chained = frames.iter().any(|f| f.record.chained_dx_px.is_some());
    let chained = has_chained.then(|| param_stats(&frames, SeriesKind::Chained));
    let series = match &chained {
        Some(c) if 2 * c.dx_px.n >= raw.dx_px.n => SeriesKind::Chained,
        _ => SeriesKind::Raw,
    };

    // Samples with all four parameters, for the periodogram.
    let usable: Vec<(f64, [f64; 4])> = frames
        .iter()
        .filter_map(|f| {
            let mut v = [0.0; 4];
            for (slot, p) in v.iter_mut().zip(PARAMS) {
                *slot = p.get(&f.record, series).0.filter(|x| x.is_finite())?;
            }
            Some(((f.log_time_ns - t0) as f64 * 1e-9, v))
        })
        .collect();
    let t: Vec<f64> = usable.iter().map(|u| u.0).collect();
    let trend_of = |p: Param| {
        let (t, y): (Vec<f64>, Vec<f64>) = frames
            .iter()
            .filter_map(|f| {
                let v = p.get(&f.record, series).0.filter(|x| x.is_finite())?;
                Some(((f.log_time_ns - t0) as f64 * 1e-9, v))
            })
            .unzip();
        trend(&t, &y)
    };
    let trend = ParamTrends {
        series,
        dx_px: trend_of(Param::Dx),
        dy_px: trend_of(Param::Dy),
        rotation_arcsec: trend_of(Param::Rotation),
        scale: trend_of(Param::Scale),
    };
    let mut periodogram = None;
    let mut spectrum = None;
    let grid = (t.len() >= MIN_PERIOD_SAMPLES)
        .then(|| FrequencyGrid::for_times(&t, opts.oversampling, opts.max_frequencies))
        .flatten()
        .filter(|g| g.max_hz() > MIN_CYCLES / g.span_s);
    if let Some(grid) = grid {
        let min_hz = MIN_CYCLES / grid.span_s;
        let ys: Vec<Vec<f64>> = (0..4)
            .map(|k| detrend(&t, &usable.iter().map(|u| u.1[k]).collect::<Vec<_>>()))
            .collect();
        let refs: Vec<&[f64]> = ys.iter().map(|y| y.as_slice()).collect();
        let power = lombscargle::periodogram(&t, &refs, &grid);
        let pk = |k: usize| {
            lombscargle::resolved_peaks(&t, &ys[k], &grid, &power[k], opts.max_peaks, min_hz)
        };
        periodogram = Some(PeriodogramReport {
            series,
            samples: t.len(),
            span_s: grid.span_s,
            frequency_min_hz: min_hz,
            frequency_max_hz: grid.max_hz(),
            frequency_step_hz: grid.step_hz,
            frequency_resolution_hz: grid.resolution_hz(),
            oversampling: grid.oversampling,
            frequencies: grid.count,
            peaks: ParamPeaks {
                dx_px: pk(0),
                dy_px: pk(1),
                rotation_arcsec: pk(2),
                scale: pk(3),
            },
        });
        // The part searched for periods.
        let first = (0..grid.count)
            .find(|&j| grid.frequency(j) >= min_hz)
            .unwrap_or(0);
        let freqs: Vec<f64> = (first..grid.count).map(|j| grid.frequency(j)).collect();
        let power: Vec<Vec<f64>> = power.into_iter().map(|p| p[first..].to_vec()).collect();
        spectrum = Some((freqs, power));
    }

    let mut outliers = Vec::new();
    for p in PARAMS {
        let picked: Vec<(&LoggedFrame, f64, f64)> = frames
            .iter()
            .filter_map(|f| {
                let (v, s) = p.get(&f.record, series);
                Some((f, v.filter(|x| x.is_finite())?, s.unwrap_or(0.0)))
            })
            .collect();
        let t: Vec<f64> = picked
            .iter()
            .map(|x| (x.0.log_time_ns - t0) as f64 * 1e-9)
            .collect();
        let y: Vec<f64> = picked.iter().map(|x| x.1).collect();
        let sigma: Vec<f64> = picked.iter().map(|x| x.2).collect();
        for d in stats::outliers(&t, &y, &sigma, opts.outlier_threshold) {
            let (f, value, _) = picked[d.index];
            outliers.push(Outlier {
                sequence: f.record.sequence,
                obs_time: f.record.obs_time.clone(),
                log_time_ns: f.log_time_ns,
                frame: f.record.align.frame.clone(),
                parameter: p.name().to_string(),
                series,
                value,
                baseline: d.baseline,
                deviation: value - d.baseline,
                sigma: d.scale,
                z: d.z,
            });
        }
    }
    outliers.sort_by_key(|o| (o.log_time_ns, o.sequence));

    let report = ChannelReport {
        channel: name.to_string(),
        frames: frames.len(),
        ok: count(Status::Ok),
        degraded: count(Status::Degraded),
        failed: count(Status::Failed),
        reference_kinds,
        start: sunjitter_core::time::format_iso_utc(t0),
        end: sunjitter_core::time::format_iso_utc(t1),
        span_s: (t1 - t0) as f64 * 1e-9,
        median_cadence_s: stats::median(&gaps),
        raw,
        chained,
        series,
        trend,
        periodogram,
        outliers,
    };
    ChannelAnalysis {
        report,
        frames,
        spectrum,
    }
}

/// The least-squares straight line of `y(t)` (t in seconds), as a [`Trend`] per hour.
fn trend(t: &[f64], y: &[f64]) -> Option<Trend> {
    let n = t.len();
    if n < 3 {
        return None;
    }
    let nf = n as f64;
    let (mt, my) = (t.iter().sum::<f64>() / nf, y.iter().sum::<f64>() / nf);
    let stt: f64 = t.iter().map(|v| (v - mt).powi(2)).sum();
    if stt <= 0.0 {
        return None;
    }
    let slope = t
        .iter()
        .zip(y)
        .map(|(a, b)| (a - mt) * (b - my))
        .sum::<f64>()
        / stt;
    let residual: f64 = t
        .iter()
        .zip(y)
        .map(|(a, b)| (b - my - slope * (a - mt)).powi(2))
        .sum();
    let sigma = (residual / (nf - 2.0) / stt).sqrt();
    Some(Trend {
        per_hour: slope * 3600.0,
        sigma_per_hour: sigma * 3600.0,
        samples: n,
    })
}

/// `y` minus its least-squares straight line in `t`.
fn detrend(t: &[f64], y: &[f64]) -> Vec<f64> {
    let n = t.len() as f64;
    let (mt, my) = (t.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let stt: f64 = t.iter().map(|v| (v - mt).powi(2)).sum();
    let sty: f64 = t.iter().zip(y).map(|(a, b)| (a - mt) * (b - my)).sum();
    let slope = if stt > 0.0 { sty / stt } else { 0.0 };
    t.iter()
        .zip(y)
        .map(|(a, b)| b - my - slope * (a - mt))
        .collect()
}

/// The human summary (no `--json`). Text from the logs is escaped: it may hold any file name.
pub fn render_text(report: &Report) -> String {
    use sunjitter_core::text::escape;
    let mut s = String::new();
    if report.channels.is_empty() {
        let _ = writeln!(s, "no /jitter messages in {} file(s)", report.files.len());
    }
    for c in &report.channels {
        let _ = writeln!(
            s,
            "{}: {} frames ({} ok, {} degraded, {} failed), {} to {} ({:.0} s{})",
            escape(&c.channel),
            c.frames,
            c.ok,
            c.degraded,
            c.failed,
            c.start,
            c.end,
            c.span_s,
            c.median_cadence_s
                .map_or(String::new(), |v| format!(", cadence {v:.1} s"))
        );
        let kinds: Vec<String> = c
            .reference_kinds
            .iter()
            .map(|(k, n)| format!("{} {n}", escape(k)))
            .collect();
        let _ = writeln!(s, "  references: {}", kinds.join(", "));
        let _ = writeln!(
            s,
            "  rms about the mean, p-p = max − min, σ = median reported 1σ"
        );
        let chained = c.chained.as_ref();
        let _ = writeln!(
            s,
            "  {:<14}{:>11}{:>11}{:>11}{}",
            "",
            "raw rms",
            "raw p-p",
            "raw σ",
            if chained.is_some() {
                "  chained rms  chained p-p    chained σ"
            } else {
                ""
            }
        );
        let rows: [(&str, &Stats, Option<&Stats>, f64); 4] = [
            ("dx [px]", &c.raw.dx_px, chained.map(|x| &x.dx_px), 1.0),
            ("dy [px]", &c.raw.dy_px, chained.map(|x| &x.dy_px), 1.0),
            (
                "rotation [″]",
                &c.raw.rotation_arcsec,
                chained.map(|x| &x.rotation_arcsec),
                1.0,
            ),
            ("scale [ppm]", &c.raw.scale, chained.map(|x| &x.scale), 1e6),
        ];
        let num = |v: Option<f64>, k: f64| v.map_or("-".to_string(), |x| format!("{:.4}", x * k));
        for (label, raw, ch, k) in rows {
            let _ = write!(
                s,
                "  {:<14}{:>11}{:>11}{:>11}",
                label,
                num(raw.rms, k),
                num(raw.peak_to_peak, k),
                num(raw.median_sigma, k)
            );
            if let Some(ch) = ch {
                let _ = write!(
                    s,
                    "{:>13}{:>13}{:>13}",
                    num(ch.rms, k),
                    num(ch.peak_to_peak, k),
                    num(ch.median_sigma, k)
                );
            }
            let _ = writeln!(s);
        }
        let tr = &c.trend;
        let slope = |t: &Option<Trend>, k: f64, unit: &str| {
            t.map_or("-".to_string(), |t| {
                sunjitter_core::text::value_pm(t.per_hour * k, Some(t.sigma_per_hour * k), unit)
            })
        };
        let _ = writeln!(
            s,
            "  trend ({} series, straight line, per hour): dx {}, dy {}, rotation {}, scale {}",
            series_name(tr.series),
            slope(&tr.dx_px, 1.0, " px"),
            slope(&tr.dy_px, 1.0, " px"),
            slope(&tr.rotation_arcsec, 1.0, "″"),
            slope(&tr.scale, 1e6, " ppm"),
        );
        match &c.periodogram {
            Some(p) => {
                let fmt = |peaks: &[Peak]| -> String {
                    if peaks.is_empty() {
                        return "none (no variation)".to_string();
                    }
                    peaks
                        .iter()
                        .map(|pk| {
                            format!(
                                "{:.1} s (power {:.2}, FAP {})",
                                pk.period_s,
                                pk.power,
                                probability(pk.false_alarm_probability)
                            )
                        })
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                let _ = writeln!(
                    s,
                    "  periods ({} series less its trend, {} samples; searched from {:.1} s, \
                     a third of the span, down to {:.1} s; bin {:.3e} Hz):",
                    series_name(p.series),
                    p.samples,
                    1.0 / p.frequency_min_hz,
                    1.0 / p.frequency_max_hz,
                    p.frequency_resolution_hz
                );
                let _ = writeln!(s, "    dx: {}", fmt(&p.peaks.dx_px));
                let _ = writeln!(s, "    dy: {}", fmt(&p.peaks.dy_px));
            }
            None => {
                let _ = writeln!(
                    s,
                    "  periods: none listed (a period needs {MIN_PERIOD_SAMPLES} samples and \
                     {MIN_CYCLES:.0} cycles in the span; {} samples over {:.0} s)",
                    t_samples(c),
                    c.span_s
                );
            }
        }
        if c.outliers.is_empty() {
            let _ = writeln!(s, "  outliers (> 5σ): none");
        } else {
            let _ = writeln!(s, "  outliers (> 5σ): {}", c.outliers.len());
            for o in c.outliers.iter().take(10) {
                let _ = writeln!(
                    s,
                    "    #{} {} {} = {:.4} (baseline {:.4}, z = {:.1})",
                    o.sequence,
                    escape(&o.obs_time),
                    o.parameter,
                    o.value,
                    o.baseline,
                    o.z
                );
            }
            if c.outliers.len() > 10 {
                let _ = writeln!(s, "    … {} more in --json", c.outliers.len() - 10);
            }
        }
    }
    render_consistency(&mut s, &report.consistency);
    render_log(&mut s, &report.log);
    s
}

fn render_consistency(s: &mut String, c: &consistency::Consistency) {
    use sunjitter_core::text::escape;
    for ch in &c.channels {
        let models: Vec<String> = ch.models.iter().map(|(m, n)| format!("{m} {n}")).collect();
        let closure = ch.closure.as_ref().map_or(String::new(), |c| {
            format!(
                "; keyframe closure within 2σ: dx {:.0} %, dy {:.0} %, rotation {:.0} %, scale {:.0} % of {}",
                100.0 * c.within_2sigma[2],
                100.0 * c.within_2sigma[3],
                100.0 * c.within_2sigma[1],
                100.0 * c.within_2sigma[0],
                c.keyframes
            )
        });
        if !models.is_empty() || !closure.is_empty() {
            let _ = writeln!(
                s,
                "{}: fitted {}{closure}",
                escape(&ch.channel),
                models.join(", ")
            );
        }
        for w in &ch.warnings {
            let _ = writeln!(s, "  WARNING: {}", escape(w));
        }
    }
    for p in &c.pairs {
        let _ = writeln!(
            s,
            "{} vs {} (chained, {} samples): dx {:.3} px RMS, {:.0} % within 1σ; dy {:.3} px RMS, {:.0} % within 1σ",
            escape(&p.channels[0]),
            escape(&p.channels[1]),
            p.samples,
            p.rms_px[0],
            100.0 * p.within_1sigma[0],
            p.rms_px[1],
            100.0 * p.within_1sigma[1]
        );
        if !p.independent {
            let _ = writeln!(
                s,
                "  (one is aligned to the other's frames: they share errors, so this is no \
                 independent check; replay each channel against its own keyframe for one)"
            );
        }
        for w in &p.warnings {
            let _ = writeln!(s, "  WARNING: {}", escape(w));
        }
    }
}

fn render_log(s: &mut String, log: &LogSummary) {
    use sunjitter_core::text::escape;
    let _ = writeln!(
        s,
        "/log: {} error(s), {} warning(s); {} input(s) with no alignment",
        log.errors,
        log.warnings,
        log.unaligned.len()
    );
    for u in log.unaligned.iter().take(10) {
        let _ = writeln!(s, "  {}: {}", escape(&u.file), escape(&u.message));
    }
    if log.unaligned.len() > 10 {
        let _ = writeln!(s, "  … {} more in --json", log.unaligned.len() - 10);
    }
}

/// Samples of the pointing series with a value (the periodogram's, at most).
fn t_samples(c: &ChannelReport) -> usize {
    let stats = match c.series {
        SeriesKind::Chained => c.chained.as_ref().unwrap_or(&c.raw),
        SeriesKind::Raw => &c.raw,
    };
    stats.dx_px.n
}

fn series_name(k: SeriesKind) -> &'static str {
    match k {
        SeriesKind::Raw => "raw",
        SeriesKind::Chained => "chained",
    }
}

#[cfg(test)]
pub(crate) mod testdata {
    use super::*;
    use sunjitter_core::record::AlignResult;

    /// A frame record with the given raw and chained dx/dy (others zero), σ 0.01 px.
    pub fn frame(
        channel: &str,
        seq: u64,
        t_s: f64,
        dx: f64,
        dy: f64,
        status: Status,
    ) -> LoggedFrame {
        let ns = 1_714_564_800_000_000_000 + (t_s * 1e9).round() as i64;
        let ok = status != Status::Failed;
        let v = |x: f64| ok.then_some(x);
        LoggedFrame {
            log_time_ns: ns,
            record: FrameAlignment {
                align: AlignResult {
                    reference: "ref.fits".into(),
                    frame: format!("f{seq:04}.fits"),
                    scale: v(1.0),
                    rotation_arcsec: v(0.0),
                    dx_px: v(dx),
                    dy_px: v(dy),
                    dx_arcsec: v(dx * 0.6),
                    dy_arcsec: v(dy * 0.6),
                    sigma_scale: v(1e-6),
                    sigma_rotation_arcsec: v(0.1),
                    sigma_dx_px: v(0.01),
                    sigma_dy_px: v(0.01),
                    sigma_dx_arcsec: v(0.01),
                    sigma_dy_arcsec: v(0.01),
                    uabjm_sigma_scale: v(1e-6),
                    uabjm_sigma_rotation_arcsec: v(0.1),
                    uabjm_sigma_dx_px: v(0.01),
                    uabjm_sigma_dy_px: v(0.01),
                    header_residual: None,
                    solar_rotation: None,
                    points: 400,
                    inliers: 380,
                    residual_rms_px: v(0.05),
                    model: None,
                    similarity: v(0.9),
                    status,
                    message: String::new(),
                    elapsed_ms: 12.5,
                },
                channel: channel.into(),
                obs_time: sunjitter_core::time::format_iso_utc(ns),
                sequence: seq,
                reference_kind: if seq == 0 {
                    sunjitter_core::record::ReferenceKind::Itself
                } else {
                    sunjitter_core::record::ReferenceKind::Keyframe
                },
                chained_dx_px: v(dx),
                chained_dy_px: v(dy),
                chained_dx_arcsec: v(0.6 * dx),
                chained_dy_arcsec: v(0.6 * dy),
                chained_rotation_arcsec: v(0.0),
                chained_scale: v(1.0),
                sigma_chained_dx_px: v(0.01),
                sigma_chained_dy_px: v(0.01),
                sigma_chained_dx_arcsec: v(0.006),
                sigma_chained_dy_arcsec: v(0.006),
                sigma_chained_rotation_arcsec: v(0.1),
                sigma_chained_scale: v(1e-6),
                pixel_checksum: None,
            },
        }
    }
}

/// A probability as people read one: two decimals, or powers of ten below 0.01.
fn probability(p: f64) -> String {
    if p >= 0.01 {
        format!("{p:.2}")
    } else {
        format!("{p:.1e}")
    }
}

#[cfg(test)]
mod tests {
    use super::testdata::frame;
    use super::*;

    #[test]
    fn counts_stats_period_and_outlier_of_a_known_series() {
        // 90 frames at 12 s, dx = 0.3 sin(2πt/120), dy = 0.2 cos(…); frames 40–44 missing (a gap),
        // frame 10 failed, frame 60 degraded with a 1 px glitch in dx.
        let mut frames = Vec::new();
        for k in 0..90u64 {
            if (40..45).contains(&k) {
                continue;
            }
            let t = 12.0 * k as f64;
            let w = 2.0 * std::f64::consts::PI * t / 120.0;
            let mut dx = 0.3 * w.sin();
            let status = match k {
                10 => Status::Failed,
                60 => {
                    dx += 1.0;
                    Status::Degraded
                }
                _ => Status::Ok,
            };
            frames.push(frame("SYNTH_171", k, t, dx, 0.2 * w.cos(), status));
        }
        let a = analyse(&frames, &InspectOptions::default());
        assert_eq!(a.len(), 1);
        let c = &a[0].report;
        assert_eq!((c.frames, c.ok, c.degraded, c.failed), (85, 83, 1, 1));
        assert_eq!(c.reference_kinds.get("self"), Some(&1));
        assert_eq!(c.median_cadence_s, Some(12.0));
        assert_eq!(c.series, SeriesKind::Chained);
        // dy: a sampled cosine of amplitude 0.2 has rms 0.2/√2 (the gap barely matters).
        let rms = c.raw.dy_px.rms.unwrap();
        assert!((rms - 0.2 / 2f64.sqrt()).abs() < 0.005, "{rms}");
        assert_eq!(c.raw.dx_px.n, 84);
        assert_eq!(c.raw.dx_px.median_sigma, Some(0.01));
        let p = c.periodogram.as_ref().unwrap();
        assert_eq!(p.samples, 84);
        assert!((p.peaks.dy_px[0].period_s - 120.0).abs() / 120.0 < 0.01);
        assert!((p.peaks.dx_px[0].frequency_hz - 1.0 / 120.0).abs() < p.frequency_resolution_hz);
        // The glitch, and only the glitch, is an outlier (in dx).
        assert_eq!(c.outliers.len(), 1, "{:?}", c.outliers);
        assert_eq!(
            (c.outliers[0].sequence, c.outliers[0].parameter.as_str()),
            (60, "dx_px")
        );
        let text = render_text(&report(&["a.mcap".into()], &a, LogSummary::default()));
        assert!(
            text.contains("SYNTH_171: 85 frames (83 ok, 1 degraded, 1 failed)"),
            "{text}"
        );
    }

    /// Deterministic noise, uniform in ±`amp` (splitmix64 of `k`).
    fn noise(k: u64, amp: f64) -> f64 {
        let mut z = k.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        let x = (z >> 11) as f64 / (1u64 << 53) as f64;
        amp * (2.0 * x - 1.0)
    }

    /// `n` frames at `cadence` s with dx = f(t), dy = g(t) plus noise of 0.02 px.
    fn series(n: u64, cadence: f64, f: impl Fn(f64) -> (f64, f64)) -> ChannelReport {
        let frames: Vec<LoggedFrame> = (0..n)
            .map(|k| {
                let t = cadence * k as f64;
                let (dx, dy) = f(t);
                let (dx, dy) = (dx + noise(2 * k, 0.02), dy + noise(2 * k + 1, 0.02));
                frame("C", k, t, dx, dy, Status::Ok)
            })
            .collect();
        analyse(&frames, &InspectOptions::default())
            .remove(0)
            .report
    }

    #[test]
    fn a_period_is_listed_only_with_three_cycles_in_the_span_and_twenty_samples() {
        let tau = 2.0 * std::f64::consts::PI;
        // 60 frames at 60 s: T = 3540 s.
        let span = 3540.0;
        for (cycles, listed) in [(4.0, true), (2.9, false), (2.0, false), (1.5, false)] {
            let period = span / cycles;
            let c = series(60, 60.0, |t| (0.3 * (tau * t / period).sin(), 0.0));
            let p = c.periodogram.as_ref().unwrap();
            assert!((p.frequency_min_hz - 3.0 / span).abs() < 1e-12);
            let found = p
                .peaks
                .dx_px
                .iter()
                .any(|pk| (pk.frequency_hz - 1.0 / period).abs() < p.frequency_resolution_hz);
            assert_eq!(found, listed, "{cycles} cycles: {:?}", p.peaks.dx_px);
            assert!(p.peaks.dx_px.iter().all(|pk| pk.period_s <= span / 3.0));
            if listed {
                assert!(p.peaks.dx_px[0].false_alarm_probability < 1e-6);
            } else {
                // Nothing else is passed off as significant either.
                assert!(
                    p.peaks
                        .dx_px
                        .iter()
                        .all(|pk| pk.false_alarm_probability > 0.01),
                    "{cycles} cycles: {:?}",
                    p.peaks.dx_px
                );
            }
        }
        // Six 2-hour cycles in 12 h, but only 11 samples: nothing is listed, and the text says why.
        let c = series(11, 4320.0, |t| (0.3 * (tau * t / 7200.0).sin(), 0.0));
        assert!(c.periodogram.is_none());
        let text = render_text(&Report {
            files: vec![],
            channels: vec![c],
            log: LogSummary::default(),
            consistency: Default::default(),
        });
        assert!(
            text.contains("periods: none listed (a period needs 20 samples and 3 cycles"),
            "{text}"
        );
    }

    #[test]
    fn a_drift_is_reported_as_a_trend_with_its_sigma_not_as_a_period() {
        // 3.7 h at 270 s (50 frames), as the demo: dy drifts −0.3 px/h; dx curves (a
        // quadratic drift of 0.5 px over the run), which a straight line does not remove.
        let span = 49.0 * 270.0;
        let c = series(50, 270.0, |t| (0.5 * (t / span).powi(2), -0.3 * t / 3600.0));
        let dy = c.trend.dy_px.unwrap();
        assert!(
            (dy.per_hour + 0.3).abs() < 3.0 * dy.sigma_per_hour,
            "{dy:?}"
        );
        // Noise uniform in ±0.02 px: σ of the slope ≈ 0.0115 / √Σ(t−t̄)² per s.
        let expected = 0.02 / 3f64.sqrt() / (50.0 * (span * span) / 12.0).sqrt() * 3600.0;
        assert!(
            dy.sigma_per_hour > 0.5 * expected && dy.sigma_per_hour < 2.0 * expected,
            "{dy:?} vs {expected}"
        );
        assert_eq!(dy.samples, 50);
        let p = c.periodogram.as_ref().unwrap();
        for (name, peaks) in [("dx", &p.peaks.dx_px), ("dy", &p.peaks.dy_px)] {
            assert!(
                peaks.iter().all(|pk| pk.false_alarm_probability > 0.01),
                "{name}: {peaks:?}"
            );
        }
        let text = render_text(&Report {
            files: vec![],
            channels: vec![c],
            log: LogSummary::default(),
            consistency: Default::default(),
        });
        assert!(
            text.contains("trend (chained series, straight line, per hour): dx "),
            "{text}"
        );
        assert!(text.contains("px, dy -0.29"), "{text}");
    }

    #[test]
    fn channels_are_separated_and_time_ordered() {
        let frames = vec![
            frame("B", 1, 24.0, 0.0, 0.0, Status::Ok),
            frame("A", 0, 0.0, 0.0, 0.0, Status::Ok),
            frame("B", 0, 0.0, 0.0, 0.0, Status::Ok),
        ];
        let a = analyse(&frames, &InspectOptions::default());
        let names: Vec<&str> = a.iter().map(|c| c.report.channel.as_str()).collect();
        assert_eq!(names, ["A", "B"]);
        assert_eq!(a[1].frames[0].record.sequence, 0);
        assert_eq!(a[1].report.span_s, 24.0);
        assert!(a[1].report.periodogram.is_none());
    }
}
