//! The `watch` daemon end to end: a real directory watcher (inotify), real files written the
//! ways instruments write them, shutdown through the future passed in.
//!
//! These tests use the library's fake frames (minimal FITS files whose header carries the
//! true pointing) and an in-memory sink, so every expectation is a known truth. Synchronisation
//! is on observable progress (the pipeline's progress channel) with generous time bounds;
//! the pauses inside writers only imitate slow instruments.

mod support;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use sunjitter_core::record::FrameAlignment;
use sunjitter_io::records::{MemorySink, Record};
use sunjitter_io::sink::LogLevel;
use sunjitter_runtime::config::{ChannelConfig, Config};
use sunjitter_runtime::fake::{FakeFrame, FakeReader, TruthAligner};
use sunjitter_runtime::ingest::expand_inputs;
use sunjitter_runtime::pipeline::{parse_iso8601_utc, replay_inputs, Progress, RunParts};
use sunjitter_runtime::reference::History;
use sunjitter_runtime::reference::PolicySpec;
use tokio::sync::watch;

const S: i64 = 1_000_000_000;
const SX: f64 = 0.05;

fn cov() -> [[f64; 4]; 4] {
    let mut c = [[0.0; 4]; 4];
    c[2][2] = SX * SX;
    c[3][3] = SX * SX;
    c
}

/// The shared quick settings, with keyframes every 4 frames and broken files reported after
/// standing unchanged 0.5 s (a garbage file that starts like a FITS header reads as one still
/// being written).
fn quick_config() -> Config {
    let mut c = support::faults::quick_config();
    c.daemon.incomplete_wait_s = 0.5;
    c.reference.keyframe_every_frames = 4;
    c
}

fn frame(channel: &str, t: i64) -> FakeFrame {
    let x = t as f64;
    FakeFrame::new(
        channel,
        t * S,
        1.0 + 1e-5 * x,
        1e-5 * x,
        0.3 * (0.7 * x).sin(),
        0.02 * x,
    )
}

/// The daemon harness, with the in-memory log it writes to (unused by the real-data tests,
/// whose MCAP files are the record).
struct Daemon {
    inner: support::daemon::Daemon,
    sink: MemorySink,
}

fn start(dir: &Path, config: Config, history: History) -> Daemon {
    let sink = MemorySink::default();
    let inner = support::daemon::spawn(
        dir,
        config,
        Arc::new(FakeReader::default()),
        Arc::new(TruthAligner::from_files(cov())),
        Box::new(sink.clone()),
        history,
    );
    Daemon { inner, sink }
}

impl Daemon {
    async fn watching(&mut self) {
        self.inner.watching().await
    }

    /// Wait until `finished` inputs have been logged.
    async fn wait_finished(&mut self, finished: u64) -> Progress {
        let what = format!("{finished} inputs logged");
        self.inner.wait_for(&what, |p| p.finished >= finished).await
    }

    async fn shutdown(self) -> (Progress, Vec<Record>) {
        let progress = self.inner.shutdown().await;
        assert!(self.sink.log.lock().unwrap().finished, "the log was closed");
        (progress, self.sink.records())
    }
}

fn messages<'a>(records: &'a [Record], channel: &str) -> Vec<&'a FrameAlignment> {
    records
        .iter()
        .filter_map(|r| match r {
            Record::Frame { message, .. } if message.channel == channel => Some(message.as_ref()),
            _ => None,
        })
        .collect()
}

fn error_logs(records: &[Record]) -> Vec<(String, String)> {
    records
        .iter()
        .filter_map(|r| match r {
            Record::Log {
                level: LogLevel::Error,
                file,
                message,
                ..
            } => Some((file.clone(), message.clone())),
            _ => None,
        })
        .collect()
}

fn key(dir: &Path, name: &str) -> String {
    dir.canonicalize().unwrap().join(name).display().to_string()
}

