//! Alerts end to end: `sunjitter watch` fed real IRIS frames with injected faults — one frame
//! displaced by a known 3 px, two blanked frames (valid FITS, nothing to align), and a pause
//! in the feed — must raise each configured alert once and resolve it once, on `/alert` in
//! the MCAP log, in the live view (the independent `@foxglove/ws-protocol` client) and through
//! the alert command (a shell command appending its stdin to a file).

mod support;

use std::collections::BTreeMap;
use std::path::Path;
use sunjitter_io::sink::Alert;
use support::monitor::*;

/// Frame indices of the IRIS cube fed in phase 1, with their alteration.
const PHASE_1: [(usize, Alter); 13] = [
    (7, Alter::None),
    (8, Alter::None),
    (9, Alter::None),
    (10, Alter::None),
    (11, Alter::Shift(3, 0)),
    (12, Alter::None),
    (13, Alter::None),
    (14, Alter::Blank),
    (15, Alter::Blank),
    (16, Alter::None),
    (17, Alter::None),
    (18, Alter::None),
    (19, Alter::None),
];
/// Fed after the silence alert was raised.
const PHASE_2: (usize, Alter) = (23, Alter::None);

fn config(reference: &Path, hook_file: &Path) -> String {
    format!(
        r#"
[daemon]
settle_s = 0.1
# All frames of a phase arrive at once; hold them long enough to be sorted by time.
reorder_window_s = 1.0
reorder_window_frames = 64
flush_interval_s = 0.1

[health]
interval_s = 0.1

# A fixed reference (frame 7, kept outside the watched directory): the offsets are absolute.
[reference]
policy = "fixed:{reference}"

[alerts]
command = ["sh", "-c", "cat >> '{hook}'"]
command_timeout_s = 10

[alerts.channels.SJI_1400]
amplitude_px = 1.5
jump_px = 1.5
rms_px = 1.0
rms_window_frames = 4
consecutive_failed = 2
silence_s = 2.0
"#,
        reference = reference.display(),
        hook = hook_file.display()
    )
}

fn hook_alerts(path: &Path) -> Vec<Alert> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: {l}")))
        .collect()
}

/// The frame index in a frame key `…/sji1400_fNNNN.fits`.
fn index_of(frame: &str) -> usize {
    let name = frame.rsplit('/').next().unwrap();
    name["sji1400_f".len().."sji1400_f".len() + 4]
        .parse()
        .unwrap()
}

