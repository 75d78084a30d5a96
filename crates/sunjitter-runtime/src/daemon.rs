//! The `watch` daemon: a directory watcher feeding the pipeline.
//!
//! ```text
//! notify (inotify) thread ──bounded──> ingest task ──spawn_blocking (≤ readers)──> file checks
//!                         (blocks when full:          │  complete FITS? frames? done before?
//!                          the kernel queue overflows, └──bounded──> pipeline (scheduler, jobs,
//!                          and we rescan: no loss)                   one writer thread)
//! ```
//!
//! - A file is taken on close-after-write or on a rename/move into the tree. A file found
//!   by a scan (start, watcher overflow or error, periodic safety net) or by a bare create
//!   event must first be unmodified for `settle_s`. Names in `ignore` (`.*`, `*.tmp`,
//!   `*.part`) and names without a configured extension are never taken.
//! - A file that does not check as complete FITS is retried with doubling delays; attempts
//!   count only while the file is not changing, so slow writers are never cut off. After
//!   `retry_attempts`: a file that ends early gets a `/log` warning and is waited for until
//!   unchanged for `incomplete_wait_s` (then reported failed, truncated); a fault of the
//!   moment (too many open files, no memory) gets a warning and is retried until it reads;
//!   any other unreadable file is reported failed on `/log` (file, reason). A warning does not
//!   finish the file, so a restart takes it again.
//! - Every path is taken at most once per run (and frames already in the log are never taken
//!   again): scans and repeated events de-duplicate against the per-path state, and a
//!   finished file whose (size, mtime) later changes gets one `/log` note.
//! - Shutdown is a future passed in: the watcher stops, files not yet taken stay for the
//!   next start, the pipeline finishes the frames in hand and closes the log.

use crate::config::{Config, DaemonConfig};
use crate::ingest::{scan_tree, wanted_dir, wanted_file};
use crate::pipeline::{
    file_stamp, inspect_file, run_pipeline, unreadable_record, waiting_record, FileOutcome,
    FileStamp, Input, Progress, RunParts, Unready,
};
use crate::ports::FrameReader;
use crate::reference::History;
use notify::event::{AccessKind, AccessMode, CreateKind, EventKind, ModifyKind, RenameMode};
use notify::{RecursiveMode, Watcher};
use std::collections::{BTreeSet, HashMap, VecDeque};
use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};
use sunjitter_core::{Error, Result};
use sunjitter_io::records::Record;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;

/// Watch `dir` and run the pipeline on every frame that appears, until `shutdown` resolves.
/// `parts.live` should be `true`. Returns the final progress counters.
pub async fn run_daemon(
    dir: &Path,
    parts: RunParts,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<Progress> {
    let root = dir.canonicalize().map_err(|e| Error::io(dir, e))?;
    if !root.is_dir() {
        return Err(Error::bad_input(dir, "not a directory"));
    }
    let config = parts.config.clone();
    let capacity = config.daemon.queue_capacity.max(1);

    let (stop_tx, stop_rx) = watch::channel(false);
    let stopper = tokio::spawn(async move {
        shutdown.await;
        tracing::info!("shutdown requested: finishing the frames in hand");
        let _ = stop_tx.send(true);
    });

    // Watcher thread → ingest. The handler blocks when the queue is full (back-pressure).
    let (signal_tx, signal_rx) = mpsc::channel::<Signal>(capacity);
    let mut watcher = notify::recommended_watcher(move |event: notify::Result<notify::Event>| {
        for signal in classify(event) {
            if signal_tx.blocking_send(signal).is_err() {
                return;
            }
        }
    })
    .map_err(|e| Error::output(&root, format!("cannot start the watcher: {e}")))?;
    let mode = if config.daemon.recursive {
        RecursiveMode::Recursive
    } else {
        RecursiveMode::NonRecursive
    };
    watcher
        .watch(&root, mode)
        .map_err(|e| Error::output(&root, format!("cannot watch: {e}")))?;
    tracing::info!(dir = %sunjitter_core::text::path(&root), recursive = config.daemon.recursive, "watching");

    let (input_tx, input_rx) = mpsc::channel::<Input>(capacity);
    let mut ingest = Ingest::new(
        root,
        config,
        parts.reader.clone(),
        Arc::new(parts.history.clone()),
    );
    // The run's own products are never its inputs, whatever link leads to them.
    ingest.excluded = parts
        .products
        .as_ref()
        .and_then(|p| sunjitter_io::outputs::file_id(p.dir()))
        .into_iter()
        .collect();
    // The start scan: after the watcher is installed, so nothing falls in between.
    ingest.rescan(None).await;
    parts.progress.send_modify(|p| p.watching = true);
    let pending = ingest.pending.clone();
    let ingest_task = tokio::spawn(ingest.run(signal_rx, input_tx, stop_rx.clone()));

    let result = run_pipeline(parts, input_rx, stop_rx, Some(pending)).await;
    drop(watcher);
    stopper.abort();
    match ingest_task.await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => tracing::error!("ingest stopped with an error: {e}"),
        Err(e) if e.is_cancelled() => {}
        Err(e) => tracing::error!("ingest task failed: {e}"),
    }
    result
}

