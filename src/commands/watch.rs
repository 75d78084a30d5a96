//! `sunjitter watch DIR --out OUT`: the daemon.

use crate::config::{Config, Overrides};
use crate::monitor::{Monitor, MonitorSetup};
use crate::outputs::{check_outputs, OutputLock};
use crate::pipeline::{read_history, EngineAligner, FitsReader, Progress, RunParts};
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
    /// Also serve the logged topics live over the Foxglove WebSocket protocol, on
    /// 127.0.0.1:8765 unless another address is given (port 0: any free port). A
    /// non-loopback address exposes the data to the network (read-only).
    #[arg(
        long,
        value_name = "ADDR:PORT",
        num_args = 0..=1,
        default_missing_value = "127.0.0.1:8765"
    )]
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
    let live = args.live.as_deref().map(parse_live_address).transpose()?;
    let config = effective_config(
        args.config.as_deref(),
        args.reference.as_deref(),
        args.recursive,
    )?;
    if !args.dir.is_dir() {
        return Err(Error::bad_input(&args.dir, "not a directory"));
    }
    // Before reading (and recovering) the log: another daemon may be writing it.
    let lock = OutputLock::acquire(&args.out)?;
    let status_file = config.health.status_path(&args.out);
    let config_file: Vec<&std::path::Path> = args.config.as_deref().into_iter().collect();
    check_outputs(&[&status_file], &config_file)?;
    let history = read_history(&args.out)?;
    let mcap =
        crate::sink::McapSink::new(&args.out, config.sink.clone(), config.to_json().to_string())?
            .holding(lock);
    let (progress_tx, progress_rx) = tokio::sync::watch::channel(Progress::default());
    let runtime = runtime()?;
    let setup = MonitorSetup {
        config: &config,
        watching: &args.dir,
        out: &args.out,
        live,
        progress: progress_rx,
    };
    let (monitor, sink) = runtime.block_on(Monitor::start(setup, mcap))?;
    let config = Arc::new(config);
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(FitsReader::from_config(&config)),
        aligner: Arc::new(EngineAligner::from_config(&config)),
        sink: Box::new(sink),
        history,
        progress: progress_tx,
        live: true,
    };
    let result = runtime
        .block_on(async { crate::daemon::run_daemon(&args.dir, parts, termination()).await });
    let stopped = {
        let _inside = runtime.enter();
        monitor.stop()
    };
    let progress = result?;
    stopped?;
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

/// `--live ADDR:PORT` (a host name is resolved; its first address is used).
pub fn parse_live_address(text: &str) -> Result<std::net::SocketAddr> {
    use std::net::ToSocketAddrs;
    let bad = || {
        Error::Usage(format!(
            "--live {text}: expected ADDR:PORT, e.g. 127.0.0.1:8765"
        ))
    };
    if let Ok(addr) = text.parse() {
        return Ok(addr);
    }
    text.to_socket_addrs()
        .map_err(|_| bad())?
        .next()
        .ok_or_else(bad)
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
