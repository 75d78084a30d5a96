//! `sunjitter status` on a daemon that is alive but cannot write its output: it says so,
//! naming the directory, instead of calling the status stale.

mod support;

use std::process::Command;
use sunjitter_core::error::ExitCode;
use support::monitor::*;

const CONFIG: &str = r#"
[health]
interval_s = 0.05
"#;

#[test]
fn status_of_a_live_daemon_with_an_unwritable_output_names_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().canonicalize().unwrap();
    let (watched, out, moved) = (root.join("in"), root.join("out"), root.join("moved"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = root.join("sunjitter.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let mut daemon = Daemon::start(&watched, &out, &config, &[]);
    daemon.expect_stderr(&["watching"]);
    wait_for("the status file", || read_status(&out));

    // The output directory goes away and a plain file takes its name: from now on the daemon
    // can write nothing there. Its last status, moved along, says it was running long ago.
    std::fs::rename(&out, &moved).unwrap();
    std::fs::write(&out, b"in the way").unwrap();
    let mut last = read_status(&moved).unwrap();
    assert_eq!(last["pid"], daemon.child.id());
    last["updated"] = "2014-03-29T14:09:38Z".into();
    std::fs::write(moved.join("status.json"), last.to_string()).unwrap();

    let shown = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("status")
        .arg(&moved)
        .output()
        .unwrap();
    assert_eq!(shown.status.code(), Some(ExitCode::Ok.code()));
    let text = String::from_utf8(shown.stdout).unwrap();
    let first = text.lines().next().unwrap();
    assert!(!first.contains("STALE"), "{text}");
    assert!(
        first.contains("OUTPUT UNWRITABLE")
            && first.contains(&format!("{}: cannot write here: ", out.display())),
        "{text}"
    );
    drop(daemon);
}

/// A `running` status whose process is gone (no process can have pid 2³² − 1): `status`
/// says it is not running rather than only stale.
#[test]
fn status_of_a_daemon_that_is_gone_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("status.json");
    let doc = serde_json::json!({
        "program": "sunjitter", "version": "0", "pid": u32::MAX, "state": "running",
        "started": "2014-03-29T14:09:38Z", "updated": "2014-03-29T14:09:38Z",
        "uptime_s": 1.0, "interval_s": 2.0, "watching": "/in", "out": "/out",
        "live": null, "frames": 0, "ok": 0, "degraded": 0, "failed": 0, "skipped": 0,
        "queue_depth": 0, "write_errors": 0, "last_error": null,
        "live_dropped": 0, "alerts_raised": 0, "alert_command_failures": 0,
        "active_alerts": [], "channels": {}
    });
    std::fs::write(&path, doc.to_string()).unwrap();
    let shown = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("status")
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(shown.status.code(), Some(ExitCode::Ok.code()));
    let text = String::from_utf8(shown.stdout).unwrap();
    assert!(
        text.lines()
            .next()
            .unwrap()
            .contains("NOT RUNNING: pid 4294967295 is gone without a clean stop"),
        "{text}"
    );
}