// ---------------------------------------------------------------------------------------------
// Watcher events

#[derive(Debug, Clone, PartialEq)]
enum Signal {
    /// A file that is complete (closed after writing, or renamed/moved in).
    Complete(PathBuf),
    /// A file that appeared by other means (create, link): taken once settled.
    Appeared(PathBuf),
    /// A directory appeared (recursive mode scans it: files may have come with it).
    Dir(PathBuf),
    /// Events may have been lost: rescan everything.
    Rescan(String),
}

fn classify(event: notify::Result<notify::Event>) -> Vec<Signal> {
    let event = match event {
        Ok(e) => e,
        Err(e) => return vec![Signal::Rescan(format!("watcher error: {e}"))],
    };
    if event.need_rescan() {
        return vec![Signal::Rescan("watcher queue overflow".into())];
    }
    let paths = event.paths;
    match event.kind {
        EventKind::Access(AccessKind::Close(AccessMode::Write)) => {
            paths.into_iter().map(Signal::Complete).collect()
        }
        EventKind::Modify(ModifyKind::Name(RenameMode::To | RenameMode::Any)) => {
            paths.into_iter().map(Signal::Complete).collect()
        }
        EventKind::Modify(ModifyKind::Name(RenameMode::Both)) => {
            paths.into_iter().skip(1).map(Signal::Complete).collect()
        }
        EventKind::Create(CreateKind::Folder) => paths.into_iter().map(Signal::Dir).collect(),
        EventKind::Create(_) => paths.into_iter().map(Signal::Appeared).collect(),
        _ => Vec::new(),
    }
}

// ---------------------------------------------------------------------------------------------
// Ingest: per-path state, retries, scans

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Origin {
    /// Known complete (close-after-write, rename): no settle delay.
    Event,
    /// Found by a scan or a create event: must be settled first.
    Scan,
}

/// Failed attempts so far, and the file's (size, mtime) at the last one.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Tries {
    attempts: u32,
    last_stamp: Option<FileStamp>,
    /// Since when the file has been seen with `last_stamp`.
    unchanged_since: Option<Instant>,
    /// `/log` already says the file is being waited for.
    warned: bool,
}

#[derive(Debug, Clone)]
enum FileState {
    Queued(Origin, Tries),
    Reading(Tries),
    Waiting {
        due: Instant,
        origin: Origin,
        tries: Tries,
    },
    Done(Option<FileStamp>),
}

/// What a blocking check of one path found.
enum Examined {
    /// Modified less than `settle_s` ago: look again later.
    NotSettled(Duration),
    Dir,
    Outcome(Box<FileOutcome>, Option<FileStamp>),
}

