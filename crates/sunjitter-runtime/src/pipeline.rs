//! The one pipeline both front ends feed: frame → channel → reference policy → engine → sink.
//!
//! ```text
//! front end (watch: watcher + readers; replay: file list)
//!   └─ bounded queue of Input ──> scheduler task: per-channel reorder buffers, partner choice
//!        └─ blocking jobs (≤ workers, ≤ 1 per channel): read image, policy step, engine
//!             └─ bounded queue of records ──> ONE writer thread: RecordSink (MCAP)
//! ```
//!
//! Determinism: per channel, frames are processed one at a time in (observation time, key)
//! order; a frame's messages depend only on its channel's earlier frames (and for
//! `channel:NAME` on the partner frame, chosen once the partner has been processed past the
//! frame's time). So `replay` of a set of frames writes what the daemon wrote for them,
//! apart from `publish_time` and the engine's own `elapsed_ms`.

use crate::config::Config;
use crate::ports::{Aligner, FrameReader};
use crate::reference::History;
use crate::reference::{
    ChannelState, LoadedFrame, PartnerFrame, PolicySpec, RestoredChannel, StepContext,
};
use std::collections::{BTreeMap, VecDeque};
use std::path::Path;
use std::sync::atomic::AtomicUsize;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};
use sunjitter_core::engine::{
    AlignOutcome, EngineConfig, FrameWork, Image, PreparedReference, Workspace,
};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::record::{FrameAlignment, Status};
use sunjitter_core::{Error, Result};
use sunjitter_io::fits::frame_key;
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::records::{now_ns, system_time_ns, McapRecordSink, Record, RecordSink};
use sunjitter_io::sink::LogLevel;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

// ---------------------------------------------------------------------------------------------
// The outside world, as small traits (the real ones wrap `fits`, `engine` and `sink`).

/// The FITS reader, with the configured limits on what a file may claim.
#[derive(Debug, Clone, Copy, Default)]
pub struct FitsReader {
    pub limits: sunjitter_io::fits::ReadLimits,
}

impl FitsReader {
    pub fn from_config(config: &Config) -> FitsReader {
        FitsReader {
            limits: sunjitter_io::fits::ReadLimits {
                max_frame_pixels: config.daemon.max_frame_pixels,
            },
        }
    }
}

impl FrameReader for FitsReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        sunjitter_io::fits::read_meta_with(path, &self.limits)
    }
    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        sunjitter_io::fits::read_frame_with(spec, &self.limits)
    }
}

/// The alignment engine. Keeps the last few prepared references (cleaned image, mask,
/// window, …), so a reference used for many frames is prepared once.
pub struct EngineAligner {
    config: EngineConfig,
    rotation: ChannelRotation,
    prepared: Mutex<Vec<(ReferenceKey, Arc<PreparedReference>)>>,
    /// Each channel's last aligned frame, cleaned and disk-checked: under `previous` it is the
    /// next reference.
    last_frames: Mutex<Vec<(String, ReferenceKey, FrameWork)>>,
    /// The flow solver's memory, shared by every reference prepared here.
    workspace: Arc<Workspace>,
}

/// At most this many prepared references are kept (a 4096² one holds ≈ 150 MB): enough for
/// a few channels processed at once.
const PREPARED_REFERENCES: usize = 3;

/// Identifies a reference image in memory: the same `Image` allocation with the same pixel
/// buffer, file and a sample of its pixels (so a freed image whose addresses are reused by
/// another is not mistaken for it).
#[derive(Debug, Clone, PartialEq)]
struct ReferenceKey {
    image: usize,
    pixels: usize,
    shape: (usize, usize),
    file: std::path::PathBuf,
    sample: Vec<u32>,
}

impl ReferenceKey {
    fn of(image: &Image) -> ReferenceKey {
        let data = &image.data;
        let n = data.len();
        let step = (n / 61).max(1);
        ReferenceKey {
            image: image as *const Image as usize,
            pixels: data.as_ptr() as usize,
            shape: data.dim(),
            file: image.meta.file.clone(),
            sample: match data.as_slice_memory_order() {
                Some(all) => all.iter().step_by(step).map(|v| v.to_bits()).collect(),
                None => data.iter().step_by(step).map(|v| v.to_bits()).collect(),
            },
        }
    }
}

impl EngineAligner {
    pub fn new(config: EngineConfig) -> EngineAligner {
        EngineAligner {
            config,
            rotation: Default::default(),
            prepared: Mutex::new(Vec::new()),
            last_frames: Mutex::new(Vec::new()),
            workspace: Default::default(),
        }
    }

    /// The whole configuration's engine, with each channel's own solar rotation profile.
    pub fn from_config(config: &crate::config::Config) -> EngineAligner {
        EngineAligner {
            rotation: ChannelRotation {
                by_channel: config.channel_rotation(),
                names: config.channel_names.clone(),
            },
            ..EngineAligner::new(config.engine.clone())
        }
    }

    pub fn config(&self) -> &EngineConfig {
        &self.config
    }

    /// The prepared reference for `reference`, from the cache or made now.
    fn prepared(&self, reference: &Image) -> Arc<PreparedReference> {
        let key = ReferenceKey::of(reference);
        let lock = || match self.prepared.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        };
        if let Some((_, p)) = lock().iter().find(|(k, _)| *k == key) {
            return p.clone();
        }
        let kept = {
            let mut last = match self.last_frames.lock() {
                Ok(g) => g,
                Err(poisoned) => poisoned.into_inner(),
            };
            let at = last.iter().position(|(_, k, _)| *k == key);
            at.map(|i| last.swap_remove(i).2)
        };
        // Prepared outside the lock: other channels keep aligning meanwhile.
        let made = Arc::new(
            match kept {
                Some(work) => PreparedReference::from_frame_work(reference, &self.config, work),
                None => PreparedReference::new(reference, &self.config),
            }
            .sharing(self.workspace.clone()),
        );
        let mut cache = lock();
        if cache.len() >= PREPARED_REFERENCES {
            cache.remove(0);
        }
        cache.push((key, made.clone()));
        made
    }
}

impl Default for EngineAligner {
    fn default() -> Self {
        EngineAligner::new(EngineConfig::default())
    }
}

impl std::fmt::Debug for EngineAligner {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EngineAligner")
            .field("config", &self.config)
            .finish_non_exhaustive()
    }
}

