//! MCAP sink: what is written is read back exactly, per the contract's layout, across segment
//! rotation, crashes (abandoned writers, truncated files) and write errors (full disk).
//!
//! The known truth is the input: every message read back must equal what was written.
//! The layout is checked with the `mcap` crate's own summary/metadata readers, independently
//! of `sunjitter_io::sink::read_logs`; `tools/check_mcap.py` checks it with the Python reader.

mod support;

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use sunjitter_core::error::ExitCode;
use sunjitter_core::record::{AlignResult, FrameAlignment, ReferenceKind, Status, TransformFields};
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::sink::{
    logged_frames, read_logs, recover_segment, LogLevel, McapSink, RecoveryOutcome,
    ReferenceChange, SinkConfig,
};

/// 2014-03-29T14:09:38Z, the first IRIS SJI frame of the bundled data, in ns.
const T0: u64 = 1_396_102_178_000_000_000;
const CADENCE_NS: u64 = 12_000_000_000;
const CONFIG_JSON: &str = r#"{"reference":"keyframe","sink":{"segment_frames":10}}"#;

/// splitmix64: full-mantissa values that a lossy float encoding would not round-trip.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn f(&mut self, scale: f64) -> f64 {
        ((self.next() >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * scale
    }
}

/// Frame `i` of `channel`: varied values, a failed frame every 7th (numbers null).
fn frame(channel: &str, i: u64, rng: &mut Rng) -> FrameAlignment {
    let failed = i % 7 == 6;
    let header_residual = (!failed && i.is_multiple_of(2)).then(|| TransformFields {
        scale: 1.0 + rng.f(1e-5),
        rotation_arcsec: rng.f(1.0),
        dx_px: rng.f(0.5),
        dy_px: rng.f(0.5),
    });
    let mut v = |s: f64| if failed { None } else { Some(rng.f(s)) };
    let align = AlignResult {
        reference: format!("/data/{channel}/f{:04}.fits", i.saturating_sub(1)),
        frame: format!("/data/{channel}/f{i:04}.fits"),
        scale: v(1e-3).map(|d| 1.0 + d),
        rotation_arcsec: v(20.0),
        dx_px: v(3.0),
        dy_px: v(3.0),
        dx_arcsec: v(1.0),
        dy_arcsec: v(1.0),
        sigma_scale: v(1e-6).map(f64::abs),
        sigma_rotation_arcsec: v(0.1).map(f64::abs),
        sigma_dx_px: v(0.01).map(f64::abs),
        sigma_dy_px: v(0.01).map(f64::abs),
        sigma_dx_arcsec: v(0.01).map(f64::abs),
        sigma_dy_arcsec: v(0.01).map(f64::abs),
        uabjm_sigma_scale: v(1e-7).map(f64::abs),
        uabjm_sigma_rotation_arcsec: v(0.05),
        uabjm_sigma_dx_px: v(1e-3),
        uabjm_sigma_dy_px: v(1e-3),
        header_residual,
        solar_rotation: None,
        points: if failed { 0 } else { 400 },
        inliers: if failed { 0 } else { 380 - i as usize % 50 },
        residual_rms_px: v(0.1),
        model: None,
        similarity: v(0.2).map(|d| 0.8 + d),
        status: if failed {
            Status::Failed
        } else if i % 5 == 4 {
            Status::Degraded
        } else {
            Status::Ok
        },
        message: if failed {
            "no usable structure: 3 inliers < 10 — “quoted” ☉".into()
        } else {
            String::new()
        },
        elapsed_ms: 100.0 + rng.f(10.0),
    };
    let chained = |rng: &mut Rng, s: f64| if failed { None } else { Some(rng.f(s)) };
    let (dx, dy) = (chained(rng, 5.0), chained(rng, 5.0));
    let (rotation, scale) = (chained(rng, 30.0), chained(rng, 1e-3).map(|d| 1.0 + d));
    let (sx, sy) = (
        chained(rng, 0.02).map(f64::abs),
        chained(rng, 0.02).map(f64::abs),
    );
    let arcsec = |v: Option<f64>| v.map(|v| v * 0.6);
    FrameAlignment {
        align,
        channel: channel.to_string(),
        obs_time: iso_time(times(i).0),
        sequence: i,
        reference_kind: if i == 0 {
            ReferenceKind::Itself
        } else {
            ReferenceKind::Keyframe
        },
        chained_dx_px: dx,
        chained_dy_px: dy,
        chained_dx_arcsec: arcsec(dx),
        chained_dy_arcsec: arcsec(dy),
        chained_rotation_arcsec: rotation,
        chained_scale: scale,
        sigma_chained_dx_px: sx,
        sigma_chained_dy_px: sy,
        sigma_chained_dx_arcsec: arcsec(sx),
        sigma_chained_dy_arcsec: arcsec(sy),
        sigma_chained_rotation_arcsec: chained(rng, 0.2).map(f64::abs),
        sigma_chained_scale: chained(rng, 1e-6).map(f64::abs),
        pixel_checksum: None,
    }
}

fn frames(channel: &str, n: u64, seed: u64) -> Vec<FrameAlignment> {
    let mut rng = Rng(seed);
    (0..n).map(|i| frame(channel, i, &mut rng)).collect()
}