#[test]
fn injected_faults_raise_each_alert_once_and_resolve_it_once() {
    let tmp = tempfile::tempdir().unwrap();
    let (watched, out) = (tmp.path().join("in"), tmp.path().join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let reference = tmp.path().join("reference_f0007.fits");
    write_frame(7, Alter::None, &reference);
    let hook_file = tmp.path().join("alerts.jsonl");
    let config_path = tmp.path().join("sunjitter.toml");
    std::fs::write(&config_path, config(&reference, &hook_file)).unwrap();
    let phase_1 = stage_frames(&tmp.path().join("stage1"), &PHASE_1);
    let phase_2 = stage_frames(&tmp.path().join("stage2"), &[PHASE_2]);

    NodeClient::require_installed();
    let mut daemon = Daemon::start(&watched, &out, &config_path, &["--live", "127.0.0.1:0"]);
    let url = live_url(&daemon.expect_stderr(&["live view", "ws://"]));
    daemon.expect_stderr(&["watching"]);
    let client = NodeClient::start(&url, &["read", "/alert"]);
    daemon.expect_stderr(&["live: subscribed", "/alert"]);
    move_in(&phase_1, &watched);
    wait_for("phase 1 logged", || {
        (status_frames(&out) == PHASE_1.len() as u64).then_some(())
    });
    // The feed pauses: no frame for longer than silence_s.
    wait_for("the silence alert", || {
        hook_alerts(&hook_file)
            .iter()
            .any(|a| a.kind == "silence_s")
            .then_some(())
    });
    move_in(&phase_2, &watched);
    wait_for("phase 2 logged and the silence resolved", || {
        let resolved = hook_alerts(&hook_file)
            .iter()
            .any(|a| a.kind == "silence_s" && a.state == "resolved");
        (status_frames(&out) == PHASE_1.len() as u64 + 1 && resolved).then_some(())
    });
    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));

    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(contents.jitter.len(), PHASE_1.len() + 1);
    let logged: Vec<Alert> = contents.alerts.iter().map(|m| m.alert.clone()).collect();
    // The command got every alert, in the same order, with the same content.
    assert_eq!(hook_alerts(&hook_file), logged);
    // So did the live view, at the same log times (the client ends when the server closes).
    let mut lines = Vec::new();
    loop {
        match client.lines.recv_timeout(PATIENCE) {
            Ok(line) => lines.push(line),
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
            Err(e) => panic!("the live client did not end with the server: {e}"),
        }
    }
    let live: Vec<(Alert, String)> = lines
        .iter()
        .filter(|l| l["event"] == "message")
        .map(|l| {
            assert_eq!(l["topic"], "/alert");
            let alert = serde_json::from_value(l["payload"].clone()).unwrap();
            (alert, l["logTime"].as_str().unwrap().to_string())
        })
        .collect();
    let logged_times: Vec<(Alert, String)> = contents
        .alerts
        .iter()
        .map(|m| (m.alert.clone(), m.log_time_ns.to_string()))
        .collect();
    assert_eq!(live, logged_times);

    // Per kind: exactly one raised then one resolved, at the frames the injected faults imply.
    let mut by_kind: BTreeMap<String, Vec<&Alert>> = BTreeMap::new();
    for a in &logged {
        by_kind.entry(a.kind.clone()).or_default().push(a);
    }
    let at = |a: &Alert| a.frame.as_deref().map(index_of);
    let expect = |kind: &str, raised: Option<usize>, resolved: Option<usize>| {
        let list = by_kind
            .get(kind)
            .unwrap_or_else(|| panic!("no {kind} alert in {logged:#?}"));
        let states: Vec<&str> = list.iter().map(|a| a.state.as_str()).collect();
        assert_eq!(states, ["raised", "resolved"], "{kind}: {list:#?}");
        assert_eq!((at(list[0]), at(list[1])), (raised, resolved), "{kind}");
        for a in list {
            assert_eq!(a.channel, "SJI_1400");
            assert!(!a.time.is_empty() && !a.message.is_empty());
        }
        (list[0], list[1])
    };
    // Frame 11 is displaced by 3 px: amplitude above 1.5 px until frame 12 …
    let (amplitude, _) = expect("amplitude_px", Some(11), Some(12));
    // … true offset 3 px plus the real pointing change since frame 7 (well under 0.6 px).
    assert!((amplitude.value - 3.0).abs() < 0.6, "{amplitude:?}");
    assert_eq!((amplitude.threshold, amplitude.unit.as_str()), (1.5, "px"));
    assert_eq!(amplitude.severity, "warning");
    // A jump of 3 px into frame 11 and back out of it (frame 12); frame 13 is calm again.
    expect("jump_px", Some(11), Some(13));
    // RMS over 4 usable frames: frame 11 is in the window until frame 17 pushes it out
    // (the blanked 14, 15 have no numbers).
    expect("rms_px", Some(11), Some(17));
    // Two blanked frames in a row (14, 15), then one with a result. (These IRIS 1400 Å
    // frames are often `degraded` for weak structure, so `consecutive_bad` is not used here.)
    let (bad, _) = expect("consecutive_failed", Some(15), Some(16));
    assert_eq!(
        (bad.value, bad.unit.as_str(), bad.severity.as_str()),
        (2.0, "frames", "error")
    );
    // The pause: raised by the clock (no frame), resolved by the next frame.
    let (silence, _) = expect("silence_s", None, Some(PHASE_2.0));
    assert!(silence.value > 2.0 && silence.unit == "s", "{silence:?}");
    assert_eq!(by_kind.len(), 5, "no other alert: {logged:#?}");

    // The blanked frames are logged as failed measurements, not lost.
    for m in &contents.jitter {
        let i = index_of(&m.record.align.frame);
        let failed = m.record.align.status == sunjitter_core::record::Status::Failed;
        assert_eq!(
            failed,
            i == 14 || i == 15,
            "frame {i}: {:?}",
            m.record.align.status
        );
    }
    // The log says so too (tracing warnings).
    assert!(log
        .iter()
        .any(|l| l.contains("ALERT") && l.contains("jump")));
    let status = read_status(&out).unwrap();
    assert_eq!(status["alerts_raised"], 5);
    assert_eq!(status["active_alerts"], serde_json::json!([]));
    assert_eq!(status["alert_command_failures"], 0);

    // Kept for CI's independent reader (tools/check_mcap.py, the official Python `mcap`).
    let fixture = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("alerts_fixture");
    let _ = std::fs::remove_dir_all(&fixture);
    std::fs::create_dir_all(&fixture).unwrap();
    for segment in &contents.segments {
        std::fs::copy(
            &segment.path,
            fixture.join(segment.path.file_name().unwrap()),
        )
        .unwrap();
    }
}

