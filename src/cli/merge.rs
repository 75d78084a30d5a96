//! `sunjitter merge SHARD_OUT… --out OUT`: join the logs of `replay --shard K/N`.

use std::path::PathBuf;
use sunjitter_core::error::Result;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output directories of `replay --shard K/N`, one per shard (any order).
    #[arg(required = true, value_name = "SHARD_OUT")]
    pub shards: Vec<PathBuf>,
    #[command(flatten)]
    pub out: super::OutArg,
    #[command(flatten)]
    pub output: super::JsonArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter merge out/iris-0 out/iris-1 out/iris-2 out/iris-3 --out out/iris
  sunjitter merge out/shards/* --out out/merged --json
The shards are the outputs of `sunjitter replay … --shard K/N` for K = 0…N−1. A set with a
shard missing, given twice, unfinished or made from other inputs or configuration is refused
and nothing is written; a merge run again replaces its own earlier output, which stays
whole until the new one takes its place.";

pub fn run(args: &Args) -> Result<sunjitter_core::error::ExitCode> {
    let mut shards = args
        .shards
        .iter()
        .map(|p| sunjitter_runtime::merge::read_shard(p))
        .collect::<Result<Vec<_>>>()?;
    sunjitter_runtime::merge::check_set(&mut shards)?;
    sunjitter_runtime::merge::check_output(&args.out.dir, &shards)?;
    let merged = sunjitter_runtime::merge::merge(&shards);
    let segments = sunjitter_runtime::merge::write(&args.out.dir, &shards, &merged)?;
    let frames: u64 = merged.frames.values().sum();
    eprintln!(
        "sunjitter: {} shards merged into {}: {frames} frames, {} with chained values carried across shards{}",
        shards.len(),
        sunjitter_core::text::path(&args.out.dir),
        merged.stitched,
        if merged.unlinked > 0 {
            format!(", {} left without (see /log)", merged.unlinked)
        } else {
            String::new()
        }
    );
    if args.output.json {
        let doc = serde_json::json!({
            "out": sunjitter_core::text::path(&args.out.dir),
            "shards": shards.len(),
            "frames": frames,
            "per_channel": merged.frames,
            "stitched": merged.stitched,
            "unlinked": merged.unlinked,
            "segments": segments.iter().map(|p| sunjitter_core::text::path(p).into_owned()).collect::<Vec<_>>(),
        });
        println!("{doc}");
    }
    Ok(sunjitter_core::error::ExitCode::Ok)
}
