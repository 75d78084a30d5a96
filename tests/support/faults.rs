//! Shared by the fault-injection tests (`tests/fault_injection.rs`, `tests/bad_input_daemon.rs`,
//! `tests/crash_restart.rs`): small real-derived frames with known truths, a cheap aligner that
//! answers from the headers, and a daemon harness.
//!
//! Frames are crops of the real AIA 171 Å image (`data/real`), written by the test as 32-bit
//! float FITS with the real header (reference pixel moved by the crop offset, a new time). The
//! test knows, independently of sunjitter, each file's pixels (so the checksum a message must
//! carry) and its offset (so the shift any message between two of them must report).
#![allow(dead_code)]

use ndarray::Array2;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use sunjitter_core::engine::{AlignOutcome, Image};
use sunjitter_core::geometry::Similarity;
use sunjitter_core::record::FrameAlignment;
use sunjitter_core::record::Status;
use sunjitter_io::records::{Record, RecordSink};
use sunjitter_io::sink::LogLevel;
use sunjitter_runtime::config::Config;
use sunjitter_runtime::fake::outcome;
use sunjitter_runtime::ports::Aligner;
use sunjitter_runtime::reference::History;

pub const AIA: &str = "data/real/aia_171_20110215T000000_128.fits";
pub const S: i64 = 1_000_000_000;
/// 2011-02-15T00:00:00Z, the AIA frame's day.
pub const T0: i64 = 1_297_728_000 * S;

/// The real image and its primary header cards (80 bytes each, `END` excluded).
pub struct Source {
    pub cards: Vec<String>,
    pub pixels: Array2<f32>,
}

pub fn source() -> Source {
    let raw = std::fs::read(AIA).unwrap();
    let mut cards = Vec::new();
    for card in raw.chunks(80) {
        let text = String::from_utf8_lossy(card).to_string();
        if text.starts_with("END ") || text.trim_end() == "END" {
            break;
        }
        cards.push(text);
    }
    let pixels = sunjitter_io::fits::read_frame(&sunjitter_io::fits::FrameSpec::file(AIA))
        .unwrap()
        .data;
    Source { cards, pixels }
}

/// One frame file, as bytes, with what the test knows about it.
#[derive(Debug, Clone)]
pub struct Frame {
    pub name: String,
    pub bytes: Vec<u8>,
    /// Crop offset (x, y) in the source image.
    pub offset: (usize, usize),
    pub obs_time_ns: i64,
    /// `xxh3_64:…` of the pixels, computed here from the values written.
    pub checksum: String,
}

fn card(key: &str, value: &str) -> String {
    format!("{key:<8}= {value:>20}")
}

