//! `inspect` analysis on a series with known truth (the motion `synth` injects, measured with
//! noise, gaps, a failed and a degraded frame, a glitch), the JSON schema, the CSV, and the
//! plot files (PNG decodes with the right size, SVG carries the axis labels).

use sunjitter_core::error::ExitCode;
use sunjitter_core::record::{AlignResult, FrameAlignment, Status};
use sunjitter_core::synth;
use sunjitter_runtime::inspect::{self, InspectOptions, LoggedFrame, SeriesKind};

const T0_NS: i64 = 1_714_564_800_000_000_000; // 2024-05-01T12:00:00Z

/// Deterministic Gaussian-ish noise (sum of 12 uniforms − 6) from a 64-bit LCG.
struct Noise(u64);
impl Noise {
    fn next(&mut self) -> f64 {
        (0..12)
            .map(|_| {
                self.0 = self
                    .0
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                (self.0 >> 11) as f64 / (1u64 << 53) as f64
            })
            .sum::<f64>()
            - 6.0
    }
}

fn record(
    channel: &str,
    seq: u64,
    t_s: f64,
    m: [f64; 4],
    sigma: f64,
    status: Status,
) -> LoggedFrame {
    let ns = T0_NS + (t_s * 1e9).round() as i64;
    let ok = status != Status::Failed;
    let v = |x: f64| ok.then_some(x);
    LoggedFrame {
        log_time_ns: ns,
        record: FrameAlignment {
            align: AlignResult {
                reference: "synth_0000.fits".into(),
                frame: format!("synth_{seq:04}.fits"),
                scale: v(m[3]),
                rotation_arcsec: v(m[2]),
                dx_px: v(m[0]),
                dy_px: v(m[1]),
                dx_arcsec: v(m[0] * 2.4),
                dy_arcsec: v(m[1] * 2.4),
                sigma_scale: v(2e-6),
                sigma_rotation_arcsec: v(0.5),
                sigma_dx_px: v(sigma),
                sigma_dy_px: v(sigma),
                sigma_dx_arcsec: v(sigma),
                sigma_dy_arcsec: v(sigma),
                uabjm_sigma_scale: v(1e-6),
                uabjm_sigma_rotation_arcsec: v(0.3),
                uabjm_sigma_dx_px: v(sigma / 2.0),
                uabjm_sigma_dy_px: v(sigma / 2.0),
                header_residual: None,
                solar_rotation: None,
                points: if ok { 400 } else { 0 },
                inliers: if ok { 370 } else { 0 },
                residual_rms_px: v(0.04),
                model: None,
                similarity: v(0.93),
                status,
                message: match status {
                    Status::Degraded => "few inliers".into(),
                    Status::Failed => "no usable structure".into(),
                    Status::Ok => String::new(),
                },
                elapsed_ms: 40.0,
            },
            channel: channel.into(),
            obs_time: sunjitter_core::time::format_iso_utc(ns),
            sequence: seq,
            reference_kind: if seq == 0 {
                sunjitter_core::record::ReferenceKind::Itself
            } else {
                sunjitter_core::record::ReferenceKind::Keyframe
            },
            chained_dx_px: v(m[0]),
            chained_dy_px: v(m[1]),
            chained_dx_arcsec: v(0.6 * m[0]),
            chained_dy_arcsec: v(0.6 * m[1]),
            chained_rotation_arcsec: v(m[2]),
            chained_scale: v(m[3]),
            sigma_chained_dx_px: v(sigma),
            sigma_chained_dy_px: v(sigma),
            sigma_chained_dx_arcsec: v(0.6 * sigma),
            sigma_chained_dy_arcsec: v(0.6 * sigma),
            sigma_chained_rotation_arcsec: v(0.5),
            sigma_chained_scale: v(2e-6),
            pixel_checksum: None,
        },
    }
}

