//! File names the file system allows but text does not: bytes that are not UTF-8, newlines,
//! escape sequences. Every such input is measured (or named on `/log`), two names never merge
//! into one frame, and nothing printed to a terminal or a log carries a control character.
//!
//! Truth: the exact set of files put in, and their names spelled with the escapes by hand
//! (`\xff` for the byte 0xFF, `\n` for a newline, `\x1b` for ESC).

mod support;

use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::Path;
use std::process::Command;
use sunjitter_core::error::ExitCode;
use support::monitor::*;

const AIA: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/data/real/aia_171_20110215T000000_128.fits"
);

/// A name from raw bytes.
fn raw(bytes: &[u8]) -> &OsStr {
    OsStr::from_bytes(bytes)
}

fn sunjitter(args: &[&OsStr]) -> (i32, Vec<u8>, Vec<u8>) {
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(args)
        .env("SUNJITTER_LOG", "info")
        .env("NO_COLOR", "1")
        .output()
        .expect("runs");
    (out.status.code().unwrap_or(-1), out.stdout, out.stderr)
}

/// The terminal must see text only: no C0 control other than the line ends, no DEL, no C1.
fn assert_printable(what: &str, bytes: &[u8]) {
    let text = String::from_utf8(bytes.to_vec())
        .unwrap_or_else(|_| panic!("{what} is not UTF-8: {bytes:?}"));
    let bad: Vec<char> = text
        .chars()
        .filter(|c| *c != '\n' && c.is_control())
        .collect();
    assert!(
        bad.is_empty(),
        "{what} holds control characters {bad:?}:\n{text}"
    );
}

/// `/jitter` frames (each `frame` as logged) and `/log` entries (level, file, message).
fn logged(out: &Path) -> (Vec<String>, Vec<(u8, String, String)>) {
    let files = sunjitter_runtime::inspect::log_files(&[out.to_path_buf()]).unwrap();
    let contents = sunjitter_io::sink::read_logs(&files).unwrap();
    let frames = contents
        .jitter
        .iter()
        .map(|m| m.record.align.frame.clone())
        .collect();
    let logs = contents
        .logs
        .iter()
        .map(|m| {
            (
                m.entry.level as u8,
                m.entry.file.clone(),
                m.entry.message.clone(),
            )
        })
        .collect();
    (frames, logs)
}

fn sorted(mut v: Vec<String>) -> Vec<String> {
    v.sort();
    v
}

/// `replay` of a directory whose names are not all UTF-8, two of them alike once made lossy
/// (`b\xfed` and `b\xffd` both read `b�d`): every file is measured once, under its own name.
#[test]
fn replay_measures_names_that_are_not_utf8_each_under_its_own_name() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().canonicalize().unwrap().join("in");
    std::fs::create_dir(&dir).unwrap();
    for name in [&b"aia.fits"[..], b"b\xfed.fits", b"b\xffd.fits"] {
        std::fs::copy(AIA, dir.join(raw(name))).unwrap();
    }
    let out = tmp.path().join("out");
    let (code, _, stderr) = sunjitter(&[
        raw(b"replay"),
        dir.as_os_str(),
        raw(b"--out"),
        out.as_os_str(),
    ]);
    assert_eq!(
        code,
        ExitCode::Ok.code(),
        "{}",
        String::from_utf8_lossy(&stderr)
    );
    let (frames, logs) = logged(&out);
    let d = dir.display();
    assert_eq!(
        sorted(frames),
        vec![
            format!("{d}/aia.fits"),
            format!(r"{d}/b\xfed.fits"),
            format!(r"{d}/b\xffd.fits"),
        ]
    );
    assert!(
        logs.iter().all(|(level, ..)| *level < 4),
        "no input finished with an error: {logs:?}"
    );
}

/// `info` of a name that is not UTF-8 reads the file and names it with the byte escaped.
#[test]
fn info_reads_a_name_that_is_not_utf8_and_names_it_escaped() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join(raw(b"caf\xe9.fits"));
    std::fs::copy(AIA, &path).unwrap();
    let (code, stdout, stderr) = sunjitter(&[raw(b"info"), raw(b"--json"), path.as_os_str()]);
    assert_eq!(
        code,
        ExitCode::Ok.code(),
        "{}",
        String::from_utf8_lossy(&stderr)
    );
    let doc: serde_json::Value = serde_json::from_slice(&stdout).unwrap();
    assert_eq!(
        doc[0]["file"],
        format!(r"{}/caf\xe9.fits", tmp.path().display())
    );
    assert_eq!(doc[0]["width"], 128);
}