struct Ingest {
    root: PathBuf,
    config: Arc<Config>,
    reader: Arc<dyn FrameReader>,
    history: Arc<History>,
    files: HashMap<PathBuf, FileState>,
    ready: VecDeque<PathBuf>,
    waiting: BTreeSet<(Instant, PathBuf)>,
    /// Paths in `files` not yet `Done` (shared with the scheduler's reorder window).
    pending: Arc<AtomicUsize>,
    /// Directories the run writes (its products), by identity: nothing inside is taken.
    excluded: Vec<sunjitter_io::outputs::FileId>,
    /// Whether a file inside them has been named in the log yet (once per run).
    excluded_noted: bool,
}

impl Ingest {
    fn new(
        root: PathBuf,
        config: Arc<Config>,
        reader: Arc<dyn FrameReader>,
        history: Arc<History>,
    ) -> Ingest {
        Ingest {
            root,
            config,
            reader,
            history,
            files: HashMap::new(),
            ready: VecDeque::new(),
            waiting: BTreeSet::new(),
            pending: Arc::new(AtomicUsize::new(0)),
            excluded: Vec::new(),
            excluded_noted: false,
        }
    }

    /// Change a path's state, keeping the count of pending (not `Done`) paths.
    fn set(&mut self, path: PathBuf, state: FileState) {
        let now_pending = !matches!(state, FileState::Done(_));
        let was_pending = self
            .files
            .insert(path, state)
            .is_some_and(|s| !matches!(s, FileState::Done(_)));
        match (was_pending, now_pending) {
            (false, true) => {
                self.pending.fetch_add(1, Ordering::SeqCst);
            }
            (true, false) => {
                self.pending.fetch_sub(1, Ordering::SeqCst);
            }
            _ => {}
        }
    }

    fn forget(&mut self, path: &Path) {
        if let Some(old) = self.files.remove(path) {
            if !matches!(old, FileState::Done(_)) {
                self.pending.fetch_sub(1, Ordering::SeqCst);
            }
        }
    }

    fn d(&self) -> &DaemonConfig {
        &self.config.daemon
    }

    async fn run(
        mut self,
        mut signals: mpsc::Receiver<Signal>,
        input: mpsc::Sender<Input>,
        mut stop: watch::Receiver<bool>,
    ) -> Result<()> {
        let capacity = self.d().queue_capacity.max(1);
        let readers = self.d().readers.max(1);
        let periodic = self.d().rescan_interval_s;
        let mut rescan_tick = tokio::time::interval(Duration::from_secs_f64(if periodic > 0.0 {
            periodic
        } else {
            86_400.0
        }));
        rescan_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        rescan_tick.tick().await; // the first tick is immediate (the start scan is done)

        let mut reading: JoinSet<(PathBuf, Examined)> = JoinSet::new();
        let mut watcher_alive = true;
        loop {
            if *stop.borrow() {
                break;
            }
            while reading.len() < readers {
                let Some(path) = self.ready.pop_front() else {
                    break;
                };
                let Some(FileState::Queued(origin, tries)) = self.files.get(&path).cloned() else {
                    continue;
                };
                self.set(path.clone(), FileState::Reading(tries));
                let (reader, config, history) = (
                    self.reader.clone(),
                    self.config.clone(),
                    self.history.clone(),
                );
                reading.spawn_blocking(move || {
                    let examined = examine(&path, origin, reader.as_ref(), &config, &history);
                    (path, examined)
                });
            }
            let next_due = self.waiting.first().map(|(t, _)| *t);
            tokio::select! {
                biased;
                changed = stop.changed() => {
                    if changed.is_err() || *stop.borrow() {
                        break;
                    }
                }
                joined = reading.join_next(), if !reading.is_empty() => {
                    let alive = match joined {
                        Some(Ok((path, examined))) => {
                            self.handle_examined(path, examined, &input).await
                        }
                        Some(Err(e)) => {
                            tracing::error!("a file check died: {e}");
                            true
                        }
                        None => true,
                    };
                    if !alive {
                        break;
                    }
                }
                signal = signals.recv(), if watcher_alive && self.ready.len() < capacity => {
                    match signal {
                        Some(signal) => {
                            if let Some(note) = self.handle_signal(signal).await {
                                if input.send(Input::Record(note)).await.is_err() {
                                    break;
                                }
                            }
                        }
                        None => {
                            tracing::error!("the watcher stopped: only periodic rescans from now on");
                            watcher_alive = false;
                        }
                    }
                }
                _ = sleep_until(next_due), if next_due.is_some() => {
                    self.release_due(Instant::now());
                }
                _ = rescan_tick.tick(), if periodic > 0.0 => {
                    self.rescan(None).await;
                }
            }
        }
        Ok(())
    }

