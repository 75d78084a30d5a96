//! The live view end to end, seen by an independent client: `@foxglove/ws-protocol` (the
//! protocol library Foxglove's own apps use, tools/live_client) against `sunjitter watch
//! --live`, fed real IRIS frames. Also the health status file of the same run.
//!
//! Needs `npm ci --prefix tools/live_client` once (the CI script does it).

mod support;

use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use sunjitter_core::error::ExitCode;
use support::monitor::*;

const CONFIG: &str = r#"
[daemon]
settle_s = 0.1
reorder_window_s = 0.3
reorder_window_frames = 64
flush_interval_s = 0.1

[health]
interval_s = 0.05

# Naming the channel advertises /jitter/SJI_1400 from the start.
[channels.SJI_1400]
"#;

/// The watched and output directories under `tmp`, the configuration `config` written there,
/// and real IRIS frames `indices` staged to be moved in.
fn setup(
    tmp: &std::path::Path,
    config: &str,
    indices: &[usize],
) -> (
    std::path::PathBuf,
    std::path::PathBuf,
    std::path::PathBuf,
    Vec<std::path::PathBuf>,
) {
    let (watched, out) = (tmp.join("in"), tmp.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let path = tmp.join("sunjitter.toml");
    std::fs::write(&path, config).unwrap();
    let frames: Vec<(usize, Alter)> = indices.iter().map(|i| (*i, Alter::None)).collect();
    let staged = stage_frames(&tmp.join("stage"), &frames);
    (watched, out, path, staged)
}

#[test]
fn an_independent_client_receives_every_logged_frame_live_and_a_stalled_one_costs_nothing() {
    NodeClient::require_installed();
    let tmp = tempfile::tempdir().unwrap();
    // Real frames 7–16 of the IRIS cube.
    let indices: Vec<usize> = (7..17).collect();
    let (watched, out, config, staged) = setup(tmp.path(), CONFIG, &indices);

    let mut daemon = Daemon::start(&watched, &out, &config, &["--live", "127.0.0.1:0"]);
    let line = daemon.expect_stderr(&["live view", "ws://127.0.0.1:"]);
    let url = live_url(&line);
    // Meanwhile, a reader of the status file: it must find a whole document every time.
    let reads = Arc::new(AtomicU64::new(0));
    let stop_reading = Arc::new(AtomicBool::new(false));
    let status_reader = {
        let (out, reads, stop) = (out.clone(), reads.clone(), stop_reading.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::SeqCst) {
                if let Ok(text) = std::fs::read_to_string(out.join("status.json")) {
                    serde_json::from_str::<serde_json::Value>(&text)
                        .unwrap_or_else(|e| panic!("status file not whole JSON ({e}): {text}"));
                    reads.fetch_add(1, Ordering::SeqCst);
                }
            }
        })
    };

    let reader = NodeClient::start(&url, &["read", "/jitter/SJI_1400"]);
    // The channel is advertised with the log's schema and encodings, then subscribed.
    let advertised = loop {
        let a = reader.expect("advertised");
        if a["topic"] == "/jitter/SJI_1400" {
            break a;
        }
    };
    assert_eq!(advertised["schemaName"], "sunjitter.FrameAlignment");
    assert_eq!(advertised["schemaEncoding"], "jsonschema");
    assert_eq!(advertised["encoding"], "json");
    let subscribed = reader.expect("subscribed");
    assert_eq!(subscribed["topic"], "/jitter/SJI_1400");
    daemon.expect_stderr(&["live: subscribed", "/jitter/SJI_1400"]);
    let stalled = NodeClient::start(&url, &["stall"]);
    stalled.expect("stalled");
    // The stalled client subscribed to every advertised topic (/alert, /jitter, /log).
    for _ in 0..3 {
        daemon.expect_stderr(&["live: subscribed", "client=\"2\""]);
    }

    move_in(&staged, &watched);
    let mut live = Vec::new();
    while live.len() < indices.len() {
        let m = reader.expect("message");
        assert_eq!(m["topic"], "/jitter/SJI_1400");
        live.push(m);
    }
    wait_for("every frame in the status file", || {
        (status_frames(&out) == indices.len() as u64).then_some(())
    });
    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));
    stop_reading.store(true, Ordering::SeqCst);
    status_reader
        .join()
        .expect("status reads were all whole JSON");
    assert!(reads.load(Ordering::SeqCst) > 0);
    // Nothing more came after the last frame.
    assert!(reader.lines.try_iter().all(|l| l["event"] != "message"));

    // The log is the truth: one message per frame, and the live ones are the same messages.
    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(contents.jitter.len(), indices.len());
    let frames: Vec<String> = contents
        .jitter
        .iter()
        .map(|m| m.record.align.frame.clone())
        .collect();
    for i in &indices {
        let name = format!("sji1400_f{i:04}.fits");
        assert_eq!(
            frames.iter().filter(|f| f.ends_with(&name)).count(),
            1,
            "{name} in {frames:?}"
        );
    }
    for (m, logged) in live.iter().zip(&contents.jitter) {
        let payload = &m["payload"];
        for field in support::jitter_fields() {
            assert!(payload.get(field).is_some(), "live message lacks {field}");
        }
        // Same message: the client's JSON decodes to exactly the logged record (JavaScript
        // prints 0.0 as 0, so compare decoded values, not text).
        let decoded: sunjitter_core::record::FrameAlignment =
            serde_json::from_value(payload.clone()).unwrap();
        assert_eq!(decoded, logged.record);
        assert_eq!(m["logTime"], logged.log_time_ns.to_string());
    }

    // The final status agrees with the log.
    let status = read_status(&out).unwrap();
    assert_eq!(status["state"], "stopped");
    let ch = &status["channels"]["SJI_1400"];
    let count = |s: sunjitter_core::record::Status| {
        contents
            .jitter
            .iter()
            .filter(|m| m.record.align.status == s)
            .count() as u64
    };
    assert_eq!(ch["frames"], indices.len() as u64);
    assert_eq!(ch["ok"], count(sunjitter_core::record::Status::Ok));
    assert_eq!(
        ch["degraded"],
        count(sunjitter_core::record::Status::Degraded)
    );
    assert_eq!(ch["failed"], count(sunjitter_core::record::Status::Failed));
    assert_eq!(status["skipped"], 0);
    assert_eq!(status["queue_depth"], 0);
    let last = contents.jitter.last().unwrap();
    assert_eq!(ch["last_frame"], last.record.align.frame.as_str());
    assert!(ch["lag_s"].as_f64().is_some_and(|l| l >= 0.0), "{ch}");
    assert_eq!(status["live"], url.as_str());
    assert_eq!(status["live_dropped"], 0);

    // `sunjitter status` prints it, for tools and for people.
    let printed = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(["status", "--json"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(printed.status.success());
    let printed: serde_json::Value = serde_json::from_slice(&printed.stdout).unwrap();
    assert_eq!(printed, status);
    let human = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("status")
        .arg(out.join("status.json"))
        .output()
        .unwrap();
    let human = String::from_utf8(human.stdout).unwrap();
    assert!(
        human.contains("stopped") && human.contains("SJI_1400"),
        "{human}"
    );
}

#[test]
fn a_client_connected_before_a_channels_first_frame_receives_every_frame() {
    NodeClient::require_installed();
    let tmp = tempfile::tempdir().unwrap();
    // No [channels.SJI_1400]: the channel is advertised with its first frame.
    let unnamed = CONFIG.replace("[channels.SJI_1400]", "");
    let indices: Vec<usize> = (7..19).collect();
    let (watched, out, config, staged) = setup(tmp.path(), &unnamed, &indices);

    let mut daemon = Daemon::start(&watched, &out, &config, &["--live", "127.0.0.1:0"]);
    let url = live_url(&daemon.expect_stderr(&["live view", "ws://127.0.0.1:"]));
    let reader = NodeClient::start(&url, &["read", "/jitter/SJI_1400"]);
    // Connected: the channels that exist are advertised; the frame channel is not among them.
    let advertised: Vec<String> = (0..2)
        .map(|_| {
            reader.expect("advertised")["topic"]
                .as_str()
                .unwrap()
                .to_string()
        })
        .collect();
    assert!(
        !advertised.iter().any(|t| t.starts_with("/jitter/")),
        "{advertised:?}"
    );

    move_in(&staged, &watched);
    while reader.expect("advertised")["topic"] != "/jitter/SJI_1400" {}
    let live: Vec<serde_json::Value> = indices.iter().map(|_| reader.expect("message")).collect();
    wait_for("every frame in the status file", || {
        (status_frames(&out) == indices.len() as u64).then_some(())
    });

    // A client subscribing now gets the channel's latest message, then whatever follows.
    let late = NodeClient::start(&url, &["read", "/jitter/SJI_1400"]);
    let latest = late.expect("message");

    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));
    assert!(reader.lines.try_iter().all(|l| l["event"] != "message"));
    assert!(late.lines.try_iter().all(|l| l["event"] != "message"));

    // The log is the truth: every logged frame came live, once, in order.
    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(contents.jitter.len(), indices.len());
    let log_times = |messages: &[&serde_json::Value]| -> Vec<String> {
        messages
            .iter()
            .map(|m| m["logTime"].as_str().unwrap().to_string())
            .collect()
    };
    let logged: Vec<String> = contents
        .jitter
        .iter()
        .map(|m| m.log_time_ns.to_string())
        .collect();
    assert_eq!(log_times(&live.iter().collect::<Vec<_>>()), logged);
    for (m, logged) in live.iter().zip(&contents.jitter) {
        let decoded: sunjitter_core::record::FrameAlignment =
            serde_json::from_value(m["payload"].clone()).unwrap();
        assert_eq!(decoded, logged.record);
    }
    assert_eq!(log_times(&[&latest]), logged[logged.len() - 1..]);
}

