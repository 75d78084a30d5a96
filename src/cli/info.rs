//! `sunjitter info FILE… [--json]`: what sunjitter understood of each file's header.
//!
//! One record per image, or per frame of a cube (`FILE.fits[N]` names a single frame).
//! Files that cannot be read are reported on stderr, one line each
//! (`sunjitter: <file>: <problem>`); the readable ones are still printed, and the exit code
//! is 2 if any file was bad. With `--json` stdout always holds exactly one JSON array
//! (empty when nothing could be read).

use serde::Serialize;
use std::path::{Path, PathBuf};
use sunjitter_core::error::Error;
use sunjitter_core::error::ExitCode;
use sunjitter_core::error::Result;
use sunjitter_core::meta::FrameMeta;
use sunjitter_io::fits::{self, FrameSpec};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// FITS files; a cube lists every frame, `FILE.fits[N]` only frame N.
    #[arg(required = true, value_name = "FILE")]
    pub files: Vec<PathBuf>,
    #[command(flatten)]
    pub output: super::JsonArg,
}

pub const EXAMPLES: &str = "\
Examples:
  sunjitter info data/real/aia_171_20110215T000000_128.fits data/real/eit_195_20040301T000010_128.fits
  sunjitter info 'data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits[3]'
  sunjitter info --json data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";

/// One `info --json` object: exactly the contract's fields.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct InfoRecord {
    pub file: String,
    pub hdu: usize,
    pub frame: Option<usize>,
    pub width: usize,
    pub height: usize,
    pub bitpix: i32,
    pub channel: String,
    pub instrument: Option<String>,
    pub wavelength: Option<f64>,
    /// ISO 8601 UTC, `null` when the header gives no time.
    pub obs_time: Option<String>,
    pub exptime_s: Option<f64>,
    pub plate_scale_arcsec: [f64; 2],
    pub rotation_deg: f64,
    pub sun_center_px: [f64; 2],
    pub rsun_arcsec: Option<f64>,
}

impl From<&FrameMeta> for InfoRecord {
    fn from(m: &FrameMeta) -> Self {
        InfoRecord {
            file: sunjitter_core::text::path(&m.file).into_owned(),
            hdu: m.hdu,
            frame: m.frame,
            width: m.width,
            height: m.height,
            bitpix: m.bitpix,
            channel: m.channel.clone(),
            instrument: m.instrument.clone(),
            wavelength: m.wavelength,
            obs_time: m.obs_time_iso(),
            exptime_s: m.exptime_s,
            plate_scale_arcsec: m.plate_scale_arcsec,
            rotation_deg: m.rotation_deg,
            sun_center_px: m.sun_center_px,
            rsun_arcsec: m.rsun_arcsec,
        }
    }
}

pub fn run(args: &Args) -> Result<ExitCode> {
    let mut records = Vec::new();
    let mut failed = 0;
    for file in &args.files {
        match describe(file) {
            Ok(metas) => records.extend(metas.iter().map(InfoRecord::from)),
            Err(e) => {
                eprintln!(
                    "sunjitter: {}",
                    sunjitter_core::text::escape(&e.to_string())
                );
                failed += 1;
            }
        }
    }
    if args.output.json {
        let text = serde_json::to_string_pretty(&records)
            .map_err(|e| Error::Usage(format!("JSON output: {e}")))?;
        println!("{text}");
    } else if !records.is_empty() {
        print!("{}", table(&records));
    }
    Ok(if failed > 0 {
        ExitCode::BadInput
    } else {
        ExitCode::Ok
    })
}

/// Metadata of one command-line argument: every frame of a file, or the one frame named.
pub fn describe(arg: &Path) -> Result<Vec<FrameMeta>> {
    // A name that is not UTF-8 cannot carry a `[N]` suffix typed as text: it names a file.
    let spec = match arg.to_str() {
        Some(text) => FrameSpec::parse(text),
        None => FrameSpec::file(arg),
    };
    let metas = fits::read_meta(&spec.path)?;
    let Some(n) = spec.frame else {
        return Ok(metas);
    };
    let is_2d = metas.len() == 1 && metas[0].frame.is_none();
    match metas
        .into_iter()
        .find(|m| m.frame == Some(n) || (is_2d && n == 0))
    {
        Some(m) => Ok(vec![m]),
        None => Err(Error::bad_input(
            &spec.path,
            format!("frame {n} does not exist"),
        )),
    }
}

/// A compact human-readable table, one line per image/frame.
pub fn table(records: &[InfoRecord]) -> String {
    let header = [
        "FILE",
        "SIZE",
        "BITPIX",
        "CHANNEL",
        "OBS_TIME (UTC)",
        "EXP s",
        "SCALE \"/px",
        "ROLL °",
        "SUN CENTRE px",
        "RSUN \"",
    ];
    let rows: Vec<[String; 10]> = records.iter().map(row).collect();
    let mut widths = header.map(|h| h.chars().count());
    for r in &rows {
        for (w, cell) in widths.iter_mut().zip(r) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    let mut line = |cells: &[String]| {
        let padded: Vec<String> = cells
            .iter()
            .zip(widths)
            .map(|(c, w)| format!("{c:<w$}"))
            .collect();
        out.push_str(padded.join("  ").trim_end());
        out.push('\n');
    };
    line(&header.map(String::from));
    rows.iter().for_each(|r| line(r));
    out
}

fn row(r: &InfoRecord) -> [String; 10] {
    let opt =
        |v: Option<f64>, digits: usize| v.map_or("-".to_string(), |v| format!("{v:.digits$}"));
    let file = match r.frame {
        Some(f) => format!("{}[{f}]", r.file),
        None => r.file.clone(),
    };
    let scale = if r.plate_scale_arcsec[0] == r.plate_scale_arcsec[1] {
        format!("{}", r.plate_scale_arcsec[0])
    } else {
        format!("{}×{}", r.plate_scale_arcsec[0], r.plate_scale_arcsec[1])
    };
    [
        file,
        format!("{}×{}", r.width, r.height),
        r.bitpix.to_string(),
        sunjitter_core::text::escape(&r.channel).into_owned(),
        r.obs_time.clone().unwrap_or_else(|| "-".into()),
        opt(r.exptime_s, 3),
        scale,
        format!("{:.4}", r.rotation_deg),
        format!("({:.2}, {:.2})", r.sun_center_px[0], r.sun_center_px[1]),
        opt(r.rsun_arcsec, 2),
    ]
}
