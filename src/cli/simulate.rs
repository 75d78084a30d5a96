//! `sunjitter simulate IMAGE [--trials N] [--seed S] [--noise K] [--json]`: the Monte Carlo
//! accuracy test of Wang et al. (§4.1 of their paper, docs/method.md) on one real image, with
//! the cross-correlation baseline.

use ndarray::Array2;
use serde::Serialize;
use std::path::PathBuf;
use sunjitter_core::engine::{self, Image};
use sunjitter_core::error::Error;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_core::geometry::Similarity;
use sunjitter_core::resample::{HighOrder, HighOrderSpline};
use sunjitter_core::simulate::{
    contract_units, draw_truths, summarise, MonteCarloSummary, TrialOutcome, TrialRanges,
};
use sunjitter_core::stats::SplitMix64;
use sunjitter_io::fits::{self, FrameSpec};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The image to transform and align back (`FILE.fits` or `FILE.fits[N]`).
    pub image: String,
    /// Number of random similarity transforms.
    #[arg(long, default_value_t = 200)]
    pub trials: usize,
    /// Seed of the random transforms and of the noise (the same seed repeats a run).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Add Gaussian noise of K times the image's background noise to both images.
    #[arg(long, value_name = "K")]
    pub noise: Option<f64>,
    /// Add the noise once, to the image before it is transformed (Wang et al.'s wording),
    /// instead of to both images.
    #[arg(long, requires = "noise")]
    pub shared_noise: bool,
    /// Trials of the translation-only comparison with cross-correlation (0 to skip).
    #[arg(long, default_value_t = 20)]
    pub cc_trials: usize,
    #[command(flatten)]
    pub output: super::JsonArg,
    #[command(flatten)]
    pub config: super::ConfigArg,
    /// Farnebäck window in pixels, instead of the one sized from the image.
    #[arg(long, value_name = "PX")]
    pub window_px: Option<usize>,
    /// Write every trial (truth, estimate, σ) as JSON lines here.
    #[arg(long, value_name = "OUT.jsonl")]
    pub trials_out: Option<PathBuf>,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter simulate data/real/aia_171_20110215T000000_128.fits --trials 10 --cc-trials 2
  sunjitter simulate data/real/trace_171_19980519T222143_1024.fits --trials 8 --cc-trials 0 --noise 1
  sunjitter simulate 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[0]' \\
      --trials 50 --json --trials-out trials.jsonl";

#[derive(Debug, Serialize)]
struct Report {
    image: String,
    width: usize,
    height: usize,
    noise_k: Option<f64>,
    /// The noise was added once, before the transform (`--shared-noise`).
    shared_noise: bool,
    /// The image's background noise per pixel (`simulate::background_noise`), the unit of K.
    background_sigma: Option<f64>,
    ranges: TrialRanges,
    similarity_trials: MonteCarloSummary,
    /// Translation-only trials: optical flow against the cross-correlation baseline.
    translation_trials: Option<MonteCarloSummary>,
    mean_elapsed_ms: f64,
}

