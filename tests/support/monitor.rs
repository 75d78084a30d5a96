//! Shared by the monitoring tests (live view, alerts, status): real IRIS frames written as the
//! daemon's input (optionally shifted by a known whole number of pixels, or blanked), and the
//! `sunjitter watch` binary run as a child process, observed through its stderr and its
//! status file; and the independent live-view client (tools/live_client, Node.js).
#![allow(dead_code)]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};
use sunjitter_io::fits::{self, FrameSpec};

/// The IRIS SJI 1400 Å cube (54 frames, 110 × 109 px, 0.16635″/px).
pub const CUBE_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";

/// Generous bound for anything the daemon does on these small frames (a failure guard only).
pub const PATIENCE: Duration = Duration::from_secs(120);

/// How to alter a real frame before it is written.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Alter {
    None,
    /// Content moved by whole pixels: what was at (x, y) appears at (x + dx, y + dy).
    Shift(isize, isize),
    /// Every pixel set to the frame's mean: a valid FITS file with no structure to align.
    Blank,
}

/// Write frame `index` of the cube as a 2-D FITS file `dest` with the frame's own header.
pub fn write_frame(index: usize, alter: Alter, dest: &Path) {
    let cube = Path::new(env!("CARGO_MANIFEST_DIR")).join(CUBE_1400);
    let (_, header) = fits::read_image_header(&cube).unwrap();
    let image = fits::read_frame(&FrameSpec::cube_frame(&cube, index)).unwrap();
    let cards = fits::frame_header_cards(&header, &image.meta);
    let src = &image.data;
    let (h, w) = src.dim();
    let data = match alter {
        Alter::None => src.clone(),
        Alter::Shift(dx, dy) => ndarray::Array2::from_shape_fn((h, w), |(y, x)| {
            // Edge pixels are repeated into the uncovered band.
            let sy = (y as isize - dy).clamp(0, h as isize - 1) as usize;
            let sx = (x as isize - dx).clamp(0, w as isize - 1) as usize;
            src[[sy, sx]]
        }),
        Alter::Blank => {
            let finite: Vec<f32> = src.iter().copied().filter(|v| v.is_finite()).collect();
            let mean = finite.iter().map(|v| *v as f64).sum::<f64>() / finite.len() as f64;
            ndarray::Array2::from_elem((h, w), mean as f32)
        }
    };
    fits::write_image(dest, data.view(), &cards).unwrap();
}

/// Write frames into `stage` (outside the watched directory) so they can be moved in at once.
pub fn stage_frames(stage: &Path, frames: &[(usize, Alter)]) -> Vec<PathBuf> {
    std::fs::create_dir_all(stage).unwrap();
    frames
        .iter()
        .map(|(index, alter)| {
            let path = stage.join(format!("sji1400_f{index:04}.fits"));
            write_frame(*index, *alter, &path);
            path
        })
        .collect()
}

/// Move staged files into the watched directory (renames: the watcher sees whole files).
pub fn move_in(files: &[PathBuf], watched: &Path) {
    for f in files {
        std::fs::rename(f, watched.join(f.file_name().unwrap())).unwrap();
    }
}

/// A `sunjitter watch` child process.
pub struct Daemon {
    pub child: Child,
    pub out: PathBuf,
    stderr: Receiver<String>,
    pub stderr_seen: Vec<String>,
}

impl Daemon {
    pub fn start(watched: &Path, out: &Path, config: &Path, extra: &[&str]) -> Daemon {
        let mut child = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
            .arg("watch")
            .arg(watched)
            .arg("--out")
            .arg(out)
            .arg("--config")
            .arg(config)
            .args(extra)
            .env("SUNJITTER_LOG", "info")
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start sunjitter watch");
        let stderr = child.stderr.take().unwrap();
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(|l| l.ok()) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Daemon {
            child,
            out: out.to_path_buf(),
            stderr: rx,
            stderr_seen: Vec::new(),
        }
    }