/// A daemon whose alert command is `sh -c SCRIPT` (killed after `timeout_s`), raising
/// consecutive_failed on the first failed frame; fed a good frame and a blank one, it runs the
/// command once. `observe` runs once the failure is counted; returns the daemon's `/log`
/// entries from the command, after it stopped.
fn run_alert_command_once(
    script: &str,
    timeout_s: f64,
    observe: impl FnOnce(),
) -> Vec<sunjitter_io::sink::LogMessage> {
    let tmp = tempfile::tempdir().unwrap();
    let (watched, out) = (tmp.path().join("in"), tmp.path().join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config_path = tmp.path().join("sunjitter.toml");
    let command = serde_json::to_string(&["sh", "-c", script]).unwrap();
    std::fs::write(
        &config_path,
        format!(
            r#"
[daemon]
settle_s = 0.1
reorder_window_s = 0.3
reorder_window_frames = 64
flush_interval_s = 0.1
[health]
interval_s = 0.1
[alerts]
command = {command}
command_timeout_s = {timeout_s}
[alerts.channels.SJI_1400]
consecutive_failed = 1
"#
        ),
    )
    .unwrap();
    let staged = stage_frames(
        &tmp.path().join("stage"),
        &[(7, Alter::None), (8, Alter::Blank)],
    );
    let mut daemon = Daemon::start(&watched, &out, &config_path, &[]);
    daemon.expect_stderr(&["watching"]);
    move_in(&staged, &watched);
    wait_for("the command failure in the status", || {
        let s = read_status(&out)?;
        (s["frames"] == 2 && s["alert_command_failures"] == 1).then_some(())
    });
    observe();
    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "{}", log.join("\n"));
    let contents = sunjitter_io::sink::read_logs(&[out]).unwrap();
    assert_eq!(contents.alerts.len(), 1);
    contents
        .logs
        .into_iter()
        .filter(|m| m.entry.file == "alerts.command")
        .collect()
}

#[test]
fn a_failing_alert_command_is_reported_on_the_log() {
    let failures = run_alert_command_once("cat > /dev/null; exit 7", 10.0, || {});
    assert_eq!(failures.len(), 1, "{failures:?}");
    assert!(
        failures[0].entry.message.contains("exit status: 7"),
        "{:?}",
        failures[0].entry
    );
    assert_eq!(
        failures[0].entry.level,
        sunjitter_io::sink::LogLevel::Warning
    );
}

#[test]
fn an_alert_command_over_its_time_limit_is_killed_with_its_children() {
    let tmp = tempfile::tempdir().unwrap();
    let pids = tmp.path().join("children.pids");
    // Two background children, their pids noted, then the script waits for them.
    let script = format!(
        "cat > /dev/null; sleep 1000 & echo $! >> '{p}'; sleep 1000 & echo $! >> '{p}'; wait",
        p = pids.display()
    );
    let failures = run_alert_command_once(&script, 2.0, || {
        // The overrun has been reported on /log.
        let children = Reap(
            std::fs::read_to_string(&pids)
                .unwrap()
                .lines()
                .map(|l| l.parse().unwrap())
                .collect(),
        );
        assert_eq!(
            children.0.len(),
            2,
            "both children started within the limit"
        );
        // SIGKILL takes effect asynchronously; the bound only guards against a hang.
        wait_for("the command's children to end", || {
            children
                .0
                .iter()
                .all(|pid| !process_running(*pid))
                .then_some(())
        });
    });
    assert_eq!(failures.len(), 1, "{failures:?}");
    assert!(
        failures[0]
            .entry
            .message
            .contains("killed after the 2 s time limit"),
        "{:?}",
        failures[0].entry
    );
}

/// Kills the listed processes when dropped, so a failed test leaves none behind.
struct Reap(Vec<u32>);

impl Drop for Reap {
    fn drop(&mut self) {
        for pid in &self.0 {
            if process_running(*pid) {
                let _ = std::process::Command::new("kill")
                    .args(["-KILL", &pid.to_string()])
                    .status();
            }
        }
    }
}
