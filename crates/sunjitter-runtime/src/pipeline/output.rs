//! The output directory: the sink for a new run, and what earlier runs logged there.

use crate::config::Config;
use crate::reference::History;
use std::path::Path;
use sunjitter_core::Result;
use sunjitter_io::records::{McapRecordSink, Record, RecordSink};
use sunjitter_io::sink::{LogContents, LogLevel};

/// Open the MCAP output in `out` for a library caller that names no run (the commands use
/// `runs::open_run`, which also refuses another run's log): lock it first, then
/// read what earlier runs logged there; whatever log `out` holds is resumed.
pub fn open_output(out: &Path, config: &Config) -> Result<(Box<dyn RecordSink>, History)> {
    let lock = sunjitter_io::outputs::OutputLock::acquire(out)?;
    let history = read_history(out)?;
    let sink =
        sunjitter_io::sink::McapSink::new(out, config.sink.clone(), config.to_json().to_string())?
            .holding(lock);
    Ok((Box::new(McapRecordSink(sink)), history))
}

/// Read the segments in `out` (recovering unfinished ones) as a [`History`].
pub fn read_history(out: &Path) -> Result<History> {
    let dirs = [out.to_path_buf()];
    let contents = sunjitter_io::sink::read_logs(&dirs)?;
    Ok(history_of(&contents))
}

/// The history of a log as read (unfinished segments are recovered on disk meanwhile).
pub fn history_of(contents: &LogContents) -> History {
    for segment in contents.segments.iter().filter(|s| !s.complete) {
        match sunjitter_io::sink::recover_segment(&segment.path) {
            Ok(outcome) => {
                tracing::warn!(segment = %segment.path.display(), "unfinished segment recovered: {outcome:?}")
            }
            Err(e) => tracing::error!("{e} (its flushed part is still counted as logged)"),
        }
    }
    let mut history = History::default();
    for m in &contents.jitter {
        history.add(&Record::Frame {
            message: Box::new(m.record.clone()),
            log_time_ns: clamp_ns(m.log_time_ns),
        });
    }
    for m in &contents.references {
        history.add(&Record::Reference {
            change: Box::new(m.change.clone()),
            log_time_ns: clamp_ns(m.log_time_ns),
        });
    }
    for m in &contents.logs {
        let level = m.entry.level;
        history.add(&Record::Log {
            level,
            file: m.entry.file.clone(),
            message: m.entry.message.clone(),
            log_time_ns: clamp_ns(m.log_time_ns),
            finishes: level >= LogLevel::Error,
        });
    }
    history
}

fn clamp_ns(ns: u64) -> i64 {
    i64::try_from(ns).unwrap_or(i64::MAX)
}
