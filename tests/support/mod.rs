//! Shared by the integration tests: the contract's field lists (contract.md), written once,
//! and the reader of `inspect --csv` output; the daemon harness ([`daemon`]), fault-injection
//! fixtures ([`faults`]) and the monitoring tests' helpers ([`monitor`]).
#![allow(dead_code)]

pub mod daemon;
pub mod faults;
pub mod monitor;

use std::collections::HashMap;
use std::path::Path;

/// `align --json`: the contract's fields plus the paper's plain-UABJM σ.
pub const ALIGN_FIELDS: [&str; 28] = [
    "reference",
    "frame",
    "scale",
    "rotation_arcsec",
    "dx_px",
    "dy_px",
    "dx_arcsec",
    "dy_arcsec",
    "sigma_scale",
    "sigma_rotation_arcsec",
    "sigma_dx_px",
    "sigma_dy_px",
    "sigma_dx_arcsec",
    "sigma_dy_arcsec",
    "uabjm_sigma_scale",
    "uabjm_sigma_rotation_arcsec",
    "uabjm_sigma_dx_px",
    "uabjm_sigma_dy_px",
    "header_residual",
    "solar_rotation",
    "points",
    "inliers",
    "residual_rms_px",
    "similarity",
    "model",
    "status",
    "message",
    "elapsed_ms",
];

/// A `/jitter/<channel>` message adds the stream context to the `align --json` fields.
pub const STREAM_FIELDS: [&str; 16] = [
    "channel",
    "obs_time",
    "sequence",
    "reference_kind",
    "chained_dx_px",
    "chained_dy_px",
    "chained_dx_arcsec",
    "chained_dy_arcsec",
    "chained_rotation_arcsec",
    "chained_scale",
    "sigma_chained_dx_px",
    "sigma_chained_dy_px",
    "sigma_chained_dx_arcsec",
    "sigma_chained_dy_arcsec",
    "sigma_chained_rotation_arcsec",
    "sigma_chained_scale",
];

/// Every field of a `/jitter/<channel>` message.
pub fn jitter_fields() -> Vec<&'static str> {
    ALIGN_FIELDS
        .iter()
        .chain(STREAM_FIELDS.iter())
        .copied()
        .collect()
}

/// Rows of a simple CSV (no quoted commas in the columns read here) keyed by header name.
pub fn read_csv(path: &Path) -> Vec<HashMap<String, String>> {
    let text = std::fs::read_to_string(path).expect("csv written");
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(String::from))
                .collect()
        })
        .collect()
}

/// Daemon settings that keep binary tests quick (the defaults are for real instruments).
pub const QUICK_DAEMON_CONFIG: &str = r#"
[daemon]
settle_s = 0.1
reorder_window_s = 0.2
flush_interval_s = 0.1
"#;