/// A daemon serving the live view with `extra` configuration, its `ws://` address, and the
/// output directory (inside `tmp`).
fn live_daemon(tmp: &std::path::Path, extra: &str) -> (Daemon, String, std::path::PathBuf) {
    let (watched, out) = (tmp.join("in"), tmp.join("out"));
    std::fs::create_dir_all(&watched).unwrap();
    let config = tmp.join("sunjitter.toml");
    std::fs::write(&config, format!("{CONFIG}\n{extra}")).unwrap();
    let mut daemon = Daemon::start(&watched, &out, &config, &["--live", "127.0.0.1:0"]);
    let url = live_url(&daemon.expect_stderr(&["live view", "ws://127.0.0.1:"]));
    // Running (and so handling SIGTERM), not just serving.
    daemon.expect_stderr(&["watching"]);
    (daemon, url, out)
}

/// The daemon's `/log` entries about the live view, after it stopped.
fn live_log(daemon: Daemon, out: &std::path::Path) -> Vec<String> {
    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));
    let contents = sunjitter_io::sink::read_logs(&[out.to_path_buf()]).unwrap();
    contents
        .logs
        .into_iter()
        .filter(|m| m.entry.file == "live")
        .map(|m| m.entry.message)
        .collect()
}

#[test]
fn a_handshake_from_a_foreign_web_origin_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (daemon, url, out) = live_daemon(tmp.path(), "");
    // A page on another site, in the operator's browser: refused, three times.
    for _ in 0..3 {
        let (code, _) = ws_handshake(&url, Some("http://evil.example"));
        assert_eq!(code, 403);
    }
    // No Origin: not a browser (the Foxglove desktop app, scripts).
    let (code, _open) = ws_handshake(&url, None);
    assert_eq!(code, 101);
    // Named once on /log, and the others counted when the daemon stops.
    let log = live_log(daemon, &out);
    assert_eq!(log.len(), 2, "{log:?}");
    assert!(
        log[0].contains("\"http://evil.example\"") && log[0].contains("live.allowed_origins"),
        "{log:?}"
    );
    assert!(log[1].contains("2 more connections refused"), "{log:?}");
}

