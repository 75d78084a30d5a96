//! `replay`: `sunjitter replay`'s pipeline over archived files, reporting its progress to a
//! Python callable; Ctrl-C stops it as SIGINT stops the command (frames in hand finished, the
//! log closed; a later run into the same log takes the rest).

use crate::errors::IntoPy;
use crate::wait::{self, OnInterrupt};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;
use sunjitter_core::{Error, Result};
use sunjitter_runtime::config::Overrides;
use sunjitter_runtime::pipeline::Progress;
use sunjitter_runtime::products::Request;
use sunjitter_runtime::replay::{ReplayRequest, ReplayRun};
use tokio::sync::{oneshot, watch};

/// The progress as a dict: `total`, `finished`, `frames`, `ok`, `degraded`, `failed`, `skipped`.
fn progress_dict<'py>(py: Python<'py>, total: u64, p: &Progress) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("total", total)?;
    d.set_item("finished", p.finished)?;
    d.set_item("frames", p.frames)?;
    d.set_item("ok", p.ok)?;
    d.set_item("degraded", p.degraded)?;
    d.set_item("failed", p.failed)?;
    d.set_item("skipped", p.skipped)?;
    d.set_item("reference_changes", p.references)?;
    d.set_item("write_errors", p.write_errors)?;
    Ok(d)
}

/// `replay`'s settings: the keyword arguments of `sunjitter.replay`, as its wrapper passes them
/// (a dict; the configuration's keys only when one is given).
#[derive(FromPyObject)]
#[pyo3(from_item_all)]
pub struct ReplayOptions {
    reference: Option<String>,
    #[pyo3(default)]
    config_path: Option<PathBuf>,
    #[pyo3(default)]
    config_table: Option<String>,
    recursive: bool,
    aligned: Option<PathBuf>,
    wcs_only: bool,
}

/// Run the pipeline over `paths` into the log directory `out` with `options`;
/// `on_progress(dict)` is called as frames finish (and first with nothing finished, when the
/// total is known). Returns the run's summary (the dict `replay --json` prints, as JSON).
#[pyfunction]
#[pyo3(signature = (paths, out, options, on_progress=None))]
pub fn replay(
    py: Python<'_>,
    paths: Vec<String>,
    out: PathBuf,
    options: ReplayOptions,
    on_progress: Option<Bound<'_, PyAny>>,
) -> PyResult<String> {
    let ReplayOptions {
        reference,
        config_path,
        config_table,
        recursive,
        aligned,
        wcs_only,
    } = options;
    let config = crate::config::Source::new(config_path, config_table);
    let (progress_tx, progress_rx) = watch::channel(Progress::default());
    let (total_tx, total_rx) = std::sync::mpsc::channel::<u64>();
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let summary_out = out.clone();
    let work = move || -> Result<Progress> {
        if wcs_only && aligned.is_none() {
            return Err(Error::Usage("wcs_only needs aligned=DIR".into()));
        }
        let overrides = Overrides {
            reference: reference.as_deref().map(str::parse).transpose()?,
            recursive,
        };
        let source = config;
        let mut config = source.load(&overrides)?;
        config.canonicalize_fixed_paths()?;
        let replay = ReplayRun::open(ReplayRequest {
            paths: &paths,
            out: &out,
            config,
            config_path: source.path(),
            products: Request {
                dir: aligned.as_deref(),
                wcs_only,
                out: &out,
            },
            shard: None,
        })?;
        let _ = total_tx.send(replay.total());
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .thread_name("sunjitter")
            .build()
            .map_err(|e| Error::output("runtime", e.to_string()))?;
        runtime.block_on(replay.run(progress_tx, async {
            let _ = stop_rx.await;
        }))
    };
    let stop = move || {
        let _ = stop_tx.send(());
    };
    let mut total = None;
    let mut shown: Option<Progress> = None;
    let tick = |py: Python<'_>| -> PyResult<()> {
        if total.is_none() {
            total = total_rx.try_recv().ok();
        }
        let (Some(total), Some(callback)) = (total, &on_progress) else {
            return Ok(());
        };
        let now = progress_rx.borrow().clone();
        if shown.as_ref() != Some(&now) {
            callback.call1((progress_dict(py, total, &now)?,))?;
            shown = Some(now);
        }
        Ok(())
    };
    let progress =
        wait::run(py, "replay", work, OnInterrupt::Stop(Box::new(stop)), tick)?.py_err()?;
    let summary = progress.summary_json(&summary_out);
    Ok(summary.to_string())
}