/// ISO 8601 UTC with ns, for times on 2014-03-29 after T0 (as `date -u -d @1396102178`
/// gives 2014-03-29T14:09:38Z).
fn iso_time(ns: u64) -> String {
    let secs = (ns - T0) / 1_000_000_000 + 14 * 3600 + 9 * 60 + 38;
    assert!(secs < 86_400, "test times stay on 2014-03-29");
    let (h, m, s) = (secs / 3600, secs / 60 % 60, secs % 60);
    format!("2014-03-29T{h:02}:{m:02}:{s:02}.{:09}Z", ns % 1_000_000_000)
}

/// Observation and processing times of frame `i` (processing 3.5 s after observation).
fn times(i: u64) -> (u64, u64) {
    let obs = T0 + i * CADENCE_NS + i * 1_234;
    (obs, obs + 3_500_000_000)
}

fn reference_change(i: u64) -> ReferenceChange {
    ReferenceChange {
        channel: "SJI_1400".into(),
        file: format!("/data/SJI_1400/f{i:04}.fits"),
        cube_frame: (i % 2 == 1).then_some(i as usize),
        obs_time: format!("2014-03-29T14:09:{:02}Z", 38 + i),
        reason: if i == 0 {
            "first frame".into()
        } else {
            format!("refresh after {i} frames")
        },
        reference_kind: ReferenceKind::Keyframe,
        sequence: i,
        replaces: (i > 0).then(|| "/data/SJI_1400/f0000.fits".into()),
        closure: None,
        cross_covariance: None,
        chain: None,
    }
}

fn config(segment_frames: u64, flush_every_frames: u64) -> SinkConfig {
    SinkConfig {
        segment_frames,
        segment_minutes: 0.0,
        flush_every_frames,
        ..SinkConfig::default()
    }
}

fn mcap_files(dir: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    files.sort();
    files
}

fn names(files: &[PathBuf]) -> Vec<String> {
    files
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect()
}

/// The whole series read back equals what was written: records, topics, both timestamps.
#[test]
fn messages_read_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 23, 1);
    let b = frames("SJI_2796", 23, 2);
    let mut sink = McapSink::new(dir.path(), config(0, 5), CONFIG_JSON.into()).unwrap();
    sink.write_reference_change(&reference_change(0), times(0).0, times(0).1)
        .unwrap();
    for i in 0..23u64 {
        let (obs, publish) = times(i);
        sink.write_frame(&a[i as usize], obs, publish).unwrap();
        sink.write_frame(&b[i as usize], obs + 1, publish + 1)
            .unwrap();
        if i == 9 {
            sink.write_reference_change(&reference_change(10), obs, publish)
                .unwrap();
            sink.write_log(
                LogLevel::Error,
                "/data/bad.fits",
                "not FITS: bad magic",
                obs,
                publish,
            )
            .unwrap();
        }
    }
    sink.write_log(
        LogLevel::Warning,
        "/data/SJI_1400/f0006.fits",
        "degraded",
        T0,
        T0 + 1,
    )
    .unwrap();
    sink.finish().unwrap();

    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert_eq!(log.segments.len(), 1);
    assert!(log.segments[0].complete, "{:?}", log.segments[0].notes);
    assert!(log.notes().is_empty(), "{:?}", log.notes());
    assert_eq!(log.jitter.len(), 46);
    for i in 0..23usize {
        let (obs, publish) = times(i as u64);
        let (ma, mb) = (&log.jitter[2 * i], &log.jitter[2 * i + 1]);
        assert_eq!(ma.record, a[i], "SJI_1400 frame {i}");
        assert_eq!(mb.record, b[i], "SJI_2796 frame {i}");
        assert_eq!(
            (ma.topic.as_str(), ma.log_time_ns, ma.publish_time_ns),
            ("/jitter/SJI_1400", obs, publish)
        );
        assert_eq!(
            (mb.topic.as_str(), mb.log_time_ns, mb.publish_time_ns),
            ("/jitter/SJI_2796", obs + 1, publish + 1)
        );
    }
    let refs: Vec<_> = log
        .references
        .iter()
        .map(|m| (m.topic.as_str(), &m.change))
        .collect();
    assert_eq!(
        refs,
        vec![
            ("/reference/SJI_1400", &reference_change(0)),
            ("/reference/SJI_1400", &reference_change(10))
        ]
    );
    assert_eq!(log.references[1].log_time_ns, times(9).0);
    assert_eq!(log.logs.len(), 2);
    let e = &log.logs[0];
    assert_eq!(
        (
            e.entry.level,
            e.entry.file.as_str(),
            e.entry.message.as_str()
        ),
        (LogLevel::Error, "/data/bad.fits", "not FITS: bad magic")
    );
    assert_eq!((e.entry.name.as_str(), e.entry.line), ("sunjitter", 0));
    assert_eq!(e.entry.timestamp.sec, times(9).0 / 1_000_000_000);
    assert_eq!(e.entry.timestamp.nsec as u64, times(9).0 % 1_000_000_000);
    assert_eq!((e.log_time_ns, e.publish_time_ns), times(9));
    assert_eq!(log.logs[1].entry.level, LogLevel::Warning);
    assert_eq!(log.metadata.len(), 1);
    assert_eq!(log.metadata[0].name, "sunjitter");
    assert_eq!(
        log.metadata[0].metadata["version"],
        env!("CARGO_PKG_VERSION")
    );
    assert_eq!(log.metadata[0].metadata["config"], CONFIG_JSON);
}

