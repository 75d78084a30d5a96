//! The MCAP sink: a run's log as segment files in an output directory, and the reader that
//! reads them back (also unfinished ones, after a crash).
//!
//! Layout (contract.md, "MCAP layout"): `/jitter/<channel>` (`sunjitter.FrameAlignment`),
//! `/reference/<channel>` (`sunjitter.ReferenceChange`), `/log` (`foxglove.Log`), all JSON with
//! JSON Schemas; a `sunjitter` metadata record (`version`, `config`) at the start of every
//! segment; zstd chunks, message indexes and a summary.
//!
//! # Files
//! Segments are named `sunjitter-<UTC start, YYYYMMDDTHHMMSSZ>-<NNNN>.mcap`, the start being
//! the `publish_time` of the segment's first message and `NNNN` the run's segment counter. A
//! new name always sorts after every segment already in the directory (the start is clamped,
//! the counter bumped), and an existing file is never overwritten (`create_new`).
//!
//! A segment has its final name from the start (no temporary name + rename): a killed process
//! leaves a file that the [`read_logs`] reader reads up to its last flushed chunk, and that
//! [`recover_segment`] turns into a finished file.
//!
//! # Durability and errors
//! Chunks are built in memory and written whole: a crash loses only what was written since the
//! last flush (every `flush_every_frames` messages, on [`McapSink::flush`] / [`McapSink::tick`],
//! at rotation and at [`McapSink::finish`]).
//!
//! `write_*` returning `Ok` means the message is *accepted*: it is on disk after the next
//! successful flush, and until then the sink keeps a copy. `Err` means *this* message was not
//! accepted (retry it later) — nothing is dropped silently. After an I/O error the open segment
//! is abandoned: it is truncated back to its last successful flush (so it never holds a message
//! twice) and rewritten as a finished file (at once if possible, else by `finish`); the next
//! call opens a new segment and first re-writes every accepted message that was not yet on
//! disk. An error from an automatic flush is not returned by the write that triggered it (that
//! message was accepted); the next call reports it if it persists. Bytes reach the file at
//! flushes (or past 4 MiB buffered), so a write error surfaces at a flush, a rotation or a
//! segment start.
//!
//! # Use in a daemon
//! One writer thread owns the sink. Call [`McapSink::tick`] when idle (flush, time rotation)
//! and [`McapSink::finish`] at shutdown. On restart: [`read_logs`] on the output directory,
//! [`recover_segment`] for each segment that is not `complete` (optional: this reader reads
//! them anyway, the official readers need it), then [`LogContents::logged_frames`] gives the
//! frames not to process again. [`McapSink::abandon`] simulates a crash in tests. Take the
//! directory's [`crate::outputs::OutputLock`] before any of this and give it to the sink
//! ([`McapSink::holding`]), so no other process recovers or writes segments meanwhile.

mod reader;
mod schemas;
mod segment;

pub use reader::{
    logged_frames, read_logs, recover_segment, AlertMessage, JitterMessage, LogContents,
    LogMessage, MetadataRecord, RecoveryOutcome, ReferenceMessage, SegmentReport,
};
pub use schemas::{
    alert_schema, frame_alignment_schema, jitter_topic, log_schema, reference_change_schema,
    reference_topic, Alert, FoxgloveTime, LogEntry, LogLevel, ReferenceChange, ReferenceClosure,
    ALERT_SCHEMA, ALERT_TOPIC, FRAME_ALIGNMENT_SCHEMA, LOG_SCHEMA, LOG_TOPIC, MESSAGE_ENCODING,
    METADATA_NAME, REFERENCE_CHANGE_SCHEMA, SCHEMA_ENCODING,
};

use segment::{SegmentFile, SegmentKey, UNLIMITED};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use sunjitter_core::record::FrameAlignment;
use sunjitter_core::{Error, Result};

/// Segment rotation and flushing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SinkConfig {
    /// Start a new segment after this many `/jitter` messages (0: never by count).
    pub segment_frames: u64,
    /// Start a new segment when the open one is this old, by `publish_time` (0: never by time).
    pub segment_minutes: f64,
    /// Flush after this many `/jitter` + `/log` messages: a crash loses at most these.
    pub flush_every_frames: u64,
    /// Target uncompressed chunk size in bytes (chunks also end at every flush).
    pub chunk_size: u64,
    /// `fsync` at every flush (survives power loss, not only a process crash).
    pub sync_on_flush: bool,
}

