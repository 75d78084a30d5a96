//! Farneback flow on real-derived frames (criterion). Run:
//!     cargo bench --bench flow                       # all cases
//!     cargo bench --bench flow -- 1024               # one size
//! and the OpenCV side on the same pair and parameters:
//!     python3 tools/bench_opencv_flow.py
//!
//! Pair: TRACE 171 (data/real/trace_171_19980519T222143_1024.fits) resized bilinearly to N²
//! (pixel-centre aligned), `next` = the same sampled at (x − 0.37, y + 0.61), i.e. moved by
//! (+0.37, −0.61) px — both made by the formula in `make_pair`, mirrored in the Python script.
//! Parameters: the paper's (levels 5, winsize 101, iterations 10, poly_n 5, poly_sigma 1.1,
//! pyr_scale 0.5, box window), 1 and 2 rayon threads. Cases:
//! - `opencv_semantics_N`: OpenCV's algorithm (what tools/bench_opencv_flow.py times);
//! - `affine_grid_N`: `FlowOptions::affine_grid` (unbiased affine window, grid stride 12,
//!   3 coarse / 2 finest iterations), whole frame;
//! - `affine_grid_disk_roi_N`: the same inside a full-disk mask's bounding box (0.49 of the
//!   frame's area, see `disk_roi`), as the engine runs it.

use criterion::{criterion_group, criterion_main, Criterion};
use fitsio::FitsFile;
use ndarray::Array2;
use std::hint::black_box;
use sunjitter_core::flow::{Farneback, FarnebackParams, Flow, FlowOptions, Roi};

const SHIFT: (f64, f64) = (0.37, -0.61);

fn trace() -> Array2<f32> {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/real/trace_171_19980519T222143_1024.fits"
    );
    let mut f = FitsFile::open(path).expect("TRACE FITS");
    let hdu = f.primary_hdu().expect("primary HDU");
    let v: Vec<f32> = hdu.read_image(&mut f).expect("image");
    Array2::from_shape_vec((1024, 1024), v).expect("1024²")
}

/// Bilinear sample of `img` at (x, y) with edge clamping.
fn bilinear(img: &Array2<f32>, x: f64, y: f64) -> f32 {
    let (h, w) = img.dim();
    let x = x.clamp(0.0, (w - 1) as f64);
    let y = y.clamp(0.0, (h - 1) as f64);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (x - x0 as f64, y - y0 as f64);
    let top = img[[y0, x0]] as f64 * (1.0 - ax) + img[[y0, x1]] as f64 * ax;
    let bot = img[[y1, x0]] as f64 * (1.0 - ax) + img[[y1, x1]] as f64 * ax;
    (top * (1.0 - ay) + bot * ay) as f32
}

/// (prev, next) of size n² derived from the TRACE image (see the module docs).
pub fn make_pair(src: &Array2<f32>, n: usize) -> (Array2<f32>, Array2<f32>) {
    let r = src.dim().0 as f64 / n as f64;
    let at = |x: f64, y: f64| bilinear(src, (x + 0.5) * r - 0.5, (y + 0.5) * r - 0.5);
    let prev = Array2::from_shape_fn((n, n), |(y, x)| at(x as f64, y as f64));
    let next = Array2::from_shape_fn((n, n), |(y, x)| at(x as f64 - SHIFT.0, y as f64 - SHIFT.1));
    (prev, next)
}

/// The bounding box of a full-disk mask: AIA's disk radius is ≈ 0.39 of the frame width
/// (1600 of 4096 px), the engine's mask keeps 0.9 of it → box side 0.70·n, 0.49 of the area.
fn disk_roi(n: usize) -> Roi {
    let r = (0.9 * 0.39 * n as f64).ceil() as usize;
    let c = n / 2;
    Roi {
        x: c - r,
        y: c - r,
        width: 2 * r,
        height: 2 * r,
    }
}

