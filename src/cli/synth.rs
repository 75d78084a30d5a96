//! `sunjitter synth --out DIR [--frames N] [--size PX] [--cadence S] [--seed S] [--jitter SPEC]
//! [--realtime] [--start UTC] [--json]`
//!
//! Writes `synth_NNNN.fits` (primary-HDU 2-D int16 images in DN, level-1-like headers with the
//! nominal pointing, channel `SYNTH_171`) and `truth.csv` with
//! `frame,file,obs_time,dx_px,dy_px,rotation_arcsec,scale`: the injected image motion of each
//! frame in the contract's convention, relative to the nominal pointing. Each file is written
//! under a temporary name and renamed into place, so a watcher never sees a partial frame.
//!
//! `--json` prints `{"out": DIR, "channel": "SYNTH_171", "frames": N, "size": PX,
//! "cadence_s": S, "seed": S, "jitter": SPEC, "truth_csv": PATH, "files": [PATH…],
//! "seconds_per_frame": T}`, where `seconds_per_frame` is the generation plus write time.

use sunjitter_core::geometry::Similarity;
use sunjitter_core::synth::{self, CardValue, JitterSpec, SunModel, SynthConfig};
use sunjitter_core::time::{parse_fits_time, TimeScale};

use fitsio::images::{ImageDescription, ImageType};
use fitsio::FitsFile;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};
use sunjitter_core::error::Error;
/// 2024-05-01T12:00:00Z, the default DATE-OBS of frame 0 (`date -u -d 2024-05-01T12:00:00Z +%s`).
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Directory to write the frames and truth.csv into (created if missing).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Number of frames.
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    /// Frame width and height in pixels.
    #[arg(long, default_value_t = 1024)]
    pub size: usize,
    /// Seconds between frames (DATE-OBS step).
    #[arg(long, default_value_t = 12.0)]
    pub cadence: f64,
    /// Seed of the scene, the random walk and the noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sum of terms: sine:AMP_PX:PERIOD_S[:x|y], walk:STEP_PX, step:PX:AT_S[:x|y],
    /// rot:ARCSEC_PER_HOUR, scale:PER_HOUR (or `none`).
    #[arg(long, default_value = synth::DEFAULT_JITTER)]
    pub jitter: String,

    /// The Sun's differential rotation between frames: howard, snodgrass, allen, or none for
    /// a Sun that does not turn. The truth stays the telescope's motion.
    #[arg(long, default_value = "howard")]
    pub solar_rotation: sunjitter_core::solar_rotation::Profile,
    /// Write one frame per cadence in wall-clock time (to feed `watch`).
    #[arg(long)]
    pub realtime: bool,
    /// DATE-OBS of the first frame, UTC `YYYY-MM-DDTHH:MM:SS[.fff]` (default: 2024-05-01T12:00:00,
    /// or now with --realtime).
    #[arg(long)]
    pub start: Option<String>,
    #[command(flatten)]
    pub output: super::JsonArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter synth --out synth --frames 10 --size 256
  sunjitter synth --out synth --jitter sine:0.3:120,walk:0.02 --solar-rotation none --seed 7
  sunjitter synth --out incoming --realtime --cadence 12";

/// Longest time a synthetic sequence spans (its last frame's DATE-OBS stays a real date).
const MAX_SPAN_S: f64 = 100.0 * 365.25 * 86_400.0;

pub fn run(args: &Args) -> Result<ExitCode> {
    sunjitter_runtime::limits::flag_int("--frames", args.frames as u64, 1, 1_000_000)?;
    sunjitter_runtime::limits::flag_float("--cadence", args.cadence, 0.0, 365.25 * 86_400.0, true)?;
    let spec: JitterSpec = args.jitter.parse()?;
    let start_ns = start_time(args)?;
    let span_s = (args.frames - 1) as f64 * args.cadence;
    let end_ns = (start_ns as f64) + span_s * 1e9;
    if span_s > MAX_SPAN_S || end_ns >= i64::MAX as f64 {
        return Err(Error::Usage(format!(
            "--frames {} at --cadence {} s span {:.3e} s, past what a DATE-OBS can carry (100 years from --start, before 2262)",
            args.frames, args.cadence, span_s
        )));
    }
    let cfg = SynthConfig {
        solar_rotation: args.solar_rotation,
        start_ns,
        ..SynthConfig::new(args.size, args.seed, args.cadence)
    };
    let began = Instant::now();
    let model = SunModel::new(&cfg)?;
    let truth = synth::jitter_truth(&spec, args.frames, args.cadence, args.seed, args.size);
    check_motion(&truth, args.size, &args.jitter)?;
    let digits = (args.frames - 1).to_string().len().max(4);
    let frame_name = |k: usize| format!("synth_{k:0digits$}.fits");
    let truth_path = args.out.join("truth.csv");
    let mut outputs = vec![truth_path.clone()];
    outputs.extend((0..args.frames).map(|k| args.out.join(frame_name(k))));
    let outputs: Vec<&Path> = outputs.iter().map(PathBuf::as_path).collect();
    sunjitter_io::outputs::check_outputs(&outputs, &[])?;
    std::fs::create_dir_all(&args.out).map_err(|e| Error::io(&args.out, e))?;

    // Written whole once the frames are (under a temporary name, renamed).
    let mut truth_csv = String::from("frame,file,obs_time,dx_px,dy_px,rotation_arcsec,scale\n");

    let wall_start = Instant::now();
    let mut files = Vec::with_capacity(args.frames);
    for (k, motion) in truth.iter().enumerate() {
        let time_s = k as f64 * args.cadence;
        let obs_ns = start_ns + (time_s * 1e9).round() as i64;
        let image = model.render(motion, time_s, k as u64);
        let name = frame_name(k);
        let path = args.out.join(&name);
        if args.realtime {
            let due = wall_start + Duration::from_secs_f64(time_s);
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
        }
        write_frame(&path, &synth::header_cards(&cfg, k, obs_ns), &image)?;
        truth_csv.push_str(&format!(
            "{k},{name},{},{:.6},{:.6},{:.6},{:.9}\n",
            sunjitter_core::time::format_iso_utc(obs_ns),
            motion.dx,
            motion.dy,
            motion.rotation_arcsec(),
            motion.scale
        ));
        tracing::debug!(frame = k, file = %path.display(), "wrote frame");
        files.push(path);
    }
    sunjitter_io::outputs::write_file_atomically(&truth_path, |w| {
        w.write_all(truth_csv.as_bytes())
    })?;
    let per_frame = if args.realtime {
        None
    } else {
        Some(began.elapsed().as_secs_f64() / args.frames as f64)
    };

    if args.output.json {
        let doc = serde_json::json!({
            "out": args.out,
            "channel": synth::CHANNEL,
            "frames": args.frames,
            "size": args.size,
            "cadence_s": args.cadence,
            "seed": args.seed,
            "jitter": args.jitter,
            "solar_rotation": args.solar_rotation,
            "truth_csv": truth_path,
            "files": files,
            "seconds_per_frame": per_frame,
        });
        println!("{doc}");
    } else {
        println!(
            "wrote {} frames of {}x{} px (channel {}) to {}; truth in {}{}",
            args.frames,
            args.size,
            args.size,
            synth::CHANNEL,
            sunjitter_core::text::path(&args.out),
            sunjitter_core::text::path(&truth_path),
            per_frame.map_or(String::new(), |s| format!("; {s:.2} s per frame"))
        );
    }
    Ok(ExitCode::Ok)
}

