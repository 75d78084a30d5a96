//! `sunjitter align REFERENCE FRAME [--json] [--aligned OUT.fits] [--quicklook OUT.png]`

use std::path::PathBuf;
use sunjitter_core::engine;
use sunjitter_core::error::Error;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_core::record::Status;
use sunjitter_io::fits::{self, FrameSpec};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The reference image (`FILE.fits`, or `FILE.fits[N]` for frame N of a cube).
    pub reference: String,
    /// The frame to align to the reference (`FILE.fits` or `FILE.fits[N]`).
    pub frame: String,
    #[command(flatten)]
    pub output: super::JsonArg,
    /// Write the frame resampled onto the reference grid, with a matching WCS.
    #[arg(long, value_name = "OUT.fits")]
    pub aligned: Option<PathBuf>,
    /// Write a red (reference) / cyan (frame) composite, before and after fine alignment.
    #[arg(long, value_name = "OUT.png")]
    pub quicklook: Option<PathBuf>,
    #[command(flatten)]
    pub config: super::ConfigArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter align 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[0]' 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[1]'
  sunjitter align 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[0]' 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[5]' --json --quicklook pair.png
  sunjitter align data/real/eit_171_20040301T010016_128.fits \\
      data/real/eit_195_20040301T000010_128.fits --aligned eit_195_on_171.fits";

pub fn run(args: &Args) -> Result<ExitCode> {
    let reference_spec = FrameSpec::parse(&args.reference);
    let frame_spec = FrameSpec::parse(&args.frame);
    let outputs: Vec<&std::path::Path> = [&args.aligned, &args.quicklook]
        .into_iter()
        .filter_map(|p| p.as_deref())
        .collect();
    let mut inputs = vec![reference_spec.path.as_path(), frame_spec.path.as_path()];
    inputs.extend(args.config.path.as_deref());
    sunjitter_io::outputs::check_outputs(&outputs, &inputs)?;
    let config = args.config.load(&Default::default())?;
    let read = fits::ReadOptions {
        plate_scales: config.plate_scales(),
        ..Default::default()
    };
    for path in args.aligned.iter().chain(&args.quicklook) {
        sunjitter_core::error::check_writable(path)?;
    }
    // Read side by side: at 4096² each read faults in tens of MB, one thread each.
    let (reference, frame) = std::thread::scope(|scope| {
        let reference = scope.spawn(|| fits::read_frame_with(&reference_spec, &read));
        let frame = fits::read_frame_with(&frame_spec, &read);
        let reference = reference
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
        (reference, frame)
    });
    let (reference, frame) = (reference?, frame?);
    let note = sunjitter_runtime::config::plate_scale_note(
        &config.channel_plate_scales(),
        &config.channel_names,
        &reference.meta.channel,
        &frame.meta.channel,
    );
    let cfg = config.engine;
    // The per-frame products read the images as read; without them their pixels are freed
    // as soon as the engine has its cleaned copies.
    let workspace =
        std::sync::Arc::new(sunjitter_io::self_tests::SelfTestCache::workspace_from_env());
    let (outcome, images) = if outputs.is_empty() {
        (
            engine::align_images_owned_in(reference, frame, &cfg, workspace),
            None,
        )
    } else {
        (
            engine::align_images_in(&reference, &frame, &cfg, workspace),
            Some((reference, frame)),
        )
    };
    let mut result = outcome.result.clone();
    if let Some(note) = note {
        if !result.message.is_empty() {
            result.message.push_str("; ");
        }
        result.message.push_str(&note);
    }
    result.reference = args.reference.clone();
    result.frame = args.frame.clone();

    if args.output.json {
        let text = serde_json::to_string_pretty(&result)
            .map_err(|e| Error::Usage(format!("cannot encode result: {e}")))?;
        println!("{text}");
    } else {
        print_human(&result);
    }

    // After the report, so `--json` prints its document even when a file cannot be written.
    if let Some((reference, frame)) = &images {
        if let Some(path) = &args.aligned {
            sunjitter_io::aligned::write_aligned(path, reference, frame, &outcome)?;
        }
        if let Some(path) = &args.quicklook {
            sunjitter_io::aligned::write_quicklook(path, reference, frame, &outcome)?;
        }
    }
    Ok(if result.status == Status::Failed {
        ExitCode::Failed
    } else {
        ExitCode::Ok
    })
}

fn print_human(r: &sunjitter_core::record::AlignResult) {
    let status = r.status.as_str();
    use sunjitter_core::text::{escape, value_pm};
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
