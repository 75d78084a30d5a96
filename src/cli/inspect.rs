//! `sunjitter inspect LOG.mcap|DIR… [--json] [--csv OUT.csv] [--plot OUT.png|OUT.svg]`
//!
//! Reads the `/jitter/<channel>` messages of one or more logs (a directory stands for its
//! `*.mcap` files in name order, i.e. a run's segments in time order) as one series per channel,
//! and prints a short summary, or with `--json` exactly one JSON document:
//!
//! ```text
//! { "files": ["…mcap", …],
//!   "channels": [ {
//!     "channel": "SYNTH_171", "frames": 80, "ok": 78, "degraded": 1, "failed": 1,
//!     "reference_kinds": {"keyframe": 79, "self": 1},
//!     "start": "2024-05-01T12:00:00.000Z", "end": "…", "span_s": 948.0, "median_cadence_s": 12.0,
//!     "raw":     { "dx_px": STATS, "dy_px": STATS, "rotation_arcsec": STATS, "scale": STATS },
//!     "chained": { same } | null,
//!     "series": "chained" | "raw",          // what trend, periodogram, outliers and plot use
//!     "trend": { "series": "chained", "dx_px": TREND, "dy_px": …, "rotation_arcsec": …,
//!                "scale": … },
//!     "periodogram": {                       // null below 20 samples
//!       "series": "chained", "samples": 79, "span_s": 948.0,
//!       "frequency_min_hz": 3/span (periods with ≥ 3 cycles in the span),
//!       "frequency_max_hz": 1/(2·median Δt),
//!       "frequency_step_hz": 1/(oversampling·span), "frequency_resolution_hz": 1/span,
//!       "oversampling": 5.0, "frequencies": 190,
//!       "peaks": { "dx_px": [PEAK, …], "dy_px": […], "rotation_arcsec": […], "scale": […] }
//!     } | null,
//!     "outliers": [ { "sequence", "obs_time", "log_time_ns", "frame", "parameter", "series",
//!                     "value", "baseline", "deviation", "sigma", "z" }, … ]
//!   } ],
//!   "log": { "warnings": 2, "errors": 1,
//!            "unaligned": [ { "file": "…fits", "message": "…" }, … ] } }
//! STATS = { "n", "mean", "rms" (about the mean), "min", "max", "peak_to_peak", "median_sigma" }
//! PEAK  = { "period_s", "frequency_hz", "power" (0–1, fraction of variance),
//!           "false_alarm_probability" (Baluev 2008) }
//! TREND = { "per_hour", "sigma_per_hour", "samples" } | null  (straight-line slope, units/h)
//! ```
//!
//! Numbers are `null` where there is nothing to compute. Definitions: [`sunjitter_runtime::inspect`]
//! (series choice, trend, detrending, which periods are listed), [`sunjitter_runtime::inspect::lombscargle`] (periodogram and its grid:
//! "within one frequency bin" means within `frequency_resolution_hz`),
//! [`sunjitter_runtime::inspect::stats::outliers`] (the 5σ test). `--csv` writes one row per frame with
//! every record field ([`sunjitter_runtime::inspect::csv`]); `--plot` draws [`sunjitter_runtime::inspect::plot`].

use std::path::PathBuf;
use sunjitter_core::error::Error;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_runtime::inspect::{self, log_files, read_frames_and_references, InspectOptions};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// MCAP logs, or directories of them (segments of one run are read as one series).
    #[arg(required = true, value_name = "LOG")]
    pub logs: Vec<PathBuf>,
    #[command(flatten)]
    pub output: super::JsonArg,
    /// Write the time series, one row per frame with every field.
    #[arg(long, value_name = "OUT.csv")]
    pub csv: Option<PathBuf>,
    /// Draw the time series and periodogram (format from the extension: .png or .svg).
    #[arg(long, value_name = "OUT.png|OUT.svg")]
    pub plot: Option<PathBuf>,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter inspect out/sji1400
  sunjitter inspect out/sji1400 --csv jitter.csv --plot jitter.png
  sunjitter inspect out/sji1400/*.mcap --json";

pub fn run(args: &Args) -> Result<ExitCode> {
    if let Some(plot) = &args.plot {
        let ext = plot
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if !matches!(ext.as_deref(), Some("png") | Some("svg")) {
            return Err(Error::Usage(format!(
                "--plot {}: the file name must end in .png or .svg",
                plot.display()
            )));
        }
    }
    for path in args.csv.iter().chain(&args.plot) {
        sunjitter_core::error::check_writable(path)?;
    }
    let files = log_files(&args.logs)?;
    let outputs: Vec<&std::path::Path> = [&args.csv, &args.plot]
        .into_iter()
        .filter_map(|p| p.as_deref())
        .collect();
    let inputs: Vec<&std::path::Path> = files.iter().map(PathBuf::as_path).collect();
    sunjitter_io::outputs::check_outputs(&outputs, &inputs)?;
    let (frames, references, log) = read_frames_and_references(&files)?;
    let analyses = inspect::analyse(&frames, &InspectOptions::default());
    let names: Vec<String> = files.iter().map(|p| p.display().to_string()).collect();
    let mut report = inspect::report(&names, &analyses, log);
    report.consistency = inspect::consistency::consistency(&frames, &references);

    if let Some(path) = &args.csv {
        sunjitter_io::outputs::write_file_atomically(path, |mut w| {
            inspect::csv::write_csv(&mut w, &analyses)
        })?;
    }
    if let Some(path) = &args.plot {
        sunjitter_io::outputs::write_atomically(path, |tmp| {
            inspect::plot::write_plot(&analyses, tmp)
        })?;
    }
    if args.output.json {
        let doc = serde_json::to_string_pretty(&report)
            .map_err(|e| Error::Usage(format!("cannot encode the report: {e}")))?;
        println!("{doc}");
    } else {
        print!("{}", inspect::render_text(&report));
    }
    Ok(ExitCode::Ok)
}