/// Write `bytes` in place in `chunks` pieces with pauses (a slow instrument writer).
fn write_slowly(path: &Path, bytes: &[u8], chunks: usize) {
    use std::io::Write;
    let mut f = std::fs::File::create(path).unwrap();
    for piece in bytes.chunks(bytes.len().div_ceil(chunks)) {
        f.write_all(piece).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(40));
    }
}

/// Publish atomically: write under a temporary name, then rename into place.
fn write_renamed(dir: &Path, name: &str, bytes: &[u8], temp: &str) {
    let tmp = dir.join(temp);
    std::fs::write(&tmp, bytes).unwrap();
    std::fs::rename(tmp, dir.join(name)).unwrap();
}

/// Every way a frame can arrive, one garbage file, then shutdown: each frame logged
/// exactly once, in time order, with the true chained pointing; one /log entry for the garbage.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watch_takes_each_complete_frame_once_in_time_order() {
    let dir = tempfile::tempdir().unwrap();
    let staging = tempfile::tempdir_in(dir.path().parent().unwrap()).unwrap();
    let watched = dir.path();
    // Two frames are there before the daemon starts (the start scan takes them).
    for t in 0..2 {
        std::fs::write(
            watched.join(format!("f{t:02}.fits")),
            frame("A", t).to_fits(),
        )
        .unwrap();
    }
    let mut daemon = start(watched, quick_config(), History::default());
    daemon.watching().await;
    let n = 12;
    for t in 2..n {
        let name = format!("f{t:02}.fits");
        let bytes = frame("A", t).to_fits();
        match t % 4 {
            0 => write_slowly(&watched.join(&name), &bytes, 4),
            1 => write_renamed(watched, &name, &bytes, &format!(".{name}.tmp")),
            2 => write_renamed(watched, &name, &bytes, &format!("{name}.part")),
            _ => {
                // Moved in from another directory: no close-after-write event here.
                let outside = staging.path().join(&name);
                std::fs::write(&outside, &bytes).unwrap();
                std::fs::rename(&outside, watched.join(&name)).unwrap();
            }
        }
        if t == 6 {
            std::fs::write(watched.join("garbage.fits"), b"this is not FITS").unwrap();
        }
    }
    daemon.wait_finished(n as u64 + 1).await;
    let (progress, records) = daemon.shutdown().await;

    let msgs = messages(&records, "A");
    assert_eq!(msgs.len(), n as usize, "one message per frame");
    let times: Vec<i64> = msgs
        .iter()
        .map(|m| parse_iso8601_utc(&m.obs_time).unwrap())
        .collect();
    assert_eq!(
        times,
        (0..n).map(|t| t * S).collect::<Vec<_>>(),
        "time order"
    );
    for (t, m) in msgs.iter().enumerate() {
        assert_eq!(m.sequence, t as u64);
        assert_eq!(m.align.frame, key(watched, &format!("f{t:02}.fits")));
        // Chained pointing = the injected pointing relative to frame 0.
        let truth = frame("A", t as i64)
            .truth
            .after(&frame("A", 0).truth.inverse());
        assert!(
            (m.chained_dx_px.unwrap() - truth.dx).abs() < 1e-9,
            "frame {t}"
        );
        assert!(
            (m.chained_dy_px.unwrap() - truth.dy).abs() < 1e-9,
            "frame {t}"
        );
        assert_eq!(
            m.reference_kind == sunjitter_core::record::ReferenceKind::Itself,
            t % 4 == 0,
            "keyframes every 4 frames"
        );
    }
    let errors = error_logs(&records);
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert_eq!(errors[0].0, key(watched, "garbage.fits"));
    assert!(errors[0].1.contains("not a FITS file"), "{}", errors[0].1);
    assert_eq!((progress.frames, progress.skipped), (n as u64, 1));
}

