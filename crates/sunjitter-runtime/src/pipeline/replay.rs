//! Replay: the same pipeline over archived files.

use super::frames::{inspect_file, unreadable_record, waiting_record, FileOutcome, Input, Unready};
use super::progress::Progress;
use super::run::{run_pipeline, RunParts};
use crate::config::Config;
use crate::ports::FrameReader;
use crate::reference::History;
use std::time::Duration;
use sunjitter_core::Result;
use tokio::sync::{mpsc, watch};

/// Check every file of a replay and list what goes into the pipeline: the frames (not yet
/// in the log) and a terminal `/log` record for each file that cannot be taken, with the
/// same reasons the daemon gives. An incomplete file is not waited for (an archive is
/// complete); a fault of the moment (too many open files) is retried with the `[daemon]`
/// back-off, and if it lasts, the file gets a `/log` warning only, so a later run takes it.
pub fn replay_inputs(
    files: &[(std::path::PathBuf, bool)],
    config: &Config,
    reader: &dyn FrameReader,
    history: &History,
) -> Vec<Input> {
    let d = &config.daemon;
    let mut inputs = Vec::new();
    for (path, explicit) in files {
        let follow = *explicit || config.daemon.follow_symlinks;
        let mut delay = Duration::from_secs_f64(d.retry_initial_s);
        let mut outcome = inspect_file(path, reader, config, history, follow);
        for _ in 1..d.retry_attempts.max(1) {
            let FileOutcome::NotReady(Unready::Transient, reason) = &outcome else {
                break;
            };
            tracing::warn!(file = %path.display(), "{reason}: reading again in {delay:?}");
            std::thread::sleep(delay);
            delay = (delay * 2).min(Duration::from_secs_f64(
                d.retry_max_s.max(d.retry_initial_s),
            ));
            outcome = inspect_file(path, reader, config, history, follow);
        }
        match outcome {
            FileOutcome::NotReady(Unready::Transient, reason) => {
                let message = format!("cannot be read for now, left for a later run: {reason}");
                inputs.push(Input::Record(waiting_record(path, message)));
            }
            FileOutcome::Frames(items, records) => {
                inputs.extend(records.into_iter().map(Input::Record));
                inputs.extend(items.into_iter().map(Input::Frame));
            }
            FileOutcome::NotReady(_, reason) => {
                inputs.push(Input::Record(unreadable_record(path, &reason)));
            }
            FileOutcome::Skip(Some(record)) | FileOutcome::Vanished(record) => {
                inputs.push(Input::Record(record))
            }
            FileOutcome::Skip(None) => {}
        }
    }
    inputs
}

