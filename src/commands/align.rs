//! `sunjitter align REFERENCE FRAME [--json] [--aligned OUT.fits] [--quicklook OUT.png]`

use crate::engine::{self, EngineConfig};
use crate::fits::{self, FrameSpec};
use crate::record::Status;
use crate::{Error, Result};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The reference image (`FILE.fits`, or `FILE.fits[N]` for frame N of a cube).
    pub reference: String,
    /// The frame to align to the reference.
    pub frame: String,
    /// Print one JSON document on stdout.
    #[arg(long)]
    pub json: bool,
    /// Write the frame resampled onto the reference grid, with a matching WCS.
    #[arg(long, value_name = "OUT.fits")]
    pub aligned: Option<PathBuf>,
    /// Write a red (reference) / cyan (frame) composite, before and after fine alignment.
    #[arg(long, value_name = "OUT.png")]
    pub quicklook: Option<PathBuf>,
    /// Configuration file (TOML); its `[engine]` table sets the alignment parameters.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
}

pub fn run(args: &Args) -> Result<i32> {
    let reference_spec = FrameSpec::parse(&args.reference);
    let frame_spec = FrameSpec::parse(&args.frame);
    let outputs: Vec<&std::path::Path> = [&args.aligned, &args.quicklook]
        .into_iter()
        .filter_map(|p| p.as_deref())
        .collect();
    let mut inputs = vec![reference_spec.path.as_path(), frame_spec.path.as_path()];
    inputs.extend(args.config.as_deref());
    crate::outputs::check_outputs(&outputs, &inputs)?;
    let cfg = load_engine_config(args.config.as_deref())?;
    for path in args.aligned.iter().chain(&args.quicklook) {
        crate::error::check_writable(path)?;
    }
    let reference = fits::read_frame(&reference_spec)?;
    let frame = fits::read_frame(&frame_spec)?;
    let outcome = engine::align_images(&reference, &frame, &cfg);
    let mut result = outcome.result.clone();
    result.reference = args.reference.clone();
    result.frame = args.frame.clone();

    if args.json {
        let text = serde_json::to_string_pretty(&result)
            .map_err(|e| Error::Usage(format!("cannot encode result: {e}")))?;
        println!("{text}");
    } else {
        print_human(&result);
    }

    // After the report, so `--json` prints its document even when a file cannot be written.
    if let Some(path) = &args.aligned {
        engine::output::write_aligned(path, &reference, &frame, &outcome)?;
    }
    if let Some(path) = &args.quicklook {
        engine::output::write_quicklook(path, &reference, &frame, &outcome)?;
    }
    Ok(if result.status == Status::Failed {
        1
    } else {
        0
    })
}

pub(crate) fn load_engine_config(path: Option<&std::path::Path>) -> Result<EngineConfig> {
    let Some(path) = path else {
        return Ok(EngineConfig::default());
    };
    #[derive(serde::Deserialize, Default)]
    struct Partial {
        #[serde(default)]
        engine: EngineConfig,
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let parsed: Partial = toml::from_str(&text)
        .map_err(|e| Error::bad_input(path, format!("invalid configuration: {}", e.message())))?;
    Ok(parsed.engine)
}

fn print_human(r: &crate::record::AlignResult) {
    let status = match r.status {
        Status::Ok => "ok",
        Status::Degraded => "degraded",
        Status::Failed => "failed",
    };
    use crate::text::escape;
    println!("{} → {}: {status}", escape(&r.reference), escape(&r.frame));
    if let (Some(s), Some(rot), Some(dx), Some(dy)) = (r.scale, r.rotation_arcsec, r.dx_px, r.dy_px)
    {
        println!("  scale     {}", value_pm(s, r.sigma_scale, ""));
        println!(
            "  rotation  {}",
            value_pm(rot, r.sigma_rotation_arcsec, "″")
        );
        println!("  dx        {}", value_pm(dx, r.sigma_dx_px, " px"));
        println!("  dy        {}", value_pm(dy, r.sigma_dy_px, " px"));
        if let (Some(ax), Some(ay)) = (r.dx_arcsec, r.dy_arcsec) {
            println!(
                "  shift     {}, {}",
                value_pm(ax, r.sigma_dx_arcsec, "″"),
                value_pm(ay, r.sigma_dy_arcsec, "″")
            );
        }
    }
    println!(
        "  points {} inliers {} residual rms {} similarity {}",
        r.points,
        r.inliers,
        r.residual_rms_px
            .map_or("-".into(), |v| format!("{v:.4} px")),
        r.similarity.map_or("-".into(), |v| format!("{v:.3}"))
    );
    if !r.message.is_empty() {
        println!("  {}", escape(&r.message));
    }
}

/// `value ± σ` in one notation, to the σ's second significant digit (`0.0770 ± 0.0957 px`).
fn value_pm(value: f64, sigma: Option<f64>, unit: &str) -> String {
    match sigma {
        Some(s) if s.is_finite() && s > 0.0 => {
            let decimals = (1 - s.log10().floor() as i32).clamp(0, 12) as usize;
            format!("{value:.decimals$} ± {s:.decimals$}{unit}")
        }
        _ => format!("{value}{unit}"),
    }
}

#[cfg(test)]
mod tests {
    use super::value_pm;

    #[test]
    fn value_and_sigma_share_a_notation_to_the_sigmas_second_digit() {
        assert_eq!(value_pm(0.07701, Some(0.09573), " px"), "0.077 ± 0.096 px");
        assert_eq!(value_pm(-376.855, Some(800.4), "″"), "-377 ± 800″");
        assert_eq!(value_pm(0.9978772, Some(3.87e-3), ""), "0.9979 ± 0.0039");
        assert_eq!(
            value_pm(0.25008, Some(5.96e-4), " px"),
            "0.25008 ± 0.00060 px"
        );
        assert_eq!(value_pm(0.0, Some(0.0), " px"), "0 px");
    }
}