/// Channels, schemas, compression, indexes and metadata per contract.md, read with the `mcap`
/// crate's summary and strict message reader (not with sunjitter's reader).
#[test]
fn layout_follows_the_contract() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("AIA_171", 12, 3);
    let mut sink = McapSink::new(dir.path(), config(0, 4), CONFIG_JSON.into()).unwrap();
    sink.write_reference_change(&reference_change(0), T0, T0)
        .unwrap();
    for (i, f) in a.iter().enumerate() {
        let (obs, publish) = times(i as u64);
        sink.write_frame(f, obs, publish).unwrap();
    }
    sink.write_log(LogLevel::Error, "/data/x.fits", "unreadable", T0, T0)
        .unwrap();
    sink.finish().unwrap();
    let files = mcap_files(dir.path());
    assert_eq!(files.len(), 1);
    let bytes = std::fs::read(&files[0]).unwrap();

    let summary = mcap::read::Summary::read(&bytes)
        .unwrap()
        .expect("summary section");
    let mut topics: BTreeMap<String, (String, String, String)> = BTreeMap::new();
    for c in summary.channels.values() {
        let s = c.schema.as_ref().expect("every channel has a schema");
        topics.insert(
            c.topic.clone(),
            (
                s.name.clone(),
                s.encoding.clone(),
                c.message_encoding.clone(),
            ),
        );
        let schema: serde_json::Value = serde_json::from_slice(&s.data).expect("schema is JSON");
        assert_eq!(schema["type"], "object");
        assert_eq!(schema["title"], s.name.as_str());
    }
    let expect = |schema: &str| {
        (
            schema.to_string(),
            "jsonschema".to_string(),
            "json".to_string(),
        )
    };
    assert_eq!(
        topics,
        BTreeMap::from([
            (
                "/jitter/AIA_171".to_string(),
                expect("sunjitter.FrameAlignment")
            ),
            ("/log".to_string(), expect("foxglove.Log")),
            (
                "/reference/SJI_1400".to_string(),
                expect("sunjitter.ReferenceChange")
            ),
        ])
    );

    // The FrameAlignment schema describes exactly the contract's fields, all required.
    let jitter = summary
        .channels
        .values()
        .find(|c| c.topic == "/jitter/AIA_171")
        .unwrap();
    let schema: serde_json::Value =
        serde_json::from_slice(&jitter.schema.as_ref().unwrap().data).unwrap();
    let mut props: Vec<&str> = schema["properties"]
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    let mut required: Vec<&str> = schema["required"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    let mut contract = support::jitter_fields();
    props.sort();
    required.sort();
    contract.sort();
    assert_eq!(required, contract);
    // Properties: the contract's, plus the additive, optional pixel checksum.
    let mut with_checksum = contract.clone();
    with_checksum.push("pixel_checksum");
    with_checksum.sort();
    assert_eq!(props, with_checksum);

    // foxglove.Log fields and types as Foxglove publishes them (docs.foxglove.dev, Log schema).
    let log = summary
        .channels
        .values()
        .find(|c| c.topic == "/log")
        .unwrap();
    let log_schema: serde_json::Value =
        serde_json::from_slice(&log.schema.as_ref().unwrap().data).unwrap();
    let mut log_props: Vec<&str> = log_schema["properties"]
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    log_props.sort();
    assert_eq!(
        log_props,
        ["file", "level", "line", "message", "name", "timestamp"]
    );
    assert_eq!(
        log_schema["properties"]["timestamp"]["properties"]["nsec"]["maximum"],
        999_999_999
    );

    // zstd chunks, each with a message index; statistics; the metadata record through its index.
    assert!(!summary.chunk_indexes.is_empty());
    for ci in &summary.chunk_indexes {
        assert_eq!(ci.compression, "zstd");
        assert!(
            !ci.message_index_offsets.is_empty(),
            "chunk without message index"
        );
    }
    let stats = summary.stats.as_ref().expect("statistics");
    assert_eq!(stats.message_count, 14);
    assert_eq!(stats.message_start_time, T0);
    assert_eq!(stats.message_end_time, times(11).0);
    assert_eq!(summary.metadata_indexes.len(), 1);
    let meta = mcap::read::metadata(&bytes, &summary.metadata_indexes[0]).unwrap();
    assert_eq!(meta.name, "sunjitter");
    assert_eq!(meta.metadata["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(meta.metadata["config"], CONFIG_JSON);

    // Each /jitter message is a JSON object with exactly the contract's keys, log_time = obs.
    let mut n = 0;
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic != "/jitter/AIA_171" {
            continue;
        }
        let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
        let mut keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        keys.sort();
        assert_eq!(keys, contract);
        assert_eq!(m.log_time, times(n).0);
        assert_eq!(v["frame"], a[n as usize].align.frame.as_str());
        n += 1;
    }
    assert_eq!(n, 12);
}

/// 25 frames, a segment every 10: three finished files named in time order, each with the
/// metadata record and the schemas/channels it uses.
#[test]
fn rotation_by_frame_count() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 25, 4);
    let mut sink = McapSink::new(dir.path(), config(10, 3), CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        let (obs, _) = times(i as u64);
        // Processing all within the same second of 2014-03-29T14:10:00Z, except the last 5.
        let publish = if i < 20 {
            T0 + 22_000_000_000 + i as u64
        } else {
            T0 + 3_600_000_000_000
        };
        sink.write_frame(f, obs, publish).unwrap();
    }
    sink.finish().unwrap();
    let files = mcap_files(dir.path());
    assert_eq!(
        names(&files),
        [
            "sunjitter-20140329T141000Z-0000.mcap",
            "sunjitter-20140329T141000Z-0001.mcap",
            "sunjitter-20140329T150938Z-0002.mcap",
        ]
    );
    assert_eq!(sink.segment_paths(), files.as_slice());
    for (file, count) in files.iter().zip([10u64, 10, 5]) {
        let bytes = std::fs::read(file).unwrap();
        let summary = mcap::read::Summary::read(&bytes)
            .unwrap()
            .expect("finished segment");
        assert_eq!(summary.stats.as_ref().unwrap().message_count, count);
        assert_eq!(summary.channels.len(), 1);
        assert_eq!(summary.metadata_indexes.len(), 1, "{}", file.display());
        let meta = mcap::read::metadata(&bytes, &summary.metadata_indexes[0]).unwrap();
        assert_eq!(
            (meta.name.as_str(), meta.metadata["config"].as_str()),
            ("sunjitter", CONFIG_JSON)
        );
    }
    // Read as one series, in order.
    let log = read_logs(&files.iter().rev().cloned().collect::<Vec<_>>()).unwrap();
    let read: Vec<_> = log.jitter.iter().map(|m| m.record.clone()).collect();
    assert_eq!(read, a);
    assert_eq!(
        log.jitter.iter().map(|m| m.segment).collect::<Vec<_>>(),
        [[0; 10].as_slice(), &[1; 10], &[2; 5]].concat()
    );
    assert_eq!(log.metadata.len(), 3);
}

