//! Driving it all: the scheduler task between the input queue, the jobs and the writer.

use super::frames::Input;
use super::job::{run_job, JobContext, JobDone, RetryingReader};
use super::progress::Progress;
use super::scheduler::{Action, Scheduler, SchedulerSettings};
use super::writer::{spawn_writer, WriterMsg};
use crate::config::Config;
use crate::ports::{Aligner, FrameReader};
use crate::reference::History;
use std::sync::atomic::AtomicUsize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use sunjitter_core::{Error, Result};
use sunjitter_io::records::{Record, RecordSink};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

/// Everything a run needs besides its input.
pub struct RunParts {
    pub config: Arc<Config>,
    pub reader: Arc<dyn FrameReader>,
    pub aligner: Arc<dyn Aligner>,
    pub sink: Box<dyn RecordSink>,
    pub history: History,
    pub progress: watch::Sender<Progress>,
    pub live: bool,
    /// Where each measured frame's FITS product goes (`--aligned DIR`), if anywhere.
    pub products: Option<Arc<crate::products::Products>>,
}

/// Run the pipeline until the input ends (replay) or `stop` turns true (daemon: frames in
/// hand are finished, buffered ones are left for the next start), then close the sink.
/// `pending_files` (daemon) counts files the front end holds that may still yield frames;
/// it decrements a file only after sending its frames.
pub async fn run_pipeline(
    parts: RunParts,
    input: mpsc::Receiver<Input>,
    stop: watch::Receiver<bool>,
    pending_files: Option<Arc<AtomicUsize>>,
) -> Result<Progress> {
    let RunParts {
        config,
        reader,
        aligner,
        sink,
        history,
        progress,
        live,
        products,
    } = parts;
    let stopping = Arc::new(AtomicBool::new(false));
    let (writer_tx, writer_rx) = mpsc::channel(config.daemon.queue_capacity.max(1));
    let progress_rx = progress.subscribe();
    let queue_progress = progress.clone();
    let writer = spawn_writer(sink, writer_rx, progress, stopping.clone());
    let settings = SchedulerSettings::from_config(&config, live);
    let scheduler = Scheduler::new(config.clone(), settings, &history);
    let ctx = JobContext {
        reader: Arc::new(RetryingReader::new(reader, &config.daemon)),
        aligner,
        products,
    };
    let flush_every = Duration::from_secs_f64(config.daemon.flush_interval_s.max(0.01));
    let driven = Driver {
        input,
        scheduler,
        ctx,
        writer: writer_tx,
        stop,
        stopping,
        flush_every,
        pending_files,
        progress: queue_progress,
    }
    .run()
    .await;
    let written = tokio::task::spawn_blocking(move || writer.join())
        .await
        .map_err(|e| Error::output("writer thread", e.to_string()))?
        .map_err(|_| Error::output("writer thread", "panicked"))?;
    // A writer that gave up says why (the log cannot be written); the driver only saw it go.
    written?;
    driven?;
    let last = progress_rx.borrow().clone();
    Ok(last)
}

/// The scheduler task: everything it owns between the front end, the jobs and the writer.
struct Driver {
    /// Frames and finished-file records from the front end. Bounded, so a busy pipeline
    /// holds the front end back; closed on stop, which the front end sees as the end.
    input: mpsc::Receiver<Input>,
    /// Per-channel order, reorder window and partner choice: which frame runs when.
    scheduler: Scheduler,
    /// What every job reads and aligns with; cloned into each blocking job.
    ctx: JobContext,
    /// Records, lags and flush requests to the writer thread, in the order they are logged.
    /// Bounded, so a slow or failing sink holds the pipeline back instead of growing memory.
    writer: mpsc::Sender<WriterMsg>,
    /// Turns true when the daemon is asked to stop (replay: on a signal).
    stop: watch::Receiver<bool>,
    /// Set once stopping, so the writer thread gives up on a sink that keeps failing.
    stopping: Arc<AtomicBool>,
    /// How often the writer flushes (and rotates segments by time) when idle.
    flush_every: Duration,
    /// Daemon: files the front end holds that may still yield frames; `None` for replay.
    pending_files: Option<Arc<AtomicUsize>>,
    /// Where the queue depths go for the health file.
    progress: watch::Sender<Progress>,
}

