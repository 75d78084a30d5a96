//! Values and inputs that once crashed or hung a run are refused before any work: exit code 2
//! and one line naming the key, flag or file and the problem (the contract), never a panic,
//! a hang or an allocation without bound; and SIGTERM stops a daemon whatever state it is in.
//!
//! Truths: the contract's exit codes and one-line messages, the documented ranges, the FITS
//! standard (a `BSCALE` must be a number; a latitude lies within ±90°), RFC 6455.

mod support;

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use sunjitter_core::error::ExitCode;
use support::{exit_status_within, logged, publish, sunjitter, WatchProcess};

const AIA: &str = "data/real/aia_171_20110215T000000_128.fits";
const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2832: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits";

fn real(p: &str) -> PathBuf {
    support::repo_file(p)
}

fn os(parts: &[&dyn AsRef<OsStr>]) -> Vec<std::ffi::OsString> {
    parts.iter().map(|p| p.as_ref().to_os_string()).collect()
}

/// Exit 2, no panic, one line on stderr containing every one of `needles`.
fn assert_one_line(run: &(i32, String, String), needles: &[&str]) {
    let (code, _, stderr) = run;
    assert_eq!(*code, 2, "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(stderr.trim_end().lines().count(), 1, "one line: {stderr}");
    for n in needles {
        assert!(stderr.contains(n), "{n:?} not in: {stderr}");
    }
}

/// Run `cmd` to its end (bounded: a hang fails the test), with stderr.
fn run_within(mut cmd: Command, secs: u64) -> (i32, String, String) {
    let mut child = cmd
        .env("SUNJITTER_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut err = String::new();
    let mut pipe = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        std::io::Read::read_to_string(&mut pipe, &mut err).unwrap();
        err
    });
    let status = exit_status_within(&mut child, secs).expect("it ended (no hang)");
    (
        status.code().unwrap_or(-1),
        String::new(),
        reader.join().unwrap(),
    )
}

fn binary(args: &[std::ffi::OsString]) -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sunjitter"));
    cmd.args(args);
    cmd
}

// ---------------------------------------------------------------------------------------------
// Ranges

#[test]
fn a_shard_count_past_the_limit_is_refused_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    for spec in ["0/4294967296", "0/18446744073709551615", "0/100001"] {
        let run = sunjitter(&os(&[
            &"replay",
            &real(AIA),
            &"--out",
            &out,
            &"--shard",
            &spec,
        ]));
        assert_eq!(run.0, ExitCode::BadInput.code(), "{}", run.2);
        assert!(!run.2.contains("panicked"), "{}", run.2);
        assert!(run.2.contains("N must be at most 100000"), "{}", run.2);
        assert!(!out.exists());
    }
}

#[test]
fn engine_and_sink_values_out_of_range_are_refused_before_any_work() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("c.toml");
    let out = tmp.path().join("out");
    for (text, key) in [
        ("[engine]\nsample = 100000\n", "engine.sample = 100000"),
        (
            "[engine]\nrefine_smoothing_px = 1e308\n",
            "engine.refine_smoothing_px",
        ),
        (
            "[engine]\nmin_correlation = nan\n",
            "engine.min_correlation",
        ),
        ("[engine]\nconvergence_px = 0\n", "engine.convergence_px"),
        (
            "[engine]\nransac_threshold_px = -1\n",
            "engine.ransac_threshold_px",
        ),
        (
            "[sink]\nchunk_size = 18446744073709551615\n",
            "sink.chunk_size",
        ),
        ("[daemon]\nsettle_s = 1e300\n", "daemon.settle_s"),
        ("[health]\ninterval_s = 1e300\n", "health.interval_s"),
    ] {
        std::fs::write(&config, text).unwrap();
        let run = sunjitter(&os(&[
            &"replay",
            &real(AIA),
            &"--out",
            &out,
            &"--config",
            &config,
        ]));
        assert_one_line(&run, &[key, "out of range"]);
        assert!(!out.exists(), "nothing was made: {text}");
        // align reads the same [engine], through the same check.
        let run = sunjitter(&os(&[
            &"align",
            &real(AIA),
            &real(AIA),
            &"--config",
            &config,
        ]));
        assert_one_line(&run, &[key]);
    }
}