fn run(
    c: &mut Criterion,
    name: &str,
    pair: &(Array2<f32>, Array2<f32>),
    options: FlowOptions,
    roi: Option<Roi>,
    threads: usize,
) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let mut solver = Farneback::new(FarnebackParams::default())
        .and_then(|f| f.with_options(options))
        .expect("params");
    let mut group = c.benchmark_group(name);
    group.sample_size(10);
    // Reused output, as a daemon does frame after frame.
    let mut out = Flow {
        u: Array2::zeros((0, 0)),
        v: Array2::zeros((0, 0)),
    };
    group.bench_function(format!("{threads}_threads"), |b| {
        b.iter(|| {
            pool.install(|| {
                solver
                    .compute_into(pair.0.view(), pair.1.view(), roi, None, &mut out)
                    .expect("flow");
                black_box(&out);
            })
        })
    });
    group.finish();
}

/// Least-squares affine fit of the flow over pixels ≥ `margin` from the edge, compared with
/// the injected warp: (scale gain, rotation gain, centre translation error x, y, RMS error).
fn accuracy(f: &Flow, a: [[f64; 2]; 2], t: [f64; 2], margin: usize) -> [f64; 5] {
    let n = f.u.dim().0;
    let c = (n as f64 - 1.0) / 2.0;
    let (mut ata, mut atu, mut atv) = ([[0f64; 3]; 3], [0f64; 3], [0f64; 3]);
    let (mut se, mut cnt) = (0.0, 0.0);
    for y in margin..n - margin {
        for x in margin..n - margin {
            let (u, v) = (f.u[[y, x]] as f64, f.v[[y, x]] as f64);
            if !(u.is_finite() && v.is_finite()) {
                continue;
            }
            let r = [1.0, x as f64 - c, y as f64 - c];
            for i in 0..3 {
                for j in 0..3 {
                    ata[i][j] += r[i] * r[j];
                }
                atu[i] += r[i] * u;
                atv[i] += r[i] * v;
            }
            let tu = a[0][0] * r[1] + a[0][1] * r[2] + t[0] + c - x as f64;
            let tv = a[1][0] * r[1] + a[1][1] * r[2] + t[1] + c - y as f64;
            se += (u - tu).powi(2) + (v - tv).powi(2);
            cnt += 1.0;
        }
    }
    let m = nalgebra::Matrix3::from_fn(|i, j| ata[i][j]);
    let inv = m.try_inverse().unwrap_or_else(nalgebra::Matrix3::zeros);
    let ku = inv * nalgebra::Vector3::from(atu);
    let kv = inv * nalgebra::Vector3::from(atv);
    let (sc_t, rot_t) = ((a[0][0] + a[1][1]) / 2.0 - 1.0, (a[0][1] - a[1][0]) / 2.0);
    // A gain of a second-order term (scale of a pure rotation) means nothing.
    let gain = |m: f64, t: f64| if t.abs() > 1e-4 { m / t } else { f64::NAN };
    [
        gain((ku[1] + kv[2]) / 2.0, sc_t),
        gain((ku[2] - kv[1]) / 2.0, rot_t),
        ku[0] - t[0],
        kv[0] - t[1],
        (se / cnt).sqrt(),
    ]
}

/// With SUNJITTER_FLOW_EVAL=DIR (warps from `tools/make_flow_fixtures.py --eval DIR`), print
/// how well each setting recovers known warps of the real TRACE image, before timing.
fn accuracy_table() {
    let Ok(dir) = std::env::var("SUNJITTER_FLOW_EVAL") else {
        return;
    };
    let read = |name: &str| -> Array2<f32> {
        let b = std::fs::read(format!("{dir}/{name}")).expect("evaluation file");
        let v: Vec<f32> = b
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let n = (v.len() as f64).sqrt() as usize;
        Array2::from_shape_vec((n, n), v).expect("square")
    };
    let prev = read("prev.f32");
    println!("accuracy (fit over pixels ≥ winsize from the edge; gain = measured/injected):");
    for case in ["small", "large", "scale", "rotation"] {
        let meta: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(format!("{dir}/{case}.json")).expect("json"),
        )
        .expect("json");
        let m = |i: usize, j: usize| meta["matrix_xy"][i][j].as_f64().unwrap_or(f64::NAN);
        let a = [[m(0, 0), m(0, 1)], [m(1, 0), m(1, 1)]];
        let t = [
            meta["shift_xy"][0].as_f64().unwrap_or(0.0),
            meta["shift_xy"][1].as_f64().unwrap_or(0.0),
        ];
        let next = read(&format!("{case}_next.f32"));
        for winsize in [101usize, 127] {
            let params = FarnebackParams {
                winsize,
                ..Default::default()
            };
            for (label, opts) in [
                ("opencv_semantics", FlowOptions::default()),
                ("affine_grid", FlowOptions::affine_grid(winsize)),
            ] {
                let f = Farneback::new(params.clone())
                    .and_then(|s| s.with_options(opts))
                    .and_then(|mut s| s.compute(prev.view(), next.view(), None, None))
                    .expect("flow");
                let r = accuracy(&f, a, t, winsize);
                println!(
                    "  {case:8} winsize {winsize:3} {label:16}: gain scale {:.4} rotation {:.4}, \
                     translation error ({:+.4}, {:+.4}) px, RMS flow error {:.4} px",
                    r[0], r[1], r[2], r[3], r[4]
                );
            }
        }
    }
}