/// The end-to-end jitter (80 frames, 12 s cadence, 0.3 px sine of period 10 frames,
/// 0.05 px random walk) as `synth` injects it, measured relative to frame 0 with σ = 0.01 px
/// noise; frames 30–34 missing, frame 50 failed, frame 20 degraded, a 0.5 px glitch at frame 65.
fn measured_series() -> (Vec<LoggedFrame>, Vec<[f64; 2]>) {
    let spec: synth::JitterSpec = "sine:0.3:120,walk:0.05,rot:30".parse().unwrap();
    let truth = synth::jitter_truth(&spec, 80, 12.0, 11, 256);
    let mut noise = Noise(3);
    let mut frames = Vec::new();
    let mut rel = Vec::new();
    for (k, m) in truth.iter().enumerate() {
        let (dx, dy) = (m.dx - truth[0].dx, m.dy - truth[0].dy);
        rel.push([dx, dy]);
        if (30..35).contains(&k) {
            continue;
        }
        let status = match k {
            50 => Status::Failed,
            20 => Status::Degraded,
            _ => Status::Ok,
        };
        let glitch = if k == 65 { 0.5 } else { 0.0 };
        let meas = [
            dx + 0.01 * noise.next() + glitch,
            dy + 0.01 * noise.next(),
            m.rotation_arcsec() + 0.5 * noise.next(),
            m.scale + 2e-6 * noise.next(),
        ];
        frames.push(record(
            synth::CHANNEL,
            k as u64,
            12.0 * k as f64,
            meas,
            0.01,
            status,
        ));
    }
    (frames, rel)
}

#[test]
fn recovers_injected_period_counts_and_glitch() {
    let (frames, rel) = measured_series();
    let a = inspect::analyse(&frames, &InspectOptions::default());
    assert_eq!(a.len(), 1);
    let c = &a[0].report;
    assert_eq!(c.channel, "SYNTH_171");
    assert_eq!((c.frames, c.ok, c.degraded, c.failed), (75, 73, 1, 1));
    assert_eq!(c.series, SeriesKind::Chained);
    let p = c.periodogram.as_ref().unwrap();
    // 74 usable samples spanning 79 × 12 s; pseudo-Nyquist 1/24 Hz.
    assert_eq!(p.samples, 74);
    assert!((p.span_s - 948.0).abs() < 1e-9);
    assert!((p.frequency_resolution_hz - 1.0 / 948.0).abs() < 1e-15);
    assert!((p.frequency_max_hz - 1.0 / 24.0).abs() <= p.frequency_step_hz);
    // The injected 120 s period, within one frequency bin, on both axes.
    for peaks in [&p.peaks.dx_px, &p.peaks.dy_px] {
        let f = peaks[0].frequency_hz;
        assert!(
            (f - 1.0 / 120.0).abs() < p.frequency_resolution_hz,
            "{peaks:?}"
        );
        assert!(peaks[0].false_alarm_probability < 1e-3);
    }
    // Truth: dy rms and p-p of the injected motion over the same frames (noise 0.01 ≪ signal).
    let kept: Vec<f64> = frames
        .iter()
        .filter(|f| f.record.align.status != Status::Failed)
        .map(|f| rel[f.record.sequence as usize][1])
        .collect();
    let mean = kept.iter().sum::<f64>() / kept.len() as f64;
    let rms = (kept.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / kept.len() as f64).sqrt();
    let got = c.chained.as_ref().unwrap().dy_px.rms.unwrap();
    assert!((got - rms).abs() < 0.005, "dy rms {got} vs truth {rms}");
    assert_eq!(c.raw.dx_px.median_sigma, Some(0.01));
    // The glitch is the only outlier.
    let seqs: Vec<(u64, &str)> = c
        .outliers
        .iter()
        .map(|o| (o.sequence, o.parameter.as_str()))
        .collect();
    assert_eq!(seqs, [(65, "dx_px")]);
}

#[test]
fn json_report_has_the_documented_fields() {
    let (frames, _) = measured_series();
    let a = inspect::analyse(&frames, &InspectOptions::default());
    let v = serde_json::to_value(inspect::report(
        &["run.mcap".into()],
        &a,
        Default::default(),
    ))
    .unwrap();
    assert_eq!(v["files"][0], "run.mcap");
    let c = &v["channels"][0];
    for key in [
        "channel",
        "frames",
        "ok",
        "degraded",
        "failed",
        "reference_kinds",
        "start",
        "end",
        "span_s",
        "median_cadence_s",
        "raw",
        "chained",
        "series",
        "periodogram",
        "outliers",
    ] {
        assert!(c.get(key).is_some(), "missing {key}");
    }
    for p in ["dx_px", "dy_px", "rotation_arcsec", "scale"] {
        for key in [
            "n",
            "mean",
            "rms",
            "min",
            "max",
            "peak_to_peak",
            "median_sigma",
        ] {
            assert!(c["raw"][p].get(key).is_some(), "raw.{p}.{key}");
        }
        let peak = &c["periodogram"]["peaks"][p][0];
        for key in [
            "period_s",
            "frequency_hz",
            "power",
            "false_alarm_probability",
        ] {
            assert!(peak.get(key).is_some(), "peaks.{p}.{key}");
        }
    }
    for key in [
        "series",
        "samples",
        "span_s",
        "frequency_min_hz",
        "frequency_max_hz",
        "frequency_step_hz",
        "frequency_resolution_hz",
        "oversampling",
        "frequencies",
        "peaks",
    ] {
        assert!(c["periodogram"].get(key).is_some(), "periodogram.{key}");
    }
    assert_eq!(c["start"], "2024-05-01T12:00:00.000Z");
    assert_eq!(c["series"], "chained");
    let o = &c["outliers"][0];
    for key in [
        "sequence",
        "obs_time",
        "log_time_ns",
        "frame",
        "parameter",
        "series",
        "value",
        "baseline",
        "deviation",
        "sigma",
        "z",
    ] {
        assert!(o.get(key).is_some(), "outliers.{key}");
    }
}

