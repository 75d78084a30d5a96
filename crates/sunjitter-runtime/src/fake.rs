//! Test doubles with known truths (used by unit and integration tests; not for production).
//!
//! A fake frame is a real, minimal FITS file (so completeness checks, partial writes and
//! renames behave as with real data) whose header cards carry the channel, the observation
//! time and the frame's true pointing `T` (origin grid → frame grid). [`TruthAligner`]
//! answers `T_frame ∘ T_reference⁻¹`, the exact transform between two such frames, with a
//! fixed covariance, so chained values have a known answer.

use crate::ports::{Aligner, FrameReader};
use ndarray::Array2;
use std::collections::HashMap;
use std::path::Path;
use sunjitter_core::engine::{AlignOutcome, Image};
use sunjitter_core::geometry::Covariance4 as Cov4;
use sunjitter_core::geometry::Similarity;
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::record::{AlignResult, Status, TransformFields};
use sunjitter_core::{Error, Result};
use sunjitter_io::fits::FrameSpec;

/// Size of fake images (not square, so x/y mix-ups show).
pub const WIDTH: usize = 12;
pub const HEIGHT: usize = 9;

/// One fake frame's content.
#[derive(Debug, Clone, PartialEq)]
pub struct FakeFrame {
    pub channel: String,
    pub obs_time_ns: Option<i64>,
    /// True pointing: origin grid → this frame's grid.
    pub truth: Similarity,
    /// The aligner fails on any pair involving this frame.
    pub bad: bool,
    /// The aligner reports `degraded` on any pair involving this frame.
    pub degraded: bool,
}

impl FakeFrame {
    pub fn new(channel: &str, obs_time_ns: i64, scale: f64, rot: f64, dx: f64, dy: f64) -> Self {
        FakeFrame {
            channel: channel.into(),
            obs_time_ns: Some(obs_time_ns),
            truth: Similarity {
                scale,
                rotation_rad: rot,
                dx,
                dy,
                center: Similarity::array_center(WIDTH, HEIGHT),
            },
            bad: false,
            degraded: false,
        }
    }

    /// The frame as FITS bytes: primary HDU with the cards, then a tiny 8-bit image.
    pub fn to_fits(&self) -> Vec<u8> {
        let mut cards = vec![
            "SIMPLE  =                    T".to_string(),
            "BITPIX  =                    8".to_string(),
            "NAXIS   =                    2".to_string(),
            format!("NAXIS1  = {:>20}", WIDTH),
            format!("NAXIS2  = {:>20}", HEIGHT),
            format!("CHANNEL = '{}'", self.channel),
        ];
        if let Some(t) = self.obs_time_ns {
            cards.push(format!("OBS_NS  = {t:>20}"));
        }
        let t = &self.truth;
        cards.push(format!("T_SCALE = {:>20e}", t.scale));
        cards.push(format!("T_ROT   = {:>20e}", t.rotation_rad));
        cards.push(format!("T_DX    = {:>20e}", t.dx));
        cards.push(format!("T_DY    = {:>20e}", t.dy));
        cards.push(format!(
            "T_BAD   = {:>20}",
            if self.bad { "T" } else { "F" }
        ));
        cards.push(format!(
            "T_DEGR  = {:>20}",
            if self.degraded { "T" } else { "F" }
        ));
        cards.push("END".to_string());
        let mut bytes = Vec::new();
        for card in cards {
            let mut c = card.into_bytes();
            c.resize(80, b' ');
            bytes.extend(c);
        }
        bytes.resize(bytes.len().div_ceil(2880) * 2880, b' ');
        let data_start = bytes.len();
        bytes.extend(std::iter::repeat_n(7u8, WIDTH * HEIGHT));
        bytes.resize(data_start + (WIDTH * HEIGHT).div_ceil(2880) * 2880, 0);
        bytes
    }

