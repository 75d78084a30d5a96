//! sunjitter's side of tools/bench_side_by_side.py: times on one FITS pair
//! - `flow_opencv_semantics`: Farneback with OpenCV's algorithm and the paper's parameters
//!   (levels 5, winsize 101, 10 iterations, poly_n 5, poly_sigma 1.1, box window), whole frame —
//!   the same computation as `cv2.calcOpticalFlowFarneback`;
//! - `flow_engine`: the same parameters with `FlowOptions::affine_grid` inside the bounding box
//!   of the engine's disk mask (0.9 R☉ from the header), as the engine's first pass runs it;
//! - `align`: the whole engine (`align_images_owned`, default configuration, as `sunjitter
//!   align` runs it; copies of the two images made before the timing), cold: the reference
//!   prepared and its self-test run inside the timing;
//! - `align_kept`: `align` as `sunjitter align` runs it again with the same reference: its
//!   self-test cases read from where the first run kept them (a directory of this process's,
//!   filled by one untimed run), the rest cold;
//! - `align_per_frame`: one frame against a reference prepared (and self-tested) beforehand,
//!   as the daemon aligns every frame after the first against a reference;
//! - `align_previous`: NEXT against a reference prepared from PREV, cold, as `replay
//!   --reference previous` aligns every frame: PREV was aligned as a frame just before (not
//!   timed), and what that did for it (cleaning, disk check, three quarters of its
//!   reference's self-test) is reused when it is prepared as the reference;
//! - `align_cross`: the whole engine, cold, PREV against CROSS.fits, a frame of another channel
//!   (its channel differs from PREV's; `tools/bench_side_by_side.py` makes one, blurred and with
//!   its intensities bent): the flow's answer is final, at full resolution.
//!
//!     cargo run --release --example bench_pair -- PREV.fits NEXT.fits [REPEATS] [CASES] [CROSS.fits]
//!
//! CASES is a comma list of the names above (default: all but `align_cross`, which needs
//! CROSS.fits). Prints one JSON line per case with the wall and CPU seconds (all threads,
//! /proc/self/stat) of every repeat.

// The binary's allocator and its settings: measured as the command line runs. Only `tune`
// is used here; the module's checks run with the binary's tests.
#[allow(dead_code, unused_imports)]
#[path = "../src/allocator.rs"]
mod allocator;

use std::sync::Arc;
use std::time::Instant;
use sunjitter_core::engine::{
    align_images_owned, align_images_owned_in, EngineConfig, PreparedReference, Workspace,
};
use sunjitter_core::flow::{Farneback, FarnebackParams, FlowOptions, Roi};
use sunjitter_io::fits::{read_frame, FrameSpec};

fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| {
        fields
            .get(i)
            .and_then(|f| f.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    (tick(11) + tick(12)) / 100.0
}

fn main() -> anyhow::Result<()> {
    allocator::tune();
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        anyhow::bail!("usage: bench_pair PREV.fits NEXT.fits [REPEATS] [CASES] [CROSS.fits]");
    }
    let prev = read_frame(&FrameSpec::parse(&args[0]))?;
    let next = read_frame(&FrameSpec::parse(&args[1]))?;
    let repeats: usize = args.get(2).map_or(Ok(3), |s| s.parse())?;
    let cases = args.get(3).cloned().unwrap_or_else(|| {
        "flow_opencv_semantics,flow_engine,align,align_per_frame,align_previous".into()
    });
    let cross = args
        .get(4)
        .map(|p| read_frame(&FrameSpec::parse(p)))
        .transpose()?;
    if cases.contains("align_cross") && cross.is_none() {
        anyhow::bail!("align_cross needs CROSS.fits");
    }
    let cfg = EngineConfig::default();
    let (h, w) = prev.data.dim();
    let meta = &prev.meta;
    let plate = meta.plate_scale_arcsec[0].abs();
    let rsun_px = meta.rsun_arcsec.unwrap_or(0.0) / plate;
    let r = (0.9 * rsun_px).ceil() as usize;
    let (cx, cy) = (
        meta.sun_center_px[0].round() as usize,
        meta.sun_center_px[1].round() as usize,
    );
    let roi = if r > 0 && cx >= r && cy >= r && cx + r <= w && cy + r <= h {
        Roi {
            x: cx - r,
            y: cy - r,
            width: 2 * r,
            height: 2 * r,
        }
    } else {
        Roi {
            x: 0,
            y: 0,
            width: w,
            height: h,
        }
    };
    let threads = rayon::current_num_threads();
    let prepared = cases.contains("align_per_frame").then(|| {
        let prepared = PreparedReference::new(&prev, &cfg);
        std::hint::black_box(prepared.align(&next)); // the reference's one-off work
        prepared
    });
    let kept_dir = tempfile::tempdir()?;
    let keeping = || {
        let cache = sunjitter_io::self_tests::SelfTestCache::at(kept_dir.path());
        Arc::new(Workspace::keeping_self_tests(Arc::new(cache)))
    };
    if cases.contains("align_kept") {
        // The first run, which keeps the self-test.
        std::hint::black_box(align_images_owned_in(
            prev.clone(),
            next.clone(),
            &cfg,
            keeping(),
        ));
    }
    // PREV's own reference, against which it is aligned as a frame (untimed) before it
    // becomes one: prepared afresh for every repeat, since only a reference that served one
    // frame hands its self-test cases on.
    let before_prev = || PreparedReference::new(&next, &cfg);
    for case in cases.split(',') {
        let mut walls = Vec::new();
        let mut cpus = Vec::new();
        for _ in 0..repeats {
            let kept = (case == "align_previous")
                .then(before_prev)
                .and_then(|p| p.align_keeping(&prev, &cfg.channel_settings()).1);
            // What `sunjitter align` hands the engine: images it has no further use for.
            let owned = match case {
                "align" | "align_kept" => Some((prev.clone(), next.clone())),
                "align_cross" => cross.as_ref().map(|c| (prev.clone(), c.clone())),
                _ => None,
            };
            let c0 = cpu_seconds();
            let t0 = Instant::now();
            match case {
                "flow_opencv_semantics" => {
                    let mut s = Farneback::new(FarnebackParams::default())?;
                    std::hint::black_box(s.compute(
                        prev.data.view(),
                        next.data.view(),
                        None,
                        None,
                    )?);
                }
                "flow_engine" => {
                    let p = FarnebackParams::default();
                    let mut s = Farneback::new(p.clone())?
                        .with_options(FlowOptions::affine_grid(p.winsize))?;
                    std::hint::black_box(s.compute(
                        prev.data.view(),
                        next.data.view(),
                        Some(roi),
                        None,
                    )?);
                }
                "align" | "align_cross" => {
                    if let Some((reference, frame)) = owned {
                        std::hint::black_box(align_images_owned(reference, frame, &cfg));
                    }
                }
                "align_kept" => {
                    if let Some((reference, frame)) = owned {
                        let workspace = keeping();
                        std::hint::black_box(align_images_owned_in(
                            reference, frame, &cfg, workspace,
                        ));
                    }
                }
                "align_per_frame" => {
                    if let Some(p) = &prepared {
                        std::hint::black_box(p.align(&next));
                    }
                }
                "align_previous" => {
                    let reference = match kept {
                        Some(work) => PreparedReference::from_frame_work(&prev, &cfg, work),
                        None => PreparedReference::new(&prev, &cfg),
                    };
                    std::hint::black_box(reference.align_keeping(&next, &cfg.channel_settings()));
                }
                other => anyhow::bail!("unknown case {other}"),
            }
            walls.push(t0.elapsed().as_secs_f64());
            cpus.push(cpu_seconds() - c0);
        }
        println!(
            "{}",
            serde_json::json!({
                "case": case, "size": [w, h], "threads": threads,
                "roi": [roi.x, roi.y, roi.width, roi.height],
                "wall_s": walls, "cpu_s": cpus,
            })
        );
    }
    Ok(())
}
