//! The health status file: what the daemon has done and how it is doing, as one JSON document
//! rewritten atomically (temporary file + rename) every `health.interval_s` and at shutdown,
//! so a reader always sees a whole document. `sunjitter status` prints it.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use sunjitter_core::{Error, Result};

/// File name of the status in the output directory (the default place).
pub const STATUS_FILE: &str = "status.json";

/// The status document.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub program: String,
    pub version: String,
    pub pid: u32,
    /// `running`, or `stopped` after a clean shutdown.
    pub state: String,
    pub started: String,
    /// When this document was written (ISO 8601 UTC).
    pub updated: String,
    pub uptime_s: f64,
    /// Seconds between rewrites while running.
    pub interval_s: f64,
    pub watching: String,
    pub out: String,
    /// `ws://ADDR:PORT` of the live view, if any.
    pub live: Option<String>,
    /// `/jitter` messages logged, and by status.
    pub frames: u64,
    pub ok: u64,
    pub degraded: u64,
    pub failed: u64,
    /// Inputs finished with a `/log` error instead of a message (unreadable files …).
    pub skipped: u64,
    /// Frames buffered or being aligned, plus files in hand that may still yield frames.
    pub queue_depth: u64,
    pub write_errors: u64,
    /// The last error: a failed write, an input finished with an error, a failed frame.
    pub last_error: Option<String>,
    /// Messages the live view dropped (its queue was full); the log has them all.
    pub live_dropped: u64,
    pub alerts_raised: u64,
    pub alert_command_failures: u64,
    /// Alerts raised and not yet resolved.
    pub active_alerts: Vec<ActiveAlert>,
    pub channels: BTreeMap<String, ChannelStatus>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ActiveAlert {
    pub channel: String,
    pub kind: String,
}

/// One channel.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ChannelStatus {
    pub frames: u64,
    pub ok: u64,
    pub degraded: u64,
    pub failed: u64,
    /// The last frame logged (`FILE` or `FILE[N]`), its observation time, and when it was
    /// logged (wall clock), all ISO 8601 UTC.
    pub last_frame: Option<String>,
    pub last_obs_time: Option<String>,
    pub last_logged: Option<String>,
    /// Seconds from the last frame's file being taken to its alignment being done.
    pub lag_s: Option<f64>,
    /// Frames of this channel buffered or being aligned.
    pub queued: u64,
    /// The message of the last failed or degraded frame.
    pub last_error: Option<String>,
}

/// Where the status of an output directory (or an explicit file) is.
pub fn resolve_path(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join(STATUS_FILE)
    } else {
        path.to_path_buf()
    }
}

/// Write `status` to `path` atomically: a temporary file beside it, then a rename.
pub fn write_atomic(path: &Path, status: &Status) -> Result<()> {
    let text = serde_json::to_string_pretty(status)
        .map_err(|e| Error::output(path, format!("cannot encode the status: {e}")))?;
    sunjitter_io::outputs::write_file_atomically(path, |w| writeln!(w, "{text}"))
        .map_err(|e| Error::output(path, format!("cannot write the status: {}", e.reason())))
}

/// Read a status file.
pub fn read(path: &Path) -> Result<Status> {
    // A status file is a few kB; a FIFO or a device is not read at all.
    let text = sunjitter_io::input::read_text(path, 16 << 20, "status file")?;
    serde_json::from_str(&text)
        .map_err(|e| Error::bad_input(path, format!("not a status file: {e}")))
}

/// Whether a `running` status has not been rewritten for three intervals.
pub fn is_stale(s: &Status, now_ns: i64) -> bool {
    s.state == "running"
        && sunjitter_core::time::parse_fits_time(&s.updated, sunjitter_core::time::TimeScale::Utc)
            .ok()
            .is_some_and(|t| (now_ns - t) as f64 / 1e9 > 3.0 * s.interval_s.max(1.0))
}

/// Why a stale status is not rewritten, as far as this machine shows: the daemon's process is
/// gone, or it is alive and the directories it writes (`status_dir`, its output) refuse new
/// files. `None` when nothing is known (then it may be hung).
pub fn diagnose_stale(s: &Status, status_dir: &Path) -> Option<String> {
    let proc_dir = Path::new("/proc");
    if !proc_dir.is_dir() {
        return None;
    }
    let cmdline = std::fs::read(proc_dir.join(s.pid.to_string()).join("cmdline")).ok();
    let is_daemon = cmdline.is_some_and(|c| {
        let argv0 = c.split(|b| *b == 0).next().unwrap_or_default();
        String::from_utf8_lossy(argv0).contains("sunjitter")
    });
    if !is_daemon {
        return Some(format!(
            "NOT RUNNING: pid {} is gone without a clean stop; last updated {}",
            s.pid, s.updated
        ));
    }
    let mut dirs = vec![status_dir.to_path_buf()];
    if !s.out.is_empty() && Path::new(&s.out) != status_dir {
        dirs.push(PathBuf::from(&s.out));
    }
    dirs.iter()
        .find_map(|d| sunjitter_core::error::check_writable_dir(d).err())
        .map(|e| {
            format!(
                "OUTPUT UNWRITABLE: pid {} is alive but cannot write {e}; status last updated {}",
                s.pid, s.updated
            )
        })
}

