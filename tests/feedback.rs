//! What a user sees while `watch` and `replay` run.
//!
//! Truths: `sunjitter synth`'s `truth.csv` (a 1.5 px step in x injected between frames 0 and
//! 1), the frame counts of the inputs, and the terminal's width (a pseudo-terminal of 80
//! columns, made here with posix_openpt).

mod support;

use support::{logged, sunjitter_ok, WatchProcess, QUICK_DAEMON_CONFIG};

/// `value ± sigma` after `label ` in `text` (the first occurrence).
fn value_pm(text: &str, label: &str) -> (f64, f64) {
    let rest = text
        .split_once(&format!("{label} "))
        .unwrap_or_else(|| panic!("no {label:?} in {text:?}"))
        .1;
    let mut words = rest.split_whitespace();
    let value: f64 = words.next().unwrap().parse().unwrap();
    assert_eq!(words.next(), Some("±"), "{text}");
    let sigma: f64 = words.next().unwrap().parse().unwrap();
    (value, sigma)
}

/// `text` without ANSI escape sequences.
fn plain(text: &str) -> String {
    let mut out = String::new();
    let mut chars = text.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            if chars.peek() == Some(&'[') {
                chars.next();
                for d in chars.by_ref() {
                    if d.is_ascii_alphabetic() {
                        break;
                    }
                }
            }
            continue;
        }
        out.push(c);
    }
    out
}

#[test]
fn each_watch_line_gives_the_shift_raw_and_chained_and_says_when_a_frame_starts_a_reference() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    sunjitter_ok(&[
        "synth",
        "--out",
        frames.to_str().unwrap(),
        "--frames",
        "4",
        "--size",
        "256",
        "--seed",
        "3",
        "--jitter",
        "step:1.5:6:x",
        "--solar-rotation",
        "none",
    ]);
    let truth = support::read_csv(&frames.join("truth.csv"));
    let dx = |k: usize| truth[k]["dx_px"].parse::<f64>().unwrap();
    assert_eq!((dx(0), dx(1)), (0.0, 1.5));

    let watched = dir.path().join("incoming");
    std::fs::create_dir_all(&watched).unwrap();
    let out = dir.path().join("log");
    let config = dir.path().join("watch.toml");
    // A new keyframe every two frames: frame 2 starts a reference, away from the first.
    std::fs::write(
        &config,
        format!(
            "{QUICK_DAEMON_CONFIG}\n[engine]\nsolar_rotation = \"none\"\n\
             [reference]\nkeyframe_every_frames = 2\n"
        ),
    )
    .unwrap();
    let mut watch = WatchProcess::spawn(&watched, &out, &config, &dir.path().join("stderr"));
    watch.wait_watching();
    for k in 0..4 {
        let name = format!("synth_{k:04}.fits");
        let tmp = watched.join(format!(".{name}.tmp"));
        std::fs::copy(frames.join(&name), &tmp).unwrap();
        std::fs::rename(&tmp, watched.join(&name)).unwrap();
    }
    watch.wait_until("four frames logged", |_| logged(&out).len() >= 4);
    let text = plain(&watch.stderr_text());
    assert!(watch.terminate().success());
    let line = |k: usize| -> String {
        let name = format!("synth_{k:04}.fits ");
        let found: Vec<&str> = text.lines().filter(|l| l.contains(&name)).collect();
        assert_eq!(found.len(), 1, "one line for frame {k}: {text}");
        let at = found[0].find("SYNTH").unwrap_or(0);
        found[0][at..].to_string()
    };
    // Within 5σ of the injected motion, and a little for the σ's own rounding.
    let near = |(v, s): (f64, f64), want: f64, what: &str| {
        assert!(
            (v - want).abs() <= 5.0 * s + 0.002,
            "{what}: {v} ± {s}, truth {want}"
        );
    };

    let first = line(0);
    assert!(
        first.ends_with("synth_0000.fits ok starts a chain"),
        "{first}"
    );

    let second = line(1);
    assert!(second.contains("synth_0001.fits ok dx "), "{second}");
    let (raw, chained) = second.split_once("; chained ").unwrap();
    near(value_pm(raw, "dx"), dx(1) - dx(0), &second);
    near(value_pm(raw, "dy"), 0.0, &second);
    near(value_pm(chained, "dx"), dx(1) - dx(0), &second);

    let third = line(2);
    assert!(
        third.contains("synth_0002.fits ok starts a reference; chained dx "),
        "{third}"
    );
    assert!(!third.contains("dx 0 px"), "{third}");
    near(value_pm(&third, "dx"), dx(2) - dx(0), &third);

    let fourth = line(3);
    let (raw, chained) = fourth.split_once("; chained ").unwrap();
    near(value_pm(raw, "dx"), dx(3) - dx(2), &fourth);
    near(value_pm(chained, "dx"), dx(3) - dx(0), &fourth);
}