impl Driver {
    async fn run(mut self) -> Result<()> {
        let mut jobs: JoinSet<JobDone> = JoinSet::new();
        let mut accepting = true;
        let mut stopped = *self.stop.borrow();
        let mut stop_alive = true;
        let mut flush_tick = tokio::time::interval(self.flush_every);
        flush_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            if stopped {
                if accepting {
                    accepting = false;
                    self.stopping.store(true, Ordering::SeqCst);
                    self.input.close();
                }
            } else {
                // Read the front end's count first, then take what it already sent: a file it
                // finished before the count was read has its frames in the queue by now.
                let pipe_empty = self
                    .pending_files
                    .as_ref()
                    .is_none_or(|p| p.load(Ordering::SeqCst) == 0);
                while accepting {
                    match self.input.try_recv() {
                        Ok(input) => self.accept(input).await?,
                        Err(mpsc::error::TryRecvError::Empty) => break,
                        Err(mpsc::error::TryRecvError::Disconnected) => {
                            accepting = false;
                            self.scheduler.set_eof();
                        }
                    }
                }
                self.scheduler.set_pipe_empty(pipe_empty);
                for action in self.scheduler.poll(Instant::now()) {
                    match action {
                        Action::Run(job) => {
                            let ctx = self.ctx.clone();
                            jobs.spawn_blocking(move || run_job(*job, &ctx));
                        }
                        Action::Emit(record) => self.send(WriterMsg::Record(record)).await?,
                    }
                }
            }
            publish_queue(
                &self.progress,
                &self.scheduler,
                self.pending_files.as_deref(),
            );
            if jobs.is_empty() && (stopped || (self.scheduler.is_eof() && self.scheduler.idle())) {
                break;
            }
            let deadline = self.scheduler.next_deadline();
            tokio::select! {
                biased;
                changed = self.stop.changed(), if stop_alive && !stopped => {
                    match changed {
                        Ok(()) => stopped = *self.stop.borrow(),
                        Err(_) => stop_alive = false, // nobody can ask any more
                    }
                }
                joined = jobs.join_next(), if !jobs.is_empty() => {
                    match joined {
                        Some(Ok(done)) => self.finished(done).await?,
                        Some(Err(e)) => {
                            return Err(Error::output("pipeline", format!("a worker died: {e}")));
                        }
                        None => {}
                    }
                }
                received = self.input.recv(), if accepting => {
                    match received {
                        Some(input) => self.accept(input).await?,
                        None => {
                            accepting = false;
                            self.scheduler.set_eof();
                        }
                    }
                }
                _ = sleep_until_opt(deadline), if deadline.is_some() => {}
                _ = flush_tick.tick() => self.send(WriterMsg::Flush).await?,
            }
        }
        Ok(())
    }

    /// A frame goes to the scheduler (or its refusal to the log); a record to the log.
    async fn accept(&mut self, input: Input) -> Result<()> {
        match input {
            Input::Frame(item) => match self.scheduler.offer(item) {
                Some(refused) => self.send(WriterMsg::Record(refused)).await,
                None => Ok(()),
            },
            Input::Record(record) => self.send(WriterMsg::Record(record)).await,
        }
    }

    /// A job's channel moves on; then its records go to the log, after the frame's lag.
    async fn finished(&mut self, mut done: JobDone) -> Result<()> {
        let records = std::mem::take(&mut done.records);
        let lag_s = done.arrived.elapsed().as_secs_f64();
        // The frame leaves the queue count before the writer counts it finished, so
        // `queued + finished` never counts a frame twice.
        self.scheduler.complete(done);
        publish_queue(
            &self.progress,
            &self.scheduler,
            self.pending_files.as_deref(),
        );
        if let Some(frame) = records.iter().find_map(|r| match r {
            Record::Frame { message, .. } => Some(message.align.frame.clone()),
            _ => None,
        }) {
            self.send(WriterMsg::Lag { frame, lag_s }).await?;
        }
        for record in records {
            self.send(WriterMsg::Record(record)).await?;
        }
        Ok(())
    }

    async fn send(&self, msg: WriterMsg) -> Result<()> {
        self.writer
            .send(msg)
            .await
            .map_err(|_| Error::output("log writer", "stopped unexpectedly"))
    }
}

/// Queue depth for the health status (only sent when it changed).
fn publish_queue(
    progress: &watch::Sender<Progress>,
    scheduler: &Scheduler,
    pending_files: Option<&AtomicUsize>,
) {
    let per_channel = scheduler.queued_by_channel();
    let files = pending_files.map_or(0, |p| p.load(Ordering::SeqCst) as u64);
    let queued = per_channel.values().sum::<u64>() + files;
    progress.send_if_modified(|p| {
        if p.queued == queued && p.queued_per_channel == per_channel {
            return false;
        }
        p.queued = queued;
        p.queued_per_channel = per_channel;
        true
    });
}

async fn sleep_until_opt(deadline: Option<Instant>) {
    if let Some(d) = deadline {
        tokio::time::sleep_until(tokio::time::Instant::from_std(d)).await;
    }
}