impl Aligner for EngineAligner {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        let channel = &frame.meta.channel;
        let name = self.rotation.names.get(channel).unwrap_or(channel);
        let profile = self.rotation.by_channel.get(name).copied();
        let (outcome, kept) = self
            .prepared(reference)
            .align_keeping(frame, profile.unwrap_or(self.config.solar_rotation));
        if let Some(work) = kept {
            let mut last = match self.last_frames.lock() {
                Ok(g) => g,
                Err(poisoned) => poisoned.into_inner(),
            };
            last.retain(|(c, _, _)| c != channel);
            last.push((channel.clone(), ReferenceKey::of(frame), work));
        }
        outcome
    }

    fn usable_as_reference(&self, image: &Image) -> std::result::Result<(), String> {
        sunjitter_core::engine::usable_as_reference(image)
    }

    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        self.prepared(image)
            .geometry()
            .map(|g| g.plate_scale_arcsec)
            .or(Some(image.meta.plate_scale_arcsec))
    }

    fn geometry_used(&self, image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        self.prepared(image).geometry()
    }
}

/// Channels whose solar rotation profile is their own, by topic name, and the header
/// channel → topic name map that finds them.
#[derive(Debug, Default)]
struct ChannelRotation {
    by_channel: std::collections::BTreeMap<String, sunjitter_core::solar_rotation::Profile>,
    names: std::collections::BTreeMap<String, String>,
}

// ---------------------------------------------------------------------------------------------
// Progress (observable by tests, the progress bar and the health file)

#[derive(Debug, Clone, Default, PartialEq)]
pub struct Progress {
    /// `/jitter` messages written, and how many of them were ok / degraded / failed.
    pub frames: u64,
    pub ok: u64,
    pub degraded: u64,
    pub failed: u64,
    /// Frames (or files) finished with a terminal `/log` entry instead of a message.
    pub skipped: u64,
    /// `/log` entries about frames that also have a message (degraded, failed, late).
    pub notes: u64,
    pub references: u64,
    pub per_channel: BTreeMap<String, u64>,
    /// Inputs (frames or files) finished so far: `frames + skipped`.
    pub finished: u64,
    /// Daemon: the watcher is installed and the files present at start are queued; files
    /// written from now on are seen by events.
    pub watching: bool,
    pub write_errors: u64,
    pub last_error: Option<String>,
    /// Frames in the pipeline not yet finished (buffered or being aligned), plus files the
    /// daemon's front end holds that may still yield frames.
    pub queued: u64,
    /// Frames buffered or being aligned, per channel.
    pub queued_per_channel: BTreeMap<String, u64>,
}

// ---------------------------------------------------------------------------------------------
// Frames entering the pipeline

/// A frame found by a front end, not yet processed.
#[derive(Debug, Clone)]
pub struct FrameItem {
    pub key: String,
    pub spec: FrameSpec,
    pub channel: String,
    pub obs_time_ns: i64,
    /// When it entered the pipeline (wall clock; reorder window and partner hold).
    pub arrived: Instant,
}

/// What the front ends send to the scheduler.
#[derive(Debug)]
pub enum Input {
    Frame(FrameItem),
    /// A finished input that produced no frame (unreadable file …): written as is.
    Record(Record),
}

/// What looking at one file gave.
#[derive(Debug)]
pub enum FileOutcome {
    /// Frames to process (already-logged ones left out) and terminal records for frames
    /// that cannot be processed (no observation time).
    Frames(Vec<FrameItem>, Vec<Record>),
    /// Not (yet) a complete FITS file; the reason is what `/log` will say if it stays so.
    NotReady(Unready, String),
    /// Never to be taken; the record says why (`None`: silently irrelevant, e.g. a directory).
    Skip(Option<Record>),
    /// Gone before it could be read: a `/log` note, and the name stays open.
    Vanished(Record),
}

/// Why a file cannot be taken yet: decides how long the daemon keeps trying.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unready {
    /// A fault of the moment, not of the file (out of file descriptors or memory,
    /// interrupted): tried again until it reads.
    Transient,
    /// Ends early, is empty, or changed while being read: likely still being written.
    Incomplete,
    /// Anything else (not FITS, a bad header, no permission).
    Unreadable,
}

impl Unready {
    /// How a reader's refusal is taken.
    pub fn of(e: &Error) -> Unready {
        if e.is_transient() {
            Unready::Transient
        } else if sunjitter_io::fits::is_incomplete(e) {
            Unready::Incomplete
        } else {
            Unready::Unreadable
        }
    }

    fn of_io(e: &std::io::Error) -> Unready {
        if sunjitter_core::error::transient_io(e) {
            Unready::Transient
        } else {
            Unready::Unreadable
        }
    }
}

/// Identity of a file's content for de-duplication: (size, mtime).
pub type FileStamp = (u64, Option<SystemTime>);

pub fn file_stamp(meta: &std::fs::Metadata) -> FileStamp {
    (meta.len(), meta.modified().ok())
}

/// Look at one file: complete FITS? which frames, which channel, which time?
/// `path` must already be in canonical form ([`crate::config::canonical_file_path`]).
pub fn inspect_file(
    path: &Path,
    reader: &dyn FrameReader,
    config: &Config,
    history: &History,
    follow_symlinks: bool,
) -> FileOutcome {
    let key = frame_key(path, None);
    let link_meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            // Not finished: a file that reappears under this name is still taken.
            return FileOutcome::Vanished(Record::note(
                &key,
                "vanished before it could be read",
                now_ns(),
            ));
        }
        Err(e) => return FileOutcome::NotReady(Unready::of_io(&e), format!("cannot read: {e}")),
    };
    if link_meta.file_type().is_symlink() && !follow_symlinks {
        return FileOutcome::Skip(Some(Record::log(
            LogLevel::Error,
            &key,
            "symbolic link not followed (set daemon.follow_symlinks = true to take it)",
            system_time_ns(link_meta.modified().ok()),
        )));
    }
    let before = match std::fs::metadata(path) {
        Ok(m) => m,
        Err(e) => return FileOutcome::NotReady(Unready::of_io(&e), format!("cannot read: {e}")),
    };
    if before.is_dir() {
        return FileOutcome::Skip(None);
    }
    let mtime_ns = system_time_ns(before.modified().ok());
    if !before.is_file() {
        return FileOutcome::Skip(Some(Record::log(
            LogLevel::Error,
            &key,
            "not a regular file",
            mtime_ns,
        )));
    }
    if history.is_done(&key) {
        return FileOutcome::Skip(None);
    }
    // The reader refuses incomplete files (truncated headers or data) with the reason.
    let metas = match reader.read_meta(path) {
        // The image may be in an extension not yet written.
        Ok(m) if m.is_empty() => {
            return FileOutcome::NotReady(Unready::Incomplete, "no image in file".into())
        }
        Ok(m) => m,
        Err(e) => return FileOutcome::NotReady(Unready::of(&e), e.reason()),
    };
    match std::fs::metadata(path) {
        Ok(after) if file_stamp(&after) == file_stamp(&before) => {}
        Ok(_) => {
            return FileOutcome::NotReady(Unready::Incomplete, "changed while being read".into())
        }
        Err(e) => return FileOutcome::NotReady(Unready::of_io(&e), format!("cannot read: {e}")),
    }
    let arrived = Instant::now();
    let mut items = Vec::new();
    let mut records = Vec::new();
    for meta in metas {
        let key = frame_key(path, meta.frame);
        if history.is_done(&key) {
            continue;
        }
        let Some(obs_time_ns) = meta.obs_time_ns else {
            records.push(Record::log(
                LogLevel::Error,
                &key,
                "no observation time in the header (DATE-OBS, DATE_OBS or T_OBS)",
                mtime_ns,
            ));
            continue;
        };
        items.push(FrameItem {
            key,
            spec: FrameSpec {
                path: path.to_path_buf(),
                frame: meta.frame,
            },
            channel: config.channel_name(&meta.channel),
            obs_time_ns,
            arrived,
        });
    }
    FileOutcome::Frames(items, records)
}