/// A burst larger than every queue: back-pressure, never a drop or a double.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_larger_than_the_queues_is_taken_completely() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = quick_config();
    config.daemon.queue_capacity = 2;
    config.daemon.readers = 1;
    let mut daemon = start(dir.path(), config, History::default());
    daemon.watching().await;
    let n = 150;
    for t in 0..n {
        let name = format!("b{t:03}.fits");
        write_renamed(
            dir.path(),
            &name,
            &frame("B", t).to_fits(),
            &format!("{name}.tmp"),
        );
    }
    daemon.wait_finished(n as u64).await;
    let (_, records) = daemon.shutdown().await;
    let msgs = messages(&records, "B");
    let mut count: BTreeMap<&str, usize> = BTreeMap::new();
    for m in &msgs {
        *count.entry(m.align.frame.as_str()).or_default() += 1;
    }
    assert_eq!(count.len(), n as usize);
    assert!(count.values().all(|c| *c == 1));
    assert!(error_logs(&records).is_empty());
}

/// Stop uncleanly half-way (the log lost its unflushed tail), restart: every frame exactly
/// once across both runs, and the resumed series continues the first one.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn restart_after_a_crash_logs_every_frame_exactly_once() {
    let dir = tempfile::tempdir().unwrap();
    let n = 16;
    for t in 0..n {
        std::fs::write(
            dir.path().join(format!("r{t:02}.fits")),
            frame("R", t).to_fits(),
        )
        .unwrap();
    }
    let mut config = quick_config();
    config.daemon.settle_s = 0.0;
    let mut first = start(dir.path(), config.clone(), History::default());
    first.wait_finished(6).await;
    let (_, first_records) = first.shutdown().await;
    // The crash: only what reached the disk survives, cut after the 5th frame message.
    let cut = first_records
        .iter()
        .enumerate()
        .filter(|(_, r)| matches!(r, Record::Frame { .. }))
        .nth(4)
        .map(|(i, _)| i)
        .unwrap();
    let survived = &first_records[..=cut];
    let mut history = History::default();
    for r in survived {
        history.add(r);
    }
    let mut second = start(dir.path(), config, history);
    second.wait_finished(n as u64 - 5).await;
    let (progress, second_records) = second.shutdown().await;
    assert_eq!(progress.frames, n as u64 - 5, "only the frames not logged");
    let mut all: Vec<&FrameAlignment> = messages(survived, "R");
    all.extend(messages(&second_records, "R"));
    let keys: Vec<String> = all.iter().map(|m| m.align.frame.clone()).collect();
    let expected: Vec<String> = (0..n)
        .map(|t| key(dir.path(), &format!("r{t:02}.fits")))
        .collect();
    assert_eq!(
        keys, expected,
        "every frame once, in order, across the two runs"
    );
    assert_eq!(
        all.iter().map(|m| m.sequence).collect::<Vec<_>>(),
        (0..n as u64).collect::<Vec<_>>(),
        "sequence numbers continue"
    );
    for (t, m) in all.iter().enumerate() {
        let truth = frame("R", t as i64)
            .truth
            .after(&frame("R", 0).truth.inverse());
        assert!(
            (m.chained_dx_px.unwrap() - truth.dx).abs() < 1e-9,
            "frame {t}"
        );
    }
}