#[test]
fn configured_web_origins_are_admitted() {
    let tmp = tempfile::tempdir().unwrap();
    let (daemon, url, out) = live_daemon(
        tmp.path(),
        "[live]\nallowed_origins = [\"https://app.foxglove.dev\"]\n",
    );
    let (code, _app) = ws_handshake(&url, Some("https://app.foxglove.dev"));
    assert_eq!(code, 101);
    let (code, _) = ws_handshake(&url, Some("http://evil.example"));
    assert_eq!(code, 403);
    let (code, _desktop) = ws_handshake(&url, None);
    assert_eq!(code, 101);
    assert_eq!(live_log(daemon, &out).len(), 1);
}

#[test]
fn connections_beyond_max_clients_are_refused_and_named_once() {
    let tmp = tempfile::tempdir().unwrap();
    let (daemon, url, out) = live_daemon(tmp.path(), "[live]\nmax_clients = 2\n");
    let admitted: Vec<_> = (0..2)
        .map(|_| {
            let (code, stream) = ws_handshake(&url, None);
            assert_eq!(code, 101);
            stream
        })
        .collect();
    for _ in 0..20 {
        let (code, _) = ws_handshake(&url, None);
        assert_eq!(code, 503);
    }
    let log = live_log(daemon, &out);
    assert_eq!(log.len(), 2, "{log:?}");
    assert!(
        log[0].contains("live.max_clients = 2 clients connected"),
        "{log:?}"
    );
    assert!(log[1].contains("19 more connections refused"), "{log:?}");
    drop(admitted);
}