/// The terminal `/log` record for a file that never became readable.
pub fn unreadable_record(path: &Path, reason: &str) -> Record {
    let mtime = std::fs::metadata(path).ok().and_then(|m| m.modified().ok());
    Record::log(
        LogLevel::Error,
        &frame_key(path, None),
        reason,
        system_time_ns(mtime),
    )
}

/// A `/log` warning about a file not taken yet (it does not finish the file).
pub fn waiting_record(path: &Path, message: String) -> Record {
    let mtime = std::fs::metadata(path).ok().and_then(|m| m.modified().ok());
    Record::note(&frame_key(path, None), message, system_time_ns(mtime))
}

// ---------------------------------------------------------------------------------------------
// Jobs

/// Reads pixels again, with the `[daemon]` back-off, after a fault of the moment (too many open
/// files, no memory): the front ends retry whole files, but the pixels are read later, by the
/// job, and a frame must not fail for good over such a fault. `retry_attempts` reads at most.
struct RetryingReader {
    inner: Arc<dyn FrameReader>,
    attempts: u32,
    first: Duration,
    longest: Duration,
}

impl RetryingReader {
    fn new(inner: Arc<dyn FrameReader>, d: &crate::config::DaemonConfig) -> RetryingReader {
        RetryingReader {
            inner,
            attempts: d.retry_attempts.max(1),
            first: Duration::from_secs_f64(d.retry_initial_s),
            longest: Duration::from_secs_f64(d.retry_max_s.max(d.retry_initial_s)),
        }
    }
}

impl FrameReader for RetryingReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        self.inner.read_meta(path)
    }

    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        let mut delay = self.first;
        for _ in 1..self.attempts {
            match self.inner.read_frame(spec) {
                Err(e) if e.is_transient() => {
                    tracing::warn!("{e}: reading again in {delay:?}");
                    std::thread::sleep(delay);
                    delay = (delay * 2).min(self.longest);
                }
                done => return done,
            }
        }
        self.inner.read_frame(spec)
    }
}

/// The reader, aligner and product writer the jobs use.
#[derive(Clone)]
pub struct JobContext {
    pub reader: Arc<dyn FrameReader>,
    pub aligner: Arc<dyn Aligner>,
    pub products: Option<Arc<crate::products::Products>>,
}

impl StepContext for JobContext {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        self.aligner.align(reference, frame)
    }
    fn usable_as_reference(&self, image: &Image) -> std::result::Result<(), String> {
        self.aligner.usable_as_reference(image)
    }
    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        self.aligner.plate_scale_used(image)
    }
    fn geometry_used(&self, image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        self.aligner.geometry_used(image)
    }
    fn load(&self, spec: &FrameSpec) -> Result<Image> {
        self.reader.read_frame(spec)
    }
}

/// One frame of one channel to process, with the channel's state moved in.
#[derive(Debug)]
pub struct Job {
    pub channel: String,
    pub state: ChannelState,
    pub item: FrameItem,
    pub partner: Option<PartnerFrame>,
    /// Emitted after a later frame of its channel (it arrived too late to reorder).
    pub late: bool,
}

#[derive(Debug)]
pub struct JobDone {
    pub channel: String,
    pub state: ChannelState,
    pub records: Vec<Record>,
    pub partner: Option<PartnerFrame>,
    /// When the frame entered the pipeline (for the ingest lag).
    pub arrived: Instant,
}

/// Run one job (blocking: reads the image, runs the engine).
pub fn run_job(job: Job, ctx: &JobContext) -> JobDone {
    let Job {
        channel,
        mut state,
        item,
        partner,
        late,
    } = job;
    let mut records = Vec::new();
    let mut partner_out = None;
    match ctx.reader.read_frame(&item.spec) {
        Err(e) => records.push(Record::log(
            LogLevel::Error,
            &item.key,
            e.reason(),
            item.obs_time_ns,
        )),
        Ok(image) => {
            let checksum = sunjitter_core::record::pixel_checksum(image.data.view());
            let frame = LoadedFrame {
                key: item.key.clone(),
                spec: item.spec.clone(),
                obs_time_ns: item.obs_time_ns,
                image: Arc::new(image),
            };
            let step = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                state.process(&frame, partner.as_ref(), ctx)
            }));
            match step {
                Ok(mut out) => {
                    // This frame's own message carries what was read (proves no torn reads).
                    for r in &mut out.records {
                        if let Record::Frame { message, .. } = r {
                            if message.align.frame == item.key {
                                message.pixel_checksum = Some(checksum.clone());
                            }
                        }
                    }
                    let notes: Vec<Record> = out
                        .records
                        .iter()
                        .filter_map(|r| match r {
                            Record::Frame {
                                message,
                                log_time_ns,
                            } => frame_note(message, *log_time_ns),
                            _ => None,
                        })
                        .collect();
                    // Written before the frame's records are logged: a frame logged is a frame
                    // whose product is in place (or whose note says why not).
                    let product_note = ctx
                        .products
                        .as_ref()
                        .and_then(|p| p.write(&item.key, &frame.image, &out, ctx));
                    partner_out = out.partner;
                    records.extend(out.records);
                    records.extend(notes);
                    records.extend(product_note);
                }
                Err(panic) => {
                    let what = sunjitter_core::text::panic_message(panic.as_ref());
                    tracing::error!(frame = %item.key, "internal error while aligning: {what}");
                    records.push(Record::log(
                        LogLevel::Error,
                        &item.key,
                        format!("internal error while aligning: {what}"),
                        item.obs_time_ns,
                    ));
                }
            }
        }
    }
    if late {
        records.push(Record::note(
            &item.key,
            "arrived after later frames of its channel: processed out of time order",
            item.obs_time_ns,
        ));
    }
    JobDone {
        channel,
        state,
        records,
        partner: partner_out,
        arrived: item.arrived,
    }
}

/// The `/log` note for a degraded or failed frame (after its message, never instead of it).
fn frame_note(message: &FrameAlignment, log_time_ns: i64) -> Option<Record> {
    let what = match message.align.status {
        Status::Ok => return None,
        Status::Degraded => "degraded",
        Status::Failed => "failed",
    };
    Some(Record::note(
        &message.align.frame,
        format!("{what}: {}", message.align.message),
        log_time_ns,
    ))
}