/// segment_minutes = 1 and a frame processed every 25 s: a new segment at the first frame at
/// least 60 s after the segment's start, i.e. at 75 s (14:10:53) and 150 s (14:12:08).
#[test]
fn rotation_by_time() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 8, 5);
    let cfg = SinkConfig {
        segment_frames: 0,
        segment_minutes: 1.0,
        flush_every_frames: 2,
        ..SinkConfig::default()
    };
    let mut sink = McapSink::new(dir.path(), cfg, CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        sink.write_frame(f, times(i as u64).0, T0 + i as u64 * 25_000_000_000)
            .unwrap();
    }
    sink.finish().unwrap();
    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert_eq!(
        names(&mcap_files(dir.path())),
        [
            "sunjitter-20140329T140938Z-0000.mcap",
            "sunjitter-20140329T141053Z-0001.mcap",
            "sunjitter-20140329T141208Z-0002.mcap",
        ]
    );
    assert_eq!(
        log.segments.iter().map(|s| s.messages).collect::<Vec<_>>(),
        [3, 3, 2]
    );
    assert_eq!(
        log.jitter
            .iter()
            .map(|m| m.record.clone())
            .collect::<Vec<_>>(),
        a
    );
}

/// A file with the name the sink would pick is never overwritten; new names sort after every
/// existing segment even when the clock says earlier.
#[test]
fn never_overwrites_and_sorts_after_existing_segments() {
    let dir = tempfile::tempdir().unwrap();
    let taken = dir.path().join("sunjitter-20140329T140938Z-0000.mcap");
    let later = dir.path().join("sunjitter-20140329T150000Z-0007.mcap");
    std::fs::write(&taken, b"someone else's file").unwrap();
    std::fs::write(&later, b"").unwrap();
    let mut sink = McapSink::new(dir.path(), config(0, 1), CONFIG_JSON.into()).unwrap();
    sink.write_frame(&frames("SJI_1400", 1, 6)[0], T0, T0)
        .unwrap();
    sink.finish().unwrap();
    assert_eq!(std::fs::read(&taken).unwrap(), b"someone else's file");
    assert_eq!(
        names(sink.segment_paths()),
        ["sunjitter-20140329T150000Z-0008.mcap"]
    );

    // And in a directory where only the clash exists, the number is bumped.
    let dir2 = tempfile::tempdir().unwrap();
    let mut sink2 = McapSink::new(dir2.path(), config(0, 1), CONFIG_JSON.into()).unwrap();
    std::fs::write(
        dir2.path().join("sunjitter-20140329T140938Z-0000.mcap"),
        b"x",
    )
    .unwrap();
    sink2
        .write_frame(&frames("SJI_1400", 1, 6)[0], T0, T0)
        .unwrap();
    sink2.finish().unwrap();
    assert_eq!(
        names(sink2.segment_paths()),
        ["sunjitter-20140329T140938Z-0001.mcap"]
    );
}

/// Writes `n` frames flushing every `every`, then abandons the sink as a crash would.
/// Returns the frames and, after each flush, (file length, frames on disk).
fn crashed_segment(dir: &Path, n: u64, every: u64) -> (Vec<FrameAlignment>, Vec<(u64, usize)>) {
    let a = frames("SJI_1400", n, 7);
    let mut sink = McapSink::new(dir, config(0, every), CONFIG_JSON.into()).unwrap();
    let mut flushes = Vec::new();
    for (i, f) in a.iter().enumerate() {
        let (obs, publish) = times(i as u64);
        sink.write_frame(f, obs, publish).unwrap();
        let path = &sink.segment_paths()[0];
        let len = std::fs::metadata(path).unwrap().len();
        if ((i + 1) as u64).is_multiple_of(every) {
            flushes.push((len, i + 1));
        }
    }
    sink.abandon();
    (a, flushes)
}