const CUBE: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";

#[test]
fn replay_off_a_terminal_prints_one_summary_line() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    sunjitter_ok(&[
        "synth",
        "--out",
        frames.to_str().unwrap(),
        "--frames",
        "5",
        "--size",
        "128",
    ]);
    let out = sunjitter_ok(&[
        "replay",
        frames.to_str().unwrap(),
        "--out",
        dir.path().join("log").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with("sunjitter: 5 frames logged to "),
        "{stderr}"
    );
    assert!(!stderr.contains('\r'), "{stderr:?}");
}

/// A pseudo-terminal of `cols` columns: (master, slave path).
fn pseudo_terminal(cols: u16) -> (std::fs::File, std::path::PathBuf) {
    use std::os::fd::FromRawFd;
    // SAFETY: plain libc calls on a descriptor this function owns; the name buffer is
    // NUL-terminated by ptsname_r on success.
    unsafe {
        let master = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
        assert!(master >= 0, "posix_openpt");
        assert_eq!(libc::grantpt(master), 0);
        assert_eq!(libc::unlockpt(master), 0);
        let mut name = [0 as libc::c_char; 128];
        assert_eq!(libc::ptsname_r(master, name.as_mut_ptr(), name.len()), 0);
        let size = libc::winsize {
            ws_row: 24,
            ws_col: cols,
            ws_xpixel: 0,
            ws_ypixel: 0,
        };
        assert_eq!(libc::ioctl(master, libc::TIOCSWINSZ, &size), 0);
        let path = std::ffi::CStr::from_ptr(name.as_ptr())
            .to_string_lossy()
            .into_owned();
        (std::fs::File::from_raw_fd(master), path.into())
    }
}

#[test]
fn replay_on_a_terminal_shows_a_progress_bar_that_fits_it() {
    let dir = tempfile::tempdir().unwrap();
    let (mut master, slave_path) = pseudo_terminal(80);
    let slave = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&slave_path)
        .unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(["replay", CUBE, "--out"])
        .arg(dir.path().join("log"))
        .env("SUNJITTER_LOG", "error")
        .stdout(std::process::Stdio::null())
        .stderr(slave)
        .spawn()
        .unwrap();
    // Read while it runs (a full terminal buffer would stop it); the read ends with an error
    // once the last holder of the slave side has exited.
    let reader = std::thread::spawn(move || {
        let mut all = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            match std::io::Read::read(&mut master, &mut buf) {
                Ok(0) | Err(_) => break,
                Ok(n) => all.extend_from_slice(&buf[..n]),
            }
        }
        String::from_utf8_lossy(&all).into_owned()
    });
    let status = support::exit_status_within(&mut child, 300).expect("replay finishes");
    assert!(status.success());
    let seen = plain(&reader.join().unwrap());
    assert!(seen.contains("/54 frames"), "no progress bar: {seen:?}");
    assert!(seen.contains(" ok "), "{seen:?}");
    assert!(
        seen.contains("sunjitter: 54 frames logged to "),
        "no summary: {seen:?}"
    );
    for piece in seen
        .split(['\r', '\n'])
        .filter(|p| p.contains("/54 frames"))
    {
        assert!(
            piece.chars().count() <= 80,
            "wider than the terminal: {piece:?}"
        );
    }
}