    fn parse(path: &Path) -> Result<FakeFrame> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        if !bytes.starts_with(b"SIMPLE  =") {
            return Err(Error::bad_input(path, "not a FITS file"));
        }
        let mut cards = HashMap::new();
        for card in bytes.chunks(80) {
            let card = String::from_utf8_lossy(card);
            if card.starts_with("END ") {
                break;
            }
            if card.len() > 10 && &card[8..10] == "= " {
                cards.insert(card[..8].trim().to_string(), card[10..].trim().to_string());
            }
        }
        let num = |k: &str| -> Result<f64> {
            cards
                .get(k)
                .and_then(|v| v.parse::<f64>().ok())
                .ok_or_else(|| Error::bad_header(path, format!("{k} missing")))
        };
        let channel = cards
            .get("CHANNEL")
            .map(|v| v.trim_matches('\'').trim().to_string())
            .ok_or_else(|| Error::bad_header(path, "CHANNEL missing"))?;
        Ok(FakeFrame {
            channel,
            obs_time_ns: cards.get("OBS_NS").and_then(|v| v.parse().ok()),
            truth: Similarity {
                scale: num("T_SCALE")?,
                rotation_rad: num("T_ROT")?,
                dx: num("T_DX")?,
                dy: num("T_DY")?,
                center: Similarity::array_center(WIDTH, HEIGHT),
            },
            bad: cards.get("T_BAD").is_some_and(|v| v == "T"),
            degraded: cards.get("T_DEGR").is_some_and(|v| v == "T"),
        })
    }

    /// The image the fake reader returns: pixels carry the truth for [`TruthAligner`].
    pub fn image(&self, path: &Path) -> Image {
        let mut data = Array2::<f32>::zeros((HEIGHT, WIDTH));
        data[[0, 0]] = if self.bad { 1.0 } else { 0.0 };
        data[[0, 1]] = if self.degraded { 1.0 } else { 0.0 };
        Image {
            data,
            meta: fake_meta(path, &self.channel, self.obs_time_ns),
        }
    }
}

pub fn fake_meta(path: &Path, channel: &str, obs_time_ns: Option<i64>) -> FrameMeta {
    FrameMeta {
        file: path.to_path_buf(),
        hdu: 0,
        frame: None,
        width: WIDTH,
        height: HEIGHT,
        bitpix: 8,
        channel: channel.into(),
        instrument: None,
        wavelength: None,
        obs_time_ns,
        exptime_s: None,
        plate_scale_arcsec: [1.0, 1.0],
        rotation_deg: 0.0,
        sun_center_px: [0.0, 0.0],
        observer: Default::default(),
        rsun_arcsec: None,
    }
}

/// Reads fake frames. Truths are kept per path so the aligner can look them up.
#[derive(Debug, Default)]
pub struct FakeReader {
    truths: std::sync::Mutex<HashMap<std::path::PathBuf, FakeFrame>>,
}

impl FakeReader {
    /// The truth of a frame read so far.
    pub fn truth(&self, path: &Path) -> Option<FakeFrame> {
        self.truths.lock().ok()?.get(path).cloned()
    }
}

impl FrameReader for FakeReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        // Refuse incomplete files as the real reader does.
        fits_completeness(path).map_err(|reason| Error::bad_input(path, reason))?;
        let frame = FakeFrame::parse(path)?;
        Ok(vec![fake_meta(path, &frame.channel, frame.obs_time_ns)])
    }

    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        let frame = FakeFrame::parse(&spec.path)?;
        if let Ok(mut t) = self.truths.lock() {
            t.insert(spec.path.clone(), frame.clone());
        }
        Ok(frame.image(&spec.path))
    }
}

/// Finds the truth of a fake image by its file.
pub type TruthLookup = Box<dyn Fn(&Path) -> Option<FakeFrame> + Send + Sync>;

/// Answers the true relative transform between two fake frames, with covariance `cov`.
pub struct TruthAligner {
    pub cov: Cov4,
    pub truth: TruthLookup,
}

impl TruthAligner {
    /// An aligner that reads truths back from the fake files themselves.
    pub fn from_files(cov: Cov4) -> TruthAligner {
        TruthAligner {
            cov,
            truth: Box::new(|p: &Path| FakeFrame::parse(p).ok()),
        }
    }
}

impl Aligner for TruthAligner {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        let ref_name = reference.meta.file.display().to_string();
        let frame_name = frame.meta.file.display().to_string();
        let (Some(r), Some(f)) = (
            (self.truth)(&reference.meta.file),
            (self.truth)(&frame.meta.file),
        ) else {
            return AlignOutcome::failed(&ref_name, &frame_name, "no truth");
        };
        if r.bad || f.bad {
            return AlignOutcome::failed(&ref_name, &frame_name, "no structure");
        }
        let rel = f.truth.after(&r.truth.inverse()).recentered(r.truth.center);
        let status = if r.degraded || f.degraded {
            Status::Degraded
        } else {
            Status::Ok
        };
        outcome(&ref_name, &frame_name, rel, self.cov, status)
    }

    fn plate_scale_used(&self, _image: &Image) -> Option<[f64; 2]> {
        Some([1.0, 1.0])
    }
}