#[test]
fn synthetic_jitter_and_cadence_beyond_any_frame_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("synth");
    for (args, needle) in [
        (vec!["--jitter", "sine:1e30:10"], "--jitter sine:1e30:10"),
        (vec!["--jitter", "step:1e30:0"], "--jitter step:1e30:0"),
        (vec!["--jitter", "walk:1e30"], "--jitter walk:1e30"),
        (vec!["--cadence", "4e9"], "--cadence"),
        (vec!["--frames", "200", "--cadence", "3e7"], "100 years"),
    ] {
        let mut all = os(&[&"synth", &"--out", &out, &"--size", &"64"]);
        all.extend(args.iter().map(std::ffi::OsString::from));
        let run = sunjitter(&all);
        assert_one_line(&run, &[needle]);
        assert!(!out.join("truth.csv").exists(), "{args:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// File descriptors, FIFOs, devices

#[test]
fn too_few_file_descriptors_are_refused_before_any_work() {
    let tmp = tempfile::tempdir().unwrap();
    for n in [8, 10, 11, 12] {
        let out = tmp.path().join(format!("out{n}"));
        let mut cmd = binary(&os(&[&"replay", &real(AIA), &"--out", &out]));
        // As `ulimit -n N` sets it: soft and hard limit.
        support::with_rlimit(&mut cmd, libc::RLIMIT_NOFILE, n);
        let run = run_within(cmd, 120);
        assert_one_line(&run, &[&format!("open-file limit is {n}")]);
        assert!(!out.exists());
    }
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
    // SAFETY: a NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

#[test]
fn a_fifo_or_a_device_is_refused_without_blocking_or_reading_forever() {
    let tmp = tempfile::tempdir().unwrap();
    let fifo = tmp.path().join("pipe.fits");
    mkfifo(&fifo);
    let config_fifo = tmp.path().join("pipe.toml");
    mkfifo(&config_fifo);
    let cases: Vec<(Vec<std::ffi::OsString>, &str)> = vec![
        (os(&[&"info", &fifo]), "FIFO"),
        (os(&[&"align", &fifo, &real(AIA)]), "FIFO"),
        (os(&[&"align", &real(AIA), &fifo]), "FIFO"),
        (os(&[&"inspect", &"/dev/zero"]), "character device"),
        (os(&[&"info", &"/dev/zero"]), "character device"),
        (
            os(&[
                &"replay",
                &real(AIA),
                &"--out",
                &tmp.path().join("o"),
                &"--config",
                &config_fifo,
            ]),
            "FIFO",
        ),
    ];
    for (args, needle) in cases {
        let run = run_within(binary(&args), 120);
        assert_one_line(&run, &[needle, "not a regular file"]);
    }
}

#[test]
fn a_fifo_in_the_watched_directory_is_named_on_the_log_and_the_daemon_goes_on() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let (watched, out, config) = support::daemon_dirs(&base, "");
    let scratch = tempfile::tempdir().unwrap();
    let frames = sunjitter_runtime::fake::split_cube(&real(SJI_1400), scratch.path()).unwrap();
    let mut daemon = WatchProcess::spawn(&watched, &out, &config, &base.join("d.stderr"));
    daemon.wait_watching();
    mkfifo(&watched.join("pipe.fits"));
    for f in &frames[..2] {
        publish(&watched, f);
    }
    daemon.wait_until("2 frames logged", |_| logged(&out).len() == 2);
    let fifo_key = watched.join("pipe.fits").display().to_string();
    daemon.wait_until("the FIFO named on /log", |_| {
        sunjitter_io::sink::read_logs(std::slice::from_ref(&out))
            .map(|c| c.logs.iter().any(|m| m.entry.file == fifo_key))
            .unwrap_or(false)
    });
    assert!(daemon.terminate().success());
    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    let notes: Vec<&str> = contents
        .logs
        .iter()
        .filter(|m| m.entry.file == fifo_key)
        .map(|m| m.entry.message.as_str())
        .collect();
    assert_eq!(notes.len(), 1, "{notes:?}");
    assert!(notes[0].contains("FIFO"), "{notes:?}");
}

// ---------------------------------------------------------------------------------------------
// SIGTERM with nowhere to write

#[test]
fn a_daemon_that_cannot_write_its_log_stops_on_sigterm() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let (watched, out, config) = support::daemon_dirs(&base, "");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sunjitter"));
    cmd.arg("watch")
        .arg(&watched)
        .args(["--out".as_ref(), out.as_os_str()])
        .args(["--config".as_ref(), config.as_os_str()])
        .env("SUNJITTER_LOG", "info")
        .env("SUNJITTER_CACHE_DIR", "")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    // No file may grow past 1 KiB, as on a full disk: no segment can even start. (Its stderr
    // is a pipe, which the limit does not reach.)
    support::with_rlimit(&mut cmd, libc::RLIMIT_FSIZE, 1024);
    let mut child = cmd.spawn().unwrap();
    let lines = std::sync::Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let reader = {
        let (lines, pipe) = (lines.clone(), child.stderr.take().unwrap());
        std::thread::spawn(move || {
            use std::io::BufRead;
            for line in std::io::BufReader::new(pipe).lines().map_while(|l| l.ok()) {
                lines.lock().unwrap().push(line);
            }
        })
    };
    let seen = |needle: &str| lines.lock().unwrap().iter().any(|l| l.contains(needle));
    let wait = |what: &str, needle: &str| {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
        while !seen(needle) {
            assert!(
                std::time::Instant::now() < deadline,
                "no {what}: {:?}",
                lines.lock().unwrap()
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    };
    wait("watching", "watching");
    let scratch = tempfile::tempdir().unwrap();
    let frames = sunjitter_runtime::fake::split_cube(&real(SJI_1400), scratch.path()).unwrap();
    for f in &frames[..2] {
        publish(&watched, f);
    }
    wait("a failed write", "writing the log failed");
    assert!(Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap()
        .success());
    let status = exit_status_within(&mut child, 120).expect("SIGTERM stops it");
    reader.join().unwrap();
    let text = lines.lock().unwrap().join("\n");
    // The work ran but its log could not be written: exit 1, one line saying where.
    assert_eq!(status.code(), Some(ExitCode::Failed.code()), "{text}");
    assert!(!text.contains("panicked"), "{text}");
    let last = text.lines().last().unwrap();
    assert!(last.starts_with("sunjitter: "), "{last}");
    assert!(last.contains(&out.display().to_string()), "{last}");
}

// ---------------------------------------------------------------------------------------------
// The contract's messages

#[test]
fn configurations_that_cannot_mean_anything_are_bad_usage() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("c.toml");
    let out = tmp.path().join("out");
    let replay = |config: &Path| {
        sunjitter(&os(&[
            &"replay",
            &real(AIA),
            &"--out",
            &out,
            &"--config",
            &config,
        ]))
    };
    std::fs::write(&config, [0x89u8, b'P', b'N', b'G', 0xff, 0x00, 0x1a]).unwrap();
    assert_one_line(&replay(&config), &["c.toml", "not text"]);
    std::fs::write(
        &config,
        "[channels.SJI_1400]\npolicy = \"channel:SJI_1400\"\n",
    )
    .unwrap();
    assert_one_line(
        &replay(&config),
        &["channels.SJI_1400", "cannot follow itself"],
    );
    for bad in ["\"\"", "\"a/b\"", "\"x\\ny\""] {
        std::fs::write(&config, format!("[channel_names]\nAIA_171 = {bad}\n")).unwrap();
        assert_one_line(&replay(&config), &["channel_names", "not a channel name"]);
    }
    assert!(!out.exists());
}

/// The real AIA file with its `HGLT_OBS` card replaced by `card` (80 columns).
fn aia_with(card: &str, dir: &Path, name: &str) -> PathBuf {
    let mut bytes = std::fs::read(real(AIA)).unwrap();
    let at = bytes
        .chunks(80)
        .position(|c| c.starts_with(b"HGLT_OBS="))
        .expect("the AIA header has HGLT_OBS")
        * 80;
    bytes[at..at + 80].copy_from_slice(format!("{card:<80}").as_bytes());
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn header_values_no_instrument_can_have_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    for (card, needle) in [
        ("BSCALE  =                  NAN", "BSCALE"),
        ("BSCALE  = 'NaN'", "BSCALE"),
        ("HGLT_OBS=                   99", "HGLT_OBS = 99"),
        ("HGLT_OBS=                 -91.5", "HGLT_OBS = -91.5"),
    ] {
        let file = aia_with(card, tmp.path(), "odd.fits");
        let run = sunjitter(&os(&[&"info", &file]));
        assert_one_line(&run, &[&file.display().to_string(), needle]);
    }
    // Within range: read as before.
    let file = aia_with("HGLT_OBS=                  7.2", tmp.path(), "fine.fits");
    let (code, _, err) = sunjitter(&os(&[&"info", &file]));
    assert_eq!(code, ExitCode::Ok.code(), "{err}");
}

#[test]
fn one_frame_of_a_cube_given_to_replay_is_refused_clearly() {
    let tmp = tempfile::tempdir().unwrap();
    let arg = format!("{}[1]", real(SJI_2832).display());
    let run = sunjitter(&os(&[&"replay", &arg, &"--out", &tmp.path().join("out")]));
    assert_one_line(&run, &["replay takes whole files", "frame 1 of"]);
}

#[test]
fn a_damaged_shard_is_named_as_damaged() {
    let tmp = tempfile::tempdir().unwrap();
    let base = tmp.path().canonicalize().unwrap();
    let frames = base.join("frames");
    support::cube_frames_into(SJI_1400, &frames, 4);
    let shards = support::replay_shards(&base, &frames, None, 2);
    // Bytes of a shard's compressed messages overwritten (a bad disk, a bad copy): just after
    // the first zstd frame's magic number (RFC 8878: 28 B5 2F FD).
    let segment = std::fs::read_dir(&shards[1])
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "mcap"))
        .unwrap();
    let mut bytes = std::fs::read(&segment).unwrap();
    let zstd = bytes
        .windows(4)
        .position(|w| w == [0x28, 0xb5, 0x2f, 0xfd])
        .expect("a zstd chunk");
    for b in &mut bytes[zstd + 8..zstd + 40] {
        *b ^= 0x55;
    }
    std::fs::write(&segment, bytes).unwrap();
    let mut args = os(&[&"merge"]);
    args.extend(shards.iter().map(|s| s.as_os_str().to_os_string()));
    args.extend(os(&[&"--out", &base.join("merged")]));
    let run = sunjitter(&args);
    assert_one_line(&run, &[&shards[1].display().to_string(), "run it again"]);
    assert!(
        run.2.contains("damaged") || run.2.contains("unfinished") || run.2.contains("unreadable"),
        "{}",
        run.2
    );
    assert!(!run.2.contains("holds 0 frame messages"), "{}", run.2);
}