/// A status file naming files with newlines and escape sequences (as a daemon writes it, or
/// one written by an older version): `status` prints each on its one line, escaped.
#[test]
fn status_prints_control_characters_in_names_escaped() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("status.json");
    let evil = "/in/evil\u{1b}]0;owned\u{7}\nsunjitter: all good\u{9b}2J.fits";
    let doc = serde_json::json!({
        "program": "sunjitter", "version": "0", "pid": 1, "state": "stopped",
        "started": "2014-03-29T14:09:38Z", "updated": "2014-03-29T14:09:38Z",
        "uptime_s": 1.0, "interval_s": 2.0, "watching": "/in\u{1b}[2J", "out": "/out",
        "live": null, "frames": 1, "ok": 0, "degraded": 0, "failed": 1, "skipped": 1,
        "queue_depth": 0, "write_errors": 0,
        "last_error": format!("{evil}: not a FITS file"),
        "live_dropped": 0, "alerts_raised": 0, "alert_command_failures": 0,
        "active_alerts": [],
        "channels": {"SJI\n1400": {"frames": 1, "ok": 0, "degraded": 0, "failed": 1,
            "last_frame": evil, "last_obs_time": null, "last_logged": null, "lag_s": null,
            "queued": 0, "last_error": format!("{evil}: failed")}}
    });
    std::fs::write(&path, doc.to_string()).unwrap();
    let (code, stdout, stderr) = sunjitter(&[raw(b"status"), path.as_os_str()]);
    assert_eq!(
        code,
        ExitCode::Ok.code(),
        "{}",
        String::from_utf8_lossy(&stderr)
    );
    assert_printable("status output", &stdout);
    let text = String::from_utf8(stdout).unwrap();
    let shown = r"/in/evil\x1b]0;owned\x07\nsunjitter: all good\u{9b}2J.fits";
    assert!(
        text.contains(&format!("last error: {shown}: not a FITS file")),
        "{text}"
    );
    assert!(text.contains(r"watching /in\x1b[2J"), "{text}");
    assert!(text.contains(r"SJI\n1400"), "{text}");
    assert!(
        !text.lines().any(|l| l.starts_with("sunjitter: all good")),
        "a forged line: {text}"
    );
}

const CONFIG: &str = r#"
[daemon]
settle_s = 0.1
retry_initial_s = 0.05
retry_max_s = 0.1
retry_attempts = 2
reorder_window_s = 0.3
flush_interval_s = 0.1

[health]
interval_s = 0.05
"#;

/// The daemon takes files named with bytes that are not UTF-8 and with a newline, measures
/// each, and names the unreadable one (newline and escape sequence in its name) on `/log`, in
/// its own log lines and in `status`, escaped: no forged log line, no raw escape sequence.
#[test]
fn watch_measures_hostile_names_and_prints_them_escaped() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().canonicalize().unwrap();
    let (watched, out) = (root.join("in"), root.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = root.join("sunjitter.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let staged = stage_frames(
        &root.join("stage"),
        &[(0, Alter::None), (1, Alter::None), (2, Alter::None)],
    );
    let names: [&[u8]; 3] = [b"plain.fits", b"b\xffd.fits", b"two\nlines.fits"];
    let shown = ["plain.fits", r"b\xffd.fits", r"two\nlines.fits"];
    let forged = b"evil\x1b[31m\nERROR sunjitter: forged.fits";
    let forged_shown = r"evil\x1b[31m\nERROR sunjitter: forged.fits";
    std::fs::write(root.join("stage/junk"), b"this is not FITS").unwrap();

    let mut daemon = Daemon::start(&watched, &out, &config, &[]);
    daemon.expect_stderr(&["watching"]);
    for (file, name) in staged.iter().zip(names) {
        std::fs::rename(file, watched.join(raw(name))).unwrap();
    }
    std::fs::rename(root.join("stage/junk"), watched.join(raw(forged))).unwrap();
    wait_for("3 frames and 1 skipped file in the status", || {
        let s = read_status(&out)?;
        (s["frames"] == 3 && s["skipped"] == 1).then_some(())
    });

    let (code, stdout, _) = sunjitter(&[raw(b"status"), out.as_os_str()]);
    assert_eq!(code, ExitCode::Ok.code());
    assert_printable("status output", &stdout);
    let w = watched.display();
    let text = String::from_utf8(stdout).unwrap();
    assert!(text.contains(&format!("{w}/{forged_shown}: ")), "{text}");

    let (status, stderr) = daemon.terminate();
    assert!(status.success(), "{stderr:?}");
    for line in &stderr {
        assert_printable("a daemon log line", line.as_bytes());
        assert!(!line.starts_with("ERROR sunjitter"), "forged: {stderr:#?}");
    }
    assert!(
        stderr
            .iter()
            .any(|l| l.contains(&format!("{w}/{forged_shown}"))),
        "the unreadable file is named in the daemon's log: {stderr:#?}"
    );
    for name in shown {
        let frame_lines = stderr
            .iter()
            .filter(|l| l.contains(&format!(" {name} ")) && l.contains(" SJI_1400 "))
            .count();
        assert_eq!(frame_lines, 1, "one line for {name}: {stderr:#?}");
    }

    let (frames, logs) = logged(&out);
    let expected: Vec<String> = shown.iter().map(|n| format!("{w}/{n}")).collect();
    assert_eq!(sorted(frames), sorted(expected));
    let errors: Vec<&(u8, String, String)> = logs.iter().filter(|(l, ..)| *l >= 4).collect();
    assert_eq!(errors.len(), 1, "{logs:?}");
    assert_eq!(errors[0].1, format!("{w}/{forged_shown}"));
}