// ---------------------------------------------------------------------------------------------
// Scheduler: per-channel order, reorder window, partner choice

/// What the scheduler wants done.
#[derive(Debug)]
pub enum Action {
    Run(Box<Job>),
    Emit(Record),
}

#[derive(Debug, Default)]
struct Lane {
    state: Option<ChannelState>,
    buffer: BTreeMap<(i64, String), FrameItem>,
    in_flight: bool,
    /// Observation time of the frame being processed.
    in_flight_ns: Option<i64>,
    last_dispatched_ns: Option<i64>,
    /// Processed, usable frames of this channel (candidates for `channel:` followers).
    history: VecDeque<PartnerFrame>,
    /// Last time a frame of this channel arrived or finished (wall clock).
    last_activity: Option<Instant>,
}

enum PartnerChoice {
    Wait,
    Unmatched(String),
    Use(Box<PartnerFrame>),
}

/// Scheduling settings.
#[derive(Debug, Clone)]
pub struct SchedulerSettings {
    /// Daemon (wall-clock reorder window and partner hold) or replay (all input known at EOF).
    pub live: bool,
    pub workers: usize,
    pub reorder_window_frames: usize,
    pub reorder_window: Duration,
    /// Longest a frame is held while files are still in the pipe (window + settle time).
    pub reorder_cap: Duration,
}

impl SchedulerSettings {
    pub fn from_config(config: &Config, live: bool) -> SchedulerSettings {
        SchedulerSettings {
            live,
            workers: config.daemon.workers.max(1),
            reorder_window_frames: config.daemon.reorder_window_frames,
            reorder_window: Duration::from_secs_f64(config.daemon.reorder_window_s),
            reorder_cap: Duration::from_secs_f64(
                config.daemon.reorder_window_s + config.daemon.settle_s,
            ),
        }
    }
}

/// Decides which frame of which channel runs next. Pure state, no I/O, no clock of its own.
pub struct Scheduler {
    config: Arc<Config>,
    settings: SchedulerSettings,
    restored: BTreeMap<String, RestoredChannel>,
    lanes: BTreeMap<String, Lane>,
    running: usize,
    eof: bool,
    /// The front end has no file in hand that could still yield frames.
    pipe_empty: bool,
}

/// Partner history kept per channel beyond what waiting followers need.
const PARTNER_HISTORY_MIN: usize = 4;

impl Scheduler {
    pub fn new(config: Arc<Config>, settings: SchedulerSettings, history: &History) -> Scheduler {
        Scheduler {
            config,
            settings,
            restored: history.channels.clone(),
            lanes: BTreeMap::new(),
            running: 0,
            eof: false,
            pipe_empty: true,
        }
    }

    /// Whether the front end still has files in hand (see [`run_pipeline`]).
    pub fn set_pipe_empty(&mut self, empty: bool) {
        self.pipe_empty = empty;
    }

    /// Take a frame; a frame of one channel more than `[daemon] max_channels` is not taken,
    /// and the `/log` record naming it comes back instead.
    pub fn offer(&mut self, item: FrameItem) -> Option<Record> {
        let cap = self.config.daemon.max_channels;
        if !self.lanes.contains_key(&item.channel) && self.lanes.len() >= cap {
            return Some(Record::log(
                LogLevel::Error,
                &item.key,
                format!(
                    "channel {}: {cap} channels are tracked already (`[daemon] max_channels`); not measured",
                    item.channel
                ),
                item.obs_time_ns,
            ));
        }
        let lane = self.lanes.entry(item.channel.clone()).or_default();
        lane.buffer
            .insert((item.obs_time_ns, item.key.clone()), item);
        None
    }

    /// No more input will come (replay: everything is known; frames are released).
    pub fn set_eof(&mut self) {
        self.eof = true;
    }

    pub fn is_eof(&self) -> bool {
        self.eof
    }

    /// Nothing buffered and nothing running.
    pub fn idle(&self) -> bool {
        self.running == 0 && self.lanes.values().all(|l| l.buffer.is_empty())
    }

    pub fn running(&self) -> usize {
        self.running
    }

    pub fn buffered(&self) -> usize {
        self.lanes.values().map(|l| l.buffer.len()).sum()
    }

    /// Frames buffered or being aligned, per channel.
    pub fn queued_by_channel(&self) -> BTreeMap<String, u64> {
        self.lanes
            .iter()
            .map(|(name, l)| (name.clone(), l.buffer.len() as u64 + u64::from(l.in_flight)))
            .collect()
    }

    /// Everything that can start now.
    pub fn poll(&mut self, now: Instant) -> Vec<Action> {
        let mut actions = Vec::new();
        loop {
            let mut progressed = false;
            let names: Vec<String> = self.lanes.keys().cloned().collect();
            for name in names {
                if self.running >= self.settings.workers {
                    return actions;
                }
                if let Some(action) = self.poll_lane(&name, now) {
                    progressed = true;
                    actions.push(action);
                }
            }
            if !progressed {
                return actions;
            }
        }
    }

    fn released(&self, lane: &Lane, now: Instant) -> bool {
        let Some(((t, _), _)) = lane.buffer.first_key_value() else {
            return false;
        };
        if self.eof {
            return true;
        }
        if !self.settings.live {
            return false;
        }
        if lane.last_dispatched_ns.is_some_and(|last| *t < last)
            || lane.buffer.len() > self.settings.reorder_window_frames
        {
            return true;
        }
        let oldest = lane.buffer.values().map(|i| i.arrived).min();
        let age = oldest.map_or(Duration::ZERO, |a| now.saturating_duration_since(a));
        // Files still in the pipe may hold earlier frames: wait for them, within the cap.
        (age >= self.settings.reorder_window && self.pipe_empty) || age >= self.settings.reorder_cap
    }

    fn poll_lane(&mut self, name: &str, now: Instant) -> Option<Action> {
        let lane = self.lanes.get(name)?;
        if lane.in_flight || !self.released(lane, now) {
            return None;
        }
        let (_, head) = lane.buffer.first_key_value()?;
        let policy = self.config.channel_policy(name);
        let partner = match &policy.policy {
            PolicySpec::Channel(partner_name) => {
                match self.choose_partner(
                    partner_name,
                    head,
                    policy.tolerance_s,
                    policy.hold_s,
                    now,
                ) {
                    PartnerChoice::Wait => return None,
                    PartnerChoice::Unmatched(why) => {
                        let lane = self.lanes.get_mut(name)?;
                        let (_, item) = lane.buffer.pop_first()?;
                        return Some(Action::Emit(Record::log(
                            LogLevel::Error,
                            &item.key,
                            why,
                            item.obs_time_ns,
                        )));
                    }
                    PartnerChoice::Use(p) => Some(*p),
                }
            }
            _ => None,
        };
        let restored = self.restored.remove(name);
        let lane = self.lanes.get_mut(name)?;
        let (_, item) = lane.buffer.pop_first()?;
        let late = lane
            .last_dispatched_ns
            .is_some_and(|t| item.obs_time_ns < t);
        lane.last_dispatched_ns = lane.last_dispatched_ns.max(Some(item.obs_time_ns));
        let state = lane.state.take().unwrap_or_else(|| match restored {
            Some(r) => ChannelState::restore(name, policy, &r),
            None => ChannelState::new(name, policy),
        });
        lane.in_flight = true;
        self.running += 1;
        Some(Action::Run(Box::new(Job {
            channel: name.to_string(),
            state,
            item,
            partner,
            late,
        })))
    }

