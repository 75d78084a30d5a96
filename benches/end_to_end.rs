//! One frame end to end, as the daemon handles it (criterion): FITS read → align (coarse →
//! flow → fit → σ) → MCAP write. Run:
//!     cargo bench --bench end_to_end               # 1024², 2048², 4096²
//!     cargo bench --bench end_to_end -- 1024       # one size
//!     RAYON_NUM_THREADS=1 cargo bench --bench end_to_end
//!
//! Frames: realistic synthetic full-disk pairs written by `sunjitter synth --frames 2 --size N`
//! (channel SYNTH_171, default jitter) into a temporary directory; frame 0 is the reference
//! (prepared once and held in memory, as the daemon keeps it), frame 1 is read, aligned and
//! logged every iteration. Peak RSS and CPU time: `examples/bench_e2e.rs` (see docs/PERFORMANCE.md).

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::process::Command;
use sunjitter::engine::{EngineConfig, PreparedReference};
use sunjitter::fits::{read_frame, FrameSpec};
use sunjitter::sink::{McapSink, SinkConfig};
use sunjitter::FrameAlignment;

fn synth_pair(dir: &Path, size: usize) -> (PathBuf, PathBuf) {
    let status = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args([
            "synth",
            "--frames",
            "2",
            "--size",
            &size.to_string(),
            "--out",
        ])
        .arg(dir)
        .status()
        .expect("run sunjitter synth");
    assert!(status.success(), "sunjitter synth failed");
    (dir.join("synth_0000.fits"), dir.join("synth_0001.fits"))
}

fn one_frame(reference: &PreparedReference, path: &Path, sink: &mut McapSink, k: u64) {
    let frame = read_frame(&FrameSpec::file(path)).expect("read frame");
    let outcome = reference.align(&frame);
    let record = FrameAlignment {
        obs_time: frame.meta.obs_time_iso().unwrap_or_default(),
        channel: frame.meta.channel.clone(),
        align: outcome.result,
        sequence: k,
        reference_kind: "fixed".into(),
        chained_dx_px: None,
        chained_dy_px: None,
        chained_dx_arcsec: None,
        chained_dy_arcsec: None,
        chained_rotation_arcsec: None,
        chained_scale: None,
        sigma_chained_dx_px: None,
        sigma_chained_dy_px: None,
        sigma_chained_dx_arcsec: None,
        sigma_chained_dy_arcsec: None,
        sigma_chained_rotation_arcsec: None,
        sigma_chained_scale: None,
        pixel_checksum: None,
    };
    let t = frame.meta.obs_time_ns.unwrap_or(0).max(0) as u64 + k;
    sink.write_frame(&record, t, t).expect("MCAP write");
    sink.flush().expect("MCAP flush");
    black_box(record);
}

/// Criterion filters benchmarks by name after setup; skip writing 4096² frames (seconds and
/// 64 MiB each) when the command line's filter cannot select that size.
fn selected(size: usize) -> bool {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    filters.is_empty()
        || filters
            .iter()
            .any(|f| format!("end_to_end_{size}").contains(f.as_str()))
}

fn bench(c: &mut Criterion) {
    let cfg = EngineConfig::default();
    for size in [1024usize, 2048, 4096] {
        if !selected(size) {
            continue;
        }
        let frames = tempfile::tempdir().expect("temp dir");
        let logs = tempfile::tempdir().expect("temp dir");
        let (reference_path, frame_path) = synth_pair(frames.path(), size);
        let reference = read_frame(&FrameSpec::file(&reference_path)).expect("read reference");
        let reference = PreparedReference::new(&reference, &cfg);
        let mut sink =
            McapSink::new(logs.path(), SinkConfig::default(), "{}".into()).expect("sink");
        let mut group = c.benchmark_group(format!("end_to_end_{size}"));
        group.sample_size(10);
        let mut k = 0u64;
        group.bench_function(format!("{}_threads", rayon::current_num_threads()), |b| {
            b.iter(|| {
                k += 1;
                one_frame(&reference, &frame_path, &mut sink, k);
            })
        });
        group.finish();
        sink.finish().expect("finish MCAP");
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
