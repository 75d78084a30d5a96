//! `replay`'s setup: the files listed and checked, the log opened (and locked), the products'
//! directory checked, then the pipeline run over them. `sunjitter replay` and the Python
//! package both run this.

use crate::config::Config;
use crate::pipeline::{replay_inputs, run_replay, EngineAligner, FitsReader};
use crate::pipeline::{Input, Progress, RunParts};
use crate::reference::History;
use sunjitter_core::Result;
use tokio::sync::watch;

/// What a replay is asked to do (`sunjitter replay`'s arguments).
pub struct ReplayRequest<'a> {
    /// Files, directories, globs or cubes.
    pub paths: &'a [String],
    /// The log directory.
    pub out: &'a std::path::Path,
    /// The effective configuration (file and flags).
    pub config: Config,
    /// The configuration file it was read from, which no output may overwrite.
    pub config_path: Option<&'a std::path::Path>,
    /// Per-frame products (`--aligned`, `--wcs-only`).
    pub products: crate::products::Request<'a>,
    /// `--shard K/N` with its `--shard-overlap`.
    pub shard: Option<(crate::shard::ShardSpec, Option<usize>)>,
}

/// A replay ready to run: its inputs listed and checked, its log opened (and locked), its
/// products' directory checked. `sunjitter replay` and the Python package both run this.
pub struct ReplayRun {
    inputs: Vec<Input>,
    parts: RunParts,
    shard: Option<crate::shard::ShardPlan>,
    /// Frames an earlier run of this same replay logged already.
    earlier_frames: u64,
}

impl ReplayRun {
    /// Everything done before the first frame is measured; errors are the command's (bad
    /// paths, a log of another run, a held output, products that cannot go where asked).
    pub fn open(request: ReplayRequest<'_>) -> Result<ReplayRun> {
        let ReplayRequest {
            paths,
            out,
            config,
            config_path,
            products,
            shard,
        } = request;
        if let Some((_, Some(n))) = shard {
            crate::limits::flag_int("--shard-overlap", n as u64, 0, 1_000_000)?;
        }
        let files = crate::ingest::expand_inputs(paths, &config)?;
        if shard.is_some() && products.dir.is_some() {
            // A shard's chains start at its own origin and its overlap frames are not its own:
            // products of different shards would not share one pointing.
            return Err(sunjitter_core::Error::Usage(
                "--aligned cannot be combined with --shard: write the products from a single run"
                    .into(),
            ));
        }
        // What no output may overwrite besides the inputs: the references and the configuration.
        let mut protected = config.reference_files();
        protected.extend(config_path.map(std::path::Path::to_path_buf));
        let products = crate::products::for_replay(products, paths, &files, &protected)?;
        let dirs: Vec<std::path::PathBuf> = paths
            .iter()
            .map(std::path::PathBuf::from)
            .filter(|p| p.is_dir())
            .collect();
        let trees: Vec<(&std::path::Path, &str)> = dirs
            .iter()
            .map(|d| (d.as_path(), "the input directory"))
            .collect();
        let mut input_files: Vec<std::path::PathBuf> =
            files.iter().map(|(p, _)| p.clone()).collect();
        input_files.extend(protected.iter().cloned());
        crate::runs::check_out_dir(out, &trees, config.daemon.recursive, &input_files)?;
        let reader = FitsReader::from_config(&config);
        let mut earlier_frames = 0;
        let (sink, history, inputs, shard) = match shard {
            None => {
                let identity = crate::runs::RunIdentity::replay(&files);
                let opened = crate::runs::open_run(out, &config, &identity)?;
                earlier_frames = opened.earlier_frames;
                let inputs = replay_inputs(&files, &config, &reader, &opened.history);
                let sink: Box<dyn sunjitter_io::records::RecordSink> =
                    Box::new(sunjitter_io::records::McapRecordSink(opened.sink));
                (sink, opened.history, inputs, None)
            }
            // A shard starts afresh: a requeued attempt replaces its earlier output.
            Some((spec, overlap)) => {
                let all = replay_inputs(&files, &config, &reader, &History::default());
                let (sink, inputs, plan) =
                    crate::shard::open_shard(out, &config, spec, overlap, all)?;
                (sink, plan.history(), inputs, Some(plan))
            }
        };
        let config = std::sync::Arc::new(config);
        let workspace = sunjitter_io::self_tests::SelfTestCache::workspace_from_env();
        let parts = RunParts {
            config: config.clone(),
            reader: std::sync::Arc::new(reader),
            aligner: std::sync::Arc::new(EngineAligner::from_config(&config).sharing(workspace)),
            sink,
            history,
            progress: watch::channel(Progress::default()).0,
            live: false,
            products,
        };
        Ok(ReplayRun {
            inputs,
            parts,
            shard,
            earlier_frames,
        })
    }

    /// Frames an earlier run of this same replay logged already (not measured again).
    pub fn earlier_frames(&self) -> u64 {
        self.earlier_frames
    }

    /// Inputs to finish: frames to measure and files that get a `/log` record instead
    /// ([`Progress::finished`] counts up to it).
    pub fn total(&self) -> u64 {
        self.inputs
            .iter()
            .filter(|i| matches!(i, Input::Frame(_) | Input::Record(_)))
            .count() as u64
    }

    /// The shard's plan, for a sharded replay.
    pub fn shard(&self) -> Option<&crate::shard::ShardPlan> {
        self.shard.as_ref()
    }

    /// Run it, reporting to `progress`, until every input is finished or `shutdown`
    /// resolves (the frames in hand are finished and the log is closed; the rest is taken by
    /// a later run into the same log).
    pub async fn run(
        self,
        progress: watch::Sender<Progress>,
        shutdown: impl std::future::Future<Output = ()> + Send + 'static,
    ) -> Result<Progress> {
        let parts = RunParts {
            progress,
            ..self.parts
        };
        run_replay(self.inputs, parts, shutdown).await
    }
}