    fn choose_partner(
        &self,
        partner: &str,
        item: &FrameItem,
        tolerance_s: f64,
        hold_s: f64,
        now: Instant,
    ) -> PartnerChoice {
        let lane = self.lanes.get(partner);
        let history = lane.map(|l| &l.history);
        let t = item.obs_time_ns;
        let tolerance_ns = (tolerance_s * 1e9) as i64;
        // A partner frame still to be processed may be nearer than any processed one.
        let nearer_pending = lane.is_some_and(|l| {
            l.buffer
                .keys()
                .next()
                .is_some_and(|(pt, _)| *pt <= t + tolerance_ns)
                || (l.in_flight && l.in_flight_ns.is_some_and(|pt| pt <= t + tolerance_ns))
        });
        if nearer_pending {
            return PartnerChoice::Wait;
        }
        let before = history.and_then(|h| h.iter().rev().find(|p| p.obs_time_ns <= t));
        let after = history.and_then(|h| h.iter().find(|p| p.obs_time_ns >= t));
        let idle = lane.is_none_or(|l| l.buffer.is_empty() && !l.in_flight);
        let exhausted = self.eof && idle;
        // Live: give up only once the partner has nothing pending, no file is in the pipe,
        // and the partner has been quiet for `hold_s` (a busy partner is waited for).
        let expired = self.settings.live
            && idle
            && self.pipe_empty
            && now.saturating_duration_since(self.hold_start(partner, item))
                >= Duration::from_secs_f64(hold_s);
        if after.is_none() && !exhausted && !expired {
            return PartnerChoice::Wait;
        }
        let mut best: Option<&PartnerFrame> = None;
        for p in [before, after].into_iter().flatten() {
            let dt = (p.obs_time_ns - t).abs();
            if dt <= tolerance_ns && best.is_none_or(|b| dt < (b.obs_time_ns - t).abs()) {
                best = Some(p);
            }
        }
        match best {
            Some(p) => PartnerChoice::Use(Box::new(p.clone())),
            None => PartnerChoice::Unmatched(format!(
                "unmatched: no {partner} frame within ±{tolerance_s} s"
            )),
        }
    }

    /// When a frame's wait for a partner began counting: its arrival or the partner's last
    /// activity, whichever is later.
    fn hold_start(&self, partner: &str, item: &FrameItem) -> Instant {
        let activity = self.lanes.get(partner).and_then(|l| l.last_activity);
        activity.map_or(item.arrived, |a| a.max(item.arrived))
    }

    /// A job finished: take its state back and record the frame for followers.
    pub fn complete(&mut self, done: JobDone) {
        self.running = self.running.saturating_sub(1);
        let lane = self.lanes.entry(done.channel.clone()).or_default();
        lane.in_flight = false;
        lane.in_flight_ns = None;
        lane.last_activity = Some(Instant::now());
        lane.state = Some(done.state);
        if let Some(p) = done.partner {
            let at = lane
                .history
                .partition_point(|q| q.obs_time_ns <= p.obs_time_ns);
            lane.history.insert(at, p);
        }
        self.prune_history(&done.channel);
    }

    /// Drop partner frames no waiting follower can still choose.
    fn prune_history(&mut self, channel: &str) {
        let mut oldest_needed: Option<i64> = None;
        let mut has_followers = false;
        for (name, lane) in &self.lanes {
            let p = self.config.channel_policy(name);
            if p.policy != PolicySpec::Channel(channel.to_string()) {
                continue;
            }
            has_followers = true;
            let tol = (p.tolerance_s * 1e9) as i64;
            let pending = lane
                .buffer
                .keys()
                .next()
                .map(|(t, _)| *t)
                .or(lane.last_dispatched_ns);
            if let Some(t) = pending {
                let need = t.saturating_sub(tol);
                oldest_needed = Some(oldest_needed.map_or(need, |o| o.min(need)));
            }
        }
        let Some(lane) = self.lanes.get_mut(channel) else {
            return;
        };
        if !has_followers {
            while lane.history.len() > PARTNER_HISTORY_MIN {
                lane.history.pop_front();
            }
            return;
        }
        if let Some(oldest) = oldest_needed {
            // Keep one frame before `oldest` (it may still be the nearest).
            while lane.history.len() > PARTNER_HISTORY_MIN
                && lane.history.get(1).is_some_and(|p| p.obs_time_ns < oldest)
            {
                lane.history.pop_front();
            }
        }
    }

    /// When the scheduler next needs a look without new input (daemon only).
    pub fn next_deadline(&self) -> Option<Instant> {
        if !self.settings.live || self.eof {
            return None;
        }
        let mut next: Option<Instant> = None;
        let mut consider = |t: Instant| next = Some(next.map_or(t, |n: Instant| n.min(t)));
        for (name, lane) in &self.lanes {
            if lane.in_flight {
                continue;
            }
            if let Some(first) = lane.buffer.values().map(|i| i.arrived).min() {
                consider(first + self.settings.reorder_window);
                consider(first + self.settings.reorder_cap);
            }
            let policy = self.config.channel_policy(name);
            if let PolicySpec::Channel(partner) = &policy.policy {
                if let Some((_, head)) = lane.buffer.first_key_value() {
                    let start = self.hold_start(partner, head);
                    consider(start + Duration::from_secs_f64(policy.hold_s));
                }
            }
        }
        next
    }
}

// ---------------------------------------------------------------------------------------------
// The writer thread

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
                    if attempts_while_stopping >= 3 {
                        return Err(e);
                    }
                }
                std::thread::sleep(delay);
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

// ---------------------------------------------------------------------------------------------
// Driving it all

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
    let driven = drive(
        input,
        scheduler,
        ctx,
        writer_tx,
        stop,
        stopping,
        flush_every,
        pending_files,
        queue_progress,
    )
    .await;
    let written = tokio::task::spawn_blocking(move || writer.join())
        .await
        .map_err(|e| Error::output("writer thread", e.to_string()))?
        .map_err(|_| Error::output("writer thread", "panicked"))?;
    driven?;
    written?;
    let last = progress_rx.borrow().clone();
    Ok(last)
}

