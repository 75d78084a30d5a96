//! One frame end to end, as the daemon handles it (criterion): FITS read → align (coarse →
//! flow → fit → σ) → MCAP write. Run:
//!     cargo bench --bench end_to_end               # 1024², 2048², 4096²
//!     cargo bench --bench end_to_end -- 1024       # one size
//!     RAYON_NUM_THREADS=1 cargo bench --bench end_to_end
//!
//! Frames: realistic synthetic full-disk pairs written by `sunjitter synth --frames 2 --size N`
//! (channel SYNTH_171, default jitter) into a temporary directory; frame 0 is the reference
//! (prepared once and held in memory, as the daemon keeps it), frame 1 is read, aligned and
//! logged every iteration. Peak RSS and CPU time: `examples/bench_e2e.rs` (see docs/performance.md).
//!
//! `cold_N`: the paths that prepare a new reference for the frame, both images in memory:
//! `same_channel` (`align_images`), `previous` (a reference prepared from frame 0 just after
//! frame 0 was aligned as a frame, as `replay --reference previous` runs) and `cross_channel`
//! (frame 1 as another channel shows it: blurred by 1.5 px, intensities bent by a power 0.8,
//! another channel name; the flow's answer is final).

// The binary's allocator and its settings: measured as the command line runs. Only `tune`
// is used here; the module's checks run with the binary's tests.
#[allow(dead_code, unused_imports)]
#[path = "../src/allocator.rs"]
mod allocator;

use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::process::Command;
use sunjitter_core::engine::{align_images, EngineConfig, Image, PreparedReference};
use sunjitter_core::record::FrameAlignment;
use sunjitter_io::fits::{read_frame, FrameSpec};
use sunjitter_io::sink::{McapSink, SinkConfig};

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
    let record = FrameAlignment::unchained(
        outcome.result,
        frame.meta.channel.clone(),
        frame.meta.obs_time_iso().unwrap_or_default(),
        k,
        sunjitter_core::record::ReferenceKind::Fixed,
    );
    let t = frame.meta.obs_time_ns.unwrap_or(0).max(0) as u64 + k;
    sink.write_frame(&record, t, t).expect("MCAP write");
    sink.flush().expect("MCAP flush");
    black_box(record);
}

/// Criterion filters benchmarks by name after setup; skip writing 4096² frames (seconds and
/// 64 MiB each) when the command line's filter cannot select that group.
fn selected(group: &str) -> bool {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    filters.is_empty() || filters.iter().any(|f| group.contains(f.as_str()))
}

/// `frame` as another channel shows it: blurred, its intensities bent, another channel name.
fn other_channel(frame: &Image) -> Image {
    let mut data = sunjitter_core::preprocess::gaussian_smooth(frame.data.view(), 1.5);
    let lo = data
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f32::INFINITY, f32::min);
    data.mapv_inplace(|v| (v - lo).powf(0.8) + lo);
    let mut meta = frame.meta.clone();
    meta.channel = format!("{}_OTHER", meta.channel);
    Image { data, meta }
}

fn cold(c: &mut Criterion) {
    allocator::tune();
    let cfg = EngineConfig::default();
    for size in [1024usize, 2048, 4096] {
        let name = format!("cold_{size}");
        if !selected(&name) {
            continue;
        }
        let frames = tempfile::tempdir().expect("temp dir");
        let (reference_path, frame_path) = synth_pair(frames.path(), size);
        let reference = read_frame(&FrameSpec::file(&reference_path)).expect("read reference");
        let frame = read_frame(&FrameSpec::file(&frame_path)).expect("read frame");
        let cross = other_channel(&frame);
        let mut group = c.benchmark_group(name);
        group.sample_size(10);
        group.bench_function("same_channel", |b| {
            b.iter(|| black_box(align_images(&reference, &frame, &cfg)))
        });
        group.bench_function("previous", |b| {
            b.iter_batched(
                // Frame 0's own reference, against which it is aligned (untimed) before it
                // becomes one: afresh each time, since only a reference that served one frame
                // hands its self-test cases on.
                || {
                    PreparedReference::new(&frame, &cfg)
                        .align_keeping(&reference, &cfg.channel_settings())
                        .1
                },
                |kept| {
                    let prepared = match kept {
                        Some(work) => PreparedReference::from_frame_work(&reference, &cfg, work),
                        None => PreparedReference::new(&reference, &cfg),
                    };
                    black_box(prepared.align_keeping(&frame, &cfg.channel_settings()))
                },
                criterion::BatchSize::PerIteration,
            )
        });
        group.bench_function("cross_channel", |b| {
            b.iter(|| black_box(align_images(&reference, &cross, &cfg)))
        });
        group.finish();
    }
}

fn bench(c: &mut Criterion) {
    allocator::tune();
    let cfg = EngineConfig::default();
    for size in [1024usize, 2048, 4096] {
        if !selected(&format!("end_to_end_{size}")) {
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

criterion_group!(benches, bench, cold);
criterion_main!(benches);