#[test]
fn a_missing_status_file_is_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("status")
        .arg(tmp.path())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(ExitCode::BadInput.code()));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("status.json"), "{err}");
}

#[test]
fn a_live_port_in_use_is_a_usage_error() {
    let tmp = tempfile::tempdir().unwrap();
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let watched = tmp.path().join("in");
    std::fs::create_dir_all(&watched).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("watch")
        .arg(&watched)
        .arg("--out")
        .arg(tmp.path().join("out"))
        .args(["--live", &addr])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(ExitCode::BadInput.code()));
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains(&format!("--live {addr}")), "{err}");
}

#[test]
fn a_client_offering_only_the_classic_subprotocol_is_served() {
    NodeClient::require_installed();
    let tmp = tempfile::tempdir().unwrap();
    let indices: Vec<usize> = (7..10).collect();
    let (watched, out, config, staged) = setup(tmp.path(), CONFIG, &indices);
    let mut daemon = Daemon::start(&watched, &out, &config, &["--live", "127.0.0.1:0"]);
    let url = live_url(&daemon.expect_stderr(&["live view", "ws://127.0.0.1:"]));
    // The classic name of the protocol (older Foxglove apps and @foxglove/ws-protocol users).
    let reader =
        NodeClient::start_offering(&url, &["read", "/jitter/SJI_1400"], "foxglove.websocket.v1");
    assert_eq!(reader.expect("open")["protocol"], "foxglove.websocket.v1");
    reader.expect("subscribed");
    daemon.expect_stderr(&["live: subscribed", "/jitter/SJI_1400"]);
    move_in(&staged, &watched);
    let live: Vec<serde_json::Value> = indices.iter().map(|_| reader.expect("message")).collect();
    // Offered both, a client gets the SDK's name; offered neither, it is told what is spoken.
    let ((code, _), head) =
        ws_handshake_offering(&url, None, "foxglove.websocket.v1, foxglove.sdk.v1");
    assert_eq!(code, 101);
    assert!(
        head.contains("Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n"),
        "{head}"
    );
    let ((code, mut refused), _) = ws_handshake_offering(&url, None, "foxglove.sdk.v1.1");
    assert_eq!(code, 400);
    let mut body = String::new();
    let _ = std::io::Read::read_to_string(&mut refused, &mut body);
    assert!(
        body.contains("foxglove.sdk.v1 and foxglove.websocket.v1"),
        "{body}"
    );
    let (exit, log) = daemon.terminate();
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));
    let contents = sunjitter_io::sink::read_logs(std::slice::from_ref(&out)).unwrap();
    assert_eq!(contents.jitter.len(), indices.len());
    for (m, logged) in live.iter().zip(&contents.jitter) {
        let decoded: sunjitter_core::record::FrameAlignment =
            serde_json::from_value(m["payload"].clone()).unwrap();
        assert_eq!(decoded, logged.record);
        assert_eq!(m["logTime"], logged.log_time_ns.to_string());
    }
}