#[allow(clippy::too_many_arguments)]
async fn drive(
    mut input: mpsc::Receiver<Input>,
    mut scheduler: Scheduler,
    ctx: JobContext,
    writer: mpsc::Sender<WriterMsg>,
    mut stop: watch::Receiver<bool>,
    stopping: Arc<AtomicBool>,
    flush_every: Duration,
    pending_files: Option<Arc<AtomicUsize>>,
    progress: watch::Sender<Progress>,
) -> Result<()> {
    let gone = || Error::output("log writer", "stopped unexpectedly");
    let mut jobs: JoinSet<JobDone> = JoinSet::new();
    let mut accepting = true;
    let mut stopped = *stop.borrow();
    let mut stop_alive = true;
    let mut flush_tick = tokio::time::interval(flush_every);
    flush_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        if stopped {
            if accepting {
                accepting = false;
                stopping.store(true, Ordering::SeqCst);
                input.close();
            }
        } else {
            // Read the front end's count first, then take what it already sent: a file it
            // finished before the count was read has its frames in the queue by now.
            let pipe_empty = pending_files
                .as_ref()
                .is_none_or(|p| p.load(Ordering::SeqCst) == 0);
            while accepting {
                match input.try_recv() {
                    Ok(Input::Frame(item)) => {
                        if let Some(refused) = scheduler.offer(item) {
                            writer
                                .send(WriterMsg::Record(refused))
                                .await
                                .map_err(|_| gone())?;
                        }
                    }
                    Ok(Input::Record(record)) => {
                        writer
                            .send(WriterMsg::Record(record))
                            .await
                            .map_err(|_| gone())?;
                    }
                    Err(mpsc::error::TryRecvError::Empty) => break,
                    Err(mpsc::error::TryRecvError::Disconnected) => {
                        accepting = false;
                        scheduler.set_eof();
                    }
                }
            }
            scheduler.set_pipe_empty(pipe_empty);
            for action in scheduler.poll(Instant::now()) {
                match action {
                    Action::Run(job) => {
                        let ctx = ctx.clone();
                        jobs.spawn_blocking(move || run_job(*job, &ctx));
                    }
                    Action::Emit(record) => {
                        writer
                            .send(WriterMsg::Record(record))
                            .await
                            .map_err(|_| gone())?;
                    }
                }
            }
        }
        publish_queue(&progress, &scheduler, pending_files.as_deref());
        if jobs.is_empty() && (stopped || (scheduler.is_eof() && scheduler.idle())) {
            break;
        }
        let deadline = scheduler.next_deadline();
        tokio::select! {
            biased;
            changed = stop.changed(), if stop_alive && !stopped => {
                match changed {
                    Ok(()) => stopped = *stop.borrow(),
                    Err(_) => stop_alive = false, // nobody can ask any more
                }
            }
            joined = jobs.join_next(), if !jobs.is_empty() => {
                match joined {
                    Some(Ok(done)) => {
                        if let Some(frame) = done.records.iter().find_map(|r| match r {
                            Record::Frame { message, .. } => Some(message.align.frame.clone()),
                            _ => None,
                        }) {
                            let lag_s = done.arrived.elapsed().as_secs_f64();
                            writer.send(WriterMsg::Lag { frame, lag_s }).await.map_err(|_| gone())?;
                        }
                        for record in &done.records {
                            writer.send(WriterMsg::Record(record.clone())).await.map_err(|_| gone())?;
                        }
                        scheduler.complete(done);
                    }
                    Some(Err(e)) => {
                        return Err(Error::output("pipeline", format!("a worker died: {e}")));
                    }
                    None => {}
                }
            }
            received = input.recv(), if accepting => {
                match received {
                    Some(Input::Frame(item)) => {
                        if let Some(refused) = scheduler.offer(item) {
                            writer.send(WriterMsg::Record(refused)).await.map_err(|_| gone())?;
                        }
                    }
                    Some(Input::Record(record)) => {
                        writer.send(WriterMsg::Record(record)).await.map_err(|_| gone())?;
                    }
                    None => {
                        accepting = false;
                        scheduler.set_eof();
                    }
                }
            }
            _ = sleep_until_opt(deadline), if deadline.is_some() => {}
            _ = flush_tick.tick() => {
                writer.send(WriterMsg::Flush).await.map_err(|_| gone())?;
            }
        }
    }
    drop(writer);
    Ok(())
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

// ---------------------------------------------------------------------------------------------
// The output directory

/// Open the MCAP output in `out` for a new run, with what earlier runs already logged there.
/// Unfinished segments (a crash) are first rewritten as finished files so every MCAP reader
/// opens them; what they held counts as logged.
/// Locks `out` first: nothing is recovered or written while another process holds it.
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
    Ok(history)
}

fn clamp_ns(ns: u64) -> i64 {
    i64::try_from(ns).unwrap_or(i64::MAX)
}

// ---------------------------------------------------------------------------------------------
// Replay: the same pipeline over archived files

/// Check every file of a replay and list what goes into the pipeline: the frames (not yet
/// in the log) and a terminal `/log` record for each file that cannot be taken, with the
/// same reasons the daemon gives. An incomplete file is not waited for (an archive is
/// complete); a fault of the moment (too many open files) is retried with the `[daemon]`
/// back-off, and if it lasts, the file gets a `/log` warning only, so a later run takes it.
pub fn replay_inputs(
    files: &[(std::path::PathBuf, bool)],
    config: &Config,
    reader: &dyn FrameReader,
    history: &History,
) -> Vec<Input> {
    let d = &config.daemon;
    let mut inputs = Vec::new();
    for (path, explicit) in files {
        let follow = *explicit || config.daemon.follow_symlinks;
        let mut delay = Duration::from_secs_f64(d.retry_initial_s);
        let mut outcome = inspect_file(path, reader, config, history, follow);
        for _ in 1..d.retry_attempts.max(1) {
            let FileOutcome::NotReady(Unready::Transient, reason) = &outcome else {
                break;
            };
            tracing::warn!(file = %path.display(), "{reason}: reading again in {delay:?}");
            std::thread::sleep(delay);
            delay = (delay * 2).min(Duration::from_secs_f64(
                d.retry_max_s.max(d.retry_initial_s),
            ));
            outcome = inspect_file(path, reader, config, history, follow);
        }
        match outcome {
            FileOutcome::NotReady(Unready::Transient, reason) => {
                let message = format!("cannot be read for now, left for a later run: {reason}");
                inputs.push(Input::Record(waiting_record(path, message)));
            }
            FileOutcome::Frames(items, records) => {
                inputs.extend(records.into_iter().map(Input::Record));
                inputs.extend(items.into_iter().map(Input::Frame));
            }
            FileOutcome::NotReady(_, reason) => {
                inputs.push(Input::Record(unreadable_record(path, &reason)));
            }
            FileOutcome::Skip(Some(record)) | FileOutcome::Vanished(record) => {
                inputs.push(Input::Record(record))
            }
            FileOutcome::Skip(None) => {}
        }
    }
    inputs
}

