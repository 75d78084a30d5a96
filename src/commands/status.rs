//! `sunjitter status [PATH|OUTDIR] [--json]`: print a daemon's health status file.

use crate::monitor::status;
use crate::Result;
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The status file, or the output directory holding `status.json` (default: `.`).
    #[arg(default_value = ".")]
    pub path: PathBuf,
    /// Print the status document as JSON.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: &Args) -> Result<i32> {
    let path = status::resolve_path(&args.path);
    let s = status::read(&path)?;
    if args.json {
        let text =
            serde_json::to_string(&s).map_err(|e| crate::Error::output(&path, e.to_string()))?;
        println!("{text}");
    } else {
        print!("{}", status::render(&s, crate::pipeline::now_ns()));
    }
    Ok(0)
}
