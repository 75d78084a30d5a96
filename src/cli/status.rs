//! `sunjitter status [PATH|OUTDIR] [--json]`: print a daemon's health status file.

use std::path::PathBuf;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_runtime::monitor::status;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The status file, or the output directory holding `status.json`.
    #[arg(default_value = ".", value_name = "PATH|OUTDIR")]
    pub path: PathBuf,
    #[command(flatten)]
    pub output: super::JsonArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter status out/watch
  sunjitter status out/watch/status.json --json";

pub fn run(args: &Args) -> Result<ExitCode> {
    let path = status::resolve_path(&args.path);
    let s = status::read(&path)?;
    if args.output.json {
        let text = serde_json::to_string(&s)
            .map_err(|e| sunjitter_core::error::Error::output(&path, e.to_string()))?;
        println!("{text}");
    } else {
        let now = sunjitter_io::records::now_ns();
        let diagnosis = if status::is_stale(&s, now) {
            let dir = match path.parent() {
                Some(p) if !p.as_os_str().is_empty() => p,
                _ => std::path::Path::new("."),
            };
            status::diagnose_stale(&s, dir)
        } else {
            None
        };
        print!(
            "{}",
            status::render_diagnosed(&s, now, diagnosis.as_deref())
        );
    }
    Ok(ExitCode::Ok)
}