    async fn handle_signal(&mut self, signal: Signal) -> Option<Record> {
        match signal {
            Signal::Complete(path) => return self.offer(path, Origin::Event),
            Signal::Appeared(path) => return self.offer(path, Origin::Scan),
            Signal::Dir(path) => {
                if !wanted_dir(&path, self.d()) {
                    return None;
                }
                if self.d().recursive {
                    self.rescan(Some(path)).await;
                } else {
                    return Some(Record::note(
                        &sunjitter_io::fits::frame_key(&path, None),
                        "directory not watched (set daemon.recursive or --recursive)",
                        sunjitter_io::records::now_ns(),
                    ));
                }
            }
            Signal::Rescan(why) => {
                tracing::warn!(
                    "{why}: rescanning {}",
                    sunjitter_core::text::path(&self.root)
                );
                self.rescan(None).await;
            }
        }
        None
    }

    /// A path seen by an event or a scan. Returns a `/log` note when a finished file changed.
    fn offer(&mut self, path: PathBuf, origin: Origin) -> Option<Record> {
        // Names that are not UTF-8 are matched by their lossy rendering, and taken all the same.
        let name = path.file_name()?.to_string_lossy();
        if !wanted_file(&name, self.d()) {
            return None;
        }
        if !self.files.contains_key(&path) {
            if let Some(real) = crate::ingest::excluded_output(&path, &self.excluded) {
                if !std::mem::replace(&mut self.excluded_noted, true) {
                    tracing::warn!(
                        file = %sunjitter_core::text::path(&path),
                        "is the run's own product ({}), reached through a link: products are never taken",
                        sunjitter_core::text::path(&real)
                    );
                }
                return None;
            }
        }
        match self.files.get(&path).cloned() {
            None => {
                self.set(path.clone(), FileState::Queued(origin, Tries::default()));
                self.ready.push_back(path);
            }
            Some(FileState::Queued(Origin::Scan, tries)) if origin == Origin::Event => {
                self.set(path, FileState::Queued(origin, tries));
            }
            Some(FileState::Queued(..)) | Some(FileState::Reading(_)) => {}
            Some(FileState::Waiting {
                due,
                origin: was,
                tries,
            }) => {
                // New activity: look again now, with a fresh attempt count.
                self.waiting.remove(&(due, path.clone()));
                let origin = if was == Origin::Event { was } else { origin };
                let tries = Tries {
                    attempts: 0,
                    ..tries
                };
                self.set(path.clone(), FileState::Queued(origin, tries));
                self.ready.push_back(path);
            }
            Some(FileState::Done(stamp)) => {
                if origin != Origin::Event {
                    return None;
                }
                let now_stamp = std::fs::metadata(&path).ok().map(|m| file_stamp(&m));
                if now_stamp.is_some() && now_stamp != stamp {
                    self.set(path.clone(), FileState::Done(now_stamp));
                    return Some(Record::note(
                        &sunjitter_io::fits::frame_key(&path, None),
                        "modified after it was processed: not processed again",
                        sunjitter_io::records::now_ns(),
                    ));
                }
            }
        }
        None
    }

