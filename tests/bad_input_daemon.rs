//! Bad input fed to a running `watch` daemon: every kind of broken file gets
//! exactly one `/log` entry naming it and saying why, good frames around them are measured by
//! the real engine as usual, and memory stays bounded (this test is alone in its binary, so
//! the process's peak RSS is the daemon's).

mod support;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use sunjitter_core::engine::Image;
use sunjitter_core::error::Result;
use sunjitter_core::meta::FrameMeta;
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::records::MemorySink;
use sunjitter_io::sink::LogLevel;
use sunjitter_runtime::pipeline::{EngineAligner, FitsReader};
use sunjitter_runtime::ports::FrameReader;
use support::faults::*;

/// The real reader, except that one file is deleted just before it is first read: the
/// "deleted between event and read" race, made deterministic.
struct DeletingReader {
    victim: PathBuf,
    done: AtomicBool,
}

impl FrameReader for DeletingReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        if path.ends_with(&self.victim) && !self.done.swap(true, Ordering::SeqCst) {
            std::fs::remove_file(path).unwrap();
        }
        FitsReader::default().read_meta(path)
    }
    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        FitsReader::default().read_frame(spec)
    }
}

/// A header-only file with these cards.
fn header(cards: &[&str]) -> Vec<u8> {
    let mut bytes: Vec<u8> = cards
        .iter()
        .chain(std::iter::once(&"END"))
        .flat_map(|c| format!("{c:<80}").into_bytes())
        .collect();
    bytes.resize(bytes.len().div_ceil(2880) * 2880, b' ');
    bytes
}

/// The AIA frame with its pixels replaced (same header, new time).
fn with_pixels(src: &Source, name: &str, t: i64, fill: impl Fn(usize, usize) -> f32) -> Frame {
    let mut s = Source {
        cards: src.cards.clone(),
        pixels: src.pixels.clone(),
    };
    for ((y, x), v) in s.pixels.indexed_iter_mut() {
        *v = fill(y, x);
    }
    crop(&s, name, (0, 0), 128, t)
}

