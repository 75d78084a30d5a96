//! Progress, observable by tests, the progress bar and the health file.

use std::collections::BTreeMap;

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

impl Progress {
    /// The run's summary, as `watch --json` and `replay --json` print it.
    pub fn summary_json(&self, out: &std::path::Path) -> serde_json::Value {
        serde_json::json!({
            "out": out.display().to_string(),
            "frames": self.frames,
            "ok": self.ok,
            "degraded": self.degraded,
            "failed": self.failed,
            "skipped": self.skipped,
            "reference_changes": self.references,
            "channels": self.per_channel,
            "write_errors": self.write_errors,
        })
    }
}
