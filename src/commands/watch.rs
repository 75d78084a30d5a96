//! `sunjitter watch DIR --out OUT`: the daemon.

use crate::config::{Config, Overrides};
use crate::pipeline::{open_output, EngineAligner, FitsReader, Progress, RunParts};
use crate::{Error, Result};
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Directory to watch for new FITS frames.
    pub dir: PathBuf,
    /// Output directory for the MCAP log segments.
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Reference policy for every channel: keyframe, previous, fixed:FILE, channel:NAME.
    #[arg(long, value_name = "POLICY")]
    pub reference: Option<String>,
    /// Configuration file (TOML); see examples/sunjitter.toml.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Watch subdirectories too.
    #[arg(long)]
    pub recursive: bool,
    /// Also serve the logged topics live over the Foxglove WebSocket protocol.
    #[arg(long, value_name = "ADDR:PORT")]
    pub live: Option<String>,
    /// On exit, print a JSON summary of the run on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Resolve the configuration from `--config` and the flags.
pub fn effective_config(
    config: Option<&std::path::Path>,
    reference: Option<&str>,
    recursive: bool,
) -> Result<Config> {
    let overrides = Overrides {
        reference: reference.map(str::parse).transpose()?,
        recursive,
    };
    let mut config = Config::load(config, &overrides)?;
    config.canonicalize_fixed_paths()?;
    Ok(config)
}

pub fn run(args: &Args) -> Result<i32> {
    if let Some(live) = &args.live {
        let addr: std::net::SocketAddr = live.parse().map_err(|_| {
            Error::Usage(format!(
                "--live {live}: expected ADDR:PORT, e.g. 127.0.0.1:8765"
            ))
        })?;
        return Err(Error::Usage(format!(
            "--live {addr}: the live Foxglove view is not implemented yet"
        )));
    }
    let config = effective_config(
        args.config.as_deref(),
        args.reference.as_deref(),
        args.recursive,
    )?;
    if !args.dir.is_dir() {
        return Err(Error::bad_input(&args.dir, "not a directory"));
    }
    let (sink, history) = open_output(&args.out, &config)?;
    let config = Arc::new(config);
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(FitsReader),
        aligner: Arc::new(EngineAligner(config.engine.clone())),
        sink,
        history,
        progress: tokio::sync::watch::channel(Progress::default()).0,
        live: true,
    };
    let runtime = runtime()?;
    let progress = runtime
        .block_on(async { crate::daemon::run_daemon(&args.dir, parts, termination()).await })?;
    tracing::info!(
        frames = progress.frames,
        skipped = progress.skipped,
        "stopped cleanly"
    );
    if args.json {
        println!("{}", summary_json(&progress, &args.out));
    }
    Ok(0)
}

pub(crate) fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("sunjitter")
        .build()
        .map_err(|e| Error::output("runtime", e.to_string()))
}

/// Resolves on SIGINT or SIGTERM. Call it inside the runtime: the handlers are installed at
/// once, so a signal that arrives before the future is first polled still stops the run
/// cleanly (instead of killing the process with the default action).
pub(crate) fn termination() -> impl std::future::Future<Output = ()> + Send + 'static {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let handlers = (
            signal(SignalKind::terminate()),
            signal(SignalKind::interrupt()),
        );
        async move {
            match handlers {
                (Ok(mut term), Ok(mut int)) => {
                    tokio::select! {
                        _ = term.recv() => {}
                        _ = int.recv() => {}
                    }
                }
                _ => {
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
        }
    }
    #[cfg(not(unix))]
    {
        async {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

/// The run summary printed with `--json`.
pub(crate) fn summary_json(p: &Progress, out: &std::path::Path) -> serde_json::Value {
    serde_json::json!({
        "out": out.display().to_string(),
        "frames": p.frames,
        "ok": p.ok,
        "degraded": p.degraded,
        "failed": p.failed,
        "skipped": p.skipped,
        "reference_changes": p.references,
        "channels": p.per_channel,
        "write_errors": p.write_errors,
    })
}