/// Every `IP:PORT` written in `text`.
fn addresses(text: &str) -> Vec<String> {
    let mut found = Vec::new();
    for (i, _) in text.match_indices("127.") {
        let tail: String = text[i..]
            .chars()
            .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == ':')
            .collect();
        if tail.contains(':') && tail.split(':').nth(1).is_some_and(|p| !p.is_empty()) {
            found.push(tail.trim_end_matches(':').to_string());
        }
    }
    found
}

#[test]
fn the_live_view_listens_on_its_one_address_and_bounds_what_a_client_sends() {
    let tmp = tempfile::tempdir().unwrap();
    let (daemon, url, out) = live_daemon(tmp.path(), "[live]\nmax_clients = 2\n");
    let public = url.strip_prefix("ws://").unwrap().to_string();

    // A client sends one text message in fragments past the bound (64 KiB): the server
    // closes the connection with 1009 (RFC 6455 §7.4.1, message too big) before holding it.
    let (code, mut stream) = ws_handshake(&url, None);
    assert_eq!(code, 101);
    let masked_frame = |fin: bool, opcode: u8, payload: &[u8]| {
        let mut frame = vec![(if fin { 0x80 } else { 0 }) | opcode, 0x80 | 126];
        frame.extend_from_slice(&(payload.len() as u16).to_be_bytes());
        let mask = [1u8, 2, 3, 4];
        frame.extend_from_slice(&mask);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        frame
    };
    let piece = vec![b' '; 16 * 1024];
    use std::io::{Read, Write};
    let mut sent = 0;
    let mut closed = None;
    for k in 0..16 {
        let frame = masked_frame(false, if k == 0 { 1 } else { 0 }, &piece);
        if stream.write_all(&frame).is_err() {
            break;
        }
        sent += piece.len();
    }
    // Read the server's frames until its close frame (or the end of the connection).
    let mut bytes = Vec::new();
    let mut buf = [0u8; 4096];
    while let Ok(n) = stream.read(&mut buf) {
        if n == 0 {
            break;
        }
        bytes.extend_from_slice(&buf[..n]);
        if let Some(at) = bytes.iter().position(|b| *b == 0x88) {
            if bytes.len() >= at + 4 {
                closed = Some(u16::from_be_bytes([bytes[at + 2], bytes[at + 3]]));
                break;
            }
        }
    }
    assert_eq!(closed, Some(1009), "sent {sent} bytes; got {bytes:?}");
    drop(stream);
    // The server goes on: two clients at once (the configured maximum) are served.
    let (a, _sa) = ws_handshake(&url, None);
    let (b, _sb) = ws_handshake(&url, None);
    assert_eq!((a, b), (101, 101));

    let (exit, log) = {
        let d = daemon;
        d.terminate()
    };
    assert!(exit.success(), "daemon exit {exit:?}:\n{}", log.join("\n"));
    // One address in the daemon's log and its status: the one it serves.
    let text = log.join("\n");
    let named = addresses(&text);
    assert!(!named.is_empty(), "{text}");
    assert!(
        named.iter().all(|a| *a == public),
        "{named:?} besides {public}"
    );
    let status = std::fs::read_to_string(out.join("status.json")).unwrap();
    assert!(addresses(&status).iter().all(|a| *a == public), "{status}");
}