/// Replay over the files the daemon took writes the same records (publish times aside),
/// including a channel aligned to another (`channel:A`) and a garbage file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_writes_what_the_daemon_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let mut config = quick_config();
    config.reference.hold_s = 0.5;
    config.reference.tolerance_s = 4.0;
    config.channels.insert(
        "C".into(),
        ChannelConfig {
            policy: Some(PolicySpec::Channel("A".into())),
            ..Default::default()
        },
    );
    let mut daemon = start(dir.path(), config.clone(), History::default());
    daemon.watching().await;
    let mut inputs = 0;
    for t in 0..10 {
        // A every 10 s; C at 10 s + 3 s (nearest A: the same step), the last C with no A near.
        write_renamed(
            dir.path(),
            &format!("a{t}.fits"),
            &frame("A", 10 * t).to_fits(),
            "x.tmp",
        );
        // Each C frame arrives once its A frame is logged (and the C frame before it, which
        // that A frame releases): otherwise, on a loaded machine, a C frame read before its A
        // frame with the A channel quiet for `hold_s` is rightly left unmatched.
        daemon.wait_finished(inputs + 1).await;
        write_renamed(
            dir.path(),
            &format!("c{t}.fits"),
            &frame("C", 10 * t + 3).to_fits(),
            "x.tmp",
        );
        inputs += 2;
    }
    write_renamed(
        dir.path(),
        "c_late.fits",
        &frame("C", 200).to_fits(),
        "x.tmp",
    );
    std::fs::write(dir.path().join("junk.fits"), b"junk").unwrap();
    inputs += 2;
    daemon.wait_finished(inputs).await;
    let (_, watched) = daemon.shutdown().await;
    assert_eq!(messages(&watched, "C").len(), 10);
    let errors = error_logs(&watched);
    assert_eq!(errors.len(), 2, "{errors:?}");
    assert!(errors
        .iter()
        .any(|(f, m)| f.ends_with("c_late.fits") && m.contains("unmatched")));

    let config = Arc::new(config);
    let files = expand_inputs(&[dir.path().display().to_string()], &config).unwrap();
    let reader = FakeReader::default();
    let inputs = replay_inputs(&files, &config, &reader, &History::default());
    let sink = MemorySink::default();
    let parts = RunParts {
        config: config.clone(),
        reader: Arc::new(reader),
        aligner: Arc::new(TruthAligner::from_files(cov())),
        sink: Box::new(sink.clone()),
        history: History::default(),
        progress: watch::channel(Progress::default()).0,
        live: false,
        products: None,
    };
    sunjitter_runtime::pipeline::run_replay(inputs, parts, std::future::pending())
        .await
        .unwrap();
    let replayed = sink.records();
    let sorted = |mut r: Vec<Record>| {
        r.sort_by_key(|r| (r.topic(), r.log_time_ns(), format!("{r:?}")));
        r
    };
    assert_eq!(sorted(watched), sorted(replayed));
}

// =============================================================================================
// Real frames, real MCAP: IRIS slit-jaw sequences split into per-frame files, the MCAP sink,
// and the log read back with the official `mcap` crate.

mod real {
    use super::*;
    use sunjitter_runtime::fake::{split_cube, SplitFrame};

    use sunjitter_io::records::RecordSink;
    use sunjitter_runtime::pipeline::{open_output, EngineAligner, FitsReader};

    pub const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
    pub const SJI_2796: &str =
        "data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";

    pub fn real_config() -> Config {
        let mut c = quick_config();
        c.reference.keyframe_every_frames = 10;
        c.sink.flush_every_frames = 5;
        c
    }

    /// One message as the official reader sees it.
    #[derive(Debug, Clone)]
    pub struct Read {
        pub topic: String,
        pub schema: String,
        pub schema_encoding: String,
        pub message_encoding: String,
        pub log_time: u64,
        pub json: serde_json::Value,
    }

    /// Read every segment in `out` (name order) with the `mcap` crate. Each must be a
    /// finished file (summary present). Returns the messages and the metadata records.
    pub fn read_mcap(out: &Path) -> (Vec<Read>, Vec<std::collections::BTreeMap<String, String>>) {
        let mut files: Vec<_> = std::fs::read_dir(out)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
            .collect();
        files.sort();
        assert!(!files.is_empty(), "no segment in {}", out.display());
        let mut messages = Vec::new();
        let mut metadata = Vec::new();
        for file in files {
            let bytes = std::fs::read(&file).unwrap();
            assert!(
                mcap::read::Summary::read(&bytes).unwrap().is_some(),
                "{} has a summary",
                file.display()
            );
            for m in mcap::MessageStream::new(&bytes).unwrap() {
                let m = m.unwrap();
                let schema = m.channel.schema.as_ref().unwrap();
                messages.push(Read {
                    topic: m.channel.topic.clone(),
                    schema: schema.name.clone(),
                    schema_encoding: schema.encoding.clone(),
                    message_encoding: m.channel.message_encoding.clone(),
                    log_time: m.log_time,
                    json: serde_json::from_slice(&m.data).unwrap(),
                });
            }
            for record in mcap::read::LinearReader::new(&bytes).unwrap() {
                if let mcap::records::Record::Metadata(md) = record.unwrap() {
                    assert_eq!(md.name, "sunjitter");
                    metadata.push(md.metadata);
                }
            }
        }
        (messages, metadata)
    }