/// The real header and pixels as a 128 × 1 × 2 cube (two rows of the real image).
fn flat_cube(src: &Source, t: i64) -> Vec<u8> {
    let iso = sunjitter_runtime::pipeline::iso8601_utc(t);
    let mut cards = Vec::new();
    for c in &src.cards {
        let key = c[..8].trim_end();
        match key {
            "BITPIX" => cards.push(format!("{key:<8}= {:>20}", -32)),
            "NAXIS" => cards.push(format!("{key:<8}= {:>20}", 3)),
            "NAXIS2" => {
                cards.push(format!("{key:<8}= {:>20}", 1));
                cards.push(format!("{:<8}= {:>20}", "NAXIS3", 2));
            }
            "T_OBS" | "DATE-OBS" => cards.push(format!("{key:<8}= '{iso}'")),
            "BLANK" | "BSCALE" | "BZERO" | "CHECKSUM" | "DATASUM" => {}
            _ => cards.push(c.clone()),
        }
    }
    let refs: Vec<&str> = cards.iter().map(String::as_str).collect();
    let mut bytes = header(&refs);
    for v in src.pixels.slice(ndarray::s![63..65, ..]).iter() {
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    bytes.resize(bytes.len().div_ceil(2880) * 2880, 0);
    bytes
}

/// Publishes one of each kind of bad input into `root` (a link points into `outside`), each
/// atomically; `g` is a good frame's bytes. Whether file permissions stop this process's
/// reads (they do not for root).
fn publish_bad_inputs(root: &Path, outside: &Path, src: &Source, g: &[u8]) -> bool {
    let t = |i: i64| T0 + 12 * S * i;
    let publish = |name: &str, bytes: &[u8]| {
        let tmp = root.join(format!(".{name}.tmp"));
        std::fs::write(&tmp, bytes).unwrap();
        std::fs::rename(&tmp, root.join(name)).unwrap();
    };
    publish("truncated.fits", &g[..g.len() / 2]);
    publish("empty.fits", b"");
    publish(
        "not_fits.fits",
        b"<!DOCTYPE html><html>404 Not Found</html>\n",
    );
    publish(
        "nan.fits",
        &with_pixels(src, "nan.fits", t(10), |_, _| f32::NAN).bytes,
    );
    publish(
        "constant.fits",
        &with_pixels(src, "constant.fits", t(11), |_, _| 1000.0).bytes,
    );
    publish(
        "one_px.fits",
        &crop(src, "one_px.fits", (64, 64), 1, t(12)).bytes,
    );
    publish(
        "bomb.fits",
        &header(&[
            "SIMPLE  =                    T",
            "BITPIX  =                  -32",
            "NAXIS   =                    2",
            "NAXIS1  =           2000000000",
            "NAXIS2  =           2000000000",
            "DATE-OBS= '2011-02-15T00:03:00'",
        ]),
    );
    // A 3-D file where a 2-D frame is expected: the real header, two planes 1 pixel high.
    publish("flat_cube.fits", &flat_cube(src, t(14)));
    publish("ghost.fits", g);
    std::fs::create_dir(root.join("subdir.fits")).unwrap();
    let target = outside.join("elsewhere.fits");
    std::fs::write(&target, g).unwrap();
    std::os::unix::fs::symlink(&target, root.join("link.fits")).unwrap();
    // Unreadable permissions. As root (CAP_DAC_OVERRIDE) mode 000 does not stop reads: then
    // the file is a good frame and is measured, which the test checks instead.
    let denied = with_pixels(src, "denied.fits", t(13), |y, x| src.pixels[[y, x]]);
    {
        use std::os::unix::fs::PermissionsExt;
        let path = root.join("denied.fits");
        let tmp = root.join(".denied.fits.tmp");
        std::fs::write(&tmp, &denied.bytes).unwrap();
        std::fs::set_permissions(&tmp, std::fs::Permissions::from_mode(0o000)).unwrap();
        std::fs::rename(&tmp, &path).unwrap();
    }
    std::fs::File::open(root.join("denied.fits")).is_err()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_bad_input_gets_one_log_entry_and_the_daemon_goes_on() {
    let src = source();
    let dir = tempfile::tempdir().unwrap();
    let outside = tempfile::tempdir().unwrap();
    let root = canonical(dir.path());
    let t = |i: i64| T0 + 12 * S * i;
    let good: Vec<Frame> = (0..8)
        .map(|i| {
            crop(
                &src,
                &format!("good{i}.fits"),
                (0, 0),
                128,
                t(if i < 4 { i } else { 40 + i }),
            )
        })
        .collect();
    let mut config = quick_config();
    config.daemon.settle_s = 0.1;
    // Files that end early are waited for this long (unchanged) before they count as broken.
    config.daemon.incomplete_wait_s = 0.5;
    let sink = MemorySink::default();
    let reader = Arc::new(DeletingReader {
        victim: PathBuf::from("ghost.fits"),
        done: AtomicBool::new(false),
    });
    let daemon = start(
        &root,
        config.clone(),
        reader,
        Arc::new(EngineAligner::new(config.engine.clone())),
        Box::new(sink.clone()),
    );
    daemon.watching().await;
    let publish = |name: &str, bytes: &[u8]| {
        let tmp = root.join(format!(".{name}.tmp"));
        std::fs::write(&tmp, bytes).unwrap();
        std::fs::rename(&tmp, root.join(name)).unwrap();
    };
    for f in &good[..4] {
        publish(&f.name, &f.bytes);
    }
    // The reference is established from good frames before anything bad arrives.
    daemon.wait_for("4 good frames", |p| p.frames >= 4).await;

    let permissions_enforced = publish_bad_inputs(&root, outside.path(), &src, &good[0].bytes);

    for f in &good[4..] {
        publish(&f.name, &f.bytes);
    }
    // Wait until every good frame has its message and every bad input its /log entry (the
    // sink is written before the progress counters move, so this sees every record).
    let bad_names = [
        "truncated.fits",
        "empty.fits",
        "not_fits.fits",
        "nan.fits",
        "constant.fits",
        "one_px.fits",
        "bomb.fits",
        "ghost.fits",
        "subdir.fits",
        "link.fits",
        "flat_cube.fits",
    ];
    // The warning a file that ends early gets while it is waited for.
    let waiting = |message: &str| message.starts_with("incomplete, waiting");
    let all_in = {
        let sink = sink.clone();
        let good: Vec<String> = good.iter().map(|f| f.name.clone()).collect();
        move || {
            let records = sink.records();
            let s = split(&records);
            let finished = |b: &str| s.logs.iter().any(|l| l.1 == b && !waiting(&l.2));
            good.iter().all(|g| s.frames.contains_key(g))
                && bad_names.iter().all(|b| finished(b))
                && (!permissions_enforced || s.logs.iter().any(|l| l.1 == "denied.fits"))
                && (permissions_enforced || s.frames.contains_key("denied.fits"))
        }
    };
    daemon
        .wait_for("every input accounted for", move |_| all_in())
        .await;
    let progress = daemon.shutdown().await;
    let records = sink.records();
    let split = split(&records);

    // The daemon kept measuring: every good frame once, after the bad input too.
    for f in &good {
        assert_eq!(
            split.frames.get(&f.name).map(Vec::len),
            Some(1),
            "{}",
            f.name
        );
    }
    // One /log entry per bad input, naming it, with the reason; before it, for a file that
    // ends early (still being written, as far as the daemon can tell), one warning that it is
    // waited for.
    let incomplete = ["truncated.fits", "empty.fits"];
    for name in incomplete {
        let warnings: Vec<_> = split
            .logs
            .iter()
            .filter(|l| l.1 == name && waiting(&l.2))
            .collect();
        assert_eq!(warnings.len(), 1, "{name}: {warnings:?}");
        assert_eq!(warnings[0].0, LogLevel::Warning);
    }
    let mut expected: Vec<(&str, &[&str])> = vec![
        ("truncated.fits", &["truncated"]),
        ("empty.fits", &["empty", "0 bytes"]),
        ("not_fits.fits", &["not a FITS file"]),
        ("nan.fits", &["failed"]),
        ("constant.fits", &["failed"]),
        ("one_px.fits", &["failed"]),
        ("bomb.fits", &["absurd", "2000000000"]),
        ("ghost.fits", &["vanished"]),
        ("subdir.fits", &["not watched"]),
        ("link.fits", &["symbolic link not followed"]),
        ("flat_cube.fits[0]", &["failed"]),
        ("flat_cube.fits[1]", &["failed"]),
    ];
    if permissions_enforced {
        expected.push(("denied.fits", &["Permission denied"]));
    }
    let logs_for = |name: &str| -> Vec<&(LogLevel, String, String)> {
        split.logs.iter().filter(|l| l.1 == name).collect()
    };
    for (name, words) in &expected {
        let base = name.split('[').next().unwrap();
        let entries: Vec<_> = records
            .iter()
            .filter_map(|r| match r {
                sunjitter_io::records::Record::Log { file, message, .. }
                    if file_name(file) == base && file.ends_with(name) && !waiting(message) =>
                {
                    Some(message.clone())
                }
                _ => None,
            })
            .collect();
        assert_eq!(entries.len(), 1, "{name}: {entries:?}");
        assert!(
            words.iter().all(|w| entries[0].contains(w)),
            "{name}: {:?} lacks {words:?}",
            entries[0]
        );
    }
    assert_eq!(
        split.logs.len(),
        expected.len() + incomplete.len(),
        "no other /log entries: {:?}",
        split.logs
    );
    for good in &good {
        assert!(logs_for(&good.name).is_empty());
    }
    if !permissions_enforced {
        assert_eq!(split.frames.get("denied.fits").map(Vec::len), Some(1));
    }
    eprintln!(
        "bad input: {} /log entries, {} frames measured, permissions enforced: {permissions_enforced}",
        split.logs.len(),
        progress.frames
    );

    // Memory stayed bounded: no header bomb or odd shape made anything large.
    let peak_kb = peak_rss_kb("self").unwrap();
    eprintln!(
        "peak RSS of the test process (daemon included): {} MiB",
        peak_kb / 1024
    );
    assert!(peak_kb < 1024 * 1024, "peak RSS {peak_kb} kB");
}