/// A `size`×`size` crop at `offset`, observed at `obs_time_ns`, as a FITS file.
pub fn crop(
    src: &Source,
    name: &str,
    offset: (usize, usize),
    size: usize,
    obs_time_ns: i64,
) -> Frame {
    let (ox, oy) = offset;
    let iso = sunjitter_runtime::pipeline::iso8601_utc(obs_time_ns);
    let mut cards = Vec::new();
    for c in &src.cards {
        let key = c[..8.min(c.len())].trim_end();
        let value = |k: &str| {
            sunjitter_core::header::parse_card(c.as_bytes())
                .value
                .and_then(|v| v.as_f64())
                .unwrap_or_else(|| panic!("{k} is numeric"))
        };
        let new = match key {
            "BITPIX" => card(key, "-32"),
            "NAXIS1" | "NAXIS2" => card(key, &size.to_string()),
            "CRPIX1" => card(key, &format!("{:.6}", value(key) - ox as f64)),
            "CRPIX2" => card(key, &format!("{:.6}", value(key) - oy as f64)),
            "T_OBS" | "DATE-OBS" | "DATE_OBS" => format!("{key:<8}= '{iso}'"),
            // Stale for the new data, or integer-only.
            "BLANK" | "BSCALE" | "BZERO" | "CHECKSUM" | "DATASUM" => continue,
            _ => c.clone(),
        };
        cards.push(format!("{new:<80}"));
    }
    cards.push(format!("{:<80}", "END"));
    let mut bytes: Vec<u8> = cards.concat().into_bytes();
    bytes.resize(bytes.len().div_ceil(2880) * 2880, b' ');
    let view = src.pixels.slice(ndarray::s![oy..oy + size, ox..ox + size]);
    for v in view.iter() {
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    bytes.resize(bytes.len().div_ceil(2880) * 2880, 0);
    Frame {
        name: name.to_string(),
        bytes,
        offset,
        obs_time_ns,
        checksum: xxh3_64(size, size, view.iter().copied()),
    }
}

/// 64-bit XXH3 (the xxHash reference algorithm, seed 0) of one byte string: width, height
/// (u64 LE) and each f32's bits (LE), gathered here value by value: what `pixel_checksum` must
/// say.
pub fn xxh3_64(width: usize, height: usize, pixels: impl Iterator<Item = f32>) -> String {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&(width as u64).to_le_bytes());
    bytes.extend_from_slice(&(height as u64).to_le_bytes());
    for p in pixels {
        bytes.extend_from_slice(&p.to_bits().to_le_bytes());
    }
    format!("xxh3_64:{:016x}", xxhash_rust::xxh3::xxh3_64(&bytes))
}

/// `n` crops of `size` px at pseudo-random offsets, 12 s apart, named `{prefix}NNNN.fits`.
pub fn crops(src: &Source, prefix: &str, n: usize, size: usize, seed: u64) -> Vec<Frame> {
    let mut rng = Lcg(seed);
    let room = src.pixels.ncols() - size;
    (0..n)
        .map(|i| {
            let offset = (
                rng.below(room as u64 + 1) as usize,
                rng.below(room as u64 + 1) as usize,
            );
            crop(
                src,
                &format!("{prefix}{i:04}.fits"),
                offset,
                size,
                T0 + 12 * S * i as i64,
            )
        })
        .collect()
}

/// A small seeded generator (Knuth's MMIX LCG): deterministic fault points.
pub struct Lcg(pub u64);

impl Lcg {
    pub fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 11
    }
    pub fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// Aligns by the headers alone: the shift between the two sun centres (the crops' only
/// difference). Cheap, so a thousand frames take seconds; the truth is the crop offsets.
pub struct HeaderShiftAligner;

impl Aligner for HeaderShiftAligner {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        let (r, f) = (&reference.meta, &frame.meta);
        let t = Similarity {
            scale: 1.0,
            rotation_rad: 0.0,
            dx: f.sun_center_px[0] - r.sun_center_px[0],
            dy: f.sun_center_px[1] - r.sun_center_px[1],
            center: Similarity::array_center(r.width, r.height),
        };
        let mut cov = [[0.0; 4]; 4];
        cov[2][2] = 1e-4;
        cov[3][3] = 1e-4;
        outcome(
            &r.file.display().to_string(),
            &f.file.display().to_string(),
            t,
            cov,
            Status::Ok,
        )
    }
}

/// Settings that keep the tests quick (the defaults are for real instruments).
pub fn quick_config() -> Config {
    let mut c = Config::default();
    c.daemon.reorder_window_s = 0.3;
    c.daemon.settle_s = 0.2;
    c.daemon.retry_initial_s = 0.05;
    c.daemon.retry_max_s = 0.2;
    c.daemon.retry_attempts = 3;
    c.daemon.flush_interval_s = 0.1;
    c.reference.keyframe_every_frames = 10;
    c
}

pub use super::daemon::Daemon;

pub fn start(
    dir: &Path,
    config: Config,
    reader: Arc<dyn sunjitter_runtime::ports::FrameReader>,
    aligner: Arc<dyn Aligner>,
    sink: Box<dyn RecordSink>,
) -> Daemon {
    super::daemon::spawn(dir, config, reader, aligner, sink, History::default())
}