    pub fn on<'a>(messages: &'a [Read], topic: &str) -> Vec<&'a Read> {
        messages.iter().filter(|m| m.topic == topic).collect()
    }

    /// A daemon on real FITS frames writing MCAP into `out`.
    pub fn start_real(dir: &Path, out: &Path, config: Config, crash: bool) -> Daemon {
        let (sink, history) = if crash {
            let sink = sunjitter_io::sink::McapSink::new(
                out,
                config.sink.clone(),
                config.to_json().to_string(),
            )
            .unwrap();
            let history = sunjitter_runtime::pipeline::read_history(out).unwrap();
            (Box::new(Crash(sink)) as Box<dyn RecordSink>, history)
        } else {
            open_output(out, &config).unwrap()
        };
        Daemon {
            inner: support::daemon::spawn(
                dir,
                config.clone(),
                Arc::new(FitsReader::default()),
                Arc::new(EngineAligner::new(config.engine.clone())),
                sink,
                history,
            ),
            sink: MemorySink::default(),
        }
    }

    /// An MCAP sink that, instead of closing cleanly, loses its unflushed tail and leaves its
    /// segment unfinished, like a killed process.
    struct Crash(sunjitter_io::sink::McapSink);

    impl RecordSink for Crash {
        fn write(&mut self, r: &Record, t: i64) -> sunjitter_core::error::Result<()> {
            sunjitter_io::records::McapRecordSink::write_to(&mut self.0, r, t)
        }
        fn flush(&mut self) -> sunjitter_core::error::Result<()> {
            self.0.flush()
        }
        fn finish(self: Box<Self>) -> sunjitter_core::error::Result<()> {
            self.0.abandon();
            Ok(())
        }
    }

    pub async fn stop_real(daemon: Daemon) -> Progress {
        daemon.inner.shutdown().await
    }

    pub fn frames(cube: &str, scratch: &Path) -> Vec<SplitFrame> {
        split_cube(Path::new(cube), scratch).unwrap()
    }
}

use real::*;