/// The status for people. Every text field is escaped: a status file names input files.
pub fn render(s: &Status, now_ns: i64) -> String {
    render_diagnosed(s, now_ns, None)
}

/// [`render`], with what [`diagnose_stale`] found shown instead of a bare STALE.
pub fn render_diagnosed(s: &Status, now_ns: i64, diagnosis: Option<&str>) -> String {
    use std::fmt::Write;
    use sunjitter_core::text::escape;
    let mut out = String::new();
    let state = match (is_stale(s, now_ns), diagnosis) {
        (true, Some(why)) => format!("{} ({why})", s.state),
        (true, None) => format!("{} (STALE: not updated since {})", s.state, s.updated),
        (false, _) => s.state.clone(),
    };
    let _ = writeln!(
        out,
        "sunjitter {} (pid {}): {}",
        escape(&s.version),
        s.pid,
        escape(&state)
    );
    let _ = writeln!(
        out,
        "  started {}, up {}, updated {}",
        escape(&s.started),
        duration(s.uptime_s),
        escape(&s.updated)
    );
    let _ = writeln!(
        out,
        "  watching {} → {}",
        escape(&s.watching),
        escape(&s.out)
    );
    if let Some(live) = &s.live {
        let _ = writeln!(
            out,
            "  live view {} ({} messages dropped)",
            escape(live),
            s.live_dropped
        );
    }
    let _ = writeln!(
        out,
        "  frames {} (ok {}, degraded {}, failed {}), skipped {}, queued {}, write errors {}",
        s.frames, s.ok, s.degraded, s.failed, s.skipped, s.queue_depth, s.write_errors
    );
    if let Some(e) = &s.last_error {
        let _ = writeln!(out, "  last error: {}", escape(e));
    }
    if s.active_alerts.is_empty() {
        let _ = writeln!(
            out,
            "  alerts: none active ({} raised so far)",
            s.alerts_raised
        );
    } else {
        let list: Vec<String> = s
            .active_alerts
            .iter()
            .map(|a| format!("{} {}", escape(&a.channel), escape(&a.kind)))
            .collect();
        let _ = writeln!(out, "  ALERTS ACTIVE: {}", list.join(", "));
    }
    if s.alert_command_failures > 0 {
        let _ = writeln!(
            out,
            "  alert command failures: {}",
            s.alert_command_failures
        );
    }
    if !s.channels.is_empty() {
        let _ = writeln!(
            out,
            "  {:<14} {:>7} {:>7} {:>8} {:>6} {:>6} {:>8}  last frame (obs time)",
            "channel", "frames", "ok", "degraded", "failed", "queued", "lag s"
        );
    }
    for (name, c) in &s.channels {
        let lag = c.lag_s.map_or("-".to_string(), |l| format!("{l:.2}"));
        let _ = writeln!(
            out,
            "  {:<14} {:>7} {:>7} {:>8} {:>6} {:>6} {:>8}  {}",
            escape(name),
            c.frames,
            c.ok,
            c.degraded,
            c.failed,
            c.queued,
            lag,
            escape(c.last_obs_time.as_deref().unwrap_or("-"))
        );
        if let Some(e) = &c.last_error {
            let _ = writeln!(out, "  {:<14} last error: {}", "", escape(e));
        }
    }
    out
}

fn duration(s: f64) -> String {
    let s = s.max(0.0) as u64;
    let (d, h, m, sec) = (s / 86_400, s / 3600 % 24, s / 60 % 60, s % 60);
    if d > 0 {
        format!("{d}d {h:02}:{m:02}:{sec:02}")
    } else {
        format!("{h:02}:{m:02}:{sec:02}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_written_status_reads_back_whole_and_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(STATUS_FILE);
        let mut s = Status {
            state: "running".into(),
            frames: 3,
            ..Default::default()
        };
        s.channels.insert(
            "SJI_1400".into(),
            ChannelStatus {
                frames: 3,
                ok: 2,
                failed: 1,
                ..Default::default()
            },
        );
        write_atomic(&path, &s).unwrap();
        s.frames = 4;
        write_atomic(&path, &s).unwrap();
        assert_eq!(read(&resolve_path(dir.path())).unwrap(), s);
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from(STATUS_FILE)]);
    }

    #[test]
    fn a_running_status_not_updated_for_long_is_shown_stale() {
        let s = Status {
            state: "running".into(),
            interval_s: 2.0,
            // 1396102178 s = 2014-03-29T14:09:38Z (`date -u -d @1396102178`).
            updated: "2014-03-29T14:09:38Z".into(),
            ..Default::default()
        };
        let t = 1_396_102_178_000_000_000i64;
        assert!(!render(&s, t + 5_000_000_000).contains("STALE"));
        assert!(render(&s, t + 7_000_000_000).contains("STALE"));
        assert_eq!(duration(90_061.0), "1d 01:01:01");
    }
}
