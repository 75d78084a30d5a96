//! Crash and restart: the real `sunjitter watch` binary, fed real IRIS
//! frames (two channels, real engine, real MCAP sink), is killed with SIGKILL at 50
//! seeded-random points while it works, and restarted each time; frames keep arriving
//! meanwhile. Then one last run finishes the backlog and stops on SIGTERM. Across all segments
//! every frame must be logged exactly once, and every segment must be a finished MCAP file
//! (the daemon recovers the unfinished ones it finds at start).
//!
//! The log is left in `$CARGO_TARGET_TMPDIR/crash_restart/out` for the official Python reader
//! (`.ci/run` runs `tools/check_mcap.py` on it).

mod support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use sunjitter_runtime::fake::split_cube;
use support::faults::Lcg;
use support::{logged, publish};

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2796: &str =
    "data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";
const KILLS: usize = 50;
const SEED: u64 = 7;

const CONFIG: &str = r#"
[daemon]
settle_s = 0.1
reorder_window_s = 0.2
retry_initial_s = 0.05
retry_max_s = 0.2
retry_attempts = 3
flush_interval_s = 0.1
[sink]
# Small segments and frequent flushes: kills land in rotations and flushes too.
segment_frames = 15
flush_every_frames = 4
[reference]
keyframe_every_frames = 10
"#;

fn spawn(watched: &Path, out: &Path, config: &Path, log: &Path, level: &str) -> Child {
    let stderr = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)
        .unwrap();
    Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("watch")
        .arg(watched)
        .arg("--out")
        .arg(out)
        .arg("--config")
        .arg(config)
        .env("RUST_LOG", level)
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap()
}

#[test]
fn sigkill_at_50_random_points_loses_and_doubles_nothing() {
    let started = Instant::now();
    let scratch = tempfile::tempdir().unwrap();
    let mut frames = split_cube(Path::new(SJI_1400), &scratch.path().join("a")).unwrap();
    frames.extend(split_cube(Path::new(SJI_2796), &scratch.path().join("b")).unwrap());
    frames.sort_by_key(|f| f.obs_time_ns);
    let total = frames.len();
    assert_eq!(total, 54 + 72);

    let base = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("crash_restart");
    let _ = std::fs::remove_dir_all(&base);
    let (watched, out) = (base.join("in"), base.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = base.join("config.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let log = base.join("daemon.stderr");

    // Frames arrive over the first 42 runs: one before each start, two while it runs.
    let mut rng = Lcg(SEED);
    let mut next = 0;
    let mut kill_points_ms = Vec::new();
    let (mut killed_with_backlog, mut killed_mid_segment) = (0, 0);
    for _ in 0..KILLS {
        if next < total {
            publish(&watched, &frames[next]);
            next += 1;
        }
        let mut child = spawn(&watched, &out, &config, &log, "warn");
        for _ in 0..2 {
            if next < total {
                publish(&watched, &frames[next]);
                next += 1;
            }
        }
        // The fault: SIGKILL at a seeded-random moment of the run (startup, recovery, scan,
        // alignment, flush or rotation, whatever it is doing then).
        let at = rng.below(700);
        kill_points_ms.push(at);
        std::thread::sleep(Duration::from_millis(at));
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        // What the kill interrupted: frames still to do, a segment left unfinished.
        if let Ok(logs) = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)) {
            let done: std::collections::BTreeSet<&str> = logs
                .jitter
                .iter()
                .map(|m| m.record.align.frame.as_str())
                .collect();
            if done.len() < next {
                killed_with_backlog += 1;
            }
            if logs.segments.iter().any(|s| !s.complete) {
                killed_mid_segment += 1;
            }
        }
    }
    assert_eq!(next, total, "every frame was published");
    let before_final = logged(&out);

    // The last run takes the backlog and stops cleanly on SIGTERM.
    let final_log = base.join("final.stderr");
    let mut child = spawn(&watched, &out, &config, &final_log, "info");
    let deadline = Instant::now() + Duration::from_secs(120);
    let watching =
        || std::fs::read_to_string(&final_log).is_ok_and(|text| text.contains("watching"));
    while logged(&out).len() < total || !watching() {
        assert!(
            Instant::now() < deadline,
            "final run stalled at {} of {total} frames",
            logged(&out).len()
        );
        assert!(child.try_wait().unwrap().is_none(), "the daemon died");
        std::thread::sleep(Duration::from_millis(100));
    }
    let term = Command::new("kill")
        .arg("-TERM")
        .arg(child.id().to_string())
        .status()
        .unwrap();
    assert!(term.success());
    let status = child.wait().unwrap();
    assert!(status.success(), "clean stop: {status}");

    // Every segment is a finished MCAP file, read with the `mcap` crate.
    let mut segments: Vec<PathBuf> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    segments.sort();
    let mut counts: BTreeMap<String, usize> = BTreeMap::new();
    let mut log_errors = Vec::new();
    for path in &segments {
        let bytes = std::fs::read(path).unwrap();
        let summary = mcap::read::Summary::read(&bytes)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
            .unwrap_or_else(|| panic!("{} is not finished", path.display()));
        // No empty leftovers (a segment killed before its first flush is removed at recovery).
        assert!(
            summary.stats.is_some_and(|s| s.message_count > 0),
            "{} holds no message",
            path.display()
        );
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            let json: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
            if m.channel.topic.starts_with("/jitter/") {
                *counts
                    .entry(json["frame"].as_str().unwrap().to_string())
                    .or_insert(0) += 1;
            } else if m.channel.topic == "/log" && json["level"].as_u64() >= Some(4) {
                log_errors.push(json.to_string());
            }
        }
    }
    let root = watched.canonicalize().unwrap();
    for f in &frames {
        let key = root.join(&f.name).display().to_string();
        assert_eq!(counts.get(&key), Some(&1), "{key}");
    }
    assert_eq!(counts.len(), total, "no message for anything else");
    assert!(log_errors.is_empty(), "{log_errors:?}");
    eprintln!(
        "crash test: {KILLS} SIGKILLs (seed {SEED}, at {kill_points_ms:?} ms after start); \
         {killed_with_backlog} left frames to do, {killed_mid_segment} left an unfinished segment; \
         {} of {total} frames logged before the last run, {} segments, {:.1} s",
        before_final.len(),
        segments.len(),
        started.elapsed().as_secs_f64()
    );
}