/// Refuse a jitter that takes a frame off its own image or past any instrument's motion: a
/// shift beyond the frame's size, a scale outside 0.5–2, a roll beyond 180°, or a value that
/// is not finite (amplitudes such as 1e30 px).
fn check_motion(truth: &[Similarity], size: usize, spec: &str) -> Result<()> {
    let limit = size as f64;
    for (k, m) in truth.iter().enumerate() {
        let rotation = m.rotation_arcsec();
        let fine = m.dx.abs() <= limit
            && m.dy.abs() <= limit
            && (0.5..=2.0).contains(&m.scale)
            && rotation.abs() <= 180.0 * 3600.0;
        if !fine {
            return Err(Error::Usage(format!(
                "--jitter {spec}: frame {k} would move by dx {:.3e} px, dy {:.3e} px, rotation {:.3e}″, scale {:.6}: beyond ±{size} px (the frame's size), ±180° or a scale of 0.5–2; give smaller amplitudes",
                m.dx, m.dy, rotation, m.scale
            )));
        }
    }
    Ok(())
}

fn start_time(args: &Args) -> Result<i64> {
    match &args.start {
        Some(s) => parse_fits_time(s, TimeScale::Utc).map_err(|_| {
            Error::Usage(format!(
                "--start '{s}' is not a UTC time like 2024-05-01T12:00:00"
            ))
        }),
        None if args.realtime => {
            let now = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .unwrap_or_default();
            Ok(now.as_secs() as i64 * 1_000_000_000)
        }
        None => Ok(synth::DEFAULT_START_NS),
    }
}

/// fitsio names a custom primary HDU `EXTNAME = '_PRIMARY'`; a level-1 file has no such card.
fn remove_extname(f: &mut FitsFile) {
    let mut status = 0;
    // SAFETY: `f` is an open, writable cfitsio handle for the duration of the call, and the key
    // name is a NUL-terminated literal; a missing key only sets `status`, which we ignore.
    unsafe {
        fitsio::sys::ffdkey(f.as_raw(), c"EXTNAME".as_ptr(), &mut status);
    }
}

/// One primary-HDU int16 image, written under a temporary name and renamed into place.
fn write_frame(path: &Path, cards: &[synth::Card], image: &ndarray::Array2<f32>) -> Result<()> {
    let fail = |e: fitsio::errors::Error| Error::output(path, e.to_string());
    let (h, w) = image.dim();
    let desc = ImageDescription {
        data_type: ImageType::Short,
        dimensions: &[h, w],
    };
    sunjitter_io::outputs::write_atomically(path, |tmp| {
        let mut f = FitsFile::create(tmp)
            .with_custom_primary(&desc)
            .open()
            .map_err(fail)?;
        remove_extname(&mut f);
        let hdu = f.primary_hdu().map_err(fail)?;
        for card in cards {
            match &card.value {
                CardValue::Str(s) => hdu.write_key(&mut f, card.key, (s.as_str(), card.comment)),
                CardValue::Float(v) => hdu.write_key(&mut f, card.key, (*v, card.comment)),
                CardValue::Int(v) => hdu.write_key(&mut f, card.key, (*v, card.comment)),
            }
            .map_err(fail)?;
        }
        let pixels: Vec<i16> = image
            .iter()
            .map(|&v| v.round().clamp(i16::MIN as f32, i16::MAX as f32) as i16)
            .collect();
        hdu.write_image(&mut f, &pixels).map_err(fail)
    })
}
