//! `sunjitter replay PATH… --out OUT`: the daemon's pipeline over archived frames.

use super::watch::{effective_config, runtime, summary_json, termination};
use crate::error::exit;
use crate::ingest::expand_inputs;
use crate::pipeline::{
    open_output, replay_inputs, EngineAligner, FitsReader, Input, Progress, RunParts,
};
use crate::reference::History;
use crate::Result;
use std::sync::Arc;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// FITS files, directories, globs or 3-D cubes (every frame is taken, in time order).
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<String>,
    #[command(flatten)]
    pub run: super::PipelineArgs,
    #[command(flatten)]
    pub output: super::JsonArg,
    /// Measure only shard K (0-based) of N of the inputs, for `sunjitter merge` to join.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<crate::shard::ShardSpec>,
    /// With --shard: frames of each channel measured before the shard's own, not logged
    /// [default: a keyframe interval; 4 for previous; 1 for channel:NAME; 0 for fixed:FILE].
    #[arg(long, value_name = "FRAMES", requires = "shard")]
    pub shard_overlap: Option<usize>,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter replay data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits --out out/sji1400
  sunjitter replay data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits \\
      data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits \\
      --config examples/demo.toml --out out/demo
  sunjitter replay 'data/real/iris_*_SJI_*.fits' --reference previous --out out/iris --json
Past one machine: run --shard K/N for K = 0…N−1 (e.g. a Slurm job array, examples/slurm/),
each into its own --out, then join them with `sunjitter merge`.";

pub fn run(args: &Args) -> Result<i32> {
    let config = effective_config(&args.run)?;
    let files = expand_inputs(&args.paths, &config)?;
    if args.shard.is_some() && args.run.aligned.is_some() {
        // A shard's chains start at its own origin and its overlap frames are not its own:
        // products of different shards would not share one pointing.
        return Err(crate::Error::Usage(
            "--aligned cannot be combined with --shard: write the products from a single run"
                .into(),
        ));
    }
    let products = crate::products::for_replay(args.run.products(), &args.paths, &files)?;
    let reader = FitsReader::from_config(&config);
    let (sink, history, inputs, shard) = match args.shard {
        None => {
            let (sink, history) = open_output(&args.run.out, &config)?;
            let inputs = replay_inputs(&files, &config, &reader, &history);
            (sink, history, inputs, None)
        }
        // A shard starts afresh: a requeued attempt replaces its earlier output.
        Some(spec) => {
            let all = replay_inputs(&files, &config, &reader, &History::default());
            let (sink, inputs, plan) =
                crate::shard::open_shard(&args.run.out, &config, spec, args.shard_overlap, all)?;
            (sink, plan.history(), inputs, Some(plan))
        }
    };
    let total = inputs
        .iter()
        .filter(|i| matches!(i, Input::Frame(_) | Input::Record(_)))
        .count() as u64;
    let config = Arc::new(config);
    let (progress_tx, mut progress_rx) = tokio::sync::watch::channel(Progress::default());
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(reader),
        aligner: Arc::new(EngineAligner::from_config(&config).sharing(super::workspace())),
        sink,
        history,
        progress: progress_tx,
        live: false,
        products,
    };

    let bar = super::Bar::new(total, "frames");
    let runtime = runtime()?;
    let result = runtime.block_on(async {
        let bar_task = {
            let bar: indicatif::ProgressBar = (*bar).clone();
            tokio::spawn(async move {
                while progress_rx.changed().await.is_ok() {
                    let p = progress_rx.borrow().clone();
                    bar.set_position(p.finished);
                    let skipped = if p.skipped > 0 {
                        format!(" {} skipped", p.skipped)
                    } else {
                        String::new()
                    };
                    bar.set_message(format!(
                        "{} ok {} degraded {} failed{skipped}",
                        p.ok, p.degraded, p.failed
                    ));
                }
            })
        };
        let result = crate::pipeline::run_replay(inputs, parts, termination()).await;
        bar_task.abort();
        result
    });
    drop(bar);
    let progress = result?;
    match &shard {
        None => eprintln!(
            "sunjitter: {} frames logged to {} ({} ok, {} degraded, {} failed), {} inputs skipped",
            progress.frames,
            crate::text::path(&args.run.out),
            progress.ok,
            progress.degraded,
            progress.failed,
            progress.skipped
        ),
        Some(plan) => eprintln!(
            "sunjitter: shard {}: frames {}..{} of {} logged to {} ({} own; {} measured with \
             the overlap: {} ok, {} degraded, {} failed), {} inputs skipped",
            plan.spec,
            plan.start,
            plan.end,
            plan.total,
            crate::text::path(&args.run.out),
            plan.owned.len(),
            progress.frames,
            progress.ok,
            progress.degraded,
            progress.failed,
            progress.skipped
        ),
    }
    if args.output.json {
        println!("{}", summary_json(&progress, &args.run.out));
    }
    // Frames that failed are results (logged as such); the run failed only if it had input
    // and not one frame gave a measurement.
    let measured = progress.ok + progress.degraded;
    Ok(if total > 0 && measured == 0 {
        exit::FAILED
    } else {
        exit::OK
    })
}