/// An abandoned writer leaves every flushed message readable, and nothing after the flush.
#[test]
fn crash_keeps_every_flushed_message() {
    let dir = tempfile::tempdir().unwrap();
    let (a, flushes) = crashed_segment(dir.path(), 10, 4);
    let file = &mcap_files(dir.path())[0];
    assert_eq!(
        std::fs::metadata(file).unwrap().len(),
        flushes.last().unwrap().0
    );
    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert_eq!(
        log.jitter
            .iter()
            .map(|m| m.record.clone())
            .collect::<Vec<_>>(),
        a[..8].to_vec()
    );
    let seg = &log.segments[0];
    assert!(!seg.complete);
    assert_eq!(seg.messages, 8);
    assert!(
        seg.notes[0].contains("unfinished segment")
            && seg.notes[0].contains("recovered 8 messages"),
        "{:?}",
        seg.notes
    );
    assert_eq!(log.metadata.len(), 1);
    // The strict official reader refuses it...
    let bytes = std::fs::read(file).unwrap();
    assert!(
        mcap::read::Summary::read(&bytes).is_err()
            || mcap::read::Summary::read(&bytes).unwrap().is_none()
    );
    // ...until it is recovered: then it is a finished file with the same messages.
    let outcome = recover_segment(file).unwrap();
    assert!(
        matches!(
            outcome,
            RecoveryOutcome::Recovered {
                messages: 8,
                dropped_bytes: 0
            }
        ),
        "{outcome:?}"
    );
    let bytes = std::fs::read(file).unwrap();
    let summary = mcap::read::Summary::read(&bytes)
        .unwrap()
        .expect("summary after recovery");
    assert_eq!(summary.stats.unwrap().message_count, 8);
    let log2 = read_logs(std::slice::from_ref(file)).unwrap();
    assert!(log2.segments[0].complete);
    assert_eq!(log2.jitter, log.jitter);
    assert_eq!(log2.metadata, log.metadata);
    assert_eq!(
        recover_segment(file).unwrap(),
        RecoveryOutcome::AlreadyComplete
    );
}

/// The file cut at every byte offset: the reader returns exactly the frames of the complete
/// chunks before the cut — a prefix of the input, never a partial or garbage message — and
/// never fails or panics.
#[test]
fn truncation_at_any_offset_recovers_a_clean_prefix() {
    let dir = tempfile::tempdir().unwrap();
    let (a, flushes) = crashed_segment(dir.path(), 12, 3);
    let bytes = std::fs::read(&mcap_files(dir.path())[0]).unwrap();
    let cut_dir = tempfile::tempdir().unwrap();
    let cut_path = cut_dir.path().join("cut.mcap");
    // Before the first flush only the header and metadata (written and flushed at open).
    let mut bounds = vec![(0u64, 0usize)];
    bounds.extend(flushes.iter().copied());
    std::fs::write(&cut_path, &bytes).unwrap();
    let cut_file = std::fs::OpenOptions::new()
        .write(true)
        .open(&cut_path)
        .unwrap();
    for t in (0..=bytes.len()).rev() {
        cut_file.set_len(t as u64).unwrap();
        let log = read_logs(std::slice::from_ref(&cut_path))
            .unwrap_or_else(|e| panic!("cut at {t}: {e}"));
        let got: Vec<_> = log.jitter.iter().map(|m| m.record.clone()).collect();
        let k = got.len();
        assert_eq!(
            got,
            a[..k].to_vec(),
            "cut at {t}: not a prefix of the input"
        );
        // The last flush whose data lies entirely before the cut bounds k from below,
        // the next flush from above.
        let j = bounds
            .iter()
            .rposition(|&(len, _)| len <= t as u64)
            .unwrap();
        let lo = bounds[j].1;
        let hi = bounds.get(j + 1).map_or(lo, |b| b.1);
        assert!(
            lo <= k && k <= hi,
            "cut at {t}: {k} frames, expected {lo}..={hi}"
        );
        assert_eq!(log.segments[0].skipped, 0);
    }
}

/// A temporary directory in RAM where there is one: this test creates and deletes hundreds of
/// files, and unlinking on a busy disk is what would make it slow.
fn scratch_dir() -> tempfile::TempDir {
    let shm = Path::new("/dev/shm");
    if shm.is_dir() {
        if let Ok(dir) = tempfile::Builder::new()
            .prefix("sunjitter-test")
            .tempdir_in(shm)
        {
            return dir;
        }
    }
    tempfile::tempdir().unwrap()
}