pub fn run(args: &Args) -> Result<ExitCode> {
    let mut config = args.config.load(&Default::default())?;
    if args.window_px.is_some() {
        config.engine.window_px = args.window_px;
        config.validate()?;
    }
    sunjitter_runtime::limits::flag_int("--trials", args.trials as u64, 1, 1_000_000)?;
    sunjitter_runtime::limits::flag_int("--cc-trials", args.cc_trials as u64, 0, 1_000_000)?;
    if let Some(k) = args.noise {
        sunjitter_runtime::limits::flag_float("--noise", k, 0.0, 1e6, false)?;
    }
    let mut cfg = config.engine;
    // The trials' transforms are random similarities, not a telescope's: scale and roll are
    // what is measured, whatever the instrument would hold them to.
    if cfg.model == sunjitter_core::engine::ModelChoice::Auto {
        cfg.model = sunjitter_core::engine::ModelChoice::Similarity;
    }
    let spec = FrameSpec::parse(&args.image);
    if let Some(out) = &args.trials_out {
        let mut inputs = vec![spec.path.as_path()];
        inputs.extend(args.config.path.as_deref());
        sunjitter_io::outputs::check_outputs(&[out], &inputs)?;
    }
    let mut reference = fits::read_frame(&spec)?;
    // Clean cosmic-ray hits and hot pixels before making frames: a spike smeared by the warp
    // is no longer recognisable as one, and would be a difference no real pair has. Every
    // suspect goes, also those the engine keeps as possibly real.
    if cfg.hot_pixel_fraction > 0.0 {
        sunjitter_core::preprocess::remove_spikes_from_scene(
            &mut reference.data,
            cfg.hot_pixel_fraction,
        );
    }
    let (h, w) = reference.data.dim();
    let center = Similarity::array_center(w, h);
    // Frames are made with a degree-9 spline, the closest to band-limited here: neither the
    // engine's quintic model nor its interpolation check's cubic frames. With the same
    // interpolator on both sides its errors cancel, and the Monte Carlo would not see what a
    // real frame (a new sampling of the sky) shows the engine.
    let spline = HighOrderSpline::new(reference.data.view(), HighOrder::Nonic);
    let background_sigma = sunjitter_core::simulate::background_noise(reference.data.view());
    let noise_sigma = match (args.noise, background_sigma) {
        (None, _) => None,
        (Some(k), Some(background)) => Some(k * background),
        (Some(_), None) => {
            return Err(Error::BadInput {
                path: PathBuf::from(&args.image),
                reason: format!(
                    "no {0}×{0} block of finite, varying pixels to measure the background \
                     noise in, so --noise has no unit",
                    sunjitter_core::simulate::NOISE_BLOCK_PX
                ),
            })
        }
    };
    let mut noise_rng = SplitMix64::new(args.seed ^ 0x05EE_D0F0_015E);

    let ranges = TrialRanges::default();
    let truths = draw_truths(args.trials, args.seed, &ranges, center);
    let progress = super::Bar::new((args.trials + args.cc_trials) as u64, "trials");
    let mut elapsed = 0.0;
    let mut lines = Vec::new();
    let mut run_trial = |truth: &Similarity, with_cc: bool, rng: &mut SplitMix64| -> TrialOutcome {
        let mut ref_data = reference.data.clone();
        let frame_data = match noise_sigma {
            Some(sigma) if args.shared_noise => {
                add_noise(&mut ref_data, sigma, rng);
                HighOrderSpline::new(ref_data.view(), HighOrder::Nonic).warp_similarity(
                    &truth.inverse(),
                    w,
                    h,
                )
            }
            Some(sigma) => {
                let mut frame_data = spline.warp_similarity(&truth.inverse(), w, h);
                add_noise(&mut ref_data, sigma, rng);
                add_noise(&mut frame_data, sigma, rng);
                frame_data
            }
            None => spline.warp_similarity(&truth.inverse(), w, h),
        };
        let r = Image {
            data: ref_data,
            meta: reference.meta.clone(),
        };
        let f = Image {
            data: frame_data,
            meta: reference.meta.clone(),
        };
        let out = engine::align_images(&r, &f, &cfg);
        elapsed += out.result.elapsed_ms;
        let cc = with_cc
            .then(|| {
                sunjitter_core::crosscorr::cc_translation(
                    r.data.view(),
                    f.data.view(),
                    out.mask.as_ref().map(|m| m.view()),
                )
            })
            .flatten()
            .map(|(dx, dy)| [dx, dy]);
        let res = &out.result;
        let trial = TrialOutcome {
            truth: contract_units(truth),
            status: res.status,
            estimate: out.transform.as_ref().map(contract_units),
            sigma: match (
                res.sigma_scale,
                res.sigma_rotation_arcsec,
                res.sigma_dx_px,
                res.sigma_dy_px,
            ) {
                (Some(a), Some(b), Some(c), Some(d)) => Some([a, b, c, d]),
                _ => None,
            },
            uabjm_sigma: match (
                res.uabjm_sigma_scale,
                res.uabjm_sigma_rotation_arcsec,
                res.uabjm_sigma_dx_px,
                res.uabjm_sigma_dy_px,
            ) {
                (Some(a), Some(b), Some(c), Some(d)) => Some([a, b, c, d]),
                _ => None,
            },
            cc,
        };
        if out.transform.is_none() {
            tracing::warn!("trial failed: {}", res.message);
        } else if res.status == sunjitter_core::record::Status::Degraded {
            tracing::debug!("trial degraded: {}", res.message);
        }
        progress.inc(1);
        trial
    };

    let outcomes: Vec<TrialOutcome> = truths
        .iter()
        .map(|t| run_trial(t, false, &mut noise_rng))
        .collect();
    let mut shift_rng = SplitMix64::new(args.seed.wrapping_add(1));
    let shift_truths: Vec<Similarity> = (0..args.cc_trials)
        .map(|_| Similarity {
            dx: shift_rng.uniform(-10.0, 10.0),
            dy: shift_rng.uniform(-10.0, 10.0),
            ..Similarity::identity(center)
        })
        .collect();
    let shift_outcomes: Vec<TrialOutcome> = shift_truths
        .iter()
        .map(|t| run_trial(t, true, &mut noise_rng))
        .collect();
    drop(progress);
    for o in outcomes.iter().chain(&shift_outcomes) {
        lines.push(serde_json::to_string(o).unwrap_or_default());
    }
    if let Some(path) = &args.trials_out {
        let text = lines.join("\n") + "\n";
        sunjitter_io::outputs::write_file_atomically(path, |w| {
            std::io::Write::write_all(w, text.as_bytes())
        })?;
    }

    let report = Report {
        image: args.image.clone(),
        width: w,
        height: h,
        noise_k: args.noise,
        shared_noise: args.shared_noise,
        background_sigma,
        ranges,
        similarity_trials: summarise(&outcomes),
        translation_trials: (!shift_outcomes.is_empty()).then(|| summarise(&shift_outcomes)),
        mean_elapsed_ms: elapsed / (outcomes.len() + shift_outcomes.len()).max(1) as f64,
    };
    if args.output.json {
        let text = serde_json::to_string_pretty(&report)
            .map_err(|e| Error::Usage(format!("cannot encode report: {e}")))?;
        println!("{text}");
    } else {
        print_table(&report);
    }
    Ok(
        if report.similarity_trials.succeeded == 0 && args.trials > 0 {
            ExitCode::Failed
        } else {
            ExitCode::Ok
        },
    )
}