/// Publish a frame atomically: written under a hidden temporary name, then renamed in.
pub fn publish(dir: &Path, f: &Frame) {
    let tmp = dir.join(format!(".{}.tmp", f.name));
    std::fs::write(&tmp, &f.bytes).unwrap();
    std::fs::rename(&tmp, dir.join(&f.name)).unwrap();
}

/// The `/jitter` and `/log` messages of an MCAP output directory, read back from disk by the
/// sink's reader, as records.
pub fn read_back(out: &Path) -> Vec<Record> {
    let logs = sunjitter_io::sink::read_logs(&[out.to_path_buf()]).unwrap();
    assert!(
        logs.segments.iter().all(|s| s.complete),
        "{:?}",
        logs.segments
    );
    logs.jitter
        .iter()
        .map(|m| Record::Frame {
            message: Box::new(m.record.clone()),
            log_time_ns: m.log_time_ns as i64,
        })
        .chain(logs.logs.iter().map(|m| {
            Record::log(
                m.entry.level,
                &m.entry.file,
                m.entry.message.clone(),
                m.log_time_ns as i64,
            )
        }))
        .collect()
}

/// `/jitter` messages by frame file name, `/log` entries as (level, file name, message).
pub struct Split<'a> {
    pub frames: BTreeMap<String, Vec<&'a FrameAlignment>>,
    pub logs: Vec<(LogLevel, String, String)>,
}

pub fn file_name(key: &str) -> String {
    let path = key.split('[').next().unwrap_or(key);
    Path::new(path)
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_default()
}

pub fn split(records: &[Record]) -> Split<'_> {
    let mut frames: BTreeMap<String, Vec<&FrameAlignment>> = BTreeMap::new();
    let mut logs = Vec::new();
    for r in records {
        match r {
            Record::Frame { message, .. } => frames
                .entry(file_name(&message.align.frame))
                .or_default()
                .push(message),
            Record::Log {
                level,
                file,
                message,
                ..
            } => logs.push((*level, file_name(file), message.clone())),
            Record::Reference { .. } => {}
        }
    }
    Split { frames, logs }
}

/// Every frame exactly once, carrying the checksum of the finished file's pixels and the true
/// shift to its reference.
pub fn assert_each_once_and_true(split: &Split<'_>, frames: &[Frame]) {
    let by_name: BTreeMap<&str, &Frame> = frames.iter().map(|f| (f.name.as_str(), f)).collect();
    let unexpected: Vec<&String> = split
        .frames
        .keys()
        .filter(|k| !by_name.contains_key(k.as_str()))
        .collect();
    assert!(
        unexpected.is_empty(),
        "messages for unknown frames: {unexpected:?}"
    );
    for f in frames {
        let got = split.frames.get(&f.name).map(Vec::len).unwrap_or(0);
        assert_eq!(got, 1, "{}: {got} messages", f.name);
        let m = split.frames[&f.name][0];
        assert_eq!(
            m.pixel_checksum.as_deref(),
            Some(f.checksum.as_str()),
            "{}: the pixels aligned are not the finished file's",
            f.name
        );
        let reference = by_name[file_name(&m.align.reference).as_str()];
        let dx = -(f.offset.0 as f64 - reference.offset.0 as f64);
        let dy = -(f.offset.1 as f64 - reference.offset.1 as f64);
        assert!(
            (m.align.dx_px.unwrap() - dx).abs() < 1e-6
                && (m.align.dy_px.unwrap() - dy).abs() < 1e-6,
            "{} vs {}: ({:?}, {:?}) instead of ({dx}, {dy})",
            f.name,
            reference.name,
            m.align.dx_px,
            m.align.dy_px
        );
    }
}

/// Peak resident memory of a process (kB), from `/proc/PID/status` `VmHWM`.
pub fn peak_rss_kb(pid: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}

pub fn canonical(dir: &Path) -> PathBuf {
    dir.canonicalize().unwrap()
}