/// Runs 9 frames (flush every 3) into a disk that fills after `budget` bytes; on each error
/// the space comes back and the caller retries, as a daemon would. Returns the frames written
/// and the number of errors seen.
fn full_disk_run(dir: &Path, budget: u64) -> (Vec<FrameAlignment>, usize) {
    let a = frames("SJI_1400", 9, 8);
    let mut sink = McapSink::new(dir, config(0, 3), CONFIG_JSON.into()).unwrap();
    sink.set_write_budget(Some(budget));
    let mut errors = 0;
    let mut next = 0;
    while next < a.len() {
        let (obs, publish) = times(next as u64);
        match sink.write_frame(&a[next], obs, publish) {
            Ok(()) => next += 1,
            Err(e) => {
                errors += 1;
                assert!(errors < 10, "budget {budget}: no progress: {e}");
                assert_eq!(e.exit_code(), ExitCode::Failed);
                assert!(
                    sink.pending_messages() <= 3,
                    "budget {budget}: pending grew"
                );
                sink.set_write_budget(None);
            }
        }
    }
    if let Err(e) = sink.finish() {
        errors += 1;
        sink.set_write_budget(None);
        sink.finish()
            .unwrap_or_else(|e2| panic!("budget {budget}: {e}, then {e2}"));
    }
    (a, errors)
}

/// A full disk at every possible byte: writes fail loudly, nothing accepted is lost or doubled,
/// and once space returns the caller's retries complete the series exactly once.
#[test]
fn full_disk_at_any_byte_loses_nothing_and_doubles_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let (_, errors) = full_disk_run(dir.path(), u64::MAX - 1);
    assert_eq!(errors, 0);
    let total: u64 = mcap_files(dir.path())
        .iter()
        .map(|f| std::fs::metadata(f).unwrap().len())
        .sum();
    // Every 9th byte: each failure window (a chunk written but not its message index, a
    // metadata record, a summary...) is wider than 9 bytes. 0..total byte-by-byte also passes.
    let mut with_errors = 0;
    let budgets: Vec<u64> = (0..total).step_by(9).collect();
    for &budget in &budgets {
        let dir = scratch_dir();
        let (a, errors) = full_disk_run(dir.path(), budget);
        with_errors += usize::from(errors > 0);
        let log = read_logs(&[dir.path().to_path_buf()])
            .unwrap_or_else(|e| panic!("budget {budget}: {e}"));
        let got: Vec<_> = log.jitter.iter().map(|m| m.record.clone()).collect();
        assert_eq!(
            got, a,
            "budget {budget}: every accepted frame exactly once, in order"
        );
        let unfinished: Vec<_> = log.segments.iter().filter(|s| !s.complete).collect();
        assert!(unfinished.is_empty(), "budget {budget}: {unfinished:?}");
        assert!(log.segments.iter().all(|s| s.skipped == 0));
    }
    assert_eq!(
        with_errors,
        budgets.len(),
        "every budget below the total size fails"
    );
}

/// While the disk stays full every call fails and nothing piles up; no file is left with a
/// message that is also re-written elsewhere.
#[test]
fn persistently_full_disk_keeps_failing_without_growing() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 6, 9);
    let mut sink = McapSink::new(dir.path(), config(0, 2), CONFIG_JSON.into()).unwrap();
    sink.write_frame(&a[0], times(0).0, times(0).1).unwrap();
    sink.write_frame(&a[1], times(1).0, times(1).1).unwrap(); // flushed
    sink.set_write_budget(Some(0));
    sink.write_frame(&a[2], times(2).0, times(2).1).unwrap(); // accepted in memory
                                                              // The automatic flush after a[3] fails; a[3] is accepted all the same.
    sink.write_frame(&a[3], times(3).0, times(3).1).unwrap();
    for _ in 0..5 {
        assert!(sink.write_frame(&a[4], times(4).0, times(4).1).is_err());
        assert!(sink.flush().is_err());
        assert_eq!(sink.pending_messages(), 2);
    }
    sink.set_write_budget(None);
    sink.write_frame(&a[4], times(4).0, times(4).1).unwrap();
    sink.write_frame(&a[5], times(5).0, times(5).1).unwrap();
    sink.finish().unwrap();
    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert_eq!(
        log.jitter
            .iter()
            .map(|m| m.record.clone())
            .collect::<Vec<_>>(),
        a
    );
}

/// Restart-resume: the frames accounted for are the /jitter frames and /log errors (not
/// warnings); `FILE[N]` is frame N of a cube.
#[test]
fn logged_frames_for_resume() {
    let dir = tempfile::tempdir().unwrap();
    let mut a = frames("SJI_1400", 3, 10);
    a[2].align.frame = "/data/cube.fits[7]".into();
    let mut sink = McapSink::new(dir.path(), config(2, 1), CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        sink.write_frame(f, times(i as u64).0, times(i as u64).1)
            .unwrap();
    }
    sink.write_log(LogLevel::Error, "/data/bad.fits", "not FITS", T0, T0)
        .unwrap();
    sink.write_log(LogLevel::Fatal, "/data/cube.fits[8]", "NaN only", T0, T0)
        .unwrap();
    sink.write_log(
        LogLevel::Warning,
        "/data/slow.fits",
        "incomplete, retrying",
        T0,
        T0,
    )
    .unwrap();
    sink.write_log(LogLevel::Error, "", "output disk full", T0, T0)
        .unwrap();
    sink.abandon(); // flushed after every message: a crash loses nothing here
    let got = logged_frames(&[dir.path().to_path_buf()]).unwrap();
    let spec = |p: &str, f: Option<usize>| FrameSpec {
        path: PathBuf::from(p),
        frame: f,
    };
    let expect: HashSet<FrameSpec> = [
        spec("/data/SJI_1400/f0000.fits", None),
        spec("/data/SJI_1400/f0001.fits", None),
        spec("/data/cube.fits", Some(7)),
        spec("/data/bad.fits", None),
        spec("/data/cube.fits", Some(8)),
    ]
    .into_iter()
    .collect();
    assert_eq!(got, expect);
    // An output directory with no log yet.
    let empty = tempfile::tempdir().unwrap();
    assert!(logged_frames(&[empty.path().to_path_buf()])
        .unwrap()
        .is_empty());
}

