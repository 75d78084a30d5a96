//! One module per subcommand: its arguments (clap), its `EXAMPLES` and its `run`.
//! `run` returns the [`ExitCode`](sunjitter_core::error::ExitCode) of work that ran (`Ok` or `Failed`);
//! errors carry their own through [`sunjitter_core::error::Error::exit_code`], and `main` maps both to the
//! process's status.
//!
//! Flags that several commands take are defined here once, so that each means and reads the
//! same everywhere: [`PipelineArgs`] (`watch`, `replay`), [`OutArg`] (theirs and `merge`'s),
//! [`ConfigArg`] and [`JsonArg`].

pub mod align;
pub mod info;
pub mod inspect;
pub mod merge;
pub mod replay;
pub mod simulate;
pub mod status;
pub mod synth;
pub mod watch;

use std::io::Write;
use std::path::PathBuf;
use std::sync::Mutex;

/// `--config` of every command that takes one.
pub const CONFIG_HELP: &str =
    "Configuration file, TOML as examples/sunjitter.toml (align uses its [engine] and channels' plate_scale_arcsec, simulate its [engine])";

/// `--json` of every command.
pub const JSON_HELP: &str = "Print the result as one JSON document on stdout";

/// `--config FILE.toml`, for every command that reads the configuration file.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ConfigArg {
    #[arg(long = "config", value_name = "FILE.toml", help = CONFIG_HELP)]
    pub path: Option<PathBuf>,
}

impl ConfigArg {
    /// The configuration: the file (or the defaults) with `overrides`, checked. The one
    /// loader of every command; `align` and `simulate` use its `[engine]`.
    pub fn load(
        &self,
        overrides: &sunjitter_runtime::config::Overrides,
    ) -> sunjitter_core::error::Result<sunjitter_runtime::config::Config> {
        sunjitter_runtime::config::Config::load(self.path.as_deref(), overrides)
    }
}

/// `--out` of every command that writes a log.
pub const OUT_HELP: &str = "Output directory for the MCAP log segments (and watch's status.json)";

/// `--out DIR`, for every command that writes a log (`watch`, `replay`, `merge`).
#[derive(Debug, Clone, clap::Args)]
pub struct OutArg {
    #[arg(id = "out", long = "out", value_name = "DIR", help = OUT_HELP)]
    pub dir: PathBuf,
}

/// `--json`, for every command.
#[derive(Debug, Clone, Copy, Default, clap::Args)]
pub struct JsonArg {
    #[arg(long = "json", help = JSON_HELP)]
    pub json: bool,
}

/// The options of the pipeline's runs, `watch` and `replay`.
#[derive(Debug, Clone, clap::Args)]
pub struct PipelineArgs {
    #[command(flatten)]
    pub out: OutArg,
    /// Reference policy of every channel: keyframe, previous, fixed:FILE, channel:NAME
    /// [default: --config's, else keyframe].
    #[arg(long, value_name = "POLICY")]
    pub reference: Option<String>,
    #[command(flatten)]
    pub config: ConfigArg,
    /// Take the files in subdirectories of the directories given too.
    #[arg(long)]
    pub recursive: bool,
    /// Write each measured frame, resampled onto its chain origin's grid with that WCS, as
    /// DIR/NAME.aligned.fits (the input tree mirrored; DIR outside it and apart from --out).
    #[arg(long, value_name = "DIR")]
    pub aligned: Option<PathBuf>,
    /// With --aligned: keep each frame's own pixels and correct only its header's pointing
    /// (CRPIXi, CDELTi, PCi_j), as DIR/NAME.wcs.fits.
    #[arg(long, requires = "aligned")]
    pub wcs_only: bool,
}

impl PipelineArgs {
    /// What `--aligned`/`--wcs-only` ask for.
    pub fn products(&self) -> sunjitter_runtime::products::Request<'_> {
        sunjitter_runtime::products::Request {
            dir: self.aligned.as_deref(),
            wcs_only: self.wcs_only,
            out: &self.out.dir,
        }
    }
}

/// File descriptors a `watch` or `replay` holds at the most besides its live clients: the
/// standard streams, the runtime's (event loop, its waker, the signal pipe), the watcher, the
/// output directory's lock, an MCAP segment, the files its readers and workers have open
/// (cfitsio, decompressed copies, the self-test cache) and a product being written, with room.
pub const MIN_OPEN_FILES: u64 = 64;

/// Make sure the process may open `need` files: the soft limit is raised toward the hard one
/// when it is lower; if even the hard limit is lower, refuse before any work (exit 2) rather
/// than fail half-way through a run.
pub fn ensure_open_files(need: u64) -> sunjitter_core::error::Result<()> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit fills the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } != 0 {
            return Ok(());
        }
        let (soft, hard) = (limit.rlim_cur, limit.rlim_max);
        if limit.rlim_cur == libc::RLIM_INFINITY || soft >= need {
            return Ok(());
        }
        if limit.rlim_max == libc::RLIM_INFINITY || hard >= need {
            limit.rlim_cur = need as libc::rlim_t;
            // SAFETY: a limit within the hard limit, for this process.
            if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &limit) } == 0 {
                return Ok(());
            }
        }
        Err(sunjitter_core::error::Error::Usage(format!(
            "the open-file limit is {soft} (ulimit -n): this run needs at least {need}; raise it (e.g. ulimit -n 1024) and run again"
        )))
    }
    #[cfg(not(unix))]
    {
        let _ = need;
        Ok(())
    }
}
// ---------------------------------------------------------------------------------------------
// Progress bars that log lines do not tear

static ACTIVE_BAR: Mutex<Option<indicatif::ProgressBar>> = Mutex::new(None);

fn set_active_bar(bar: Option<indicatif::ProgressBar>) {
    if let Ok(mut active) = ACTIVE_BAR.lock() {
        *active = bar;
    }
}

/// A progress bar on stderr, drawn only when stderr is a terminal (on a pipe or a file,
/// nothing). While it lives, log lines written through [`BarAwareStderr`] hide it for the
/// moment they are written; dropping it clears it.
pub struct Bar(indicatif::ProgressBar);

impl Bar {
    /// `len` steps of `what` (`frames`, `trials`).
    pub fn new(len: u64, what: &str) -> Bar {
        let bar = indicatif::ProgressBar::with_draw_target(
            Some(len),
            indicatif::ProgressDrawTarget::hidden(),
        );
        // `wide_bar` takes what the terminal's width leaves: one line that never wraps.
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{wide_bar}] {pos}/{len} {prefix} {msg} (eta {eta})",
        ) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_prefix(what.to_string());
        if std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
        }
        set_active_bar(Some(bar.clone()));
        Bar(bar)
    }
}

impl std::ops::Deref for Bar {
    type Target = indicatif::ProgressBar;
    fn deref(&self) -> &indicatif::ProgressBar {
        &self.0
    }
}

impl Drop for Bar {
    fn drop(&mut self) {
        self.0.finish_and_clear();
        set_active_bar(None);
    }
}

/// A `tracing_subscriber` writer for stderr that hides the active [`Bar`] while a log line
/// is written, so bars and logs never tear. Use it in the binary:
/// `tracing_subscriber::fmt().with_writer(sunjitter::cli::BarAwareStderr)`.
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
