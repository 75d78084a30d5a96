//! `sunjitter replay PATH… --out OUT`: the daemon's pipeline over archived frames.

use super::watch::{effective_config, runtime, summary_json, termination};
use crate::error::exit;
use crate::pipeline::{
    expand_inputs, open_output, replay_inputs, EngineAligner, FitsReader, Input, Progress, RunParts,
};
use crate::Result;
use std::sync::Arc;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// FITS files, directories, globs or 3-D cubes (every frame is taken, in time order).
    #[arg(required = true, value_name = "PATH")]
    pub paths: Vec<String>,
    #[command(flatten)]
    pub run: super::PipelineArgs,
    #[arg(long, help = super::JSON_HELP)]
    pub json: bool,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter replay data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits --out out/sji1400
  sunjitter replay data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits \\
      data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits \\
      --config examples/demo.toml --out out/demo
  sunjitter replay 'data/real/iris_*_SJI_*.fits' --reference previous --out out/iris --json";

pub fn run(args: &Args) -> Result<i32> {
    let config = effective_config(&args.run)?;
    let files = expand_inputs(&args.paths, &config)?;
    let products = crate::products::for_replay(&args.run, &args.paths, &files)?;
    let (sink, history) = open_output(&args.run.out, &config)?;
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
    drop(bar);
    let progress = result?;
    eprintln!(
        "sunjitter: {} frames logged to {} ({} ok, {} degraded, {} failed), {} inputs skipped",
        progress.frames,
        crate::text::path(&args.run.out),
        progress.ok,
        progress.degraded,
        progress.failed,
        progress.skipped
    );
    if args.json {
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