/// The main daemon test: real SJI 1400 frames arriving every way an instrument
/// writes them, one garbage file, shutdown, and the MCAP read back with the `mcap` crate.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_frames_are_logged_once_each_in_time_order_to_mcap() {
    let scratch = tempfile::tempdir().unwrap();
    let frames = real::frames(SJI_1400, scratch.path());
    assert_eq!(frames.len(), 54);
    let dir = tempfile::tempdir().unwrap();
    let out = tempfile::tempdir().unwrap();
    let watched = dir.path();
    for f in &frames[..3] {
        std::fs::write(watched.join(&f.name), &f.bytes).unwrap();
    }
    let mut daemon = start_real(watched, out.path(), real_config(), false);
    daemon.watching().await;
    for (i, f) in frames.iter().enumerate().skip(3) {
        match i % 3 {
            0 => write_slowly(&watched.join(&f.name), &f.bytes, 3),
            1 => write_renamed(watched, &f.name, &f.bytes, &format!(".{}.tmp", f.name)),
            _ => write_renamed(watched, &f.name, &f.bytes, &format!("{}.part", f.name)),
        }
        if i == 20 {
            std::fs::write(watched.join("garbage.fits"), b"SIMPLE  = this is not FITS").unwrap();
        }
    }
    daemon.wait_finished(55).await;
    let progress = stop_real(daemon).await;
    assert_eq!((progress.frames, progress.skipped), (54, 1));

    let (messages, metadata) = read_mcap(out.path());
    let jitter = on(&messages, "/jitter/SJI_1400");
    assert_eq!(jitter.len(), 54, "exactly one message per frame");
    let expected_keys: Vec<String> = frames.iter().map(|f| key(watched, &f.name)).collect();
    let keys: Vec<&str> = jitter
        .iter()
        .map(|m| m.json["frame"].as_str().unwrap())
        .collect();
    assert_eq!(
        keys, expected_keys,
        "every frame once, in observation-time order"
    );
    for (i, (m, f)) in jitter.iter().zip(&frames).enumerate() {
        // The split files carry DATE-OBS to the millisecond (rounded).
        let obs_ms = (f.obs_time_ns + 500_000).div_euclid(1_000_000);
        assert_eq!(
            m.log_time,
            obs_ms as u64 * 1_000_000,
            "log_time = observation time"
        );
        assert_eq!(m.json["sequence"], i as u64);
        assert_eq!(
            (m.schema.as_str(), m.schema_encoding.as_str()),
            ("sunjitter.FrameAlignment", "jsonschema")
        );
        assert_eq!(m.message_encoding, "json");
        let object = m.json.as_object().unwrap();
        for field in &support::jitter_fields() {
            assert!(object.contains_key(*field), "message {i} lacks `{field}`");
        }
        assert_eq!(m.json["channel"], "SJI_1400");
        assert_eq!(
            parse_iso8601_utc(m.json["obs_time"].as_str().unwrap()).unwrap(),
            m.log_time as i64,
            "obs_time is the ISO form of log_time"
        );
    }
    assert_eq!(jitter[0].json["reference_kind"], "self");
    let logs: Vec<&Read> = on(&messages, "/log")
        .into_iter()
        .filter(|m| m.json["level"] == 4)
        .collect();
    assert_eq!(logs.len(), 1, "{logs:?}");
    assert_eq!(logs[0].json["file"], key(watched, "garbage.fits"));
    assert!(!on(&messages, "/reference/SJI_1400").is_empty());
    // The metadata record holds the version and the effective configuration.
    let config: serde_json::Value = serde_json::from_str(&metadata[0]["config"]).unwrap();
    assert_eq!(config["reference"]["keyframe_every_frames"], 10);
    assert_eq!(metadata[0]["version"], env!("CARGO_PKG_VERSION"));
}

/// SJI 2796 aligned to SJI 1400 (`channel:SJI_1400`): every 2796 frame is logged against the
/// SJI 1400 frame nearest in time (computed here from the frames' own times).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_cross_channel_frames_use_the_nearest_partner() {
    let scratch = tempfile::tempdir().unwrap();
    let a = real::frames(SJI_1400, &scratch.path().join("a"));
    let b = real::frames(SJI_2796, &scratch.path().join("b"));
    let dir = tempfile::tempdir().unwrap();
    let out = tempfile::tempdir().unwrap();
    let mut config = real_config();
    config.reference.hold_s = 2.0;
    config.channels.insert(
        "SJI_2796".into(),
        ChannelConfig {
            policy: Some(PolicySpec::Channel("SJI_1400".into())),
            tolerance_s: Some(150.0),
            ..Default::default()
        },
    );
    let mut daemon = start_real(dir.path(), out.path(), config, false);
    daemon.watching().await;
    let mut all: Vec<&sunjitter_runtime::fake::SplitFrame> = a.iter().chain(&b).collect();
    all.sort_by_key(|f| f.obs_time_ns);
    for f in &all {
        write_renamed(dir.path(), &f.name, &f.bytes, "incoming.tmp");
    }
    daemon.wait_finished(all.len() as u64).await;
    stop_real(daemon).await;

    let (messages, _) = read_mcap(out.path());
    let follower = on(&messages, "/jitter/SJI_2796");
    let logs: Vec<_> = on(&messages, "/log")
        .iter()
        .map(|m| m.json.clone())
        .collect();
    assert_eq!(follower.len(), b.len(), "{logs:#?}");
    assert_eq!(on(&messages, "/jitter/SJI_1400").len(), a.len());
    for (m, f) in follower.iter().zip(&b) {
        let nearest = a
            .iter()
            .min_by_key(|p| ((p.obs_time_ns - f.obs_time_ns).abs(), p.obs_time_ns))
            .unwrap();
        assert!((nearest.obs_time_ns - f.obs_time_ns).abs() <= 150 * S);
        assert_eq!(m.json["reference_kind"], "channel");
        assert_eq!(
            m.json["reference"],
            key(dir.path(), &nearest.name),
            "frame {}",
            f.name
        );
    }
    let changes = on(&messages, "/reference/SJI_2796");
    assert!(changes.iter().all(|c| c.json["reason"]
        .as_str()
        .unwrap()
        .contains("nearest SJI_1400")));
}