/// An engine-like outcome for a known transform and covariance.
pub fn outcome(
    reference: &str,
    frame: &str,
    t: Similarity,
    cov: Cov4,
    status: Status,
) -> AlignOutcome {
    let arcsec = sunjitter_core::geometry::ARCSEC_PER_RAD;
    let sd = |i: usize| Some(cov[i][i].sqrt());
    AlignOutcome {
        result: AlignResult {
            reference: reference.into(),
            frame: frame.into(),
            scale: Some(t.scale),
            rotation_arcsec: Some(t.rotation_rad * arcsec),
            dx_px: Some(t.dx),
            dy_px: Some(t.dy),
            dx_arcsec: Some(t.dx),
            dy_arcsec: Some(t.dy),
            sigma_scale: sd(0),
            sigma_rotation_arcsec: sd(1).map(|s| s * arcsec),
            sigma_dx_px: sd(2),
            sigma_dy_px: sd(3),
            sigma_dx_arcsec: sd(2),
            sigma_dy_arcsec: sd(3),
            uabjm_sigma_scale: sd(0),
            uabjm_sigma_rotation_arcsec: sd(1).map(|s| s * arcsec),
            uabjm_sigma_dx_px: sd(2),
            uabjm_sigma_dy_px: sd(3),
            header_residual: Some(TransformFields {
                scale: t.scale,
                rotation_arcsec: t.rotation_rad * arcsec,
                dx_px: t.dx,
                dy_px: t.dy,
            }),
            solar_rotation: None,
            points: 400,
            inliers: 400,
            residual_rms_px: Some(0.0),
            similarity: Some(0.99),
            model: (status != Status::Failed).then_some(sunjitter_core::record::Model::Similarity),
            status,
            message: if status == Status::Degraded {
                "few inliers".into()
            } else {
                String::new()
            },
            elapsed_ms: 0.0,
        },
        transform: Some(t),
        coarse: None,
        covariance: Some(cov),
        uabjm_covariance: Some(cov),
        mask: None,
        // Arcsec equal pixels here (`dx_arcsec` = `dx_px`).
        reference_geometry: Some(sunjitter_core::engine::UsedGeometry {
            plate_scale_arcsec: [1.0, 1.0],
            sun_center_px: t.center,
            from_disk: false,
        }),
    }
}

