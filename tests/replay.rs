//! `sunjitter replay` end to end: the binary over the bundled IRIS slit-jaw cubes, resuming
//! into an existing output, the same messages as the daemon, and usage errors.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use sunjitter_core::error::ExitCode;
use sunjitter_runtime::config::{Config, Overrides};
use sunjitter_runtime::fake::split_cube;
use sunjitter_runtime::pipeline::{open_output, EngineAligner, FitsReader};

mod support;

use support::sunjitter;

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2796: &str =
    "data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";

/// Quick daemon settings and the bundled pair: SJI 2796 follows SJI 1400.
const CONFIG: &str = r#"
[daemon]
settle_s = 0.1
reorder_window_s = 0.3
flush_interval_s = 0.2
[reference]
keyframe_every_frames = 10
hold_s = 2.0
[channels.SJI_2796]
policy = "channel:SJI_1400"
tolerance_s = 150.0
"#;

#[derive(Debug, Clone, PartialEq)]
struct Msg {
    topic: String,
    log_time: u64,
    json: serde_json::Value,
}

/// Every message of every segment in `out`, read with the `mcap` crate (finished files only).
fn read_mcap(out: &Path) -> (Vec<Msg>, Vec<serde_json::Value>) {
    let mut files: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    files.sort();
    let mut messages = Vec::new();
    let mut configs = Vec::new();
    for file in files {
        let bytes = std::fs::read(&file).unwrap();
        assert!(mcap::read::Summary::read(&bytes).unwrap().is_some());
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            messages.push(Msg {
                topic: m.channel.topic.clone(),
                log_time: m.log_time,
                json: serde_json::from_slice(&m.data).unwrap(),
            });
        }
        for record in mcap::read::LinearReader::new(&bytes).unwrap() {
            match record.unwrap() {
                mcap::records::Record::Metadata(md) if md.name == "sunjitter" => {
                    configs.push(serde_json::from_str(&md.metadata["config"]).unwrap());
                }
                _ => {}
            }
        }
    }
    (messages, configs)
}

fn on<'a>(messages: &'a [Msg], topic: &str) -> Vec<&'a Msg> {
    messages.iter().filter(|m| m.topic == topic).collect()
}

fn canonical(path: &str) -> String {
    std::fs::canonicalize(path).unwrap().display().to_string()
}

