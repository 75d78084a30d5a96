//! The writer thread: the one place records reach the sink.

use super::progress::Progress;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};
use sunjitter_core::record::Status;
use sunjitter_core::{Error, Result};
use sunjitter_io::records::{now_ns, Record, RecordSink};
use sunjitter_io::sink::LogLevel;
use tokio::sync::{mpsc, watch};

#[derive(Debug)]
pub enum WriterMsg {
    Record(Record),
    Flush,
    /// The ingest lag of a frame whose records follow (see [`RecordSink::note_lag`]).
    Lag {
        frame: String,
        lag_s: f64,
    },
}

/// Start the one thread that owns the sink. It writes records in the order received,
/// flushes on request, retries failed writes (the pipeline waits meanwhile: nothing is lost)
/// and finishes the sink when the channel closes.
pub fn spawn_writer(
    mut sink: Box<dyn RecordSink>,
    mut rx: mpsc::Receiver<WriterMsg>,
    progress: watch::Sender<Progress>,
    stopping: Arc<AtomicBool>,
) -> std::thread::JoinHandle<Result<()>> {
    std::thread::Builder::new()
        .name("sunjitter-writer".into())
        .spawn(move || {
            while let Some(msg) = rx.blocking_recv() {
                match msg {
                    WriterMsg::Flush => {
                        if let Err(e) = sink.flush() {
                            tracing::error!("flushing the log failed: {e}");
                            progress.send_modify(|p| {
                                p.write_errors += 1;
                                p.last_error = Some(e.to_string());
                            });
                        }
                    }
                    WriterMsg::Lag { frame, lag_s } => sink.note_lag(&frame, lag_s),
                    WriterMsg::Record(record) => {
                        write_with_retry(sink.as_mut(), &record, &progress, &stopping)?;
                        progress.send_modify(|p| count(p, &record));
                    }
                }
            }
            sink.flush()?;
            sink.finish()
        })
        .unwrap_or_else(|e| {
            // Thread creation failure: report it through the join handle.
            let reason = e.to_string();
            std::thread::spawn(move || Err(Error::output("writer thread", reason)))
        })
}

fn write_with_retry(
    sink: &mut dyn RecordSink,
    record: &Record,
    progress: &watch::Sender<Progress>,
    stopping: &AtomicBool,
) -> Result<()> {
    let mut delay = Duration::from_millis(100);
    let mut attempts_while_stopping = 0;
    let mut failures = 0u64;
    let started = Instant::now();
    loop {
        match sink.write(record, now_ns()) {
            Ok(()) => {
                if failures > 0 {
                    // Say in the log itself that it had a gap in time (nothing was lost).
                    let note = Record::log(
                        LogLevel::Warning,
                        "",
                        format!(
                            "log output was unwritable for {:.1} s ({failures} failed attempts); \
                             input waited meanwhile, nothing was lost",
                            started.elapsed().as_secs_f64()
                        ),
                        now_ns(),
                    );
                    tracing::warn!("writing the log resumed after {failures} failed attempts");
                    if sink.write(&note, now_ns()).is_ok() {
                        progress.send_modify(|p| count(p, &note));
                    }
                }
                return Ok(());
            }
            Err(e) => {
                failures += 1;
                tracing::error!("writing the log failed (will retry; input waits): {e}");
                progress.send_modify(|p| {
                    p.write_errors += 1;
                    p.last_error = Some(e.to_string());
                });
                if stopping.load(Ordering::SeqCst) {
                    attempts_while_stopping += 1;
                    if attempts_while_stopping >= 2 {
                        return Err(e);
                    }
                }
                // A stop (SIGTERM) cuts the wait short: the last attempt follows at once.
                let until = Instant::now() + delay;
                while Instant::now() < until && !stopping.load(Ordering::SeqCst) {
                    std::thread::sleep(
                        Duration::from_millis(20)
                            .min(until.saturating_duration_since(Instant::now())),
                    );
                }
                delay = (delay * 2).min(Duration::from_secs(5));
            }
        }
    }
}

fn count(p: &mut Progress, record: &Record) {
    match record {
        Record::Frame { message, .. } => {
            p.frames += 1;
            p.finished += 1;
            match message.align.status {
                Status::Ok => p.ok += 1,
                Status::Degraded => p.degraded += 1,
                Status::Failed => p.failed += 1,
            }
            *p.per_channel.entry(message.channel.clone()).or_default() += 1;
        }
        Record::Reference { .. } => p.references += 1,
        Record::Log { finishes: true, .. } => {
            p.skipped += 1;
            p.finished += 1;
        }
        Record::Log { .. } => p.notes += 1,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sunjitter_io::records::MemorySink;

    #[test]
    fn writer_retries_until_the_sink_accepts() {
        // A sink that fails its first three writes: nothing may be lost or doubled.
        struct Flaky(MemorySink, usize);
        impl RecordSink for Flaky {
            fn write(&mut self, r: &Record, t: i64) -> Result<()> {
                if self.1 > 0 {
                    self.1 -= 1;
                    return Err(Error::output("disk", "full"));
                }
                self.0.write(r, t)
            }
            fn flush(&mut self) -> Result<()> {
                Ok(())
            }
            fn finish(self: Box<Self>) -> Result<()> {
                Box::new(self.0).finish()
            }
        }
        let memory = MemorySink::default();
        let (tx, rx) = mpsc::channel(4);
        let (ptx, prx) = watch::channel(Progress::default());
        let handle = spawn_writer(
            Box::new(Flaky(memory.clone(), 3)),
            rx,
            ptx,
            Arc::new(AtomicBool::new(false)),
        );
        for i in 0..3 {
            let r = Record::log(LogLevel::Error, &format!("f{i}"), "x", i);
            tx.blocking_send(WriterMsg::Record(r)).unwrap();
        }
        drop(tx);
        handle.join().unwrap().unwrap();
        let files: Vec<String> = memory
            .records()
            .into_iter()
            .filter_map(|r| match r {
                Record::Log { file, .. } => Some(file),
                _ => None,
            })
            .collect();
        assert_eq!(
            files,
            ["f0", "", "f1", "f2"],
            "the outage is noted after f0"
        );
        assert_eq!((prx.borrow().write_errors, prx.borrow().finished), (3, 3));
    }
}