/// CPU seconds (user + system, all threads) this process has used, from /proc/self/stat.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are the 12th and 13th.
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|x| x.parse().unwrap_or(0.0))
        .collect();
    if f.len() < 13 {
        return f64::NAN;
    }
    // Clock ticks are 100 Hz on Linux.
    (f[11] + f[12]) / 100.0
}

/// With SUNJITTER_FLOW_CPU set, print wall and CPU time per call for each case (median of 3):
/// on a shared machine the CPU time is the load-independent figure.
fn cpu_table() {
    if std::env::var_os("SUNJITTER_FLOW_CPU").is_none() {
        return;
    }
    let src = trace();
    let fast = FlowOptions::affine_grid(FarnebackParams::default().winsize);
    println!("wall / CPU seconds per call (median of 3):");
    for n in [1024usize, 2048, 4096] {
        let pair = make_pair(&src, n);
        let mut cases = vec![
            ("affine_grid", fast.clone(), None),
            ("affine_grid_disk_roi", fast.clone(), Some(disk_roi(n))),
        ];
        if n <= 2048 {
            cases.insert(0, ("opencv_semantics", FlowOptions::default(), None));
        }
        for (label, opts, roi) in cases {
            for threads in [1usize, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("thread pool");
                let mut solver = Farneback::new(FarnebackParams::default())
                    .and_then(|f| f.with_options(opts.clone()))
                    .expect("params");
                let mut out = Flow {
                    u: Array2::zeros((0, 0)),
                    v: Array2::zeros((0, 0)),
                };
                let mut runs: Vec<(f64, f64)> = (0..3)
                    .map(|_| {
                        let (t0, c0) = (std::time::Instant::now(), cpu_seconds());
                        pool.install(|| {
                            solver
                                .compute_into(pair.0.view(), pair.1.view(), roi, None, &mut out)
                                .expect("flow")
                        });
                        (t0.elapsed().as_secs_f64(), cpu_seconds() - c0)
                    })
                    .collect();
                runs.sort_by(|a, b| a.0.total_cmp(&b.0));
                let (wall, cpu) = runs[1];
                println!("  {label:22} {n}² {threads} thread(s): wall {wall:.3} s, CPU {cpu:.2} s");
            }
        }
    }
}

fn bench(c: &mut Criterion) {
    accuracy_table();
    cpu_table();
    let src = trace();
    let fast = FlowOptions::affine_grid(FarnebackParams::default().winsize);
    for n in [1024usize, 2048, 4096] {
        let pair = make_pair(&src, n);
        for threads in [1usize, 2] {
            if n <= 2048 {
                // OpenCV's algorithm (dense, constant window, 10 iterations on every level).
                run(
                    c,
                    &format!("opencv_semantics_{n}"),
                    &pair,
                    FlowOptions::default(),
                    None,
                    threads,
                );
            }
            run(
                c,
                &format!("affine_grid_{n}"),
                &pair,
                fast.clone(),
                None,
                threads,
            );
            run(
                c,
                &format!("affine_grid_disk_roi_{n}"),
                &pair,
                fast.clone(),
                Some(disk_roi(n)),
                threads,
            );
        }
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