/// Run the pipeline over `inputs` (from [`replay_inputs`]) in observation-time order per
/// channel. `shutdown` stops early (what is not logged is taken by the next run).
pub async fn run_replay(
    inputs: Vec<Input>,
    parts: RunParts,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> Result<Progress> {
    let capacity = parts.config.daemon.queue_capacity.max(1);
    let (tx, rx) = mpsc::channel(capacity);
    let (stop_tx, stop_rx) = watch::channel(false);
    let producer = tokio::spawn(async move {
        for input in inputs {
            if tx.send(input).await.is_err() {
                break;
            }
        }
    });
    let stopper = tokio::spawn(async move {
        shutdown.await;
        let _ = stop_tx.send(true);
        // Keep the sender alive: a closed channel must not read as a stop.
        std::future::pending::<()>().await;
    });
    let result = run_pipeline(
        RunParts {
            live: false,
            ..parts
        },
        rx,
        stop_rx,
        None,
    )
    .await;
    producer.abort();
    stopper.abort();
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::ChannelConfig;
    use crate::fake::{FakeFrame, FakeReader, TruthAligner};
    use crate::ingest::expand_inputs;
    use crate::pipeline::parse_iso8601_utc;
    use crate::reference::PolicySpec;
    use std::collections::HashMap;
    use std::path::Path;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    use sunjitter_core::engine::Image;
    use sunjitter_core::meta::FrameMeta;
    use sunjitter_core::record::FrameAlignment;
    use sunjitter_core::Error;
    use sunjitter_io::fits::FrameSpec;
    use sunjitter_io::records::{MemorySink, Record};

    const S: i64 = 1_000_000_000;

    fn cov() -> crate::reference::Cov4 {
        let mut c = [[0.0; 4]; 4];
        c[2][2] = 0.01;
        c[3][3] = 0.01;
        c
    }

    fn write(dir: &Path, name: &str, frame: &FakeFrame) -> std::path::PathBuf {
        let path = dir.join(name);
        std::fs::write(&path, frame.to_fits()).unwrap();
        crate::config::canonical_file_path(&path).unwrap()
    }

    fn replay(dir: &Path, config: Config, history: History) -> (Progress, Vec<Record>) {
        let config = Arc::new(config);
        let reader = FakeReader::default();
        let files = expand_inputs(&[dir.display().to_string()], &config).unwrap();
        let inputs = replay_inputs(&files, &config, &reader, &history);
        let sink = MemorySink::default();
        let parts = RunParts {
            config: config.clone(),
            reader: Arc::new(reader),
            aligner: Arc::new(TruthAligner::from_files(cov())),
            sink: Box::new(sink.clone()),
            history,
            progress: watch::channel(Progress::default()).0,
            live: false,
            products: None,
        };
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let progress = rt
            .block_on(run_replay(inputs, parts, std::future::pending()))
            .unwrap();
        assert!(sink.log.lock().unwrap().finished, "sink finished");
        (progress, sink.records())
    }

    fn frames_of<'a>(records: &'a [Record], channel: &str) -> Vec<&'a FrameAlignment> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Frame { message, .. } if message.channel == channel => {
                    Some(message.as_ref())
                }
                _ => None,
            })
            .collect()
    }

    fn logs(records: &[Record]) -> Vec<(String, String)> {
        records
            .iter()
            .filter_map(|r| match r {
                Record::Log { file, message, .. } => Some((file.clone(), message.clone())),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn replay_emits_each_frame_once_in_time_order_per_channel() {
        let dir = tempfile::tempdir().unwrap();
        // Names deliberately not in time order; two channels interleaved.
        let times_a = [50, 10, 40, 20, 30];
        for (i, t) in times_a.iter().enumerate() {
            let f = FakeFrame::new("A", t * S, 1.0, 0.0, 0.1 * *t as f64, 0.0);
            write(dir.path(), &format!("z{i}_a.fits"), &f);
        }
        for (i, t) in [15, 5, 25].iter().enumerate() {
            let f = FakeFrame::new("B", t * S, 1.0, 0.0, 0.0, 0.2 * *t as f64);
            write(dir.path(), &format!("b{i}.fits"), &f);
        }
        std::fs::write(dir.path().join("garbage.fits"), b"not a fits file at all").unwrap();
        let mut no_time = FakeFrame::new("A", 0, 1.0, 0.0, 0.0, 0.0);
        no_time.obs_time_ns = None;
        let no_time_path = write(dir.path(), "notime.fits", &no_time);

        let (progress, records) = replay(dir.path(), Config::default(), History::default());
        let a = frames_of(&records, "A");
        let times: Vec<i64> = a
            .iter()
            .map(|m| parse_iso8601_utc(&m.obs_time).unwrap() / S)
            .collect();
        assert_eq!(times, [10, 20, 30, 40, 50]);
        assert_eq!(
            a.iter().map(|m| m.sequence).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        assert_eq!(frames_of(&records, "B").len(), 3);
        // Chained dx is the true 0.1·t relative to the first frame (t = 10).
        for (m, t) in a.iter().zip(times) {
            assert!((m.chained_dx_px.unwrap() - 0.1 * (t - 10) as f64).abs() < 1e-9);
        }
        let logs = logs(&records);
        assert_eq!(logs.len(), 2, "{logs:?}");
        assert!(logs
            .iter()
            .any(|(f, m)| f.ends_with("garbage.fits") && m.contains("not a FITS file")));
        assert!(logs
            .iter()
            .any(|(f, m)| *f == no_time_path.display().to_string()
                && m.contains("no observation time")));
        assert_eq!(
            (progress.frames, progress.skipped, progress.finished),
            (8, 2, 10)
        );
    }

    #[test]
    fn channel_policy_picks_the_nearest_partner_within_tolerance() {
        let dir = tempfile::tempdir().unwrap();
        let mut keys = HashMap::new();
        for t in [0, 10, 20, 30] {
            let f = FakeFrame::new("P", t * S, 1.0, 0.0, t as f64, 0.0);
            keys.insert(
                t,
                write(dir.path(), &format!("p{t}.fits"), &f)
                    .display()
                    .to_string(),
            );
        }
        // 12 → P10, 16 → P20, 25 → tie → earlier (P20), 39 → P30 (9 s), 45 → unmatched (> 10 s).
        for t in [12, 16, 25, 39, 45] {
            let f = FakeFrame::new("F", t * S, 1.0, 0.0, t as f64, 1.0);
            write(dir.path(), &format!("f{t}.fits"), &f);
        }
        let mut config = Config::default();
        config.channels.insert(
            "F".into(),
            ChannelConfig {
                policy: Some(PolicySpec::Channel("P".into())),
                tolerance_s: Some(10.0),
                ..Default::default()
            },
        );
        let (_, records) = replay(dir.path(), config, History::default());
        let f = frames_of(&records, "F");
        let refs: Vec<&str> = f.iter().map(|m| m.align.reference.as_str()).collect();
        assert_eq!(refs, [&keys[&10], &keys[&20], &keys[&20], &keys[&30]]);
        for m in &f {
            assert_eq!(
                m.reference_kind,
                sunjitter_core::record::ReferenceKind::Channel
            );
            // Partner chain (dx = t_p) then partner → frame (dx = t_f − t_p): dx = t_f; dy = 1.
            let t = parse_iso8601_utc(&m.obs_time).unwrap() / S;
            assert!((m.chained_dx_px.unwrap() - t as f64).abs() < 1e-9);
            assert!((m.chained_dy_px.unwrap() - 1.0).abs() < 1e-9);
        }
        let logs = logs(&records);
        assert_eq!(logs.len(), 1);
        assert!(
            logs[0].0.ends_with("f45.fits") && logs[0].1.contains("unmatched"),
            "{logs:?}"
        );
        // The partner changed three times (P10, P20, P30).
        let changes = records
            .iter()
            .filter(|r| matches!(r, Record::Reference { change, .. } if change.channel == "F"))
            .count();
        assert_eq!(changes, 3);
    }

    #[test]
    fn replay_output_does_not_depend_on_worker_count() {
        let dir = tempfile::tempdir().unwrap();
        for t in 0..12 {
            for ch in ["A", "B", "C"] {
                let offset = (ch.as_bytes()[0] - b'A') as i64 + 1;
                let f = FakeFrame::new(
                    ch,
                    (t * 10 + offset) * S,
                    1.0 + 1e-4 * t as f64,
                    1e-4 * t as f64,
                    t as f64,
                    -(t as f64),
                );
                write(dir.path(), &format!("{ch}{t:02}.fits"), &f);
            }
        }
        let run = |workers| {
            let mut config = Config::default();
            config.daemon.workers = workers;
            config.reference.keyframe_every_frames = 5;
            config.channels.insert(
                "C".into(),
                ChannelConfig {
                    policy: Some(PolicySpec::Channel("A".into())),
                    ..Default::default()
                },
            );
            let (_, mut records) = replay(dir.path(), config, History::default());
            records.sort_by_key(|r| (r.topic(), r.log_time_ns(), format!("{r:?}")));
            records
        };
        let one = run(1);
        // 36 frames; keyframes at 0, 5, 10 in A and B; C follows A, a new partner each frame.
        assert_eq!(one.len(), 36 + 3 + 3 + 12);
        assert_eq!(one, run(3));
    }

    #[test]
    fn frames_already_in_the_log_are_not_processed_again() {
        let dir = tempfile::tempdir().unwrap();
        for t in 0..6 {
            write(
                dir.path(),
                &format!("f{t}.fits"),
                &FakeFrame::new("A", t * S, 1.0, 0.0, t as f64, 0.0),
            );
        }
        let mut config = Config::default();
        config.reference.keyframe_every_frames = 4;
        let (_, full) = replay(dir.path(), config.clone(), History::default());
        // Pretend the first run logged frames 0..3 (and their reference changes).
        let mut history = History::default();
        let cut = full
            .iter()
            .position(|r| matches!(r, Record::Frame { message, .. } if message.sequence == 3))
            .unwrap();
        for r in &full[..=cut] {
            history.add(r);
        }
        let (progress, rest) = replay(dir.path(), config, history);
        assert_eq!(progress.frames, 2);
        assert_eq!(
            &full[cut + 1..],
            &rest[..],
            "the resumed run continues the same series"
        );
    }

    /// A reader out of file descriptors for its first `fails` checks, then the fake reader.
    struct OutOfDescriptors {
        fails: AtomicUsize,
    }

    impl FrameReader for OutOfDescriptors {
        fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
            let left = self.fails.load(Ordering::SeqCst);
            if left > 0 {
                self.fails.store(left - 1, Ordering::SeqCst);
                let emfile = std::io::Error::from_raw_os_error(libc::EMFILE);
                return Err(Error::io(path, emfile));
            }
            FakeReader::default().read_meta(path)
        }
        fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
            FakeReader::default().read_frame(spec)
        }
    }

    #[test]
    fn replay_reads_again_after_a_fault_of_the_moment_and_never_fails_a_file_over_it() {
        let dir = tempfile::tempdir().unwrap();
        write(
            dir.path(),
            "f.fits",
            &FakeFrame::new("A", S, 1.0, 0.0, 0.0, 0.0),
        );
        let mut config = Config::default();
        config.daemon.retry_initial_s = 0.001;
        config.daemon.retry_max_s = 0.002;
        config.daemon.retry_attempts = 3;
        let files = expand_inputs(&[dir.path().display().to_string()], &config).unwrap();
        let inputs = |fails| {
            let reader = OutOfDescriptors {
                fails: AtomicUsize::new(fails),
            };
            replay_inputs(&files, &config, &reader, &History::default())
        };
        // Two faults, the third check reads: the frame goes in.
        assert!(matches!(&inputs(2)[..], [Input::Frame(_)]));
        // Still out of descriptors after every attempt: a warning, which does not finish the
        // file (a later run takes it).
        match &inputs(3)[..] {
            [Input::Record(r @ Record::Log { message, .. })] => {
                assert!(
                    message.starts_with("cannot be read for now")
                        && message.contains("Too many open files"),
                    "{message}"
                );
                let mut history = History::default();
                history.add(r);
                assert!(history.done.is_empty());
            }
            other => panic!("{other:?}"),
        }
    }
}
