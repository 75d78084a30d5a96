//! Honest numbers on real, evolving sequences: the bundled IRIS slit-jaw cubes (3.7 h of an
//! active region through an X1 flare; data/README.md).
//!
//! Truths from physics and consistency, not from the code's own output:
//! - closure: `align(i, k)` and `align(j, k) ∘ align(i, j)` measure one transform, so their
//!   difference must lie within its σ (2σ for at least 80 % of triples, on every parameter);
//! - two channels through one telescope: SJI 1400 and SJI 2796 see the same pointing, so
//!   their chained series, each measured on its own, must agree within their σ (55–90 % of
//!   the differences inside the combined 1σ, neither too small nor inflated) and to 0.11 px
//!   RMS;
//! - a telescope's plate scale and roll do not change by per cents in hours: the chained
//!   scale stays within 0.5 % of 1 and scale and roll scatter no more than 1.5× their σ.

use std::path::{Path, PathBuf};
use std::process::Command;
use sunjitter_core::engine::{align_images, EngineConfig};
use sunjitter_core::geometry::{Similarity, ARCSEC_PER_RAD};
use sunjitter_core::record::{FrameAlignment, Status};
use sunjitter_io::fits::{read_frame, FrameSpec};

const SJI_1400: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2796: &str =
    "data/real/iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";

fn frame(cube: &str, n: usize) -> sunjitter_core::engine::Image {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(cube);
    read_frame(&FrameSpec {
        path,
        frame: Some(n),
    })
    .expect("bundled cube frame")
}

/// The transform and σ of an alignment, `None` when it failed.
fn measured(r: &sunjitter_core::record::AlignResult) -> Option<(Similarity, [f64; 4])> {
    let t = Similarity {
        scale: r.scale?,
        rotation_rad: r.rotation_arcsec? / ARCSEC_PER_RAD,
        dx: r.dx_px?,
        dy: r.dy_px?,
        center: [0.0, 0.0],
    };
    let s = [
        r.sigma_scale?,
        r.sigma_rotation_arcsec? / ARCSEC_PER_RAD,
        r.sigma_dx_px?,
        r.sigma_dy_px?,
    ];
    (r.status != Status::Failed).then_some((t, s))
}

/// Per parameter, the fraction of `triples` of `cube` whose closure lies within 2σ (the
/// three alignments' σ in quadrature), and how many triples had three answers.
fn closure(cube: &str, triples: &[(usize, usize, usize)]) -> ([f64; 4], usize) {
    let cfg = EngineConfig::default();
    let mut within = [0usize; 4];
    let mut n = 0;
    for &(i, j, k) in triples {
        let (fi, fj, fk) = (frame(cube, i), frame(cube, j), frame(cube, k));
        let c = Similarity::array_center(fi.data.ncols(), fi.data.nrows());
        let at = |m: (Similarity, [f64; 4])| (Similarity { center: c, ..m.0 }, m.1);
        let (Some(ij), Some(jk), Some(ik)) = (
            measured(&align_images(&fi, &fj, &cfg).result).map(at),
            measured(&align_images(&fj, &fk, &cfg).result).map(at),
            measured(&align_images(&fi, &fk, &cfg).result).map(at),
        ) else {
            continue;
        };
        n += 1;
        let composed = jk.0.after(&ij.0).params();
        let direct = ik.0.params();
        for p in 0..4 {
            let sigma = (ij.1[p].powi(2) + jk.1[p].powi(2) + ik.1[p].powi(2)).sqrt();
            if (composed[p] - direct[p]).abs() <= 2.0 * sigma {
                within[p] += 1;
            }
        }
    }
    (within.map(|w| w as f64 / n.max(1) as f64), n)
}

/// Triples spread over the cube: (i, i + 2, i + 5), every third frame.
fn triples(frames: usize) -> Vec<(usize, usize, usize)> {
    (0..frames - 5)
        .step_by(3)
        .map(|i| (i, i + 2, i + 5))
        .collect()
}

#[test]
fn closure_of_frame_triples_holds_within_their_sigma() {
    for (cube, frames) in [(SJI_1400, 54), (SJI_2796, 72)] {
        let (within, n) = closure(cube, &triples(frames));
        assert!(n >= 12, "{cube}: {n} triples with three answers");
        eprintln!(
            "{cube}: within 2σ of {n} triples: scale {:.0} %, rotation {:.0} %, dx {:.0} %, dy {:.0} %",
            100.0 * within[0],
            100.0 * within[1],
            100.0 * within[2],
            100.0 * within[3]
        );
        for (p, w) in ["scale", "rotation", "dx", "dy"].iter().zip(within) {
            assert!(
                w >= 0.8,
                "{cube}: {p} closes within 2σ on {:.0} % of {n}",
                100.0 * w
            );
        }
    }
}

