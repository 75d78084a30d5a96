//! One writer per output directory: a second `watch` or a `replay` on a `--out` a daemon holds
//! is refused (exit 2, naming the directory and the holder's pid) before it touches the log,
//! and the first daemon logs every frame once. A daemon killed with SIGKILL leaves its lock
//! file, which does not block a restart.

mod support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use sunjitter_core::error::ExitCode;
use sunjitter_runtime::fake::{split_cube, SplitFrame};
use support::{exit_status_within, logged, publish, WatchProcess, QUICK_DAEMON_CONFIG};

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";

struct Setup {
    _scratch: tempfile::TempDir,
    watched: PathBuf,
    out: PathBuf,
    config: PathBuf,
    frames: Vec<SplitFrame>,
    base: PathBuf,
}

fn setup(frames: usize) -> Setup {
    let scratch = tempfile::tempdir().unwrap();
    let base = scratch.path().to_path_buf();
    let mut all = split_cube(Path::new(SJI_1400), &base.join("split")).unwrap();
    all.truncate(frames);
    let (watched, out) = (base.join("in"), base.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = base.join("config.toml");
    std::fs::write(&config, QUICK_DAEMON_CONFIG).unwrap();
    Setup {
        _scratch: scratch,
        watched,
        out,
        config,
        frames: all,
        base,
    }
}

/// Bytes of every file in `out`, by name.
fn snapshot(out: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect()
}

fn assert_refused_naming(stderr: &str, out: &Path, pid: u32) {
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line: {stderr}");
    assert!(lines[0].contains(&out.display().to_string()), "{stderr}");
    assert!(lines[0].contains(&format!("pid {pid}")), "{stderr}");
}

/// A second `watch` of the same directory into the same log exits 2 naming `holder`.
fn second_daemon_is_refused(s: &Setup, holder: u32) {
    let mut second = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("watch")
        .arg(&s.watched)
        .arg("--out")
        .arg(&s.out)
        .arg("--config")
        .arg(&s.config)
        .env("SUNJITTER_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let status = exit_status_within(&mut second, 60).expect("the second daemon refuses to start");
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut second.stderr.take().unwrap(), &mut stderr).unwrap();
    assert_eq!(status.code(), Some(ExitCode::BadInput.code()), "{stderr}");
    assert_refused_naming(&stderr, &s.out, holder);
}

#[test]
fn a_second_daemon_on_one_out_is_refused_and_the_first_logs_every_frame_once() {
    let s = setup(10);
    let mut first = WatchProcess::spawn(&s.watched, &s.out, &s.config, &s.base.join("1.stderr"));
    first.wait_watching();

    // The same directory watched twice into the same log.
    second_daemon_is_refused(&s, first.pid());

    for f in &s.frames {
        publish(&s.watched, f);
    }
    let out = s.out.clone();
    first.wait_until("10 frames logged", |_| logged(&out).len() == 10);
    let status = first.terminate();
    assert!(status.success(), "clean stop: {status}");

    let counts = logged(&s.out);
    let root = s.watched.canonicalize().unwrap();
    for f in &s.frames {
        let key = root.join(&f.name).display().to_string();
        assert_eq!(counts.get(&key), Some(&1), "{key}: {counts:?}");
    }
    assert_eq!(counts.len(), 10, "{counts:?}");

    // On stderr, one line per frame: its channel, file name and logged status, with the shift.
    let stderr = std::fs::read_to_string(s.base.join("1.stderr")).unwrap();
    let frame_lines: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains(" SJI_1400 "))
        .collect();
    assert_eq!(frame_lines.len(), 10, "{stderr}");
    let logs = sunjitter_io::sink::read_logs(std::slice::from_ref(&s.out)).unwrap();
    for m in &logs.jitter {
        let a = &m.record.align;
        assert_eq!(m.record.channel, "SJI_1400");
        let name = Path::new(&a.frame).file_name().unwrap().to_str().unwrap();
        let status = serde_json::to_value(a.status).unwrap();
        let shown = format!(" SJI_1400 {name} {} ", status.as_str().unwrap());
        let lines: Vec<&&str> = frame_lines.iter().filter(|l| l.contains(&shown)).collect();
        assert_eq!(lines.len(), 1, "{shown}: {stderr}");
        if m.record.reference_kind == sunjitter_core::record::ReferenceKind::Itself {
            assert!(lines[0].contains(" starts a "), "{stderr}");
        } else if a.dx_px.is_some() {
            assert!(
                lines[0].contains(" dx ") && lines[0].contains(" px dy "),
                "{stderr}"
            );
        }
    }
}

#[test]
fn replay_into_a_held_out_is_refused_and_leaves_the_log_alone() {
    let s = setup(1);
    let mut daemon = WatchProcess::spawn(&s.watched, &s.out, &s.config, &s.base.join("d.stderr"));
    daemon.wait_watching();
    let archived = s.base.join("archive");
    std::fs::create_dir_all(&archived).unwrap();
    publish(&archived, &s.frames[0]);
    let before = snapshot(&s.out);

    let (code, _, stderr) = support::sunjitter(&[
        "replay".as_ref(),
        archived.as_os_str(),
        "--out".as_ref(),
        s.out.as_os_str(),
    ] as &[&std::ffi::OsStr]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert_refused_naming(&stderr, &s.out, daemon.pid());
    assert_eq!(snapshot(&s.out), before, "the log is untouched");
    assert!(daemon.terminate().success());
}

#[test]
fn a_lock_file_left_by_a_killed_daemon_does_not_block_a_restart() {
    let s = setup(1);
    let mut killed = WatchProcess::spawn(&s.watched, &s.out, &s.config, &s.base.join("k.stderr"));
    killed.wait_watching();
    killed.kill();
    assert!(
        s.out.join(sunjitter_io::outputs::LOCK_FILE).is_file(),
        "the lock file stays behind"
    );

    let mut restarted =
        WatchProcess::spawn(&s.watched, &s.out, &s.config, &s.base.join("r.stderr"));
    restarted.wait_watching();
    publish(&s.watched, &s.frames[0]);
    let out = s.out.clone();
    restarted.wait_until("the frame logged", |_| logged(&out).len() == 1);
    let status = restarted.terminate();
    assert!(status.success(), "clean stop: {status}");
    assert_eq!(logged(&s.out).values().sum::<usize>(), 1);
}

#[test]
fn removing_the_lock_file_lets_no_second_writer_in() {
    let s = setup(6);
    let mut first = WatchProcess::spawn(&s.watched, &s.out, &s.config, &s.base.join("1.stderr"));
    first.wait_watching();
    // The pid file is only a name for the message: the lock is on the directory itself.
    std::fs::remove_file(s.out.join(sunjitter_io::outputs::LOCK_FILE)).unwrap();
    let before = snapshot(&s.out);

    // Linux names the holder from the kernel's list of locks.
    second_daemon_is_refused(&s, first.pid());
    let (code, _, stderr) = support::sunjitter(&[
        "replay".as_ref(),
        s.watched.as_os_str(),
        "--out".as_ref(),
        s.out.as_os_str(),
    ] as &[&std::ffi::OsStr]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert_eq!(snapshot(&s.out), before, "the refused runs touched nothing");

    for f in &s.frames {
        publish(&s.watched, f);
    }
    let out = s.out.clone();
    first.wait_until("6 frames logged", |_| logged(&out).len() == 6);
    assert!(first.terminate().success());
    let counts = logged(&s.out);
    assert_eq!(counts.len(), 6, "{counts:?}");
    assert!(counts.values().all(|&n| n == 1), "{counts:?}");
}
