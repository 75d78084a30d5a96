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
use sunjitter::flow::{Farneback, FarnebackParams, FlowOptions, Roi};

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
    group.bench_function(format!("{threads}_threads"), |b| {
        b.iter(|| {
            pool.install(|| {
                black_box(
                    solver
                        .compute(pair.0.view(), pair.1.view(), roi, None)
                        .expect("flow"),
                )
            })
        })
    });
    group.finish();
}

fn bench(c: &mut Criterion) {
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