    /// Returns false when the pipeline has gone (stop).
    async fn handle_examined(
        &mut self,
        path: PathBuf,
        examined: Examined,
        input: &mpsc::Sender<Input>,
    ) -> bool {
        let now = Instant::now();
        let tries = match self.files.get(&path) {
            Some(FileState::Reading(tries)) => *tries,
            _ => Tries::default(),
        };
        let (outcome, stamp) = match examined {
            Examined::NotSettled(wait) => {
                self.wait(path, now + wait, Origin::Scan, tries);
                return true;
            }
            Examined::Dir => {
                self.forget(&path);
                if self.d().recursive && wanted_dir(&path, self.d()) {
                    self.rescan(Some(path)).await;
                }
                return true;
            }
            Examined::Outcome(outcome, stamp) => (*outcome, stamp),
        };
        match outcome {
            FileOutcome::Frames(items, records) => {
                // Send first, then count the file done (see `run_pipeline`'s pending files).
                for record in records {
                    if input.send(Input::Record(record)).await.is_err() {
                        return false;
                    }
                }
                for item in items {
                    if input.send(Input::Frame(item)).await.is_err() {
                        return false;
                    }
                }
                self.set(path, FileState::Done(stamp));
                true
            }
            FileOutcome::Vanished(note) => {
                self.forget(&path);
                input.send(Input::Record(note)).await.is_ok()
            }
            FileOutcome::Skip(record) => {
                if let Some(r) = record {
                    if input.send(Input::Record(r)).await.is_err() {
                        return false;
                    }
                }
                self.set(path, FileState::Done(stamp));
                true
            }
            FileOutcome::NotReady(kind, reason) => {
                let unchanged = stamp.is_some() && stamp == tries.last_stamp;
                // Attempts count only while the file stands still; a fault of the moment
                // is no sign of a writer at work.
                let attempts = if unchanged || kind == Unready::Transient {
                    tries.attempts + 1
                } else {
                    1
                };
                let unchanged_since = match tries.unchanged_since {
                    Some(since) if unchanged => since,
                    _ => now,
                };
                let tried = attempts >= self.d().retry_attempts.max(1);
                let wait = Duration::from_secs_f64(self.d().incomplete_wait_s);
                let give_up = tried
                    && match kind {
                        Unready::Transient => false,
                        Unready::Incomplete => now.duration_since(unchanged_since) >= wait,
                        Unready::Unreadable => true,
                    };
                if give_up {
                    tracing::warn!(file = %sunjitter_core::text::path(&path), "giving up after {attempts} attempts: {reason}");
                    let reason = if kind == Unready::Incomplete && !wait.is_zero() {
                        format!("{reason} (unchanged for {} s)", wait.as_secs_f64())
                    } else {
                        reason
                    };
                    let record = unreadable_record(&path, &reason);
                    if input.send(Input::Record(record)).await.is_err() {
                        return false;
                    }
                    self.set(path, FileState::Done(stamp));
                    return true;
                }
                let mut warned = tries.warned;
                if tried && !warned {
                    warned = true;
                    let message = match kind {
                        Unready::Incomplete => format!(
                            "incomplete, waiting for the rest (up to {} s unchanged): {reason}",
                            wait.as_secs_f64()
                        ),
                        _ => format!("cannot be read for now, retrying: {reason}"),
                    };
                    tracing::warn!(file = %path.display(), "{message}");
                    let note = waiting_record(&path, message);
                    if input.send(Input::Record(note)).await.is_err() {
                        return false;
                    }
                }
                let delay = backoff(self.d(), attempts);
                tracing::debug!(file = %sunjitter_core::text::path(&path), attempts, "not ready ({reason}); retry in {delay:?}");
                let tries = Tries {
                    attempts,
                    last_stamp: stamp,
                    unchanged_since: Some(unchanged_since),
                    warned,
                };
                self.wait(path, now + delay, Origin::Event, tries);
                true
            }
        }
    }

    fn wait(&mut self, path: PathBuf, due: Instant, origin: Origin, tries: Tries) {
        self.waiting.insert((due, path.clone()));
        self.set(path, FileState::Waiting { due, origin, tries });
    }