/// A sink dropped without `finish` still closes its segment cleanly.
#[test]
fn dropping_the_sink_finishes_the_segment() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 5, 11);
    {
        let mut sink = McapSink::new(dir.path(), config(0, 100), CONFIG_JSON.into()).unwrap();
        for (i, f) in a.iter().enumerate() {
            sink.write_frame(f, times(i as u64).0, times(i as u64).1)
                .unwrap();
        }
    }
    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert!(log.segments[0].complete);
    assert_eq!(log.jitter.len(), 5);
}

/// Bad input to the reader: a non-MCAP file is a bad-input error naming it; an empty segment
/// (a crash right after creating it) is a note; a missing path is an error.
#[test]
fn reader_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("notes.mcap");
    std::fs::write(&garbage, b"this is not an mcap file at all").unwrap();
    let err = read_logs(std::slice::from_ref(&garbage)).unwrap_err();
    assert_eq!(err.exit_code(), ExitCode::BadInput);
    assert!(
        err.to_string().contains("notes.mcap") && err.to_string().contains("not an MCAP"),
        "{err}"
    );

    let dir2 = tempfile::tempdir().unwrap();
    std::fs::write(
        dir2.path().join("sunjitter-20140329T140938Z-0000.mcap"),
        &mcap::MAGIC[..3],
    )
    .unwrap();
    std::fs::write(dir2.path().join("readme.txt"), b"not a segment").unwrap();
    let log = read_logs(&[dir2.path().to_path_buf()]).unwrap();
    assert_eq!(log.segments.len(), 1);
    assert!(
        log.segments[0].notes[0].contains("empty segment"),
        "{:?}",
        log.segments[0].notes
    );
    assert!(log.jitter.is_empty());

    let missing = dir.path().join("missing");
    assert_eq!(
        read_logs(&[missing]).unwrap_err().exit_code(),
        ExitCode::BadInput
    );
}

/// A record that JSON cannot carry (NaN where a number is required) is refused before it is
/// written, so the log never holds a message the reader would drop.
#[test]
fn unencodable_record_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = frames("SJI_1400", 1, 12).remove(0);
    f.align.elapsed_ms = f64::NAN;
    let mut sink = McapSink::new(dir.path(), config(0, 1), CONFIG_JSON.into()).unwrap();
    let err = sink.write_frame(&f, T0, T0).unwrap_err();
    assert_eq!(err.exit_code(), ExitCode::Failed);
    assert_eq!(sink.pending_messages(), 0);
    sink.finish().unwrap();
    assert!(read_logs(&[dir.path().to_path_buf()])
        .unwrap()
        .jitter
        .is_empty());
}

/// Writes the fixture `tools/check_mcap.py` checks in CI (see the script's docstring):
/// `$CARGO_TARGET_TMPDIR/mcap_sink_fixture/`: three finished segments and one recovered.
#[test]
fn writes_fixture_for_the_python_reader_check() {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("mcap_sink_fixture");
    let _ = std::fs::remove_dir_all(&dir);
    let a = frames("SJI_1400", 20, 13);
    let b = frames("SJI_2796", 20, 14);
    let mut sink = McapSink::new(&dir, config(15, 5), CONFIG_JSON.into()).unwrap();
    sink.write_reference_change(&reference_change(0), T0, T0)
        .unwrap();
    for i in 0..20 {
        let (obs, publish) = times(i as u64);
        sink.write_frame(&a[i], obs, publish).unwrap();
        sink.write_frame(&b[i], obs, publish).unwrap();
    }
    sink.write_log(LogLevel::Error, "/data/bad.fits", "not FITS", T0, T0)
        .unwrap();
    sink.finish().unwrap();
    // A third segment from a crashed run, then recovered.
    let mut rng = Rng(15);
    let c: Vec<_> = (100..108).map(|i| frame("SJI_1400", i, &mut rng)).collect();
    let mut crashed = McapSink::new(&dir, config(0, 3), CONFIG_JSON.into()).unwrap();
    for (i, f) in c.iter().enumerate() {
        crashed
            .write_frame(f, times(100 + i as u64).0, times(100 + i as u64).1)
            .unwrap();
    }
    crashed.abandon();
    // 40 /jitter messages at 15 per segment: 15, 15, 10 (+ the /reference and /log ones).
    let files = mcap_files(&dir);
    assert_eq!(files.len(), 4);
    assert!(matches!(
        recover_segment(&files[3]).unwrap(),
        RecoveryOutcome::Recovered { messages: 6, .. }
    ));
}

