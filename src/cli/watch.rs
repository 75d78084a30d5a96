//! `sunjitter watch DIR --out OUT`: the daemon.

use std::path::PathBuf;
use std::sync::Arc;
use sunjitter_core::error::Error;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_io::outputs::check_outputs_outside;
use sunjitter_runtime::config::{Config, Overrides};
use sunjitter_runtime::monitor::{Monitor, MonitorSetup};
use sunjitter_runtime::pipeline::{EngineAligner, FitsReader, Progress, RunParts};
use sunjitter_runtime::runs::open_run;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Directory to watch for new FITS frames.
    pub dir: PathBuf,
    #[command(flatten)]
    pub run: super::PipelineArgs,
    /// Also serve the logged topics live to Foxglove over WebSocket [no value: 127.0.0.1:8765;
    /// port 0: any free port].
    #[arg(
        long,
        value_name = "ADDR:PORT",
        num_args = 0..=1,
        default_missing_value = "127.0.0.1:8765"
    )]
    pub live: Option<String>,
    #[command(flatten)]
    pub output: super::JsonArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter watch incoming/ --out out/watch
  sunjitter watch incoming/ --out out/watch --config examples/sunjitter.toml --recursive
  sunjitter watch incoming/ --out out/watch --live 127.0.0.1:8765
Each logged frame gets one line on stderr; `sunjitter status out/watch` shows the health.
With --json, the run's summary is printed when the daemon stops.
A --live address beyond loopback serves the data (read-only) to the network.";

/// Resolve the configuration from `--config` and the flags.
pub fn effective_config(args: &super::PipelineArgs) -> Result<Config> {
    let overrides = Overrides {
        reference: args.reference.as_deref().map(str::parse).transpose()?,
        recursive: args.recursive,
    };
    let mut config = args.config.load(&overrides)?;
    config.canonicalize_fixed_paths()?;
    Ok(config)
}

pub fn run(args: &Args) -> Result<ExitCode> {
    let live = args.live.as_deref().map(parse_live_address).transpose()?;
    let config = effective_config(&args.run)?;
    let clients = if live.is_some() {
        config.live.max_clients as u64
    } else {
        0
    };
    super::ensure_open_files(super::MIN_OPEN_FILES + clients)?;
    if !args.dir.is_dir() {
        return Err(Error::bad_input(&args.dir, "not a directory"));
    }
    let root = args
        .dir
        .canonicalize()
        .map_err(|e| Error::io(&args.dir, e))?;
    // What no output may overwrite: the references and the configuration (and, as trees,
    // the watched directory and the products).
    let mut protected = config.reference_files();
    protected.extend(args.run.config.path.clone());
    let products = sunjitter_runtime::products::open(
        args.run.products(),
        std::slice::from_ref(&root),
        &protected,
        &root,
    )?;
    let watched: (&std::path::Path, &str) = (&root, "the watched directory");
    sunjitter_runtime::runs::check_out_dir(&args.run.out.dir, &[watched], true, &[])?;
    let status_file = config.health.status_path(&args.run.out.dir);
    let mut trees = vec![watched];
    if let Some(dir) = args.run.aligned.as_deref() {
        trees.push((dir, "the --aligned directory"));
    }
    let protected_refs: Vec<&std::path::Path> = protected.iter().map(|p| p.as_path()).collect();
    check_outputs_outside(&[&status_file], &protected_refs, &trees)?;
    // Before reading (and recovering) the log: another daemon may be writing it.
    let identity = sunjitter_runtime::runs::RunIdentity::watch(&root);
    let opened = open_run(&args.run.out.dir, &config, &identity)?;
    if let Some(dir) = status_file.parent().filter(|d| !d.as_os_str().is_empty()) {
        sunjitter_core::error::check_writable_dir(dir)?;
    }
    if opened.earlier_frames > 0 {
        tracing::info!(
            frames = opened.earlier_frames,
            "resuming the log in {}: frames already logged are not measured again",
            sunjitter_core::text::path(&args.run.out.dir)
        );
    }
    let (history, mcap) = (opened.history, opened.sink);
    let (progress_tx, progress_rx) = tokio::sync::watch::channel(Progress::default());
    let runtime = runtime()?;
    let setup = MonitorSetup {
        config: &config,
        watching: &args.dir,
        out: &args.run.out.dir,
        live,
        progress: progress_rx,
    };
    let (monitor, sink) = runtime.block_on(Monitor::start(setup, mcap))?;
    let config = Arc::new(config);
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(FitsReader::from_config(&config)),
        aligner: Arc::new(
            EngineAligner::from_config(&config)
                .sharing(sunjitter_io::self_tests::SelfTestCache::workspace_from_env()),
        ),
        sink: Box::new(sink),
        history,
        progress: progress_tx,
        live: true,
        products,
    };
    let result = runtime.block_on(async {
        sunjitter_runtime::daemon::run_daemon(&args.dir, parts, termination()?).await
    });
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
    if args.output.json {
        println!("{}", progress.summary_json(&args.run.out.dir));
    }
    Ok(ExitCode::Ok)
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
/// cleanly (instead of killing the process with the default action). A handler that cannot
/// be installed is an error, before any work: a run that could not be stopped is not started.
pub(crate) fn termination() -> Result<impl std::future::Future<Output = ()> + Send + 'static> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let install = |kind: SignalKind, name: &str| {
            signal(kind).map_err(|e| {
                Error::output(
                    "signal handlers",
                    format!("cannot install the {name} handler: {e}"),
                )
            })
        };
        let mut term = install(SignalKind::terminate(), "SIGTERM")?;
        let mut int = install(SignalKind::interrupt(), "SIGINT")?;
        Ok(async move {
            tokio::select! {
                _ = term.recv() => {}
                _ = int.recv() => {}
            }
        })
    }
    #[cfg(not(unix))]
    {
        Ok(async {
            let _ = tokio::signal::ctrl_c().await;
        })
    }
}