/// Run the binary to completion: exit code, stdout, stderr.
pub fn sunjitter<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> (i32, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(args)
        .env("SUNJITTER_LOG", "warn")
        .output()
        .expect("runs");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Run the binary, which must succeed; its output.
pub fn sunjitter_ok(args: &[&str]) -> std::process::Output {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(args)
        .output()
        .expect("binary runs");
    assert!(
        out.status.success(),
        "sunjitter {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A `sunjitter watch` process, its stderr in a file.
pub struct WatchProcess {
    pub child: std::process::Child,
    pub stderr: std::path::PathBuf,
}

impl WatchProcess {
    pub fn spawn(watched: &Path, out: &Path, config: &Path, stderr: &Path) -> WatchProcess {
        let file = std::fs::File::create(stderr).unwrap();
        let child = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
            .arg("watch")
            .arg(watched)
            .arg("--out")
            .arg(out)
            .arg("--config")
            .arg(config)
            .env("SUNJITTER_LOG", "info")
            .stdout(std::process::Stdio::null())
            .stderr(file)
            .spawn()
            .unwrap();
        WatchProcess {
            child,
            stderr: stderr.to_path_buf(),
        }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn stderr_text(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }

    /// Wait (bounded) until `ready` holds, failing if the process exits meanwhile.
    pub fn wait_until(&mut self, what: &str, mut ready: impl FnMut(&Self) -> bool) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
        while !ready(self) {
            if let Some(status) = self.child.try_wait().unwrap() {
                panic!("the daemon exited ({status}): {}", self.stderr_text());
            }
            assert!(
                std::time::Instant::now() < deadline,
                "timed out waiting for {what}: {}",
                self.stderr_text()
            );
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
    }

    /// Wait until the daemon watches its directory (its `watching` log line).
    pub fn wait_watching(&mut self) {
        self.wait_until("the daemon to start watching", |d| {
            d.stderr_text().contains("watching")
        });
    }

    /// SIGTERM, then the exit status (a clean stop is success).
    pub fn terminate(mut self) -> std::process::ExitStatus {
        let term = std::process::Command::new("kill")
            .arg("-TERM")
            .arg(self.pid().to_string())
            .status()
            .unwrap();
        assert!(term.success());
        self.child.wait().unwrap()
    }

    /// SIGKILL, then wait for the process to be gone.
    pub fn kill(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }
}

/// Wait (bounded) for a process started by a test to exit, killing it if it does not.
pub fn exit_status_within(
    child: &mut std::process::Child,
    secs: u64,
) -> Option<std::process::ExitStatus> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        if std::time::Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// Publish a split frame into `watched` as instruments do: written under a hidden temporary
/// name, then renamed into place.
pub fn publish(watched: &Path, f: &sunjitter_runtime::fake::SplitFrame) {
    let tmp = watched.join(format!(".{}.tmp", f.name));
    std::fs::write(&tmp, &f.bytes).unwrap();
    std::fs::rename(&tmp, watched.join(&f.name)).unwrap();
}

/// Frame keys logged in `out` so far, with their counts (the library's reader, which also
/// reads segments still being written).
pub fn logged(out: &Path) -> std::collections::BTreeMap<String, usize> {
    let mut counts = std::collections::BTreeMap::new();
    if let Ok(logs) = sunjitter_io::sink::read_logs(&[out.to_path_buf()]) {
        for m in &logs.jitter {
            *counts.entry(m.record.align.frame.clone()).or_insert(0) += 1;
        }
    }
    counts
}

/// A file of the repository (`data/real/…`).
pub fn repo_file(relative: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(relative)
}

/// The first `n` frames of a real cube, each written into `dir` as a FITS file of its own.
pub fn cube_frames_into(cube: &str, dir: &Path, n: usize) -> Vec<std::path::PathBuf> {
    std::fs::create_dir_all(dir).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    sunjitter_runtime::fake::split_cube(&repo_file(cube), scratch.path())
        .unwrap()
        .into_iter()
        .take(n)
        .map(|f| {
            let path = dir.join(&f.name);
            std::fs::write(&path, &f.bytes).unwrap();
            path
        })
        .collect()
}

/// `replay INPUT --shard K/N --out BASE/shard-K` for every K (with `--config` when given),
/// each of which must succeed: the shard outputs.
pub fn replay_shards(
    base: &Path,
    input: &Path,
    config: Option<&Path>,
    count: usize,
) -> Vec<std::path::PathBuf> {
    (0..count)
        .map(|k| {
            let out = base.join(format!("shard-{k}"));
            let mut args: Vec<std::ffi::OsString> = vec!["replay".into(), input.into()];
            if let Some(c) = config {
                args.extend(["--config".into(), c.into()]);
            }
            args.extend(["--out".into(), out.clone().into()]);
            args.extend(["--shard".into(), format!("{k}/{count}").into()]);
            let (code, _, err) = sunjitter(&args);
            assert_eq!(code, 0, "shard {k}/{count}: {err}");
            out
        })
        .collect()
}

/// A watched directory `BASE/in` (created), `BASE/out` for the log and `BASE/c.toml` holding
/// [`QUICK_DAEMON_CONFIG`] followed by `extra`.
pub fn daemon_dirs(
    base: &Path,
    extra: &str,
) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    let watched = base.join("in");
    std::fs::create_dir_all(&watched).unwrap();
    let config = base.join("c.toml");
    std::fs::write(&config, format!("{QUICK_DAEMON_CONFIG}{extra}")).unwrap();
    (watched, base.join("out"), config)
}

/// Run `cmd` with the resource limit `resource` (soft and hard) at `value`. Past
/// `RLIMIT_FSIZE`, a write then fails (EFBIG) as on a full disk instead of the process being
/// killed (SIGXFSZ ignored).
pub fn with_rlimit(
    cmd: &mut std::process::Command,
    resource: libc::__rlimit_resource_t,
    value: u64,
) {
    use std::os::unix::process::CommandExt;
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            let l = libc::rlimit {
                rlim_cur: value,
                rlim_max: value,
            };
            libc::setrlimit(resource, &l);
            if resource == libc::RLIMIT_FSIZE {
                libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            }
            Ok(())
        });
    }
}