/// `replay CUBE --out OUT`, one channel on its own; its frame messages in time order.
fn replay(cube: &str, out: &Path) -> Vec<FrameAlignment> {
    let run = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(["replay", cube, "--out"])
        .arg(out)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("SUNJITTER_LOG", "warn")
        .env("SUNJITTER_CACHE_DIR", "")
        .output()
        .expect("run sunjitter");
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let files: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    let contents = sunjitter_io::sink::read_logs(&files).expect("read the log");
    let mut frames: Vec<_> = contents.jitter.into_iter().map(|m| m.record).collect();
    frames.sort_by_key(|m| m.sequence);
    frames
}

/// Seconds of `obs_time` (ISO 8601 UTC).
fn seconds(m: &FrameAlignment) -> f64 {
    sunjitter_core::time::parse_fits_time(&m.obs_time, sunjitter_core::time::TimeScale::Utc)
        .expect("obs_time") as f64
        * 1e-9
}

#[test]
fn two_channels_of_one_telescope_agree_within_their_sigma_and_scale_and_roll_hold() {
    let dir = tempfile::tempdir().unwrap();
    let a = replay(SJI_1400, &dir.path().join("a"));
    let b = replay(SJI_2796, &dir.path().join("b"));

    // A telescope's plate scale and roll: within 0.5 % and scattering as their σ.
    for series in [&a, &b] {
        let usable: Vec<&FrameAlignment> = series
            .iter()
            .filter(|m| m.align.status != Status::Failed)
            .collect();
        for m in &usable {
            let s = m.chained_scale.unwrap();
            assert!(
                (s - 1.0).abs() <= 0.005,
                "{}: chained scale {s}",
                m.align.frame
            );
        }
        let rms_z = |value: fn(&FrameAlignment) -> (f64, f64), centre: f64| {
            let z: Vec<f64> = usable
                .iter()
                .map(|m| value(m))
                .filter(|(_, s)| *s > 0.0)
                .map(|(v, s)| (v - centre) / s)
                .collect();
            (z.iter().map(|z| z * z).sum::<f64>() / z.len() as f64).sqrt()
        };
        let scale = rms_z(
            |m| (m.chained_scale.unwrap(), m.sigma_chained_scale.unwrap()),
            1.0,
        );
        let roll = rms_z(
            |m| {
                (
                    m.chained_rotation_arcsec.unwrap(),
                    m.sigma_chained_rotation_arcsec.unwrap(),
                )
            },
            0.0,
        );
        assert!(
            scale <= 1.5 && roll <= 1.5,
            "scale {scale:.2}σ, roll {roll:.2}σ"
        );
        // Every measurement names its model; a frame that starts a reference fitted none.
        for m in &usable {
            let itself = m.reference_kind == sunjitter_core::record::ReferenceKind::Itself;
            assert_eq!(m.align.model.is_none(), itself, "{}", m.align.frame);
        }
    }

    // SJI 2796 against SJI 1400 interpolated to its times, each offset by its mean (the two
    // chains start from their own first frames).
    let chained = |s: &[FrameAlignment]| -> Vec<(f64, [f64; 2], [f64; 2])> {
        s.iter()
            .filter(|m| m.align.status != Status::Failed)
            .map(|m| {
                (
                    seconds(m),
                    [m.chained_dx_px.unwrap(), m.chained_dy_px.unwrap()],
                    [
                        m.sigma_chained_dx_px.unwrap(),
                        m.sigma_chained_dy_px.unwrap(),
                    ],
                )
            })
            .collect()
    };
    let (a, b) = (chained(&a), chained(&b));
    let mut diffs = Vec::new();
    for &(t, v, s) in &b {
        let i = a.partition_point(|x| x.0 < t);
        if i == 0 || i == a.len() {
            continue;
        }
        let (lo, hi) = (&a[i - 1], &a[i]);
        let w = (t - lo.0) / (hi.0 - lo.0);
        let lerp = |a: f64, b: f64| a + w * (b - a);
        diffs.push(std::array::from_fn::<_, 2, _>(|k| {
            let value = lerp(lo.1[k], hi.1[k]);
            let sigma = lerp(lo.2[k], hi.2[k]);
            (v[k] - value, s[k].hypot(sigma))
        }));
    }
    assert!(diffs.len() >= 60, "{} common samples", diffs.len());
    for k in 0..2 {
        let n = diffs.len() as f64;
        let mean = diffs.iter().map(|d| d[k].0).sum::<f64>() / n;
        let rms = (diffs.iter().map(|d| (d[k].0 - mean).powi(2)).sum::<f64>() / n).sqrt();
        let within = diffs
            .iter()
            .filter(|d| (d[k].0 - mean).abs() <= d[k].1)
            .count() as f64
            / n;
        eprintln!(
            "axis {k}: {rms:.3} px RMS, {:.0} % within 1σ",
            100.0 * within
        );
        assert!(rms <= 0.11, "axis {k}: {rms:.3} px RMS");
        assert!(
            (0.55..=0.9).contains(&within),
            "axis {k}: {:.0} % within 1σ",
            100.0 * within
        );
    }
}