#[test]
fn csv_has_a_row_per_frame() {
    let (frames, _) = measured_series();
    let a = inspect::analyse(&frames, &InspectOptions::default());
    let mut buf = Vec::new();
    inspect::csv::write_csv(&mut buf, &a).unwrap();
    let text = String::from_utf8(buf).unwrap();
    assert_eq!(text.lines().count(), 1 + 75);
    let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
    assert_eq!(header[0], "log_time_ns");
    let status = header.iter().position(|h| *h == "status").unwrap();
    let failed = text
        .lines()
        .filter(|l| l.split(',').nth(status) == Some("failed"))
        .count();
    assert_eq!(failed, 1);
}

/// Walk the PNG chunks, checking each CRC; return (width, height, IDAT bytes).
fn png_info(bytes: &[u8]) -> (u32, u32, usize) {
    fn crc32(data: &[u8]) -> u32 {
        let mut c = 0xFFFF_FFFFu32;
        for &b in data {
            c ^= b as u32;
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let (mut pos, mut w, mut h, mut idat, mut ended) = (8, 0, 0, 0, false);
    while pos + 12 <= bytes.len() {
        let len = u32::from_be_bytes(bytes[pos..pos + 4].try_into().unwrap()) as usize;
        let kind = &bytes[pos + 4..pos + 8];
        let data = &bytes[pos + 8..pos + 8 + len];
        let crc = u32::from_be_bytes(bytes[pos + 8 + len..pos + 12 + len].try_into().unwrap());
        assert_eq!(
            crc,
            crc32(&bytes[pos + 4..pos + 8 + len]),
            "bad CRC in {:?}",
            kind
        );
        match kind {
            b"IHDR" => {
                w = u32::from_be_bytes(data[0..4].try_into().unwrap());
                h = u32::from_be_bytes(data[4..8].try_into().unwrap());
            }
            b"IDAT" => idat += len,
            b"IEND" => ended = true,
            _ => {}
        }
        pos += 12 + len;
    }
    assert!(ended, "no IEND");
    (w, h, idat)
}

#[test]
fn plots_are_written_and_readable() {
    let (frames, _) = measured_series();
    let mut frames = frames;
    // A second channel, to check the legend and colours.
    let (other, _) = measured_series();
    frames.extend(other.into_iter().map(|mut f| {
        f.record.channel = "SYNTH_304".into();
        f
    }));
    let a = inspect::analyse(&frames, &InspectOptions::default());
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("jitter.png");
    let svg = dir.path().join("jitter.svg");
    inspect::plot::write_plot(&a, &png).unwrap();
    inspect::plot::write_plot(&a, &svg).unwrap();
    let (w, h, idat) = png_info(&std::fs::read(&png).unwrap());
    // One row of panels per channel: the one-channel figure is as wide and less tall.
    let one = dir.path().join("one.png");
    inspect::plot::write_plot(&a[..1], &one).unwrap();
    let (w1, h1, _) = png_info(&std::fs::read(&one).unwrap());
    assert_eq!((w, w1), (2000, 2000));
    assert!(h > h1, "two channels {h} px, one {h1} px");
    // A blank RGB image deflates to a few kB; curves, bands and text make far more.
    assert!(idat > 40_000, "IDAT only {idat} bytes");
    let text = std::fs::read_to_string(&svg).unwrap();
    // The series starts 2024-05-01 12:00:00 UTC and lasts 948 s: the first time tick carries
    // the date, the later ones the clock.
    for label in [
        "dx [px]",
        "dy [px]",
        "rotation [″]",
        "scale - 1 [ppm]",
        "period [s]",
        "time (UTC)",
        "2024-05-01 12:00",
        "\n12:15\n",
        "SYNTH_171",
        "SYNTH_304",
        "raw (frame → its reference)",
        "chained (to the first reference)",
        "120.",
        "degraded",
        "failed",
    ] {
        assert!(text.contains(label), "SVG lacks {label:?}");
    }
    // An unknown extension is a usage error (exit 2), not a panic.
    let err = inspect::plot::write_plot(&a, &dir.path().join("x.gif")).unwrap_err();
    assert_eq!(err.exit_code(), ExitCode::BadInput);
}

#[test]
fn command_reads_a_run_split_over_segments() {
    use sunjitter_io::sink::{McapSink, SinkConfig};
    let (frames, _) = measured_series();
    let dir = tempfile::tempdir().unwrap();
    let logs = dir.path().join("log");
    let config = SinkConfig {
        segment_frames: 30,
        segment_minutes: 0.0,
        ..SinkConfig::default()
    };
    let mut sink = McapSink::new(&logs, config, "{}".into()).unwrap();
    for f in &frames {
        let t = f.log_time_ns as u64;
        sink.write_frame(&f.record, t, t + 1_000_000_000).unwrap();
    }
    sink.finish().unwrap();
    let segments = sink.segment_paths().len();
    assert_eq!(segments, 3);

    let csv = dir.path().join("series.csv");
    let png = dir.path().join("series.png");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("inspect")
        .arg(&logs)
        .arg("--json")
        .arg("--csv")
        .arg(&csv)
        .arg("--plot")
        .arg(&png)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["files"].as_array().unwrap().len(), 3);
    let c = &v["channels"][0];
    assert_eq!(
        (c["frames"].as_u64(), c["failed"].as_u64()),
        (Some(75), Some(1))
    );
    let period = c["periodogram"]["peaks"]["dx_px"][0]["period_s"]
        .as_f64()
        .unwrap();
    let bin = c["periodogram"]["frequency_resolution_hz"]
        .as_f64()
        .unwrap();
    assert!((1.0 / period - 1.0 / 120.0).abs() < bin, "{period}");
    assert_eq!(std::fs::read_to_string(&csv).unwrap().lines().count(), 76);
    assert!(std::fs::metadata(&png).unwrap().len() > 40_000);

    // Human output, and bad input: a missing log is exit 2 with the path named.
    let text = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("inspect")
        .arg(&logs)
        .output()
        .unwrap();
    let text = String::from_utf8(text.stdout).unwrap();
    assert!(
        text.contains("SYNTH_171: 75 frames (73 ok, 1 degraded, 1 failed)"),
        "{text}"
    );
    let missing = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("inspect")
        .arg(dir.path().join("nope.mcap"))
        .output()
        .unwrap();
    assert_eq!(missing.status.code(), Some(ExitCode::BadInput.code()));
    assert!(String::from_utf8_lossy(&missing.stderr).contains("nope.mcap"));
}

/// A file that never becomes a frame (not FITS) is only on `/log`; `inspect` must still
/// account for it, while the real frames land in their channels.
#[test]
fn inspect_accounts_for_inputs_that_only_reached_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("log");
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let bad = root.join("data/malformed/not_actually_fits.fits");
    let replay = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("replay")
        .arg(&bad)
        .arg(root.join("data/real/eit_171_20040301T010016_128.fits"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        replay.status.success(),
        "{}",
        String::from_utf8_lossy(&replay.stderr)
    );
    let json = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(["inspect", "--json"])
        .arg(&out)
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&json.stdout).unwrap();
    assert_eq!(v["channels"].as_array().unwrap().len(), 1);
    assert_eq!(v["channels"][0]["frames"], 1);
    assert_eq!(v["log"]["errors"], 1);
    let unaligned = v["log"]["unaligned"].as_array().unwrap();
    assert_eq!(unaligned.len(), 1);
    assert!(unaligned[0]["file"]
        .as_str()
        .unwrap()
        .ends_with("not_actually_fits.fits"));
    assert!(unaligned[0]["message"]
        .as_str()
        .unwrap()
        .contains("not a FITS file"));

    let text = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("inspect")
        .arg(&out)
        .output()
        .unwrap();
    let text = String::from_utf8(text.stdout).unwrap();
    assert!(
        text.contains("/log: 1 error(s), 0 warning(s); 1 input(s) with no alignment"),
        "{text}"
    );
}
