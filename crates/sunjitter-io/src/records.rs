//! The messages a run writes, as one type ([`Record`]), and where they go ([`RecordSink`]):
//! the MCAP log in production ([`McapRecordSink`]), memory in tests and dry runs
//! ([`MemorySink`]). Written by the pipeline's one writer thread.

use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use sunjitter_core::record::FrameAlignment;
use sunjitter_core::{Error, Result};

use crate::sink::{LogLevel, McapSink, ReferenceChange};

/// One message for the sink. `log_time_ns` is the frame's observation time where there is a
/// frame, else the file's modification time (so replay and watch agree).
#[derive(Debug, Clone, PartialEq)]
pub enum Record {
    /// `/jitter/<channel>`.
    Frame {
        message: Box<FrameAlignment>,
        log_time_ns: i64,
    },
    /// `/reference/<channel>`.
    Reference {
        change: Box<ReferenceChange>,
        log_time_ns: i64,
    },
    /// `/log`. `file` is a frame key (`PATH` or `PATH[N]`). In a log read back, an entry at
    /// `Error` marks that frame (or file) finished for good; warnings are notes about frames
    /// that have their own message.
    Log {
        level: LogLevel,
        file: String,
        message: String,
        log_time_ns: i64,
        /// This entry stands for the input (no message comes for it); `false` for notes.
        finishes: bool,
    },
}

impl Record {
    /// A `/log` entry; at `Error` it finishes its input (no message will come for it).
    pub fn log(
        level: LogLevel,
        file: &str,
        message: impl Into<String>,
        log_time_ns: i64,
    ) -> Record {
        Record::Log {
            level,
            file: sunjitter_core::text::escape(file).into_owned(),
            message: sunjitter_core::text::escape(&message.into()).into_owned(),
            log_time_ns,
            finishes: level >= LogLevel::Error,
        }
    }

    /// A `/log` warning about a frame that has (or had) its own message.
    pub fn note(file: &str, message: impl Into<String>, log_time_ns: i64) -> Record {
        Record::Log {
            level: LogLevel::Warning,
            file: sunjitter_core::text::escape(file).into_owned(),
            message: sunjitter_core::text::escape(&message.into()).into_owned(),
            log_time_ns,
            finishes: false,
        }
    }

    pub fn log_time_ns(&self) -> i64 {
        match self {
            Record::Frame { log_time_ns, .. }
            | Record::Reference { log_time_ns, .. }
            | Record::Log { log_time_ns, .. } => *log_time_ns,
        }
    }

    /// The MCAP topic this record goes to.
    pub fn topic(&self) -> String {
        match self {
            Record::Frame { message, .. } => format!("/jitter/{}", message.channel),
            Record::Reference { change, .. } => format!("/reference/{}", change.channel),
            Record::Log { .. } => "/log".into(),
        }
    }
}

/// Where records go: the MCAP sink in production. Called from the one writer thread.
pub trait RecordSink: Send {
    fn write(&mut self, record: &Record, publish_time_ns: i64) -> Result<()>;
    fn flush(&mut self) -> Result<()>;
    /// Close cleanly (MCAP: summary and index).
    fn finish(self: Box<Self>) -> Result<()>;
    /// Seconds from the frame `frame` (a frame key) entering the pipeline until its alignment
    /// finished; sent just before the frame's records. Monitoring sinks use it; default: ignored.
    fn note_lag(&mut self, _frame: &str, _lag_s: f64) {}
}

/// A sink that keeps records in memory (tests, dry runs). Clones share the same log.
#[derive(Debug, Clone, Default)]
pub struct MemorySink {
    pub log: Arc<Mutex<MemoryLog>>,
}

#[derive(Debug, Default)]
pub struct MemoryLog {
    /// Records with their publish times, in write order.
    pub records: Vec<(Record, i64)>,
    pub flushes: usize,
    pub finished: bool,
}

impl RecordSink for MemorySink {
    fn write(&mut self, record: &Record, publish_time_ns: i64) -> Result<()> {
        let mut log = self
            .log
            .lock()
            .map_err(|_| Error::output("memory", "poisoned"))?;
        log.records.push((record.clone(), publish_time_ns));
        Ok(())
    }
    fn flush(&mut self) -> Result<()> {
        if let Ok(mut log) = self.log.lock() {
            log.flushes += 1;
        }
        Ok(())
    }
    fn finish(self: Box<Self>) -> Result<()> {
        if let Ok(mut log) = self.log.lock() {
            log.finished = true;
        }
        Ok(())
    }
}

impl MemorySink {
    pub fn records(&self) -> Vec<Record> {
        self.log
            .lock()
            .map(|l| l.records.iter().map(|(r, _)| r.clone()).collect())
            .unwrap_or_default()
    }
}

/// Now, in ns since the Unix epoch.
pub fn system_time_ns(t: Option<SystemTime>) -> i64 {
    let t = t.unwrap_or_else(SystemTime::now);
    match t.duration_since(SystemTime::UNIX_EPOCH) {
        Ok(d) => i64::try_from(d.as_nanos()).unwrap_or(i64::MAX),
        Err(e) => -i64::try_from(e.duration().as_nanos()).unwrap_or(i64::MAX),
    }
}

pub fn now_ns() -> i64 {
    system_time_ns(Some(SystemTime::now()))
}

/// MCAP timestamps are unsigned: times before 1970 are written as 0.
pub fn mcap_ns(ns: i64) -> u64 {
    u64::try_from(ns).unwrap_or(0)
}

/// The MCAP sink behind the [`RecordSink`] interface.
pub struct McapRecordSink(pub McapSink);

impl RecordSink for McapRecordSink {
    fn write(&mut self, record: &Record, publish_time_ns: i64) -> Result<()> {
        McapRecordSink::write_to(&mut self.0, record, publish_time_ns)
    }

    fn flush(&mut self) -> Result<()> {
        // Idle flush, and rotation by time.
        self.0.tick(mcap_ns(now_ns()))
    }

    fn finish(mut self: Box<Self>) -> Result<()> {
        self.0.finish()
    }
}

impl McapRecordSink {
    /// Write one record to an MCAP sink.
    pub fn write_to(sink: &mut McapSink, record: &Record, publish_time_ns: i64) -> Result<()> {
        let publish = mcap_ns(publish_time_ns);
        match record {
            Record::Frame {
                message,
                log_time_ns,
            } => sink.write_frame(message, mcap_ns(*log_time_ns), publish),
            Record::Reference {
                change,
                log_time_ns,
            } => sink.write_reference_change(change, mcap_ns(*log_time_ns), publish),
            Record::Log {
                level,
                file,
                message,
                log_time_ns,
                ..
            } => sink.write_log(*level, file, message, mcap_ns(*log_time_ns), publish),
        }
    }
}
