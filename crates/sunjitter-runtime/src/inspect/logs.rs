//! The logs `inspect` reads: which files, and their `/jitter` and `/log` messages.

use super::{summarise_log, LogSummary, LoggedFrame};
use std::path::PathBuf;
use sunjitter_core::{Error, Result};
use sunjitter_io::sink::ReferenceChange;

/// The logs to read: files as given, directories replaced by their `*.mcap` files in name order.
pub fn log_files(args: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for arg in args {
        let meta = std::fs::metadata(arg).map_err(|e| Error::io(arg, e))?;
        if meta.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(arg)
                .map_err(|e| Error::io(arg, e))?
                .filter_map(|entry| entry.ok().map(|e| e.path()))
                .filter(|p| {
                    p.extension()
                        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
                })
                .collect();
            if found.is_empty() {
                return Err(Error::bad_input(arg, "directory holds no .mcap files"));
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(arg.clone());
        }
    }
    files.dedup();
    Ok(files)
}

/// Every `/jitter/<channel>` message of `files`, with its `log_time`, and the `/log` tally;
/// damaged or unfinished segments are read as far as they go, with a warning naming what was
/// skipped.
pub fn read_frames(files: &[PathBuf]) -> Result<(Vec<LoggedFrame>, LogSummary)> {
    read_frames_and_references(files).map(|(frames, _, log)| (frames, log))
}

/// [`read_frames`], and the `/reference` messages (their keyframe closures).
pub fn read_frames_and_references(
    files: &[PathBuf],
) -> Result<(Vec<LoggedFrame>, Vec<ReferenceChange>, LogSummary)> {
    let contents = sunjitter_io::sink::read_logs(files)?;
    for note in contents.notes() {
        tracing::warn!("{note}");
    }
    let frames: Vec<LoggedFrame> = contents
        .jitter
        .into_iter()
        .map(|m| LoggedFrame {
            log_time_ns: i64::try_from(m.log_time_ns).unwrap_or(i64::MAX),
            record: m.record,
        })
        .collect();
    let entries = contents.logs.iter().map(|m| {
        (
            m.entry.level as u8,
            m.entry.file.as_str(),
            m.entry.message.as_str(),
        )
    });
    let log = summarise_log(entries, &frames);
    let references = contents.references.into_iter().map(|r| r.change).collect();
    Ok((frames, references, log))
}