    /// Wait for a stderr line containing every one of `parts`; panics (with the log) if the
    /// daemon exits or `PATIENCE` passes first.
    pub fn expect_stderr(&mut self, parts: &[&str]) -> String {
        let deadline = Instant::now() + PATIENCE;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.stderr.recv_timeout(left) {
                Ok(line) => {
                    self.stderr_seen.push(line.clone());
                    if parts.iter().all(|p| line.contains(p)) {
                        return line;
                    }
                }
                Err(_) => panic!(
                    "no daemon log line with {parts:?}; log so far:\n{}",
                    self.stderr_seen.join("\n")
                ),
            }
        }
    }

    /// SIGTERM, then the exit status (the daemon finishes the frames in hand).
    pub fn terminate(mut self) -> (ExitStatus, Vec<String>) {
        let pid = self.child.id().to_string();
        let killed = Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        assert!(killed.success());
        let status = self.child.wait().unwrap();
        self.stderr_seen.extend(self.stderr.try_iter());
        // The reader thread ends with the pipe; collect what is left.
        while let Ok(line) = self.stderr.recv_timeout(Duration::from_secs(5)) {
            self.stderr_seen.push(line);
        }
        (status, std::mem::take(&mut self.stderr_seen))
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Poll `check` (an observation of files the daemon writes) until it gives a value.
pub fn wait_for<T>(what: &str, mut check: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + PATIENCE;
    loop {
        if let Some(v) = check() {
            return v;
        }
        assert!(Instant::now() < deadline, "gave up waiting for {what}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The daemon's status document, if the file is there.
pub fn read_status(out: &Path) -> Option<serde_json::Value> {
    let text = std::fs::read_to_string(out.join("status.json")).ok()?;
    Some(serde_json::from_str(&text).expect("the status file is always a whole JSON document"))
}

/// Frames logged so far according to the status file.
pub fn status_frames(out: &Path) -> u64 {
    read_status(out)
        .and_then(|s| s["frames"].as_u64())
        .unwrap_or(0)
}

// ---------------------------------------------------------------------------------------------
// The live-view client: `@foxglove/ws-protocol` in Node.js (needs `npm ci --prefix
// tools/live_client`).

fn client_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/live_client")
}

/// The node client, its stdout lines parsed as JSON.
pub struct NodeClient {
    child: Child,
    pub lines: Receiver<serde_json::Value>,
}

impl NodeClient {
    /// Fails (never skips) when the client is not installed.
    pub fn require_installed() {
        let dir = client_dir();
        assert!(
            dir.join("node_modules/@foxglove/ws-protocol").is_dir()
                && dir.join("node_modules/ws").is_dir(),
            "the live-view test client is not installed: run `npm ci --prefix tools/live_client`"
        );
    }

    pub fn start(url: &str, args: &[&str]) -> NodeClient {
        NodeClient::start_offering(url, args, "foxglove.sdk.v1")
    }

    /// [`NodeClient::start`], the client offering `subprotocols` (comma-separated).
    pub fn start_offering(url: &str, args: &[&str], subprotocols: &str) -> NodeClient {
        NodeClient::require_installed();
        let dir = client_dir();
        let mut child = Command::new("node")
            .arg(dir.join("client.js"))
            .arg(url)
            .args(args)
            .env("SUBPROTOCOLS", subprotocols)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("node (Node.js ≥ 18) must be installed to run the live-view test");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(|l| l.ok()) {
                let value: serde_json::Value =
                    serde_json::from_str(&line).unwrap_or_else(|e| panic!("{e}: {line}"));
                if tx.send(value).is_err() {
                    break;
                }
            }
        });
        NodeClient { child, lines: rx }
    }

    /// Next line whose `event` is `event`; panics if the client ends or `PATIENCE` passes.
    pub fn expect(&self, event: &str) -> serde_json::Value {
        loop {
            let line = self
                .lines
                .recv_timeout(PATIENCE)
                .unwrap_or_else(|_| panic!("live client: no {event:?} event"));
            if line["event"] == event {
                return line;
            }
        }
    }
}

impl Drop for NodeClient {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The `ws://…` address in the daemon's "live view … listening" log line.
pub fn live_url(line: &str) -> String {
    line[line.find("ws://").expect("a ws:// address")..]
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || ":/.".contains(*c))
        .collect()
}

/// Whether process `pid` is still running: absent and zombie (ended, not yet reaped by its
/// parent) processes are not.
pub fn process_running(pid: u32) -> bool {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return false;
    };
    // The state follows the command name, which is in parentheses and may contain spaces.
    let state = stat
        .rsplit(')')
        .next()
        .and_then(|r| r.split_whitespace().next());
    !matches!(state, None | Some("Z") | Some("X"))
}

/// A WebSocket handshake for the Foxglove protocol made by hand on a raw TCP connection to the
/// live view at `url` (`ws://HOST:PORT`), with an `Origin` header when given: the response's
/// HTTP status code, and the connection (open, for a `101`).
pub fn ws_handshake(url: &str, origin: Option<&str>) -> (u16, std::net::TcpStream) {
    ws_handshake_offering(url, origin, "foxglove.sdk.v1").0
}

/// [`ws_handshake`] offering `subprotocols`: also the response's head (status line and
/// headers, as text).
pub fn ws_handshake_offering(
    url: &str,
    origin: Option<&str>,
    subprotocols: &str,
) -> ((u16, std::net::TcpStream), String) {
    use std::io::{Read, Write};
    let host = url.strip_prefix("ws://").expect("a ws:// address");
    let mut stream = std::net::TcpStream::connect(host).unwrap();
    stream.set_read_timeout(Some(PATIENCE)).unwrap();
    let origin = origin.map_or(String::new(), |o| format!("Origin: {o}\r\n"));
    let request = format!(
        "GET / HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Protocol: {subprotocols}\r\n{origin}\r\n"
    );
    stream.write_all(request.as_bytes()).unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8];
    while !head.ends_with(b"\r\n\r\n") {
        let n = stream.read(&mut byte).expect("a response to the handshake");
        assert_eq!(
            n,
            1,
            "closed without a response: {:?}",
            String::from_utf8_lossy(&head)
        );
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head).into_owned();
    let code = head
        .strip_prefix("HTTP/1.1 ")
        .and_then(|r| r.get(..3))
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("not an HTTP response: {head}"));
    ((code, stream), head)
}
