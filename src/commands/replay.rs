//! `sunjitter replay PATH… --out OUT`: the daemon's pipeline over archived frames.

use super::watch::{effective_config, runtime, summary_json, termination};
use crate::pipeline::{
    expand_inputs, open_output, replay_inputs, EngineAligner, FitsReader, Input, Progress, RunParts,
};
use crate::Result;
use indicatif::{ProgressBar, ProgressStyle};
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// FITS files, directories, globs or 3-D cubes (every frame is taken, in time order).
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<String>,
    /// Output directory for the MCAP log segments.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Reference policy for every channel: keyframe, previous, fixed:FILE, channel:NAME.
    #[arg(long, value_name = "POLICY")]
    pub reference: Option<String>,
    /// Configuration file (TOML); see examples/sunjitter.toml.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Take files in subdirectories of directory arguments too.
    #[arg(long)]
    pub recursive: bool,
    /// Print a JSON summary of the run on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: &Args) -> Result<i32> {
    let config = effective_config(
        args.config.as_deref(),
        args.reference.as_deref(),
        args.recursive,
    )?;
    let files = expand_inputs(&args.paths, &config)?;
    let (sink, history) = open_output(&args.out, &config)?;
    let reader = FitsReader::from_config(&config);
    let inputs = replay_inputs(&files, &config, &reader, &history);
    let total = inputs
        .iter()
        .filter(|i| matches!(i, Input::Frame(_) | Input::Record(_)))
        .count() as u64;
    let config = Arc::new(config);
    let (progress_tx, mut progress_rx) = tokio::sync::watch::channel(Progress::default());
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(reader),
        aligner: Arc::new(EngineAligner::from_config(&config)),
        sink,
        history,
        progress: progress_tx,
        live: false,
    };

    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames ({eta}) {msg}",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    set_active_bar(Some(bar.clone()));
    let runtime = runtime()?;
    let result = runtime.block_on(async {
        let bar_task = {
            let bar = bar.clone();
            tokio::spawn(async move {
                while progress_rx.changed().await.is_ok() {
                    let p = progress_rx.borrow().clone();
                    bar.set_position(p.finished);
                    bar.set_message(format!(
                        "{} ok, {} degraded, {} failed, {} skipped",
                        p.ok, p.degraded, p.failed, p.skipped
                    ));
                }
            })
        };
        let result = crate::pipeline::run_replay(inputs, parts, termination()).await;
        bar_task.abort();
        result
    });
    bar.finish_and_clear();
    set_active_bar(None);
    let progress = result?;
    eprintln!(
        "sunjitter: {} frames logged to {} ({} ok, {} degraded, {} failed), {} inputs skipped",
        progress.frames,
        crate::text::path(&args.out),
        progress.ok,
        progress.degraded,
        progress.failed,
        progress.skipped
    );
    if args.json {
        println!("{}", summary_json(&progress, &args.out));
    }
    // Frames that failed are results (logged as such); the run failed only if it had input
    // and not one frame gave a measurement.
    let measured = progress.ok + progress.degraded;
    Ok(if total > 0 && measured == 0 { 1 } else { 0 })
}

// ---------------------------------------------------------------------------------------------
// Logs that do not tear the progress bar

static ACTIVE_BAR: Mutex<Option<ProgressBar>> = Mutex::new(None);

fn set_active_bar(bar: Option<ProgressBar>) {
    if let Ok(mut active) = ACTIVE_BAR.lock() {
        *active = bar;
    }
}

/// A `tracing_subscriber` writer for stderr that hides the active progress bar while a log
/// line is written, so bars and logs never tear. Use it in the binary:
/// `tracing_subscriber::fmt().with_writer(sunjitter::commands::replay::BarAwareStderr)`.
#[derive(Debug, Clone, Copy, Default)]
pub struct BarAwareStderr;

/// One log event's bytes, written in one piece when dropped.
pub struct BarAwareLine(Vec<u8>);

impl Write for BarAwareLine {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for BarAwareLine {
    fn drop(&mut self) {
        let bytes = std::mem::take(&mut self.0);
        let write = || {
            let mut err = std::io::stderr().lock();
            let _ = err.write_all(&bytes);
            let _ = err.flush();
        };
        let bar = ACTIVE_BAR.lock().ok().and_then(|b| b.clone());
        match bar {
            Some(bar) => bar.suspend(write),
            None => write(),
        }
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for BarAwareStderr {
    type Writer = BarAwareLine;
    fn make_writer(&'a self) -> Self::Writer {
        BarAwareLine(Vec::with_capacity(256))
    }
}