/// The fake reader's stand-in for the real reader's structure checks: `path` holds complete FITS HDUs: every header has its END card and the file is
/// as long as the headers say. A file still being written fails here (and is retried);
/// absurd headers (`NAXIS1 = 2000000000`) fail with the size they claim.
pub fn fits_completeness(path: &Path) -> std::result::Result<(), String> {
    use std::io::{Read, Seek, SeekFrom};
    const BLOCK: u64 = 2880;
    const MAX_HEADER_BLOCKS: u64 = 10_000;
    let mut file = std::fs::File::open(path).map_err(|e| format!("cannot open: {e}"))?;
    let size = file
        .metadata()
        .map_err(|e| format!("cannot stat: {e}"))?
        .len();
    if size == 0 {
        return Err("empty file (0 bytes)".into());
    }
    let mut start = Vec::with_capacity(9);
    (&mut file)
        .take(9)
        .read_to_end(&mut start)
        .map_err(|e| format!("cannot read: {e}"))?;
    if start.starts_with(&[0x1f, 0x8b]) {
        return Ok(()); // gzip: the reader checks it as it decompresses
    }
    if !b"SIMPLE  =".starts_with(&start) {
        return Err("not a FITS file (it does not start with SIMPLE)".into());
    }
    let mut offset = 0u64;
    let mut hdu = 0usize;
    let mut block = [0u8; BLOCK as usize];
    loop {
        // Header
        let mut cards: std::collections::HashMap<String, String> = std::collections::HashMap::new();
        let mut blocks = 0u64;
        let mut ended = false;
        while !ended {
            if offset + (blocks + 1) * BLOCK > size {
                return Err(format!(
                    "truncated: HDU {hdu} header is cut off at byte {size} (no END card)"
                ));
            }
            if blocks >= MAX_HEADER_BLOCKS {
                return Err(format!(
                    "HDU {hdu} header has no END card in {MAX_HEADER_BLOCKS} blocks"
                ));
            }
            file.seek(SeekFrom::Start(offset + blocks * BLOCK))
                .and_then(|_| file.read_exact(&mut block))
                .map_err(|e| format!("cannot read: {e}"))?;
            if blocks == 0 {
                let first = String::from_utf8_lossy(&block[..9]).to_string();
                let expected = if hdu == 0 { "SIMPLE  =" } else { "XTENSION=" };
                if first != expected {
                    if hdu == 0 {
                        return Err("not a FITS file (it does not start with SIMPLE)".into());
                    }
                    return Ok(()); // trailing bytes after the last HDU
                }
            }
            for card in block.chunks(80) {
                let card = String::from_utf8_lossy(card);
                let name = card[..8.min(card.len())].trim_end().to_string();
                if name == "END" {
                    ended = true;
                    break;
                }
                if card.len() > 10 && &card[8..10] == "= " {
                    let value = card[10..]
                        .split('/')
                        .next()
                        .unwrap_or("")
                        .trim()
                        .to_string();
                    cards.entry(name).or_insert(value);
                }
            }
            blocks += 1;
        }
        let int = |k: &str| -> std::result::Result<i64, String> {
            cards
                .get(k)
                .ok_or_else(|| format!("HDU {hdu} header lacks {k}"))?
                .parse::<i64>()
                .map_err(|_| format!("HDU {hdu} header: {k} is not an integer"))
        };
        let bitpix = int("BITPIX")?;
        let naxis = int("NAXIS")?;
        if !(0..=999).contains(&naxis) || ![8, 16, 32, 64, -32, -64].contains(&bitpix) {
            return Err(format!(
                "HDU {hdu} header: BITPIX {bitpix} / NAXIS {naxis} invalid"
            ));
        }
        let mut pixels: u64 = if naxis == 0 { 0 } else { 1 };
        for i in 1..=naxis {
            let n = int(&format!("NAXIS{i}"))?;
            if n < 0 {
                return Err(format!("HDU {hdu} header: NAXIS{i} = {n}"));
            }
            pixels = pixels
                .checked_mul(n as u64)
                .ok_or_else(|| format!("HDU {hdu} header: data size overflows"))?;
        }
        let pcount = if hdu == 0 {
            0
        } else {
            int("PCOUNT").unwrap_or(0).max(0) as u64
        };
        let gcount = if hdu == 0 {
            1
        } else {
            int("GCOUNT").unwrap_or(1).max(0) as u64
        };
        let data = if naxis == 0 {
            0
        } else {
            pixels
                .checked_add(pcount)
                .and_then(|n| n.checked_mul(gcount))
                .and_then(|n| n.checked_mul(bitpix.unsigned_abs() / 8))
                .ok_or_else(|| format!("HDU {hdu} header: data size overflows"))?
        };
        let data_start = offset + blocks * BLOCK;
        let data_end = data_start
            .checked_add(data)
            .ok_or_else(|| format!("HDU {hdu} header: data size overflows"))?;
        if data_end > size {
            return Err(format!(
                "truncated: HDU {hdu} needs {data_end} bytes, the file has {size}"
            ));
        }
        let padded = data_end.div_ceil(BLOCK) * BLOCK;
        if padded + BLOCK > size {
            return Ok(());
        }
        offset = padded;
        hdu += 1;
    }
}

/// One frame of a real cube written as its own FITS file (as `examples/split_cube.rs` does).
#[derive(Debug, Clone)]
pub struct SplitFrame {
    pub name: String,
    pub bytes: Vec<u8>,
    pub obs_time_ns: i64,
    pub channel: String,
}

/// Split a real cube into per-frame FITS files' bytes, in frame order (files are written in
/// `scratch` and read back), for tests that feed a watcher a real sequence.
pub fn split_cube(cube: &Path, scratch: &Path) -> Result<Vec<SplitFrame>> {
    use sunjitter_io::fits;
    let metas = fits::read_meta(cube)?;
    let (_, header) = fits::read_image_header(cube)?;
    std::fs::create_dir_all(scratch).map_err(|e| Error::io(scratch, e))?;
    let stem = cube.file_stem().and_then(|s| s.to_str()).unwrap_or("frame");
    let mut out = Vec::new();
    for meta in &metas {
        let index = meta.frame.unwrap_or(0);
        let image = fits::read_frame(&FrameSpec::cube_frame(cube, index))?;
        let cards = fits::frame_header_cards(&header, &image.meta);
        let name = format!("{stem}_f{index:04}.fits");
        let path = scratch.join(&name);
        fits::write_image(&path, image.data.view(), &cards)?;
        let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
        out.push(SplitFrame {
            name,
            bytes,
            obs_time_ns: meta
                .obs_time_ns
                .ok_or_else(|| Error::bad_header(cube, "frame without time"))?,
            channel: meta.channel.clone(),
        });
    }
    Ok(out)
}