#[test]
fn replay_of_the_iris_cubes_logs_every_frame_once_in_time_order() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("c.toml");
    std::fs::write(&config, CONFIG).unwrap();
    let out = tmp.path().join("out");
    let (code, stdout, stderr) = sunjitter(&[
        "replay",
        SJI_2796,
        SJI_1400,
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--json",
    ]);
    let summary: serde_json::Value = serde_json::from_str(&stdout).expect(&stderr);
    let (messages, configs) = read_mcap(&out);

    // astropy: NAXIS3 = 54 (SJI 1400) and 72 (SJI 2796).
    for (topic, cube, n) in [
        ("/jitter/SJI_1400", SJI_1400, 54),
        ("/jitter/SJI_2796", SJI_2796, 72),
    ] {
        let msgs = on(&messages, topic);
        let frames: Vec<&str> = msgs
            .iter()
            .map(|m| m.json["frame"].as_str().unwrap())
            .collect();
        let expected: Vec<String> = (0..n)
            .map(|i| format!("{}[{i}]", canonical(cube)))
            .collect();
        assert_eq!(frames, expected, "{topic}: every frame once, in time order");
        assert!(msgs.windows(2).all(|w| w[0].log_time < w[1].log_time));
        let seq: Vec<u64> = msgs
            .iter()
            .map(|m| m.json["sequence"].as_u64().unwrap())
            .collect();
        assert_eq!(seq, (0..n as u64).collect::<Vec<_>>());
        assert_eq!(summary["channels"][&topic[8..]], n);
    }
    // Cross-channel: every SJI 2796 frame is aligned to an SJI 1400 frame.
    let sji_1400 = canonical(SJI_1400);
    for m in on(&messages, "/jitter/SJI_2796") {
        assert_eq!(m.json["reference_kind"], "channel");
        assert!(m.json["reference"].as_str().unwrap().starts_with(&sji_1400));
    }
    assert_eq!(
        on(&messages, "/jitter/SJI_1400")[0].json["reference_kind"],
        "self"
    );
    // The summary agrees with the log; exit code 1 only if no frame gave a measurement.
    assert_eq!(summary["frames"], 126);
    let measured = summary["ok"].as_u64().unwrap() + summary["degraded"].as_u64().unwrap();
    assert!(measured > 0);
    assert_eq!(code, ExitCode::Ok.code(), "{stderr}");
    assert_eq!(
        configs[0]["channels"]["SJI_2796"]["policy"],
        "channel:SJI_1400"
    );
    assert_eq!(configs[0]["reference"]["keyframe_every_frames"], 10);

    // /reference names its reference by `file` and the cube index `cube_frame` (an integer;
    // `frame` is a frame's name, a string, on every topic that has one).
    let changes = on(&messages, "/reference/SJI_1400");
    assert!(!changes.is_empty());
    for c in &changes {
        assert!(c.json["cube_frame"].is_u64(), "{}", c.json);
        assert!(c.json.get("frame").is_none(), "{}", c.json);
    }
    // The chained series in arcsec: the px ones times the plate scale of the chain's origin
    // (SJI 1400 frame 0: its header's 0.16635″/px, astropy; no disk to check it against).
    // The SJI 2796 frames continue SJI 1400's chain.
    for m in messages.iter().filter(|m| m.topic.starts_with("/jitter/")) {
        for (px, arcsec) in [
            ("chained_dx_px", "chained_dx_arcsec"),
            ("chained_dy_px", "chained_dy_arcsec"),
            ("sigma_chained_dx_px", "sigma_chained_dx_arcsec"),
            ("sigma_chained_dy_px", "sigma_chained_dy_arcsec"),
        ] {
            match (m.json[px].as_f64(), m.json[arcsec].as_f64()) {
                (Some(p), Some(a)) => {
                    assert!(
                        (a - 0.16635 * p).abs() <= 1e-9 * (1.0 + a.abs()),
                        "{}",
                        m.json
                    )
                }
                (None, None) => {}
                _ => panic!("{px} and {arcsec} disagree on null: {}", m.json),
            }
        }
    }
}

#[test]
fn replay_of_nothing_but_garbage_exits_1() {
    // The run works (the garbage is logged on /log) but measures nothing: exit code 1.
    let tmp = tempfile::tempdir().unwrap();
    let junk = tmp.path().join("junk.fits");
    std::fs::write(&junk, b"not FITS").unwrap();
    let out = tmp.path().join("out");
    let (code, stdout, _) = sunjitter(&[
        "replay",
        junk.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    let summary: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(
        (code, summary["skipped"].as_u64()),
        (ExitCode::Failed.code(), Some(1))
    );
    let (messages, _) = read_mcap(&out);
    let logs = on(&messages, "/log");
    assert_eq!(logs.len(), 1);
    assert_eq!(
        logs[0].json["file"],
        junk.canonicalize().unwrap().display().to_string()
    );
}

#[test]
fn replay_into_an_existing_log_adds_only_frames_not_yet_logged() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    let (_, first, _) = sunjitter(&["replay", SJI_1400, "--out", out_s, "--json"]);
    let (_, second, _) = sunjitter(&["replay", SJI_1400, "--out", out_s, "--json"]);
    let first: serde_json::Value = serde_json::from_str(&first).unwrap();
    let second: serde_json::Value = serde_json::from_str(&second).unwrap();
    assert_eq!(
        (first["frames"].as_u64(), second["frames"].as_u64()),
        (Some(54), Some(0))
    );
    let (messages, _) = read_mcap(&out);
    assert_eq!(on(&messages, "/jitter/SJI_1400").len(), 54, "nothing twice");
}

#[test]
fn usage_errors_exit_2_naming_the_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let out_s = out.to_str().unwrap();
    let (code, _, err) = sunjitter(&["replay", "no/such/file.fits", "--out", out_s]);
    assert_eq!(code, ExitCode::BadInput.code());
    assert!(
        err.contains("no/such/file.fits") && err.contains("no such file"),
        "{err}"
    );
    let (code, _, err) = sunjitter(&[
        "replay",
        SJI_1400,
        "--out",
        out_s,
        "--reference",
        "sometimes",
    ]);
    assert_eq!(code, ExitCode::BadInput.code());
    assert!(err.contains("sometimes"), "{err}");
    let bad = tmp.path().join("bad.toml");
    std::fs::write(&bad, "[daemon]\nworkerz = 2\n").unwrap();
    let (code, _, err) = sunjitter(&[
        "replay",
        SJI_1400,
        "--out",
        out_s,
        "--config",
        bad.to_str().unwrap(),
    ]);
    assert_eq!(code, ExitCode::BadInput.code());
    assert!(err.contains("bad.toml") && err.contains("workerz"), "{err}");
    let (code, _, err) = sunjitter(&["watch", ".", "--out", out_s, "--live", "8765"]);
    assert_eq!(code, ExitCode::BadInput.code());
    assert!(err.contains("expected ADDR:PORT"), "{err}");
    assert!(!out.exists(), "nothing was written");
}

