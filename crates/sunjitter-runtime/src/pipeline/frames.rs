//! Frames entering the pipeline: what a front end finds in a file, and the records for files
//! it cannot take.

use crate::config::Config;
use crate::ports::FrameReader;
use crate::reference::History;
use std::path::Path;
use std::time::{Instant, SystemTime};
use sunjitter_core::Error;
use sunjitter_io::fits::frame_key;
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::records::{now_ns, system_time_ns, Record};
use sunjitter_io::sink::LogLevel;

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
    if let Some(kind) = sunjitter_io::input::special_kind(&before) {
        // Never opened: a FIFO would block the reader, a device never end.
        return FileOutcome::Skip(Some(Record::log(
            LogLevel::Error,
            &key,
            format!("is {kind}, not a regular file"),
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
