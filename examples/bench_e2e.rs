//! End-to-end timing of one frame as the daemon handles it: FITS read → align (coarse → flow →
//! fit → σ) → MCAP write, with CPU time and peak RSS. Run (release):
//!
//!     sunjitter synth --out /tmp/s4096 --frames 6 --size 4096
//!     cargo run --release --example bench_e2e -- /tmp/s4096/synth_0000.fits /tmp/s4096/synth_000[1-5].fits
//!     RAYON_NUM_THREADS=1 cargo run --release --example bench_e2e -- ...   # thread scaling
//!
//! The first argument is the reference (read and prepared once — cleaned, disk-checked,
//! masked — as the daemon keeps it, timed separately); every further argument is one frame. Per frame it prints read / align / write wall times and the
//! process CPU time (all threads, from /proc/self/stat); at the end the median and min–max, the
//! peak RSS (VmHWM from /proc/self/status, i.e. for the whole run), the rayon thread count and
//! the load average (the machine may be shared: compare CPU times when wall times are noisy).

// The binary's allocator and its settings: measured as the command line runs. Only `tune`
// is used here; the module's checks run with the binary's tests.
#[allow(dead_code, unused_imports)]
#[path = "../src/allocator.rs"]
mod allocator;

use std::path::PathBuf;
use std::time::{Instant, SystemTime, UNIX_EPOCH};
use sunjitter_core::engine::{EngineConfig, PreparedReference};
use sunjitter_core::record::FrameAlignment;
use sunjitter_io::fits::{read_frame, FrameSpec};
use sunjitter_io::sink::{McapSink, SinkConfig};

/// Process CPU time (user + system, all threads) in seconds, from /proc/self/stat.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        fields
            .get(i)
            .and_then(|f| f.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    // `rest` starts at field 3 (state); clock ticks are 100 Hz on Linux.
    (tick(14 - 3) + tick(15 - 3)) / 100.0
}

fn status_kib(key: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn summary(name: &str, v: &[f64]) {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let median = if s.len() % 2 == 1 {
        s[s.len() / 2]
    } else {
        (s[s.len() / 2 - 1] + s[s.len() / 2]) / 2.0
    };
    println!(
        "{name:<10} median {median:8.3} s   min {:8.3} s   max {:8.3} s",
        s[0],
        s[s.len() - 1]
    );
}

fn main() -> anyhow::Result<()> {
    allocator::tune();
    // Stage timings: SUNJITTER_LOG=sunjitter=debug.
    if let Ok(filter) = tracing_subscriber::EnvFilter::try_from_env("SUNJITTER_LOG") {
        tracing_subscriber::fmt()
            .with_writer(std::io::stderr)
            .with_env_filter(filter)
            .init();
    }
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        anyhow::bail!("usage: bench_e2e REFERENCE.fits FRAME.fits [FRAME.fits …]");
    }
    let out = tempfile::tempdir()?;
    let cfg = EngineConfig::default();
    let load_start = loadavg();
    let reference = read_frame(&FrameSpec::parse(&args[0]))?;
    let (h, w) = reference.data.dim();
    let mut sink = McapSink::new(out.path(), SinkConfig::default(), "{}".into())?;
    println!(
        "{w}×{h}, {} frames, rayon threads {}, load average at start {load_start}",
        args.len() - 1,
        rayon::current_num_threads()
    );
    let (cpu0, t0) = (cpu_seconds(), Instant::now());
    let prepared = PreparedReference::new(&reference, &cfg);
    drop(reference);
    println!(
        "reference prepared once: {:.3} s wall, {:.2} s CPU",
        t0.elapsed().as_secs_f64(),
        cpu_seconds() - cpu0
    );
    println!("frame                      read_s  align_s  write_s  total_s    cpu_s  status");
    let (mut totals, mut cpus, mut aligns) = (Vec::new(), Vec::new(), Vec::new());
    for (k, path) in args[1..].iter().enumerate() {
        let cpu0 = cpu_seconds();
        let t0 = Instant::now();
        let frame = read_frame(&FrameSpec::parse(path))?;
        let t1 = Instant::now();
        let outcome = prepared.align(&frame);
        let t2 = Instant::now();
        let record = FrameAlignment::unchained(
            outcome.result,
            frame.meta.channel.clone(),
            frame.meta.obs_time_iso().unwrap_or_default(),
            k as u64,
            sunjitter_core::record::ReferenceKind::Fixed,
        );
        let now_ns = SystemTime::now().duration_since(UNIX_EPOCH)?.as_nanos() as u64;
        let log_ns = frame.meta.obs_time_ns.map_or(now_ns, |t| t.max(0) as u64);
        sink.write_frame(&record, log_ns, now_ns)?;
        sink.flush()?;
        let t3 = Instant::now();
        let cpu = cpu_seconds() - cpu0;
        let total = (t3 - t0).as_secs_f64();
        println!(
            "{:<25} {:7.3}  {:7.3}  {:7.3}  {:7.3}  {:7.2}  {:?} dx {:.4} dy {:.4}",
            PathBuf::from(path)
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            (t1 - t0).as_secs_f64(),
            (t2 - t1).as_secs_f64(),
            (t3 - t2).as_secs_f64(),
            total,
            cpu,
            record.align.status,
            record.align.dx_px.unwrap_or(f64::NAN),
            record.align.dy_px.unwrap_or(f64::NAN),
        );
        totals.push(total);
        cpus.push(cpu);
        aligns.push((t2 - t1).as_secs_f64());
    }
    sink.finish()?;
    summary("total", &totals);
    summary("align", &aligns);
    summary("cpu", &cpus);
    let mut sorted = totals.clone();
    sorted.sort_by(f64::total_cmp);
    println!(
        "frames per 12 s at the median wall time: {:.1}",
        12.0 / sorted[sorted.len() / 2]
    );
    println!(
        "peak RSS (VmHWM) {:.0} MiB; load average at end {}",
        status_kib("VmHWM:").unwrap_or(0) as f64 / 1024.0,
        loadavg()
    );
    Ok(())
}