fn add_noise(img: &mut Array2<f32>, sigma: f64, rng: &mut SplitMix64) {
    img.iter_mut()
        .for_each(|v| *v += (sigma * rng.gaussian()) as f32);
}

fn print_table(r: &Report) {
    let s = &r.similarity_trials;
    println!(
        "Monte Carlo on {} ({}×{}), {} trials ({} aligned{}){}",
        r.image,
        r.width,
        r.height,
        s.trials,
        s.succeeded,
        if s.degraded > 0 {
            format!(", {} of them degraded", s.degraded)
        } else {
            String::new()
        },
        r.noise_k
            .zip(r.background_sigma)
            .map(|(k, b)| format!(
                ", {} noise {k}× background σ {b:.4} = {:.4}",
                if r.shared_noise {
                    "shared"
                } else {
                    "independent"
                },
                k * b
            ))
            .unwrap_or_default()
    );
    println!(
        "{:<26}{:>14}{:>14}{:>14}{:>14}",
        "", "scale", "rotation ″", "dx px", "dy px"
    );
    type Column = fn(&sunjitter_core::simulate::ParameterSummary) -> f64;
    // The last field says whether the row is a fraction of trials (printed as one in every
    // column) or a value in each column's unit.
    let rows: [(&str, Column, bool); 8] = [
        ("RMSE of residuals", |p| p.rmse, false),
        ("mean residual (bias)", |p| p.bias, false),
        ("RMS of σ (calibrated)", |p| p.rms_sigma, false),
        ("within 1σ", |p| p.within_1sigma, true),
        ("within 3σ", |p| p.within_3sigma, true),
        ("RMS of UABJM σ", |p| p.rms_uabjm_sigma, false),
        ("UABJM within 1σ", |p| p.uabjm_within_1sigma, true),
        ("UABJM within 3σ", |p| p.uabjm_within_3sigma, true),
    ];
    if s.succeeded == 0 {
        println!("no trial aligned, so there is nothing to summarise (the warnings say why)");
    }
    for (name, f, fraction) in rows.into_iter().filter(|_| s.succeeded > 0) {
        let columns = [&s.scale, &s.rotation_arcsec, &s.dx_px, &s.dy_px].map(f);
        if fraction {
            let [a, b, c, d] = columns;
            println!("{name:<26}{a:>14.3}{b:>14.3}{c:>14.3}{d:>14.3}");
        } else {
            let [a, b, c, d] = columns;
            println!("{name:<26}{a:>14.3e}{b:>14.4}{c:>14.5}{d:>14.5}");
        }
    }
    if let Some(t) = &r.translation_trials {
        if let Some(cc) = t.cc_rmse_px {
            println!(
                "translation-only trials ({}): OF RMSE {:.5} / {:.5} px, CC RMSE {:.5} / {:.5} px",
                t.trials, t.dx_px.rmse, t.dy_px.rmse, cc[0], cc[1]
            );
        }
    }
    println!("mean time per alignment: {:.0} ms", r.mean_elapsed_ms);
}