    fn release_due(&mut self, now: Instant) {
        while let Some((due, path)) = self.waiting.first().cloned() {
            if due > now {
                break;
            }
            self.waiting.pop_first();
            if let Some(FileState::Waiting { origin, tries, .. }) = self.files.get(&path).cloned() {
                self.set(path.clone(), FileState::Queued(origin, tries));
                self.ready.push_back(path);
            }
        }
    }

    async fn rescan(&mut self, under: Option<PathBuf>) {
        let root = under.unwrap_or_else(|| self.root.clone());
        let daemon = self.d().clone();
        let excluded = self.excluded.clone();
        let found = tokio::task::spawn_blocking(move || {
            scan_tree(
                &root,
                daemon.recursive,
                daemon.follow_symlinks,
                &daemon,
                &excluded,
            )
        })
        .await;
        match found {
            Ok(Ok(found)) => {
                for path in found {
                    if !self.files.contains_key(&path) {
                        self.offer(path, Origin::Scan);
                    }
                }
            }
            Ok(Err(e)) => tracing::error!("rescan failed: {e}"),
            Err(e) => tracing::error!("rescan failed: {e}"),
        }
    }
}

fn backoff(d: &DaemonConfig, attempts: u32) -> Duration {
    let exp = 2f64.powi(attempts.saturating_sub(1).min(30) as i32);
    Duration::from_secs_f64((d.retry_initial_s * exp).min(d.retry_max_s.max(d.retry_initial_s)))
}

async fn sleep_until(deadline: Option<Instant>) {
    if let Some(d) = deadline {
        tokio::time::sleep_until(tokio::time::Instant::from_std(d)).await;
    }
}

