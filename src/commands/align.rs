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
    let cfg = load_engine_config(args.config.as_deref())?;
    for path in args.aligned.iter().chain(&args.quicklook) {
        crate::error::check_writable(path)?;
    }
    let reference = fits::read_frame(&FrameSpec::parse(&args.reference))?;
    let frame = fits::read_frame(&FrameSpec::parse(&args.frame))?;
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
        let sig = |v: Option<f64>| v.map_or("?".to_string(), |v| format!("{v:.2e}"));
        println!("  scale     {s:.7} ± {}", sig(r.sigma_scale));
        println!("  rotation  {rot:.3}″ ± {}", sig(r.sigma_rotation_arcsec));
        println!("  dx        {dx:.4} px ± {}", sig(r.sigma_dx_px));
        println!("  dy        {dy:.4} px ± {}", sig(r.sigma_dy_px));
        if let (Some(ax), Some(ay)) = (r.dx_arcsec, r.dy_arcsec) {
            println!("  shift     ({ax:.3}″, {ay:.3}″)");
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