/// A damaged byte inside one chunk of a finished file: that chunk (its CRC fails) is skipped
/// and named in a note; every other message is read exactly, nothing garbled appears.
#[test]
fn damaged_chunk_is_skipped_not_garbled() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 12, 16);
    let mut sink = McapSink::new(dir.path(), config(0, 3), CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        let (obs, publish) = times(i as u64);
        sink.write_frame(f, obs, publish).unwrap();
    }
    sink.finish().unwrap();
    let file = mcap_files(dir.path()).remove(0);
    let mut bytes = std::fs::read(&file).unwrap();
    // Chunk positions from the mcap crate's summary: 4 chunks of 3 frames (flush every 3).
    let summary = mcap::read::Summary::read(&bytes).unwrap().unwrap();
    assert_eq!(summary.chunk_indexes.len(), 4);
    let second = &summary.chunk_indexes[1];
    let middle = second.chunk_start_offset + second.chunk_length / 2;
    bytes[middle as usize] ^= 0x5a;
    std::fs::write(&file, &bytes).unwrap();
    let log = read_logs(std::slice::from_ref(&file)).unwrap();
    let got: Vec<_> = log.jitter.iter().map(|m| m.record.clone()).collect();
    assert_eq!(got, [&a[..3], &a[6..]].concat());
    let notes = log.notes().join("\n");
    assert!(
        notes.contains(&format!(
            "damaged chunk at byte {}",
            second.chunk_start_offset
        )),
        "{notes}"
    );
}

/// `tick` for an idle daemon: it flushes what is pending (so a crash then loses nothing), and
/// closes the segment once it is due by time even if no further frame arrives.
#[test]
fn tick_flushes_and_rotates_when_idle() {
    let dir = tempfile::tempdir().unwrap();
    let a = frames("SJI_1400", 3, 17);
    let cfg = SinkConfig {
        segment_frames: 0,
        segment_minutes: 10.0,
        flush_every_frames: 100,
        ..SinkConfig::default()
    };
    let mut sink = McapSink::new(dir.path(), cfg.clone(), CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        sink.write_frame(f, times(i as u64).0, T0 + i as u64)
            .unwrap();
    }
    assert_eq!(sink.pending_messages(), 3);
    sink.tick(T0 + 60_000_000_000).unwrap(); // one minute later: flush only
    assert_eq!(sink.pending_messages(), 0);
    sink.abandon();
    let log = read_logs(&[dir.path().to_path_buf()]).unwrap();
    assert_eq!(
        log.jitter
            .iter()
            .map(|m| m.record.clone())
            .collect::<Vec<_>>(),
        a
    );
    assert!(!log.segments[0].complete);

    let dir2 = tempfile::tempdir().unwrap();
    let mut sink = McapSink::new(dir2.path(), cfg, CONFIG_JSON.into()).unwrap();
    sink.write_frame(&a[0], times(0).0, T0).unwrap();
    sink.tick(T0 + 599_000_000_000).unwrap(); // 9 min 59 s: still open
    sink.abandon();
    assert!(!read_logs(&[dir2.path().to_path_buf()]).unwrap().segments[0].complete);
    let dir3 = tempfile::tempdir().unwrap();
    let mut sink = McapSink::new(
        dir3.path(),
        SinkConfig {
            segment_minutes: 10.0,
            ..config(0, 100)
        },
        CONFIG_JSON.into(),
    )
    .unwrap();
    sink.write_frame(&a[0], times(0).0, T0).unwrap();
    sink.tick(T0 + 600_000_000_000).unwrap(); // 10 min: closed, finished
    sink.abandon();
    let log = read_logs(&[dir3.path().to_path_buf()]).unwrap();
    assert!(log.segments[0].complete);
    assert_eq!(log.jitter.len(), 1);
}

/// Random damage anywhere in a finished segment (single bytes set to random values, 600
/// times): the reader never panics, and every message it returns is one that was written, in
/// the written order — chunk CRCs keep damaged messages out.
#[test]
fn random_damage_never_yields_garbage() {
    let dir = scratch_dir();
    let a = frames("SJI_1400", 12, 18);
    let mut sink = McapSink::new(dir.path(), config(0, 3), CONFIG_JSON.into()).unwrap();
    for (i, f) in a.iter().enumerate() {
        sink.write_frame(f, times(i as u64).0, times(i as u64).1)
            .unwrap();
    }
    sink.finish().unwrap();
    let file = mcap_files(dir.path()).remove(0);
    let clean = std::fs::read(&file).unwrap();
    let mut rng = Rng(99);
    let mut partial = 0;
    for trial in 0..600 {
        let mut bytes = clean.clone();
        let at = (rng.next() % bytes.len() as u64) as usize;
        let value = (rng.next() % 256) as u8;
        bytes[at] = value;
        std::fs::write(&file, &bytes).unwrap();
        let Ok(log) = read_logs(std::slice::from_ref(&file)) else {
            assert!(
                at < 8,
                "trial {trial}: only damaged magic bytes may refuse the file"
            );
            continue;
        };
        let got: Vec<_> = log.jitter.iter().map(|m| m.record.clone()).collect();
        let mut expected = a.iter();
        for g in &got {
            assert!(
                expected.any(|e| e == g),
                "trial {trial}: byte {at} = {value}: a message that was never written"
            );
        }
        for m in &log.jitter {
            assert_eq!(m.log_time_ns, times(m.record.sequence).0, "trial {trial}");
        }
        partial += usize::from(got.len() < a.len());
    }
    assert!(partial > 0, "some damage should have cost messages");
}