/// Kill-and-restart: the first run dies after some frames (its unflushed tail is lost, its
/// segment unfinished); the restart recovers the segment and logs the rest: across all
/// segments every frame exactly once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_restart_after_a_crash_logs_every_frame_exactly_once() {
    let scratch = tempfile::tempdir().unwrap();
    let frames = real::frames(SJI_1400, scratch.path());
    let dir = tempfile::tempdir().unwrap();
    let out = tempfile::tempdir().unwrap();
    for f in &frames {
        std::fs::write(dir.path().join(&f.name), &f.bytes).unwrap();
    }
    let mut config = real_config();
    config.daemon.settle_s = 0.0;
    config.daemon.workers = 1;
    let mut first = start_real(dir.path(), out.path(), config.clone(), true);
    first.wait_finished(20).await;
    stop_real(first).await;

    let history = sunjitter_runtime::pipeline::read_history(out.path()).unwrap();
    let survived = history.done.len();
    assert!(survived < 54, "the crash lost the rest");
    let mut second = start_real(dir.path(), out.path(), config, false);
    second.wait_finished((54 - survived) as u64).await;
    let progress = stop_real(second).await;
    assert_eq!(
        progress.frames as usize,
        54 - survived,
        "only frames not in the log"
    );

    let (messages, _) = read_mcap(out.path());
    let jitter = on(&messages, "/jitter/SJI_1400");
    let keys: Vec<&str> = jitter
        .iter()
        .map(|m| m.json["frame"].as_str().unwrap())
        .collect();
    let expected: Vec<String> = frames.iter().map(|f| key(dir.path(), &f.name)).collect();
    assert_eq!(
        keys, expected,
        "every frame exactly once across the segments, in order"
    );
    let sequences: Vec<u64> = jitter
        .iter()
        .map(|m| m.json["sequence"].as_u64().unwrap())
        .collect();
    assert_eq!(sequences, (0..54).collect::<Vec<u64>>());
}

/// At most `[daemon] max_channels` channels are tracked: each frame of a channel beyond them
/// is named on `/log` and not measured; the tracked channels lose nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_of_a_channel_beyond_the_cap_are_named_not_measured() {
    let dir = tempfile::tempdir().unwrap();
    let watched = dir.path();
    for channel in ["A", "B", "C"] {
        for t in 0..3 {
            std::fs::write(
                watched.join(format!("{channel}{t}.fits")),
                frame(channel, t).to_fits(),
            )
            .unwrap();
        }
    }
    let mut config = quick_config();
    config.daemon.max_channels = 2;
    let mut daemon = start(watched, config, History::default());
    daemon.watching().await;
    daemon.wait_finished(9).await;
    let (_, records) = daemon.shutdown().await;

    let counts: Vec<usize> = ["A", "B", "C"]
        .iter()
        .map(|c| messages(&records, c).len())
        .collect();
    let mut sorted = counts.clone();
    sorted.sort();
    assert_eq!(sorted, [0, 3, 3], "two channels measured whole: {counts:?}");
    let refused = ["A", "B", "C"][counts.iter().position(|&n| n == 0).unwrap()];
    let mut errors = error_logs(&records);
    errors.sort();
    let expected: Vec<String> = (0..3)
        .map(|t| key(watched, &format!("{refused}{t}.fits")))
        .collect();
    assert_eq!(
        errors.iter().map(|e| e.0.clone()).collect::<Vec<_>>(),
        expected
    );
    for (_, message) in &errors {
        assert!(
            message.contains(&format!(
                "channel {refused}: 2 channels are tracked already"
            )),
            "{message}"
        );
    }
}