/// Run the pipeline over `inputs` (from [`replay_inputs`]) in observation-time order per
/// channel. `shutdown` stops early (what is not logged is taken by the next run).
pub async fn run_replay(
    inputs: Vec<Input>,
    parts: RunParts,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<Progress> {
    let capacity = parts.config.daemon.queue_capacity.max(1);
    let (tx, rx) = mpsc::channel(capacity);
    let (stop_tx, stop_rx) = watch::channel(false);
    let producer = tokio::spawn(async move {
        for input in inputs {
            if tx.send(input).await.is_err() {
                break;
            }
        }
    });
    let stopper = tokio::spawn(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
        // Keep the sender alive: a closed channel must not read as a stop.
        std::future::pending::<()>().await;
    });
    let result = run_pipeline(
        RunParts {
            live: false,
            ..parts
        },
        rx,
        stop_rx,
        None,
    )
    .await;
    producer.abort();
    stopper.abort();
    result
}

// ---------------------------------------------------------------------------------------------
// Paths and time

/// ISO 8601 UTC with milliseconds, e.g. `2014-03-29T14:09:38.680Z` (the contract's `obs_time`).
pub fn iso8601_utc(ns: i64) -> String {
    sunjitter_core::time::format_iso_utc(ns)
}

/// Parse an ISO 8601 UTC time back to ns since the epoch.
pub fn parse_iso8601_utc(s: &str) -> Option<i64> {
    sunjitter_core::time::parse_fits_time(s, sunjitter_core::time::TimeScale::Utc).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ChannelConfig;
    use crate::fake::{FakeFrame, FakeReader, TruthAligner};
    use crate::ingest::expand_inputs;
    use std::collections::HashMap;
    use sunjitter_io::records::MemorySink;

    const S: i64 = 1_000_000_000;

    fn cov() -> crate::reference::Cov4 {
        let mut c = [[0.0; 4]; 4];
        c[2][2] = 0.01;
        c[3][3] = 0.01;
        c
    }

    fn write(dir: &Path, name: &str, frame: &FakeFrame) -> std::path::PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, frame.to_fits()).unwrap();
        crate::config::canonical_file_path(&path).unwrap()
    }

    fn replay(dir: &Path, config: Config, history: History) -> (Progress, Vec<Record>) {
        let config = Arc::new(config);
        let reader = FakeReader::default();
        let files = expand_inputs(&[dir.display().to_string()], &config).unwrap();
        let inputs = replay_inputs(&files, &config, &reader, &history);
        let sink = MemorySink::default();
        let parts = RunParts {
            config: config.clone(),
            reader: Arc::new(reader),
            aligner: Arc::new(TruthAligner::from_files(cov())),
            sink: Box::new(sink.clone()),
            history,
            progress: watch::channel(Progress::default()).0,
            live: false,
            products: None,
        };
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let progress = rt
            .block_on(run_replay(inputs, parts, std::future::pending()))
            .unwrap();
        assert!(sink.log.lock().unwrap().finished, "sink finished");
        (progress, sink.records())
    }

    fn frames_of<'a>(records: &'a [Record], channel: &str) -> Vec<&'a FrameAlignment> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Frame { message, .. } if message.channel == channel => {
                    Some(message.as_ref())
                }
                _ => None,
            })
            .collect()
    }

    fn logs(records: &[Record]) -> Vec<(String, String)> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Log { file, message, .. } => Some((file.clone(), message.clone())),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn replay_emits_each_frame_once_in_time_order_per_channel() {
        let dir = tempfile::tempdir().unwrap();
        // Names deliberately not in time order; two channels interleaved.
        let times_a = [50, 10, 40, 20, 30];
        for (i, t) in times_a.iter().enumerate() {
            let f = FakeFrame::new("A", t * S, 1.0, 0.0, 0.1 * *t as f64, 0.0);
            write(dir.path(), &format!("z{i}_a.fits"), &f);
        }
        for (i, t) in [15, 5, 25].iter().enumerate() {
            let f = FakeFrame::new("B", t * S, 1.0, 0.0, 0.0, 0.2 * *t as f64);
            write(dir.path(), &format!("b{i}.fits"), &f);
        }
        std::fs::write(dir.path().join("garbage.fits"), b"not a fits file at all").unwrap();
        let mut no_time = FakeFrame::new("A", 0, 1.0, 0.0, 0.0, 0.0);
        no_time.obs_time_ns = None;
        let no_time_path = write(dir.path(), "notime.fits", &no_time);

        let (progress, records) = replay(dir.path(), Config::default(), History::default());
        let a = frames_of(&records, "A");
        let times: Vec<i64> = a
            .iter()
            .map(|m| parse_iso8601_utc(&m.obs_time).unwrap() / S)
            .collect();
        assert_eq!(times, [10, 20, 30, 40, 50]);
        assert_eq!(
            a.iter().map(|m| m.sequence).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        assert_eq!(frames_of(&records, "B").len(), 3);
        // Chained dx is the true 0.1·t relative to the first frame (t = 10).
        for (m, t) in a.iter().zip(times) {
            assert!((m.chained_dx_px.unwrap() - 0.1 * (t - 10) as f64).abs() < 1e-9);
        }
        let logs = logs(&records);
        assert_eq!(logs.len(), 2, "{logs:?}");
        assert!(logs
            .iter()
            .any(|(f, m)| f.ends_with("garbage.fits") && m.contains("not a FITS file")));
        assert!(logs
            .iter()
            .any(|(f, m)| *f == no_time_path.display().to_string()
                && m.contains("no observation time")));
        assert_eq!(
            (progress.frames, progress.skipped, progress.finished),
            (8, 2, 10)
        );
    }

    #[test]
    fn channel_policy_picks_the_nearest_partner_within_tolerance() {
        let dir = tempfile::tempdir().unwrap();
        let mut keys = HashMap::new();
        for t in [0, 10, 20, 30] {
            let f = FakeFrame::new("P", t * S, 1.0, 0.0, t as f64, 0.0);
            keys.insert(
                t,
                write(dir.path(), &format!("p{t}.fits"), &f)
                    .display()
                    .to_string(),
            );
        }
        // 12 → P10, 16 → P20, 25 → tie → earlier (P20), 39 → P30 (9 s), 45 → unmatched (> 10 s).
        for t in [12, 16, 25, 39, 45] {
            let f = FakeFrame::new("F", t * S, 1.0, 0.0, t as f64, 1.0);
            write(dir.path(), &format!("f{t}.fits"), &f);
        }
        let mut config = Config::default();
        config.channels.insert(
            "F".into(),
            ChannelConfig {
                policy: Some(PolicySpec::Channel("P".into())),
                tolerance_s: Some(10.0),
                ..Default::default()
            },
        );
        let (_, records) = replay(dir.path(), config, History::default());
        let f = frames_of(&records, "F");
        let refs: Vec<&str> = f.iter().map(|m| m.align.reference.as_str()).collect();
        assert_eq!(refs, [&keys[&10], &keys[&20], &keys[&20], &keys[&30]]);
        for m in &f {
            assert_eq!(
                m.reference_kind,
                sunjitter_core::record::ReferenceKind::Channel
            );
            // Partner chain (dx = t_p) then partner → frame (dx = t_f − t_p): dx = t_f; dy = 1.
            let t = parse_iso8601_utc(&m.obs_time).unwrap() / S;
            assert!((m.chained_dx_px.unwrap() - t as f64).abs() < 1e-9);
            assert!((m.chained_dy_px.unwrap() - 1.0).abs() < 1e-9);
        }
        let logs = logs(&records);
        assert_eq!(logs.len(), 1);
        assert!(
            logs[0].0.ends_with("f45.fits") && logs[0].1.contains("unmatched"),
            "{logs:?}"
        );
        // The partner changed three times (P10, P20, P30).
        let changes = records
            .iter()
            .filter(|r| matches!(r, Record::Reference { change, .. } if change.channel == "F"))
            .count();
        assert_eq!(changes, 3);
    }

    #[test]
    fn replay_output_does_not_depend_on_worker_count() {
        let dir = tempfile::tempdir().unwrap();
        for t in 0..12 {
            for ch in ["A", "B", "C"] {
                let offset = (ch.as_bytes()[0] - b'A') as i64 + 1;
                let f = FakeFrame::new(
                    ch,
                    (t * 10 + offset) * S,
                    1.0 + 1e-4 * t as f64,
                    1e-4 * t as f64,
                    t as f64,
                    -(t as f64),
                );
                write(dir.path(), &format!("{ch}{t:02}.fits"), &f);
            }
        }
        let run = |workers| {
            let mut config = Config::default();
            config.daemon.workers = workers;
            config.reference.keyframe_every_frames = 5;
            config.channels.insert(
                "C".into(),
                ChannelConfig {
                    policy: Some(PolicySpec::Channel("A".into())),
                    ..Default::default()
                },
            );
            let (_, mut records) = replay(dir.path(), config, History::default());
            records.sort_by_key(|r| (r.topic(), r.log_time_ns(), format!("{r:?}")));
            records
        };
        let one = run(1);
        // 36 frames; keyframes at 0, 5, 10 in A and B; C follows A, a new partner each frame.
        assert_eq!(one.len(), 36 + 3 + 3 + 12);
        assert_eq!(one, run(3));
    }

    #[test]
    fn frames_already_in_the_log_are_not_processed_again() {
        let dir = tempfile::tempdir().unwrap();
        for t in 0..6 {
            write(
                dir.path(),
                &format!("f{t}.fits"),
                &FakeFrame::new("A", t * S, 1.0, 0.0, t as f64, 0.0),
            );
        }
        let mut config = Config::default();
        config.reference.keyframe_every_frames = 4;
        let (_, full) = replay(dir.path(), config.clone(), History::default());
        // Pretend the first run logged frames 0..3 (and their reference changes).
        let mut history = History::default();
        let cut = full
            .iter()
            .position(|r| matches!(r, Record::Frame { message, .. } if message.sequence == 3))
            .unwrap();
        for r in &full[..=cut] {
            history.add(r);
        }
        let (progress, rest) = replay(dir.path(), config, history);
        assert_eq!(progress.frames, 2);
        assert_eq!(
            &full[cut + 1..],
            &rest[..],
            "the resumed run continues the same series"
        );
    }

    #[test]
    fn iso_times_match_python_datetime() {
        // python: datetime.fromisoformat(s).replace(tzinfo=timezone.utc).timestamp()
        for (s, ns) in [
            ("2014-03-29T14:09:38.680Z", 1_396_102_178_680_000_000i64),
            ("1998-05-19T22:21:43.000Z", 895_616_503_000_000_000),
            ("2000-02-29T00:00:00.000Z", 951_782_400_000_000_000),
            ("1969-12-31T23:59:59.500Z", -500_000_000),
        ] {
            assert_eq!(iso8601_utc(ns), s);
            assert_eq!(parse_iso8601_utc(s), Some(ns));
        }
    }

    /// A reader out of file descriptors for its first `fails` checks, then the fake reader.
    struct OutOfDescriptors {
        fails: AtomicUsize,
    }

    impl FrameReader for OutOfDescriptors {
        fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
            let left = self.fails.load(Ordering::SeqCst);
            if left > 0 {
                self.fails.store(left - 1, Ordering::SeqCst);
                let emfile = std::io::Error::from_raw_os_error(libc::EMFILE);
                return Err(Error::io(path, emfile));
            }
            FakeReader::default().read_meta(path)
        }
        fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
            FakeReader::default().read_frame(spec)
        }
    }

    #[test]
    fn replay_reads_again_after_a_fault_of_the_moment_and_never_fails_a_file_over_it() {
        let dir = tempfile::tempdir().unwrap();
        write(
            dir.path(),
            "f.fits",
            &FakeFrame::new("A", S, 1.0, 0.0, 0.0, 0.0),
        );
        let mut config = Config::default();
        config.daemon.retry_initial_s = 0.001;
        config.daemon.retry_max_s = 0.002;
        config.daemon.retry_attempts = 3;
        let files = expand_inputs(&[dir.path().display().to_string()], &config).unwrap();
        let inputs = |fails| {
            let reader = OutOfDescriptors {
                fails: AtomicUsize::new(fails),
            };
            replay_inputs(&files, &config, &reader, &History::default())
        };
        // Two faults, the third check reads: the frame goes in.
        assert!(matches!(&inputs(2)[..], [Input::Frame(_)]));
        // Still out of descriptors after every attempt: a warning, which does not finish the
        // file (a later run takes it).
        match &inputs(3)[..] {
            [Input::Record(r @ Record::Log { message, .. })] => {
                assert!(
                    message.starts_with("cannot be read for now")
                        && message.contains("Too many open files"),
                    "{message}"
                );
                let mut history = History::default();
                history.add(r);
                assert!(history.done.is_empty());
            }
            other => panic!("{other:?}"),
        }
    }

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
        let files: Vec<String> = logs(&memory.records())
            .into_iter()
            .map(|(f, _)| f)
            .collect();
        assert_eq!(
            files,
            ["f0", "", "f1", "f2"],
            "the outage is noted after f0"
        );
        assert_eq!((prx.borrow().write_errors, prx.borrow().finished), (3, 3));
    }
}
