//! No command writes over what it reads or over a log: an output path that is an input (by any
//! spelling, or a hard link), a log segment, or inside a directory a running daemon holds is
//! refused (exit 2, one line naming the path and why) and nothing is written.

mod support;

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use sunjitter_core::error::ExitCode;
use sunjitter_runtime::fake::split_cube;
use support::{sunjitter, WatchProcess, QUICK_DAEMON_CONFIG};

const AIA: &str = "data/real/aia_171_20110215T000000_128.fits";
const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";

fn args(parts: &[&dyn AsRef<std::ffi::OsStr>]) -> Vec<OsString> {
    parts.iter().map(|p| p.as_ref().to_os_string()).collect()
}

/// Exit 2 with one line on stderr naming `path` and saying `why`.
fn assert_refused(run: (i32, String, String), path: &Path, why: &str) {
    let (code, _, stderr) = run;
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line: {stderr}");
    assert!(lines[0].contains(&path.display().to_string()), "{stderr}");
    assert!(lines[0].contains(why), "{stderr}");
}

/// `ref.fits` and `frame.fits` (the same image), `sub/`, and `link.fits`, a hard link to the frame.
fn images(dir: &Path) -> (PathBuf, PathBuf) {
    let (reference, frame) = (dir.join("ref.fits"), dir.join("frame.fits"));
    std::fs::copy(AIA, &reference).unwrap();
    std::fs::copy(AIA, &frame).unwrap();
    std::fs::create_dir(dir.join("sub")).unwrap();
    std::fs::hard_link(&frame, dir.join("link.fits")).unwrap();
    (reference, frame)
}

/// A finished log of two IRIS frames in `dir/out`, written by `replay`.
fn replayed_log(dir: &Path) -> PathBuf {
    let frames = split_cube(Path::new(SJI_1400), &dir.join("split")).unwrap();
    let archive = dir.join("archive");
    std::fs::create_dir_all(&archive).unwrap();
    for f in &frames[..2] {
        std::fs::write(archive.join(&f.name), &f.bytes).unwrap();
    }
    let out = dir.join("out");
    let (code, _, stderr) = sunjitter(&args(&[&"replay", &archive, &"--out", &out]));
    assert_eq!(code, ExitCode::Ok.code(), "{stderr}");
    out
}

fn segments(out: &Path) -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    found.sort();
    found
}

#[test]
fn align_refuses_to_write_over_its_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (reference, frame) = images(d);
    let original = std::fs::read(&frame).unwrap();
    let spellings = [
        ("--aligned", frame.clone()),
        ("--aligned", d.join("sub/../frame.fits")),
        ("--aligned", d.join("link.fits")),
        ("--aligned", reference.clone()),
        ("--quicklook", frame.clone()),
    ];
    for (flag, target) in &spellings {
        let run = sunjitter(&args(&[&"align", &reference, &frame, flag, target]));
        assert_refused(run, target, "is an input");
        assert_eq!(
            std::fs::read(&frame).unwrap(),
            original,
            "{flag} {target:?}"
        );
        assert_eq!(
            std::fs::read(&reference).unwrap(),
            original,
            "{flag} {target:?}"
        );
    }
    // Both outputs on one file: refused before either is written.
    let png = d.join("q.png");
    let run = sunjitter(&args(&[
        &"align",
        &reference,
        &frame,
        &"--aligned",
        &png,
        &"--quicklook",
        &d.join("sub/../q.png"),
    ]));
    assert_refused(run, &d.join("sub/../q.png"), "named twice");
    assert!(!png.exists());
    // Distinct outputs are written.
    let aligned = d.join("aligned.fits");
    let (code, _, stderr) = sunjitter(&args(&[
        &"align",
        &reference,
        &frame,
        &"--aligned",
        &aligned,
        &"--quicklook",
        &png,
    ]));
    assert_eq!(code, ExitCode::Ok.code(), "{stderr}");
    assert!(aligned.is_file() && png.is_file());
}

#[test]
fn simulate_refuses_to_write_trials_over_its_image() {
    let dir = tempfile::tempdir().unwrap();
    let (_, frame) = images(dir.path());
    let original = std::fs::read(&frame).unwrap();
    let link = dir.path().join("link.fits");
    let run = sunjitter(&args(&[
        &"simulate",
        &frame,
        &"--trials",
        &"1",
        &"--trials-out",
        &link,
    ]));
    assert_refused(run, &link, "is an input");
    assert_eq!(std::fs::read(&frame).unwrap(), original);
}

#[test]
fn inspect_refuses_to_write_over_a_log_segment_and_the_log_stays_usable() {
    let dir = tempfile::tempdir().unwrap();
    let out = replayed_log(dir.path());
    let segment = segments(&out).remove(0);
    let original = std::fs::read(&segment).unwrap();

    let run = sunjitter(&args(&[&"inspect", &out, &"--csv", &segment]));
    assert_refused(run, &segment, "is an input");
    assert_eq!(std::fs::read(&segment).unwrap(), original);

    // A log that is not an input of the command is recognised by its content.
    let copy = dir.path().join("copy.bin");
    std::fs::copy(&segment, &copy).unwrap();
    let run = sunjitter(&args(&[&"inspect", &out, &"--csv", &copy]));
    assert_refused(run, &copy, "is an MCAP log");
    assert_eq!(std::fs::read(&copy).unwrap(), original);

    // A new `.mcap` name in a log directory would be read as a segment.
    let fresh = out.join("series.mcap");
    let run = sunjitter(&args(&[&"inspect", &out, &"--csv", &fresh]));
    assert_refused(run, &fresh, ".mcap");
    assert!(!fresh.exists());

    let (code, _, stderr) = sunjitter(&args(&[&"inspect", &out, &"--csv", &out.join("s.csv")]));
    assert_eq!(code, ExitCode::Ok.code(), "{stderr}");
    assert_eq!(segments(&out).len(), 1, "the log is whole and readable");
}

#[test]
fn nothing_is_written_into_a_directory_a_running_daemon_holds() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (reference, frame) = images(d);
    let (watched, out) = (d.join("in"), d.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = d.join("config.toml");
    std::fs::write(&config, QUICK_DAEMON_CONFIG).unwrap();
    let mut daemon = WatchProcess::spawn(&watched, &out, &config, &d.join("daemon.stderr"));
    daemon.wait_watching();
    let held = format!("pid {}", daemon.pid());

    let png = out.join("q.png");
    let run = sunjitter(&args(&[&"align", &reference, &frame, &"--quicklook", &png]));
    assert_refused(run, &png, &held);
    assert!(!png.exists());

    let run = sunjitter(&args(&[
        &"synth",
        &"--out",
        &out,
        &"--frames",
        &"1",
        &"--size",
        &"64",
    ]));
    assert_refused(run, &out.join("truth.csv"), &held);
    assert!(!out.join("truth.csv").exists());

    assert!(daemon.terminate().success());
}