/// The daemon on real split frames, then `replay` of the same files: the same messages
/// (apart from publish times and the engine's own timing, `elapsed_ms`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_writes_what_watch_wrote_for_the_same_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let config_path = tmp.path().join("c.toml");
    std::fs::write(&config_path, CONFIG).unwrap();
    let watched = tmp.path().join("in");
    std::fs::create_dir(&watched).unwrap();
    let mut frames = split_cube(Path::new(SJI_1400), &tmp.path().join("s1")).unwrap();
    frames.extend(split_cube(Path::new(SJI_2796), &tmp.path().join("s2")).unwrap());
    frames.sort_by_key(|f| f.obs_time_ns);
    frames.truncate(60);

    let config = Config::load(Some(&config_path), &Overrides::default()).unwrap();
    let out_watch = tmp.path().join("watch");
    let (sink, history) = open_output(&out_watch, &config).unwrap();
    let daemon = support::daemon::spawn(
        &watched,
        config.clone(),
        Arc::new(FitsReader::default()),
        Arc::new(EngineAligner::new(config.engine.clone())),
        sink,
        history,
    );
    daemon.watching().await;
    // Frames arrive in time order, as from an instrument: each one reaches the scheduler
    // before the next is written, so the daemon sees the order `replay` reads.
    for (k, f) in frames.iter().enumerate() {
        let tmp_name = watched.join(format!(".{}.tmp", f.name));
        std::fs::write(&tmp_name, &f.bytes).unwrap();
        std::fs::rename(&tmp_name, watched.join(&f.name)).unwrap();
        let seen = k as u64 + 1;
        daemon
            .wait_for("the frame to reach the scheduler", |p| {
                p.queued_per_channel.values().sum::<u64>() + p.finished >= seen
            })
            .await;
    }
    let n = frames.len() as u64;
    daemon.wait_for("every frame", |p| p.finished >= n).await;
    daemon.shutdown().await;

    let out_replay = tmp.path().join("replay");
    let (_, stdout, stderr) = sunjitter(&[
        "replay",
        watched.to_str().unwrap(),
        "--out",
        out_replay.to_str().unwrap(),
        "--config",
        config_path.to_str().unwrap(),
        "--json",
    ]);
    let summary: serde_json::Value = serde_json::from_str(&stdout).expect(&stderr);
    assert_eq!(summary["frames"], n);

    let comparable = |out: &Path| {
        let (messages, _) = read_mcap(out);
        let mut v: Vec<(String, u64, String)> = messages
            .into_iter()
            .map(|mut m| {
                if let Some(o) = m.json.as_object_mut() {
                    o.remove("elapsed_ms");
                }
                (m.topic, m.log_time, m.json.to_string())
            })
            .collect();
        v.sort();
        v
    };
    let (w, r) = (comparable(&out_watch), comparable(&out_replay));
    assert_eq!(w.len(), r.len());
    for (a, b) in w.iter().zip(&r) {
        assert_eq!(a, b);
    }
}