/// The blocking part: settle check, then the full file check.
fn examine(
    path: &Path,
    origin: Origin,
    reader: &dyn FrameReader,
    config: &Config,
    history: &History,
) -> Examined {
    let meta = std::fs::symlink_metadata(path).ok();
    if let Some(m) = &meta {
        if m.is_dir() {
            return Examined::Dir;
        }
        if origin == Origin::Scan && !m.file_type().is_symlink() {
            let settle = Duration::from_secs_f64(config.daemon.settle_s);
            let age = m
                .modified()
                .ok()
                .and_then(|t| SystemTime::now().duration_since(t).ok())
                .unwrap_or(settle);
            if age < settle {
                return Examined::NotSettled(settle - age);
            }
        }
    }
    let stamp = std::fs::metadata(path).ok().map(|m| file_stamp(&m));
    // A reader bug on some odd file must not lose the file silently (a panic here would
    // leave it "reading" forever): it is finished with a /log entry instead.
    let inspected = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        inspect_file(path, reader, config, history, config.daemon.follow_symlinks)
    }));
    let outcome = inspected.unwrap_or_else(|panic| {
        let what = sunjitter_core::text::panic_message(panic.as_ref());
        tracing::error!(file = %sunjitter_core::text::path(path), "internal error while reading: {what}");
        FileOutcome::Skip(Some(unreadable_record(
            path,
            &format!("internal error while reading: {what}"),
        )))
    });
    Examined::Outcome(Box::new(outcome), stamp)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::name_matches;
    use sunjitter_io::sink::LogLevel;

    #[test]
    fn wildcards_follow_shell_rules() {
        for (p, s, m) in [
            (".*", ".hidden.fits", true),
            (".*", "visible.fits", false),
            ("*.tmp", "a.fits.tmp", true),
            ("*.part", "a.fits", false),
            ("f??.fits", "f01.fits", true),
            ("f??.fits", "f1.fits", false),
            ("f[0-4].fits", "f3.fits", true),
            ("f[0-4].fits", "f7.fits", false),
            ("f[!0-4].fits", "f7.fits", true),
            ("*", "", true),
        ] {
            assert_eq!(name_matches(p, s), m, "{p} vs {s}");
        }
    }

    #[test]
    fn temporary_and_foreign_names_are_not_taken() {
        let d = DaemonConfig::default();
        assert!(wanted_file("frame_001.fits", &d));
        assert!(wanted_file("FRAME.FTS", &d));
        assert!(!wanted_file(".frame_001.fits", &d));
        assert!(!wanted_file("frame_001.fits.tmp", &d));
        assert!(!wanted_file("frame_001.fits.part", &d));
        assert!(!wanted_file("notes.txt", &d));
    }

    #[test]
    fn close_write_and_renames_are_complete_creates_are_not() {
        use notify::Event;
        let p = PathBuf::from("/w/a.fits");
        let close =
            Event::new(EventKind::Access(AccessKind::Close(AccessMode::Write))).add_path(p.clone());
        assert_eq!(classify(Ok(close)), vec![Signal::Complete(p.clone())]);
        let moved =
            Event::new(EventKind::Modify(ModifyKind::Name(RenameMode::To))).add_path(p.clone());
        assert_eq!(classify(Ok(moved)), vec![Signal::Complete(p.clone())]);
        let both = Event::new(EventKind::Modify(ModifyKind::Name(RenameMode::Both)))
            .add_path("/w/.a.tmp".into())
            .add_path(p.clone());
        assert_eq!(classify(Ok(both)), vec![Signal::Complete(p.clone())]);
        let create = Event::new(EventKind::Create(CreateKind::File)).add_path(p.clone());
        assert_eq!(classify(Ok(create)), vec![Signal::Appeared(p.clone())]);
        let overflow = Event::new(EventKind::Other).set_flag(notify::event::Flag::Rescan);
        assert!(matches!(classify(Ok(overflow))[..], [Signal::Rescan(_)]));
        let modify = Event::new(EventKind::Modify(ModifyKind::Data(
            notify::event::DataChange::Any,
        )))
        .add_path(p);
        assert!(
            classify(Ok(modify)).is_empty(),
            "a write in progress is not a complete file"
        );
    }

    /// Drive the ingest with hand-made signals: repeated events and rescans must hand each
    /// file to the pipeline exactly once; a garbage file once, as a `/log` record.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn rescans_and_repeated_events_hand_each_file_over_once() {
        use crate::fake::{FakeFrame, FakeReader};
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().canonicalize().unwrap();
        let mut config = Config::default();
        config.daemon.settle_s = 0.0;
        config.daemon.retry_initial_s = 0.01;
        config.daemon.retry_max_s = 0.02;
        config.daemon.retry_attempts = 2;
        config.daemon.queue_capacity = 2;
        let write = |name: &str, t: i64| {
            let f = FakeFrame::new("A", t, 1.0, 0.0, 0.0, 0.0);
            std::fs::write(root.join(name), f.to_fits()).unwrap();
            root.join(name)
        };
        let early = write("early.fits", 1); // found by the start scan
        let ingest = Ingest::new(
            root.clone(),
            Arc::new(config),
            Arc::new(FakeReader::default()),
            Arc::new(History::default()),
        );
        let pending = ingest.pending.clone();
        let (sig_tx, sig_rx) = mpsc::channel(2);
        let (in_tx, mut in_rx) = mpsc::channel(2);
        let (stop_tx, stop_rx) = watch::channel(false);
        let task = tokio::spawn(ingest.run(sig_rx, in_tx, stop_rx));
        let mut paths = vec![early];
        for i in 0..20 {
            paths.push(write(&format!("f{i:02}.fits"), 10 + i));
        }
        std::fs::write(root.join("junk.fits"), b"junk").unwrap();
        std::fs::write(root.join(".hidden.fits"), b"junk").unwrap();
        let sender = tokio::spawn(async move {
            for round in 0..3 {
                for p in &paths {
                    sig_tx.send(Signal::Complete(p.clone())).await.unwrap();
                }
                sig_tx
                    .send(Signal::Rescan(format!("round {round}")))
                    .await
                    .unwrap();
            }
            sig_tx
                .send(Signal::Complete(root.join(".hidden.fits")))
                .await
                .unwrap();
            // A file gone before it is read, and a directory in a non-recursive watch.
            sig_tx
                .send(Signal::Complete(root.join("ghost.fits")))
                .await
                .unwrap();
            std::fs::create_dir(root.join("sub")).unwrap();
            sig_tx.send(Signal::Dir(root.join("sub"))).await.unwrap();
            sig_tx
        });
        let mut frames = std::collections::BTreeMap::new();
        let mut logs = Vec::new();
        while frames.len() < 21 || logs.len() < 3 {
            let next = tokio::time::timeout(Duration::from_secs(30), in_rx.recv()).await;
            match next.expect("ingest made progress").expect("ingest alive") {
                Input::Frame(item) => *frames.entry(item.key).or_insert(0) += 1,
                Input::Record(r) => logs.push(r),
            }
        }
        let _sig_tx = sender.await.unwrap();
        // Nothing more may come: stop, then drain what is left.
        stop_tx.send(true).unwrap();
        task.await.unwrap().unwrap();
        while let Ok(extra) = in_rx.try_recv() {
            match extra {
                Input::Frame(item) => *frames.entry(item.key).or_insert(0) += 1,
                Input::Record(r) => logs.push(r),
            }
        }
        assert_eq!(frames.len(), 21);
        assert!(frames.values().all(|n| *n == 1), "{frames:?}");
        assert_eq!(
            pending.load(Ordering::SeqCst),
            0,
            "every file finished, none pending"
        );
        assert_eq!(logs.len(), 3, "{logs:?}");
        let find = |name: &str| {
            logs.iter()
                .find_map(|r| match r {
                    Record::Log {
                        file,
                        message,
                        level,
                        finishes,
                        ..
                    } if file.ends_with(name) => Some((message.clone(), *level, *finishes)),
                    _ => None,
                })
                .unwrap_or_else(|| panic!("no /log entry for {name}: {logs:?}"))
        };
        let (junk, level, finishes) = find("junk.fits");
        assert!(
            junk.contains("not a FITS file") && finishes && level == LogLevel::Error,
            "{junk}"
        );
        let (ghost, _, finishes) = find("ghost.fits");
        assert!(ghost.contains("vanished") && !finishes, "{ghost}");
        let (sub, _, finishes) = find("sub");
        assert!(sub.contains("not watched") && !finishes, "{sub}");
    }

    /// A reader that panics on some file: the file is finished with one `/log` error naming
    /// it, rather than staying "reading" forever with only a tracing line.
    #[test]
    fn a_reader_panic_finishes_the_file_with_a_log_entry() {
        struct Panicking;
        impl FrameReader for Panicking {
            fn read_meta(&self, _: &Path) -> Result<Vec<sunjitter_core::meta::FrameMeta>> {
                panic!("boom")
            }
            fn read_frame(
                &self,
                _: &sunjitter_io::fits::FrameSpec,
            ) -> Result<sunjitter_core::engine::Image> {
                panic!("boom")
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().canonicalize().unwrap().join("odd.fits");
        std::fs::write(&path, b"SIMPLE  =").unwrap();
        let examined = examine(
            &path,
            Origin::Event,
            &Panicking,
            &Config::default(),
            &History::default(),
        );
        let Examined::Outcome(outcome, _) = examined else {
            panic!("not examined")
        };
        match *outcome {
            FileOutcome::Skip(Some(Record::Log {
                level,
                file,
                message,
                finishes,
                ..
            })) => {
                assert_eq!(level, LogLevel::Error);
                assert!(finishes);
                assert_eq!(file, path.display().to_string());
                assert_eq!(message, "internal error while reading: boom");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn backoff_doubles_up_to_the_cap() {
        let d = DaemonConfig {
            retry_initial_s: 0.25,
            retry_max_s: 1.0,
            ..Default::default()
        };
        let delays: Vec<f64> = (1..=5).map(|a| backoff(&d, a).as_secs_f64()).collect();
        assert_eq!(delays, [0.25, 0.5, 1.0, 1.0, 1.0]);
    }
}