impl Default for SinkConfig {
    fn default() -> Self {
        SinkConfig {
            // About a day of one 12 s channel; hourly files from the time limit first.
            segment_frames: 10_000,
            segment_minutes: 60.0,
            flush_every_frames: 10,
            chunk_size: 1024 * 1024,
            sync_on_flush: false,
        }
    }
}

impl SinkConfig {
    fn validate(&self) -> Result<()> {
        if !(self.segment_minutes.is_finite() && self.segment_minutes >= 0.0) {
            return Err(Error::Usage(format!(
                "sink: segment_minutes must be a number ≥ 0, not {}",
                self.segment_minutes
            )));
        }
        if self.flush_every_frames == 0 {
            return Err(Error::Usage("sink: flush_every_frames must be ≥ 1".into()));
        }
        if self.chunk_size == 0 {
            return Err(Error::Usage("sink: chunk_size must be ≥ 1 byte".into()));
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Kind {
    Jitter,
    Reference,
    Log,
    Alert,
}

impl Kind {
    fn schema(self) -> (&'static str, fn() -> serde_json::Value) {
        match self {
            Kind::Jitter => (FRAME_ALIGNMENT_SCHEMA, frame_alignment_schema),
            Kind::Reference => (REFERENCE_CHANGE_SCHEMA, reference_change_schema),
            Kind::Log => (LOG_SCHEMA, log_schema),
            Kind::Alert => (ALERT_SCHEMA, alert_schema),
        }
    }
}

/// An accepted message (kept until it is on disk, to re-write it after an error).
#[derive(Debug, Clone)]
struct Pending {
    kind: Kind,
    topic: String,
    sequence: u32,
    log_time_ns: u64,
    publish_time_ns: u64,
    data: Vec<u8>,
}

struct OpenSegment {
    path: PathBuf,
    writer: mcap::Writer<SegmentFile>,
    poisoned: Arc<AtomicBool>,
    /// Second handle on the file, to truncate it after an error.
    handle: File,
    /// File length after the last successful flush.
    durable_len: u64,
    started_ns: u64,
    frames: u64,
    schema_ids: HashMap<Kind, u16>,
    channel_ids: HashMap<String, u16>,
}

/// A segment abandoned after an error, still to be truncated to its last good flush.
struct Broken {
    path: PathBuf,
    handle: File,
    durable_len: u64,
}

/// A handle on a sink's write budget (test hook, see [`McapSink::write_budget`]).
#[doc(hidden)]
#[derive(Debug, Clone)]
pub struct WriteBudget(Arc<AtomicU64>);

impl WriteBudget {
    /// At most `bytes` more bytes reach the files (then `StorageFull`); `None`: no limit.
    pub fn set(&self, bytes: Option<u64>) {
        self.0.store(
            bytes.map_or(UNLIMITED, |b| b.min(UNLIMITED - 1)),
            Ordering::SeqCst,
        );
    }
}

/// Writes a run's log as MCAP segment files (see the module docs for the guarantees).
pub struct McapSink {
    dir: PathBuf,
    config: SinkConfig,
    run_config_json: String,
    open: Option<OpenSegment>,
    broken: Option<Broken>,
    /// Abandoned segments, truncated to their last flush, not yet rewritten as finished files.
    unfinished: Vec<PathBuf>,
    pending: Vec<Pending>,
    unflushed: u64,
    segments_started: u32,
    last_key: Option<SegmentKey>,
    sequences: HashMap<String, u32>,
    budget: Arc<AtomicU64>,
    paths: Vec<PathBuf>,
    /// Released when the sink is dropped, after its last write.
    lock: Option<crate::outputs::OutputLock>,
    /// Further metadata records written at the start of every segment, after `sunjitter`.
    segment_metadata: Vec<(String, BTreeMap<String, String>)>,
}

impl McapSink {
    /// A sink writing into `dir` (created if missing). `run_config_json` is the full effective
    /// configuration as JSON, stored in every segment's `sunjitter` metadata record.
    pub fn new(dir: &Path, config: SinkConfig, run_config_json: String) -> Result<McapSink> {
        config.validate()?;
        if let Err(e) = serde_json::from_str::<serde_json::Value>(&run_config_json) {
            return Err(Error::Usage(format!(
                "sink: the run configuration is not JSON: {e}"
            )));
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::unwritable(dir, e))?;
        if !dir.is_dir() {
            return Err(Error::Unwritable {
                path: dir.to_path_buf(),
                reason: "not a directory".into(),
            });
        }
        // Segments are created when the first record comes: find out now, not then.
        sunjitter_core::error::check_writable_dir(dir)?;
        let last_key = segment::newest_existing(dir)
            .map_err(|e| Error::output(dir, format!("cannot list output directory: {e}")))?;
        Ok(McapSink {
            dir: dir.to_path_buf(),
            config,
            run_config_json,
            open: None,
            broken: None,
            unfinished: Vec::new(),
            pending: Vec::new(),
            unflushed: 0,
            segments_started: 0,
            last_key,
            sequences: HashMap::new(),
            budget: Arc::new(AtomicU64::new(UNLIMITED)),
            paths: Vec::new(),
            lock: None,
            segment_metadata: Vec::new(),
        })
    }

    /// Also write the metadata record `name` at the start of every segment (e.g. which part
    /// of a sharded run the log holds).
    pub fn with_segment_metadata(
        mut self,
        name: impl Into<String>,
        metadata: BTreeMap<String, String>,
    ) -> McapSink {
        self.segment_metadata.push((name.into(), metadata));
        self
    }

    /// Write a metadata record into the open segment (opening one if needed), flushed at once.
    pub fn write_metadata(
        &mut self,
        name: &str,
        metadata: BTreeMap<String, String>,
        publish_time_ns: u64,
    ) -> Result<()> {
        self.prepare(publish_time_ns)?;
        let Some(seg) = self.open.as_mut() else {
            return Err(Error::output(&self.dir, "no open segment"));
        };
        let record = mcap::records::Metadata {
            name: name.to_string(),
            metadata,
        };
        if let Err(e) = seg.writer.write_metadata(&record) {
            let path = seg.path.clone();
            self.break_open();
            return Err(Error::output(path, format!("cannot write metadata: {e}")));
        }
        self.flush_open()
    }

    /// The sink keeps the output directory's lock for as long as it lives.
    pub fn holding(mut self, lock: crate::outputs::OutputLock) -> McapSink {
        self.lock = Some(lock);
        self
    }

    /// Logs one frame on `/jitter/<record.channel>`. `log_time_ns` is the frame's observation
    /// time, `publish_time_ns` when it was processed (both ns since the Unix epoch).
    pub fn write_frame(
        &mut self,
        record: &FrameAlignment,
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        let data = self.encode(record)?;
        // The reader must be able to decode what we write (e.g. NaN in a non-optional field
        // would become `null`): refuse it here, where the caller can still log it on `/log`.
        if let Err(e) = serde_json::from_slice::<FrameAlignment>(&data) {
            return Err(Error::output(
                &self.dir,
                format!(
                    "frame {}: record does not survive JSON: {e}",
                    record.align.frame
                ),
            ));
        }
        self.accept(
            Kind::Jitter,
            jitter_topic(&record.channel),
            data,
            log_time_ns,
            publish_time_ns,
        )
    }

    /// Logs a reference change on `/reference/<change.channel>`.
    pub fn write_reference_change(
        &mut self,
        change: &ReferenceChange,
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        let data = self.encode(change)?;
        let topic = reference_topic(&change.channel);
        self.accept(Kind::Reference, topic, data, log_time_ns, publish_time_ns)
    }

    /// Logs a warning or error about an input `file` (`FILE` or `FILE[N]`) on `/log`.
    /// The entry's `timestamp` is `log_time_ns`.
    pub fn write_log(
        &mut self,
        level: LogLevel,
        file: &str,
        message: &str,
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        let entry = LogEntry {
            timestamp: FoxgloveTime::from_ns(log_time_ns),
            level,
            message: message.to_string(),
            name: "sunjitter".to_string(),
            file: file.to_string(),
            line: 0,
        };
        let data = self.encode(&entry)?;
        self.accept(
            Kind::Log,
            LOG_TOPIC.to_string(),
            data,
            log_time_ns,
            publish_time_ns,
        )
    }

    /// Logs an alert on `/alert`.
    pub fn write_alert(
        &mut self,
        alert: &Alert,
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        let data = self.encode(alert)?;
        self.accept(
            Kind::Alert,
            ALERT_TOPIC.to_string(),
            data,
            log_time_ns,
            publish_time_ns,
        )
    }

    /// Writes everything accepted so far to disk (ends the current chunk).
    pub fn flush(&mut self) -> Result<()> {
        if self.open.is_none() && self.pending.is_empty() {
            return self.repair_broken();
        }
        if self.open.is_none() {
            let first = self.pending[0].publish_time_ns;
            self.prepare(first)?;
        }
        self.flush_open()
    }

    /// For an idle caller (e.g. every few seconds): closes the open segment if it is due by
    /// time at `now_ns`, else flushes what is not yet on disk.
    pub fn tick(&mut self, now_ns: u64) -> Result<()> {
        let due = self
            .open
            .as_ref()
            .is_some_and(|seg| self.rotation_due(seg, now_ns, false));
        if due {
            self.close_open()
        } else if !self.pending.is_empty() || self.broken.is_some() {
            self.flush()
        } else {
            Ok(())
        }
    }

    /// Finishes the open segment (summary and indexes) and closes it, and rewrites any segment
    /// abandoned after an error as a finished file. On error nothing accepted is lost (an
    /// unfinished segment stays readable by [`read_logs`]): call again later. Writing after
    /// `finish` starts a new segment.
    pub fn finish(&mut self) -> Result<()> {
        if self.open.is_none() && !self.pending.is_empty() {
            let first = self.pending[0].publish_time_ns;
            self.prepare(first)?;
        }
        if self.open.is_some() {
            self.close_open()?;
        } else {
            self.repair_broken()?;
        }
        self.recover_unfinished()
    }

    /// Drops the sink as a crash would: the open segment keeps only what was flushed, nothing
    /// more is written, accepted-but-unflushed messages are lost. For crash tests.
    pub fn abandon(mut self) {
        if let Some(seg) = self.open.take() {
            seg.poisoned.store(true, Ordering::SeqCst);
        }
        self.pending.clear();
        self.broken = None;
        self.unfinished.clear();
    }

    /// Segment files this sink has created, in order.
    pub fn segment_paths(&self) -> &[PathBuf] {
        &self.paths
    }

    /// Accepted messages not yet known to be on disk.
    pub fn pending_messages(&self) -> usize {
        self.pending.len()
    }

    /// Test hook simulating a full disk: at most `bytes` more bytes reach the files (a short
    /// write, then `StorageFull`); `None` lifts the limit.
    #[doc(hidden)]
    pub fn set_write_budget(&mut self, bytes: Option<u64>) {
        self.write_budget().set(bytes);
    }

    /// Test hook: [`McapSink::set_write_budget`] through a handle that stays usable after the
    /// sink has moved to the daemon's writer thread (fault-injection tests fill the "disk"
    /// while the daemon runs, then free it).
    #[doc(hidden)]
    pub fn write_budget(&self) -> WriteBudget {
        WriteBudget(self.budget.clone())
    }

    fn encode<T: Serialize>(&self, value: &T) -> Result<Vec<u8>> {
        serde_json::to_vec(value)
            .map_err(|e| Error::output(&self.dir, format!("cannot encode message as JSON: {e}")))
    }

    fn accept(
        &mut self,
        kind: Kind,
        topic: String,
        data: Vec<u8>,
        log_time_ns: u64,
        publish_time_ns: u64,
    ) -> Result<()> {
        self.prepare(publish_time_ns)?;
        let sequence = self.sequences.get(&topic).copied().unwrap_or(0);
        let message = Pending {
            kind,
            topic,
            sequence,
            log_time_ns,
            publish_time_ns,
            data,
        };
        let Some(seg) = self.open.as_mut() else {
            return Err(Error::output(&self.dir, "no open segment"));
        };
        if let Err(e) = write_message(seg, &message) {
            let path = seg.path.clone();
            self.break_open();
            return Err(Error::output(path, format!("cannot write message: {e}")));
        }
        if kind == Kind::Jitter {
            seg.frames += 1;
        }
        if kind != Kind::Reference {
            self.unflushed += 1;
        }
        self.sequences
            .insert(message.topic.clone(), sequence.wrapping_add(1));
        self.pending.push(message);
        if self.unflushed >= self.config.flush_every_frames {
            if let Err(e) = self.flush_open() {
                // The message is accepted and kept; the next call re-writes it or reports.
                tracing::warn!("{e}");
            }
        }
        Ok(())
    }

    /// Makes an open, healthy segment ready for a message published at `publish_time_ns`:
    /// truncates an abandoned one, rotates a full one, opens (and re-fills) a new one.
    fn prepare(&mut self, publish_time_ns: u64) -> Result<()> {
        self.repair_broken()?;
        let due = self
            .open
            .as_ref()
            .is_some_and(|seg| self.rotation_due(seg, publish_time_ns, true));
        if due {
            self.close_open()?;
        }
        if self.open.is_none() {
            self.open_segment(publish_time_ns)?;
        }
        Ok(())
    }

    fn rotation_due(&self, seg: &OpenSegment, now_ns: u64, by_count: bool) -> bool {
        let full =
            by_count && self.config.segment_frames > 0 && seg.frames >= self.config.segment_frames;
        let minutes = self.config.segment_minutes;
        let old = minutes > 0.0 && now_ns.saturating_sub(seg.started_ns) as f64 >= minutes * 60e9;
        full || old
    }

    /// The next segment name: after every existing one, from the UTC start `publish_time_ns`.
    fn next_key(&self, publish_time_ns: u64) -> SegmentKey {
        let candidate = SegmentKey {
            stamp: segment::utc_stamp(publish_time_ns),
            number: self.segments_started,
        };
        match &self.last_key {
            Some(last) if candidate <= *last => SegmentKey {
                stamp: last.stamp.clone(),
                number: last.number + 1,
            },
            _ => candidate,
        }
    }

    fn open_segment(&mut self, publish_time_ns: u64) -> Result<()> {
        // Only into the directory this sink locked, never one put in its place.
        if let Some(lock) = &self.lock {
            lock.verify()?;
        }
        let mut key = self.next_key(publish_time_ns);
        let (path, file) = loop {
            let path = self.dir.join(key.file_name());
            match OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(file) => break (path, file),
                // Never overwrite: someone else has this name, take the next number.
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => key.number += 1,
                Err(e) => return Err(Error::output(path, format!("cannot create segment: {e}"))),
            }
        };
        self.last_key = Some(key);
        self.segments_started += 1;
        match self.start_writer(&path, file, publish_time_ns) {
            Ok(seg) => {
                self.paths.push(path);
                self.open = Some(seg);
            }
            Err(e) => {
                // Nothing useful in it yet; do not leave an empty segment behind.
                let _ = std::fs::remove_file(&path);
                return Err(e);
            }
        }
        // Re-write what was accepted but never reached the disk (after an error).
        if !self.pending.is_empty() {
            let replay = std::mem::take(&mut self.pending);
            let mut failure = None;
            if let Some(seg) = self.open.as_mut() {
                for message in &replay {
                    if let Err(e) = write_message(seg, message) {
                        failure = Some((seg.path.clone(), e));
                        break;
                    }
                    if message.kind == Kind::Jitter {
                        seg.frames += 1;
                    }
                }
            }
            self.pending = replay;
            if let Some((path, e)) = failure {
                self.break_open();
                return Err(Error::output(
                    path,
                    format!("cannot re-write messages: {e}"),
                ));
            }
            self.flush_open()?;
        }
        Ok(())
    }

    fn start_writer(&self, path: &Path, file: File, started_ns: u64) -> Result<OpenSegment> {
        let fail = |what: &str, e: &dyn std::fmt::Display| {
            Error::output(path, format!("cannot {what} segment: {e}"))
        };
        let handle = file.try_clone().map_err(|e| fail("open", &e))?;
        let poisoned = Arc::new(AtomicBool::new(false));
        let out = SegmentFile::new(
            file,
            poisoned.clone(),
            self.budget.clone(),
            self.config.sync_on_flush,
        );
        let options = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(self.config.chunk_size))
            // Build each chunk in memory and write it whole: a crash never leaves a chunk
            // with a placeholder header on disk.
            .disable_seeking(true)
            .compression_threads(0)
            .library(format!("sunjitter {}", env!("CARGO_PKG_VERSION")));
        let result = (|| {
            let mut writer = options.create(out)?;
            let mut metadata = BTreeMap::new();
            metadata.insert("version".to_string(), env!("CARGO_PKG_VERSION").to_string());
            metadata.insert("config".to_string(), self.run_config_json.clone());
            writer.write_metadata(&mcap::records::Metadata {
                name: METADATA_NAME.to_string(),
                metadata,
            })?;
            for (name, metadata) in &self.segment_metadata {
                writer.write_metadata(&mcap::records::Metadata {
                    name: name.clone(),
                    metadata: metadata.clone(),
                })?;
            }
            writer.flush()?;
            Ok::<_, mcap::McapError>(writer)
        })();
        let writer = match result {
            Ok(w) => w,
            Err(e) => {
                poisoned.store(true, Ordering::SeqCst);
                return Err(fail("start", &e));
            }
        };
        let durable_len = handle.metadata().map_err(|e| fail("stat", &e))?.len();
        Ok(OpenSegment {
            path: path.to_path_buf(),
            writer,
            poisoned,
            handle,
            durable_len,
            started_ns,
            frames: 0,
            schema_ids: HashMap::new(),
            channel_ids: HashMap::new(),
        })
    }

    fn flush_open(&mut self) -> Result<()> {
        let Some(seg) = self.open.as_mut() else {
            return Ok(());
        };
        let result = seg
            .writer
            .flush()
            .map_err(|e| e.to_string())
            .and_then(|()| seg.handle.metadata().map_err(|e| e.to_string()));
        match result {
            Ok(meta) => {
                seg.durable_len = meta.len();
                self.pending.clear();
                self.unflushed = 0;
                Ok(())
            }
            Err(e) => {
                let path = seg.path.clone();
                self.break_open();
                Err(Error::output(path, format!("cannot flush segment: {e}")))
            }
        }
    }

    fn close_open(&mut self) -> Result<()> {
        let Some(seg) = self.open.take() else {
            return Ok(());
        };
        let OpenSegment {
            path,
            mut writer,
            poisoned,
            handle,
            durable_len,
            ..
        } = seg;
        let result = match writer.finish() {
            // The summary is still in the file buffer: write it out.
            Ok(_) => writer.into_inner().flush().and_then(|()| {
                if self.config.sync_on_flush {
                    handle.sync_all()?;
                }
                Ok(())
            }),
            Err(e) => {
                poisoned.store(true, Ordering::SeqCst);
                drop(writer);
                Err(std::io::Error::other(e))
            }
        };
        match result {
            Ok(()) => {
                self.pending.clear();
                self.unflushed = 0;
                Ok(())
            }
            Err(e) => {
                poisoned.store(true, Ordering::SeqCst);
                tracing::warn!(
                    "{}: cannot finish segment; truncating to its last flush",
                    path.display()
                );
                self.broken = Some(Broken {
                    path: path.clone(),
                    handle,
                    durable_len,
                });
                let _ = self.repair_broken();
                Err(Error::output(path, format!("cannot finish segment: {e}")))
            }
        }
    }

    /// Abandons the open segment after an error; keeps `pending` for the next segment.
    fn break_open(&mut self) {
        if let Some(seg) = self.open.take() {
            seg.poisoned.store(true, Ordering::SeqCst);
            tracing::warn!(
                "{}: abandoning segment after a write error; truncating to its last flush",
                seg.path.display()
            );
            self.broken = Some(Broken {
                path: seg.path,
                handle: seg.handle,
                durable_len: seg.durable_len,
            });
            // The writer's Drop tries to finish the file; poisoned writes make that a no-op.
            drop(seg.writer);
        }
        let _ = self.repair_broken();
    }

    /// Cuts an abandoned segment back to its last good flush, so no message that will be
    /// re-written elsewhere stays in it.
    fn repair_broken(&mut self) -> Result<()> {
        let Some(broken) = self.broken.as_ref() else {
            return Ok(());
        };
        let result = broken.handle.set_len(broken.durable_len).and_then(|()| {
            if self.config.sync_on_flush {
                broken.handle.sync_all()?;
            }
            Ok(())
        });
        match result {
            Ok(()) => {
                self.unfinished.push(broken.path.clone());
                self.broken = None;
                // Best effort now (the disk may still be full); `finish` insists.
                if let Err(e) = self.recover_unfinished() {
                    tracing::warn!("{e}");
                }
                Ok(())
            }
            Err(e) => Err(Error::output(
                &broken.path,
                format!("cannot truncate abandoned segment to its last flush: {e}"),
            )),
        }
    }

    /// Rewrites abandoned (truncated) segments as finished files; see [`recover_segment`].
    fn recover_unfinished(&mut self) -> Result<()> {
        let mut first_error = None;
        let sync = self.config.sync_on_flush;
        self.unfinished
            .retain(|path| match reader::recover_segment_with(path, sync) {
                Ok(_) => false,
                Err(e) => {
                    first_error.get_or_insert(e);
                    true
                }
            });
        first_error.map_or(Ok(()), Err)
    }
}

fn write_message(seg: &mut OpenSegment, message: &Pending) -> mcap::McapResult<()> {
    let schema_id = match seg.schema_ids.get(&message.kind) {
        Some(&id) => id,
        None => {
            let (name, schema) = message.kind.schema();
            let bytes = serde_json::to_vec(&schema()).unwrap_or_default();
            let id = seg.writer.add_schema(name, SCHEMA_ENCODING, &bytes)?;
            seg.schema_ids.insert(message.kind, id);
            id
        }
    };
    let channel_id = match seg.channel_ids.get(&message.topic) {
        Some(&id) => id,
        None => {
            let id = seg.writer.add_channel(
                schema_id,
                &message.topic,
                MESSAGE_ENCODING,
                &BTreeMap::new(),
            )?;
            seg.channel_ids.insert(message.topic.clone(), id);
            id
        }
    };
    seg.writer.write_to_known_channel(
        &mcap::records::MessageHeader {
            channel_id,
            sequence: message.sequence,
            log_time: message.log_time_ns,
            publish_time: message.publish_time_ns,
        },
        &message.data,
    )
}

impl Drop for McapSink {
    /// A sink dropped without `finish` still finishes its segment (best effort).
    fn drop(&mut self) {
        let busy = self.open.is_some() || self.broken.is_some();
        if busy || !self.pending.is_empty() || !self.unfinished.is_empty() {
            if let Err(e) = self.finish() {
                tracing::error!("closing the MCAP log: {e}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_send<T: Send>() {}

    #[test]
    fn sink_can_move_to_a_writer_thread() {
        assert_send::<McapSink>();
    }

    #[test]
    fn config_defaults_fill_missing_toml_fields() {
        let config: SinkConfig = toml::from_str("segment_frames = 5").unwrap();
        assert_eq!(config.segment_frames, 5);
        assert_eq!(
            config.flush_every_frames,
            SinkConfig::default().flush_every_frames
        );
        assert!(toml::from_str::<SinkConfig>("segment_frame = 5").is_err());
    }

    #[test]
    fn bad_config_is_a_usage_error() {
        let dir = tempfile::tempdir().unwrap();
        for config in [
            SinkConfig {
                flush_every_frames: 0,
                ..Default::default()
            },
            SinkConfig {
                segment_minutes: f64::NAN,
                ..Default::default()
            },
            SinkConfig {
                segment_minutes: -1.0,
                ..Default::default()
            },
        ] {
            let err = McapSink::new(dir.path(), config, "{}".into())
                .err()
                .unwrap();
            assert_eq!(
                err.exit_code(),
                sunjitter_core::error::ExitCode::BadInput,
                "{err}"
            );
        }
        let err = McapSink::new(dir.path(), SinkConfig::default(), "{oops".into())
            .err()
            .unwrap();
        assert_eq!(
            err.exit_code(),
            sunjitter_core::error::ExitCode::BadInput,
            "{err}"
        );
    }
}
