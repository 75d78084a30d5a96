//! `sunjitter replay PATH… --out OUT`: the daemon's pipeline over archived frames.

use super::watch::{effective_config, runtime, termination};
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_runtime::pipeline::Progress;
use sunjitter_runtime::replay::{ReplayRequest, ReplayRun};

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
    pub shard: Option<sunjitter_runtime::shard::ShardSpec>,
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

pub fn run(args: &Args) -> Result<ExitCode> {
    let config = effective_config(&args.run)?;
    super::ensure_open_files(super::MIN_OPEN_FILES)?;
    let replay = ReplayRun::open(ReplayRequest {
        paths: &args.paths,
        out: &args.run.out.dir,
        config,
        config_path: args.run.config.path.as_deref(),
        products: args.run.products(),
        shard: args.shard.map(|spec| (spec, args.shard_overlap)),
    })?;
    let total = replay.total();
    let earlier = replay.earlier_frames();
    let shard = replay.shard().cloned();
    let (progress_tx, mut progress_rx) = tokio::sync::watch::channel(Progress::default());

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
        let result = match termination() {
            Ok(stop) => replay.run(progress_tx, stop).await,
            Err(e) => Err(e),
        };
        bar_task.abort();
        result
    });
    drop(bar);
    let progress = result?;
    match &shard {
        None if progress.frames == 0 && progress.skipped == 0 && earlier > 0 => eprintln!(
            "sunjitter: all {earlier} frames already logged in {} (nothing left to measure)",
            sunjitter_core::text::path(&args.run.out.dir),
        ),
        None => eprintln!(
            "sunjitter: {} frames logged to {} ({} ok, {} degraded, {} failed), {} inputs skipped{}",
            progress.frames,
            sunjitter_core::text::path(&args.run.out.dir),
            progress.ok,
            progress.degraded,
            progress.failed,
            progress.skipped,
            if earlier > 0 {
                format!("; {earlier} frames were logged before")
            } else {
                String::new()
            }
        ),
        Some(plan) => eprintln!(
            "sunjitter: shard {}: frames {}..{} of {} logged to {} ({} own; {} measured with \
             the overlap: {} ok, {} degraded, {} failed), {} inputs skipped",
            plan.spec,
            plan.start,
            plan.end,
            plan.total,
            sunjitter_core::text::path(&args.run.out.dir),
            plan.owned.len(),
            progress.frames,
            progress.ok,
            progress.degraded,
            progress.failed,
            progress.skipped
        ),
    }
    if args.output.json {
        println!("{}", progress.summary_json(&args.run.out.dir));
    }
    // Frames that failed are results (logged as such); the run failed only if it had input
    // and not one frame gave a measurement.
    let measured = progress.ok + progress.degraded;
    Ok(if total > 0 && measured == 0 {
        ExitCode::Failed
    } else {
        ExitCode::Ok
    })
}
