//! A daemon running in the test's own tokio runtime (the library's `run_daemon`), started
//! from its parts and stopped on demand. The time bounds only stop a hung daemon: the tests
//! of one file share two cores and run at once.
#![allow(dead_code)]

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use sunjitter_io::records::RecordSink;
use sunjitter_runtime::config::Config;
use sunjitter_runtime::pipeline::{Progress, RunParts};
use sunjitter_runtime::ports::{Aligner, FrameReader};
use sunjitter_runtime::reference::History;
use tokio::sync::{oneshot, watch};

/// How long a wait may take before the daemon counts as hung.
const HUNG: Duration = Duration::from_secs(600);

/// A daemon running in this process.
pub struct Daemon {
    pub progress: watch::Receiver<Progress>,
    stop: oneshot::Sender<()>,
    handle: tokio::task::JoinHandle<sunjitter_core::error::Result<Progress>>,
}

/// Run a daemon on `dir` with `config`, `reader`, `aligner` and `sink`, continuing `history`
/// (what earlier runs logged, as [`sunjitter_runtime::pipeline::read_history`] gives it).
pub fn spawn(
    dir: &Path,
    config: Config,
    reader: Arc<dyn FrameReader>,
    aligner: Arc<dyn Aligner>,
    sink: Box<dyn RecordSink>,
    history: History,
) -> Daemon {
    let (progress_tx, progress) = watch::channel(Progress::default());
    let parts = RunParts {
        config: Arc::new(config),
        reader,
        aligner,
        sink,
        history,
        progress: progress_tx,
        live: true,
        products: None,
    };
    let (stop, stopped) = oneshot::channel::<()>();
    let dir = dir.to_path_buf();
    let handle = tokio::spawn(async move {
        sunjitter_runtime::daemon::run_daemon(&dir, parts, async {
            let _ = stopped.await;
        })
        .await
    });
    Daemon {
        progress,
        stop,
        handle,
    }
}

impl Daemon {
    /// Wait until the predicate holds on the progress counters.
    pub async fn wait_for(&self, what: &str, f: impl Fn(&Progress) -> bool) -> Progress {
        let mut rx = self.progress.clone();
        let wait = async move { rx.wait_for(|p| f(p)).await.map(|p| p.clone()) };
        match tokio::time::timeout(HUNG, wait).await {
            Ok(Ok(p)) => p,
            _ => panic!(
                "timed out waiting for {what}: {:?}",
                *self.progress.borrow()
            ),
        }
    }

    pub async fn watching(&self) {
        self.wait_for("the watcher", |p| p.watching).await;
    }

    /// Stop the daemon and return its final counters (it must stop cleanly).
    pub async fn shutdown(self) -> Progress {
        let _ = self.stop.send(());
        tokio::time::timeout(HUNG, self.handle)
            .await
            .expect("stops in time")
            .expect("task")
            .expect("clean run")
    }
}
