//! The `watch` daemon end to end: a real directory watcher (inotify), real files written the
//! ways instruments write them, shutdown through the future passed in.
//!
//! These tests use the library's fake frames (minimal FITS files whose header carries the
//! true pointing) and an in-memory sink, so every expectation is a known truth. Synchronisation
//! is on observable progress (the pipeline's progress channel) with generous time bounds;
//! the pauses inside writers only imitate slow instruments.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;
use sunjitter::config::{ChannelConfig, Config};
use sunjitter::pipeline::fake::{FakeFrame, FakeReader, TruthAligner};
use sunjitter::pipeline::{
    expand_inputs, parse_iso8601_utc, replay_inputs, History, LogLevel, MemorySink, Progress,
    Record, RunParts,
};
use sunjitter::reference::PolicySpec;
use sunjitter::FrameAlignment;
use tokio::sync::{oneshot, watch};

const S: i64 = 1_000_000_000;
const SX: f64 = 0.05;

fn cov() -> [[f64; 4]; 4] {
    let mut c = [[0.0; 4]; 4];
    c[2][2] = SX * SX;
    c[3][3] = SX * SX;
    c
}

/// Settings that keep the tests quick (defaults are for real instruments).
fn quick_config() -> Config {
    let mut c = Config::default();
    c.daemon.reorder_window_s = 0.3;
    c.daemon.settle_s = 0.2;
    c.daemon.retry_initial_s = 0.05;
    c.daemon.retry_max_s = 0.2;
    c.daemon.retry_attempts = 3;
    c.sink.flush_interval_s = 0.1;
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

struct Daemon {
    progress: watch::Receiver<Progress>,
    stop: oneshot::Sender<()>,
    handle: tokio::task::JoinHandle<sunjitter::Result<Progress>>,
    sink: MemorySink,
}

fn start(dir: &Path, config: Config, history: History) -> Daemon {
    let sink = MemorySink::default();
    let (progress_tx, progress) = watch::channel(Progress::default());
    let parts = RunParts {
        config: Arc::new(config),
        reader: Arc::new(FakeReader::default()),
        aligner: Arc::new(TruthAligner::from_files(cov())),
        sink: Box::new(sink.clone()),
        history,
        progress: progress_tx,
        live: true,
    };
    let (stop, stopped) = oneshot::channel::<()>();
    let dir = dir.to_path_buf();
    let handle = tokio::spawn(async move {
        sunjitter::daemon::run_daemon(&dir, parts, async {
            let _ = stopped.await;
        })
        .await
    });
    Daemon {
        progress,
        stop,
        handle,
        sink,
    }
}

impl Daemon {
    /// Wait (bounded) until `finished` inputs have been logged.
    async fn wait_finished(&mut self, finished: u64) -> Progress {
        let mut rx = self.progress.clone();
        let wait = async move {
            rx.wait_for(|p| p.finished >= finished)
                .await
                .map(|p| p.clone())
        };
        match tokio::time::timeout(Duration::from_secs(60), wait).await {
            Ok(Ok(p)) => p,
            _ => panic!("timed out: {:?}", *self.progress.borrow()),
        }
    }

    async fn shutdown(self) -> (Progress, Vec<Record>) {
        let _ = self.stop.send(());
        let progress = tokio::time::timeout(Duration::from_secs(60), self.handle)
            .await
            .expect("stops in time")
            .expect("task")
            .expect("clean run");
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
            m.reference_kind == "self",
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
    let mut inputs = 0;
    for t in 0..10 {
        // A every 10 s; C at 10 s + 3 s (nearest A: the same step), the last C with no A near.
        write_renamed(
            dir.path(),
            &format!("a{t}.fits"),
            &frame("A", 10 * t).to_fits(),
            "x.tmp",
        );
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
    };
    sunjitter::pipeline::run_replay(inputs, parts, std::future::pending())
        .await
        .unwrap();
    let replayed = sink.records();
    let sorted = |mut r: Vec<Record>| {
        r.sort_by_key(|r| (r.topic(), r.log_time_ns(), format!("{r:?}")));
        r
    };
    assert_eq!(sorted(watched), sorted(replayed));
}
