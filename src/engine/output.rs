//! Files `align` can write besides its numbers: the resampled frame and a quick-look composite.
//!
//! Both render the frame on the reference grid through the engine's transform (the
//! refinement's quintic B-spline, NaN where the frame has no data), so what a person sees is what was measured.

use super::{AlignOutcome, Image};
use crate::fits;
use crate::geometry::Similarity;
use crate::header::{Header, HeaderValue};
use crate::meta::FrameMeta;
use crate::resample::HighOrderSpline;
use crate::{Error, Result};
use ndarray::{Array2, ArrayView2};
use plotters::prelude::{BitMapBackend, DrawingBackend};
use std::path::Path;

/// The frame resampled onto the reference grid, written as f32 FITS.
///
/// Header: the frame's own cards (time, exposure, instrument, observer…), minus whatever
/// describes its old pixel grid (WCS of axes 1–2, `XCEN`/`YCEN`, `SOLAR_R`, roll keys) and
/// the data statistics the resampling invalidates; plus the reference's grid cards (its WCS
/// as the reference had it: `CRPIXi`, `CDELTi`, `CRVALi`, `CTYPEi`, `CUNITi`, `CROTA2` or
/// `PCi_j`…), plus `HISTORY` saying what was done with which transform.
pub fn write_aligned(
    path: &Path,
    reference: &Image,
    frame: &Image,
    outcome: &AlignOutcome,
) -> Result<()> {
    let transform = require_transform(path, outcome)?;
    let (h, w) = reference.data.dim();
    let aligned = HighOrderSpline::new(frame.data.view(), super::refine::MODEL)
        .warp_similarity(&transform, w, h);

    let (_, ref_header) = fits::read_image_header(&reference.meta.file)?;
    let (_, frame_header) = fits::read_image_header(&frame.meta.file)?;
    let reference_cards = fits::frame_header_cards(&ref_header, &reference.meta);
    let frame_cards = fits::frame_header_cards(&frame_header, &frame.meta);
    let mut history = commentary(&frame_header, "HISTORY");
    history.extend(alignment_history(
        &reference.meta,
        &frame.meta,
        &transform,
        outcome,
    ));
    let comments = commentary(&frame_header, "COMMENT");
    let mut cards = aligned_header_cards(&reference_cards, &frame_cards, &comments, &history);
    if let Some(used) = outcome.reference_geometry.filter(|g| g.from_disk) {
        let note = use_checked_geometry(&mut cards, &reference.meta, &used);
        cards.extend(
            note.into_iter()
                .map(|t| ("HISTORY".to_string(), HeaderValue::Str(t))),
        );
    }
    fits::write_image(path, aligned.view(), &cards)
}

/// Where the reference's header was refused for the disk its image shows, the alignment used
/// the disk-checked plate scale and Sun centre: the aligned image's WCS says so too.
/// `CDELTi` (or the columns of `CDi_j`) are scaled to the plate scale used, the reference point
/// moves to the Sun centre used (`CRPIXi` there, `CRVALi` = 0, exact for any zenithal
/// projection), radii in pixels (`SOLAR_R`, `R_SUN`) follow the plate scale, and cards that
/// describe the old grid otherwise (alternate WCS, `XCEN`/`YCEN`, `FOVX`/`FOVY`, `*_MP`) go.
/// Returns the HISTORY lines that say what was done.
fn use_checked_geometry(
    cards: &mut Vec<(String, HeaderValue)>,
    header: &FrameMeta,
    used: &super::UsedGeometry,
) -> Vec<String> {
    let factor = [0, 1].map(|j| {
        let old = header.plate_scale_arcsec[j].abs();
        if old > 0.0 {
            used.plate_scale_arcsec[j].abs() / old
        } else {
            1.0
        }
    });
    let has = |cards: &[(String, HeaderValue)], k: &str| cards.iter().any(|(c, _)| c == k);
    let uses_cd = ["CD1_1", "CD1_2", "CD2_1", "CD2_2"]
        .iter()
        .any(|k| has(cards, k));
    const OLD_GRID: [&str; 7] = ["XCEN", "YCEN", "FOVX", "FOVY", "X0_MP", "Y0_MP", "IMSCL_MP"];
    cards.retain(|(k, _)| !(OLD_GRID.contains(&k.as_str()) || is_alternate_grid_key(k)));
    let rsun = header.rsun_arcsec;
    let old_plate = header.plate_scale_arcsec[0].abs();
    for (key, value) in cards.iter_mut() {
        let scaled = |v: &HeaderValue, f: f64| v.as_f64().map(|x| HeaderValue::Float(x * f));
        let new = match key.as_str() {
            "CDELT1" if !uses_cd => scaled(value, factor[0]),
            "CDELT2" if !uses_cd => scaled(value, factor[1]),
            "CD1_1" | "CD2_1" => scaled(value, factor[0]),
            "CD1_2" | "CD2_2" => scaled(value, factor[1]),
            "CRPIX1" => Some(HeaderValue::Float(used.sun_center_px[0] + 1.0)),
            "CRPIX2" => Some(HeaderValue::Float(used.sun_center_px[1] + 1.0)),
            "CRVAL1" | "CRVAL2" => Some(HeaderValue::Float(0.0)),
            // A radius in pixels of the header's grid (its product with that plate scale is
            // the Sun's radius in arcsec), now in pixels of the grid used.
            "SOLAR_R" | "R_SUN" => value.as_f64().and_then(|r| {
                let in_pixels = rsun.is_some_and(|a| (r * old_plate / a - 1.0).abs() < 0.01);
                in_pixels.then(|| HeaderValue::Float(r / factor[0]))
            }),
            _ => None,
        };
        if let Some(new) = new {
            *value = new;
        }
    }
    for (key, value) in [
        ("CRPIX1", used.sun_center_px[0] + 1.0),
        ("CRPIX2", used.sun_center_px[1] + 1.0),
        ("CRVAL1", 0.0),
        ("CRVAL2", 0.0),
    ] {
        if !has(cards, key) {
            cards.push((key.to_string(), HeaderValue::Float(value)));
        }
    }
    for (j, key) in ["CDELT1", "CDELT2"].into_iter().enumerate() {
        if !uses_cd && !has(cards, key) {
            cards.push((key.to_string(), HeaderValue::Float(factor[j])));
        }
    }
    let p = used.plate_scale_arcsec;
    let c = used.sun_center_px;
    vec![
        "the reference header's disk disagreed with its image: the alignment".to_string(),
        format!(
            "used {:.6}, {:.6} arcsec/px (header: {:.6}, {:.6})",
            p[0].abs(),
            p[1].abs(),
            header.plate_scale_arcsec[0].abs(),
            header.plate_scale_arcsec[1].abs()
        ),
        format!(
            "and Sun centre ({:.3}, {:.3}) px, 0-based (header: ({:.3}, {:.3}))",
            c[0], c[1], header.sun_center_px[0], header.sun_center_px[1]
        ),
        "WCS written with these: CDELT, CRPIX at the Sun centre, CRVAL = 0".to_string(),
    ]
}

/// An alternate description (`…A`–`…Z`) of axes 1–2.
fn is_alternate_grid_key(key: &str) -> bool {
    is_grid_key(key)
        && key
            .as_bytes()
            .last()
            .is_some_and(|b| b.is_ascii_uppercase())
        && key.len() > 1
        && {
            let stem = &key[..key.len() - 1];
            stem.bytes().last().is_some_and(|b| b.is_ascii_digit())
                || ["WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS"].contains(&stem)
        }
}

/// Red = reference, green + blue = frame; after coarse (header) alignment on the left, after
/// fine alignment on the right (the paper's figure 6). Where the two agree the picture is
/// grey; misregistered structure shows red/cyan fringes.
pub fn write_quicklook(
    path: &Path,
    reference: &Image,
    frame: &Image,
    outcome: &AlignOutcome,
) -> Result<()> {
    let transform = require_transform(path, outcome)?;
    let (h, w) = reference.data.dim();
    let coarse = outcome
        .coarse
        .unwrap_or_else(|| Similarity::identity(Similarity::array_center(w, h)));
    let look = quicklook_rgb(
        reference.data.view(),
        frame.data.view(),
        &coarse,
        &transform,
    )
    .ok_or_else(|| {
        Error::output(
            path,
            "no finite pixels to show; nothing written".to_string(),
        )
    })?;
    write_png(path, &look)
}

fn require_transform(path: &Path, outcome: &AlignOutcome) -> Result<Similarity> {
    outcome.transform.ok_or_else(|| {
        let why = outcome.result.message.lines().next().unwrap_or("");
        Error::output(path, format!("alignment failed ({why}); nothing written"))
    })
}

// ---------------------------------------------------------------------------------------------
// Aligned FITS header
// ---------------------------------------------------------------------------------------------

/// Frame cards without its grid description, then the reference's grid cards, then the
/// frame's comments and the history.
fn aligned_header_cards(
    reference_cards: &[(String, HeaderValue)],
    frame_cards: &[(String, HeaderValue)],
    comments: &[String],
    history: &[String],
) -> Vec<(String, HeaderValue)> {
    let mut cards: Vec<(String, HeaderValue)> = frame_cards
        .iter()
        .filter(|(k, _)| !is_grid_key(k) && !is_data_statistic(k) && !is_container_key(k))
        .cloned()
        .collect();
    for (key, value) in reference_cards.iter().filter(|(k, _)| is_grid_key(k)) {
        // `frame_header_cards` removed the third axis; a cube's WCSAXES = 3 no longer holds.
        let value = if key.starts_with("WCSAXES") {
            HeaderValue::Int(2)
        } else {
            value.clone()
        };
        cards.push((key.clone(), value));
    }
    let commentary_cards = |key: &str, lines: &[String]| {
        lines
            .iter()
            .map(|t| (key.to_string(), HeaderValue::Str(t.clone())))
            .collect::<Vec<_>>()
    };
    cards.extend(commentary_cards("COMMENT", comments));
    cards.extend(commentary_cards("HISTORY", history));
    cards
}

/// Cards that describe the pixel grid of axes 1–2 (the WCS, with alternates `…A`–`…Z`) or the
/// instrument's pointing in grid terms. On the aligned image these are the reference's.
fn is_grid_key(key: &str) -> bool {
    const INSTRUMENT_GRID: [&str; 14] = [
        "XCEN", "YCEN", "FOVX", "FOVY", "SOLAR_R", "R_SUN", "X0_MP", "Y0_MP", "IMSCL_MP",
        "SC_ROLL", "SC_X0", "SC_Y0", "SAT_ROT", "INST_ROT",
    ];
    const AXIS_KEYS: [&str; 9] = [
        "CTYPE", "CUNIT", "CRPIX", "CRVAL", "CDELT", "CROTA", "CNAME", "CRDER", "CSYER",
    ];
    if INSTRUMENT_GRID.contains(&key) || key == "CROTA" {
        return true;
    }
    // Alternate WCS descriptions carry one trailing letter.
    let base = match key.as_bytes().last() {
        Some(b) if b.is_ascii_uppercase() && key.len() > 1 => {
            let stem = &key[..key.len() - 1];
            if stem.bytes().last().is_some_and(|b| b.is_ascii_digit())
                || ["WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS"].contains(&stem)
            {
                stem
            } else {
                key
            }
        }
        _ => key,
    };
    if [
        "WCSAXES", "WCSNAME", "LONPOLE", "LATPOLE", "RADESYS", "EQUINOX",
    ]
    .contains(&base)
    {
        return true;
    }
    let axis12 = |n: &str| n == "1" || n == "2";
    if AXIS_KEYS
        .iter()
        .any(|p| base.strip_prefix(p).is_some_and(axis12))
    {
        return true;
    }
    // PCi_j, CDi_j, PVi_m, PSi_m, and the old PC00i00j.
    let matrix = ["PC", "CD", "PV", "PS"].iter().any(|p| {
        base.strip_prefix(p)
            .and_then(|ij| ij.split_once('_'))
            .is_some_and(|(i, j)| axis12(i) && j.parse::<u32>().is_ok())
    });
    let old_pc = base
        .strip_prefix("PC00")
        .is_some_and(|r| r.len() == 4 && axis12(&r[..1]) && &r[1..3] == "00" && axis12(&r[3..]));
    matrix || old_pc
}

/// Cards of the HDU that held the frame rather than of the image: extension and binary-table
/// structure, and the tile compression of `ZIMAGE` files (whose header is a table's). The
/// output is a plain primary image.
fn is_container_key(key: &str) -> bool {
    const EXACT: [&str; 24] = [
        "EXTNAME", "EXTVER", "EXTLEVEL", "INHERIT", "TFIELDS", "THEAP", "ZIMAGE", "ZSIMPLE",
        "ZBITPIX", "ZNAXIS", "ZCMPTYPE", "ZMASKCMP", "ZQUANTIZ", "ZDITHER0", "ZBLANK", "ZSCALE",
        "ZZERO", "ZHECKSUM", "ZDATASUM", "ZEXTEND", "ZPCOUNT", "ZGCOUNT", "ZTENSION", "ZBLOCKED",
    ];
    const NUMBERED: [&str; 13] = [
        "TTYPE", "TFORM", "TUNIT", "TDIM", "TZERO", "TSCAL", "TNULL", "TDISP", "TBCOL", "ZNAXIS",
        "ZTILE", "ZNAME", "ZVAL",
    ];
    EXACT.contains(&key)
        || NUMBERED.iter().any(|p| {
            key.strip_prefix(p)
                .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
        })
}

/// Statistics of the original pixel values (and checksums) that resampling makes false.
fn is_data_statistic(key: &str) -> bool {
    matches!(
        key,
        "CHECKSUM"
            | "DATASUM"
            | "DATAMIN"
            | "DATAMAX"
            | "DATAMEAN"
            | "DATAMEDN"
            | "DATARMS"
            | "DATASKEW"
            | "DATAKURT"
            | "DATAVALS"
            | "MISSVALS"
            | "TOTVALS"
            | "PERCENTD"
    ) || key
        .strip_prefix("DATAP")
        .is_some_and(|p| p.len() == 2 && p.bytes().all(|b| b.is_ascii_digit()))
}

/// The text of a header's commentary cards named `key` (`HISTORY`, `COMMENT`).
fn commentary(header: &Header, key: &str) -> Vec<String> {
    header
        .cards()
        .iter()
        .filter(|c| c.key == key && c.value.is_none())
        .map(|c| c.comment.trim().to_string())
        .filter(|t| !t.is_empty())
        .collect()
}

fn describe(meta: &FrameMeta) -> String {
    match meta.frame {
        Some(n) => format!("{}[{n}]", meta.file.display()),
        None => meta.file.display().to_string(),
    }
}

fn alignment_history(
    reference: &FrameMeta,
    frame: &FrameMeta,
    t: &Similarity,
    outcome: &AlignOutcome,
) -> Vec<String> {
    let r = &outcome.result;
    let status = serde_json::to_value(r.status)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default();
    let sig = |v: Option<f64>| v.map_or("?".to_string(), |v| format!("{v:.3e}"));
    // Short lines: each fits one 72-character HISTORY card (paths may still wrap).
    vec![
        format!(
            "sunjitter {}: frame resampled onto the reference's pixel grid",
            env!("CARGO_PKG_VERSION")
        ),
        format!("reference: {}", describe(reference)),
        format!("frame: {}", describe(frame)),
        "quintic B-spline; NaN where the frame has no data; WCS = reference's".to_string(),
        format!(
            "p_frame = s R(theta) (p_ref - c) + c + (dx, dy), c = ({}, {}) px",
            t.center[0], t.center[1]
        ),
        format!(
            "scale = {:.9}, rotation = {:.6} arcsec",
            t.scale,
            t.rotation_arcsec()
        ),
        format!("dx = {:.6} px, dy = {:.6} px (0-based pixels)", t.dx, t.dy),
        format!(
            "sigma: scale {}, rotation {} arcsec",
            sig(r.sigma_scale),
            sig(r.sigma_rotation_arcsec)
        ),
        format!(
            "sigma: dx {} px, dy {} px; status {status}",
            sig(r.sigma_dx_px),
            sig(r.sigma_dy_px)
        ),
    ]
}

// ---------------------------------------------------------------------------------------------
// Quick-look composite
// ---------------------------------------------------------------------------------------------

/// Largest panel side in the quick-look; larger images are block-averaged down.
const MAX_PANEL_PX: usize = 1024;
/// Small images are enlarged (pixel replication) to at least about this size, to be seen.
const MIN_PANEL_PX: usize = 512;
/// Display range: these percentiles of each image's finite pixels map to black and white.
const LOW_PERCENTILE: f64 = 1.0;
const HIGH_PERCENTILE: f64 = 99.5;
/// Grey strip between the panels, px.
const GAP_PX: usize = 8;

/// An RGB picture (row 0 at the top): two panels of `(width − GAP_PX) / 2 × height` side by side.
#[derive(Debug, Clone)]
struct Quicklook {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

/// The two panels: frame through `coarse` (left) and through `fine` (right), on the reference
/// grid. Each image's display range comes from its own pixels (1–99.5 %), the same for both
/// panels, then a square-root stretch so faint disk structure shows beside active regions.
/// `y` points up on screen (row 0 of the array at the bottom), as solar images are shown.
/// `None` when either image has no finite pixel.
fn quicklook_rgb(
    reference: ArrayView2<f32>,
    frame: ArrayView2<f32>,
    coarse: &Similarity,
    fine: &Similarity,
) -> Option<Quicklook> {
    let (h, w) = reference.dim();
    let ref_range = percentile_range(reference)?;
    let frame_range = percentile_range(frame)?;
    let spline = HighOrderSpline::new(frame, super::refine::MODEL);
    let red = resize(&stretch(reference, ref_range));
    let before = resize(&stretch(
        spline.warp_similarity(coarse, w, h).view(),
        frame_range,
    ));
    let after = resize(&stretch(
        spline.warp_similarity(fine, w, h).view(),
        frame_range,
    ));
    let (ph, pw) = red.dim();
    let width = 2 * pw + GAP_PX;
    let mut rgb = vec![64u8; width * ph * 3];
    for (panel, cyan) in [&before, &after].into_iter().enumerate() {
        let x0 = panel * (pw + GAP_PX);
        for y in 0..ph {
            let row = ph - 1 - y;
            for x in 0..pw {
                let i = 3 * (row * width + x0 + x);
                let (r, c) = (to_byte(red[[y, x]]), to_byte(cyan[[y, x]]));
                rgb[i] = r;
                rgb[i + 1] = c;
                rgb[i + 2] = c;
            }
        }
    }
    Some(Quicklook {
        width,
        height: ph,
        rgb,
    })
}

/// The `LOW_PERCENTILE`/`HIGH_PERCENTILE` values of the finite pixels (at most ~1M sampled).
fn percentile_range(img: ArrayView2<f32>) -> Option<(f32, f32)> {
    let step = (img.len() / 1_000_000).max(1);
    let mut values: Vec<f32> = img
        .iter()
        .step_by(step)
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    if values.is_empty() {
        return None;
    }
    let mut at = |pct: f64| {
        let k = ((pct / 100.0) * (values.len() - 1) as f64).round() as usize;
        *values.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let lo = at(LOW_PERCENTILE);
    let hi = at(HIGH_PERCENTILE);
    // A flat image still shows (as black) rather than dividing by zero.
    Some((lo, if hi > lo { hi } else { lo + 1.0 }))
}

/// Clip to `range`, map to 0–1, square root. NaN stays NaN.
fn stretch(img: ArrayView2<f32>, (lo, hi): (f32, f32)) -> Array2<f32> {
    img.mapv(|v| ((v - lo) / (hi - lo)).clamp(0.0, 1.0).sqrt())
}

fn to_byte(v: f32) -> u8 {
    if v.is_finite() {
        (v * 255.0).round().clamp(0.0, 255.0) as u8
    } else {
        0
    }
}

/// Block-average big images down to at most `MAX_PANEL_PX`, replicate small ones up to about
/// `MIN_PANEL_PX` (integer factors, so every output pixel is a whole input block).
fn resize(img: &Array2<f32>) -> Array2<f32> {
    let (h, w) = img.dim();
    let side = w.max(h).max(1);
    if side > MAX_PANEL_PX {
        let k = side.div_ceil(MAX_PANEL_PX);
        let (oh, ow) = (h.div_ceil(k), w.div_ceil(k));
        Array2::from_shape_fn((oh, ow), |(y, x)| {
            let (mut sum, mut n) = (0.0f64, 0usize);
            for yy in y * k..((y + 1) * k).min(h) {
                for xx in x * k..((x + 1) * k).min(w) {
                    let v = img[[yy, xx]];
                    if v.is_finite() {
                        sum += v as f64;
                        n += 1;
                    }
                }
            }
            if n == 0 {
                f32::NAN
            } else {
                (sum / n as f64) as f32
            }
        })
    } else {
        let u = (MIN_PANEL_PX / side).max(1);
        Array2::from_shape_fn((h * u, w * u), |(y, x)| img[[y / u, x / u]])
    }
}

/// Encode with plotters' bitmap backend (PNG chosen by the `.png` name of a temporary file,
/// renamed into place so a half-written picture is never seen under `path`).
fn write_png(path: &Path, look: &Quicklook) -> Result<()> {
    let out_err = |reason: String| Error::output(path, reason);
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .ok_or_else(|| out_err("not a UTF-8 file name".into()))?;
    let tmp = path.with_file_name(format!(".{name}.{}.tmp.png", std::process::id()));
    let size = (look.width as u32, look.height as u32);
    let drawn = {
        let mut backend = BitMapBackend::new(&tmp, size);
        backend
            .blit_bitmap((0, 0), size, &look.rgb)
            .and_then(|_| backend.present())
    };
    if let Err(e) = drawn {
        let _ = std::fs::remove_file(&tmp);
        return Err(out_err(format!("cannot write the PNG: {e}")));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        out_err(format!("cannot move the written file into place: {e}"))
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::test_data::read_real;
    use crate::resample::SplineImage;

    #[test]
    fn grid_keys_are_the_wcs_of_axes_one_and_two_and_pointing() {
        for k in [
            "CRPIX1", "CRPIX2", "CDELT1", "CDELT2", "CRVAL1", "CTYPE2", "CUNIT1", "CROTA2",
            "CROTA", "PC1_1", "PC2_1", "CD1_2", "PV2_1", "PC001001", "PC002001", "CRPIX1A",
            "WCSAXES", "WCSNAME", "LONPOLE", "XCEN", "SOLAR_R", "SC_ROLL",
        ] {
            assert!(is_grid_key(k), "{k}");
        }
        for k in [
            "CRPIX3", "PC3_1", "DATE-OBS", "EXPTIME", "INSTRUME", "WAVELNTH", "RSUN_OBS",
            "DSUN_OBS", "CDELT12", "PCOUNT", "CROTAX", "TELESCOP",
        ] {
            assert!(!is_grid_key(k), "{k}");
        }
        // Tile-compressed AIA/HMI files: the header is a binary table's.
        for k in [
            "ZIMAGE", "ZNAXIS1", "ZTILE2", "ZCMPTYPE", "TFORM1", "TTYPE1", "EXTNAME",
        ] {
            assert!(is_container_key(k), "{k}");
        }
        // IRIS slit-jaw per-window keys are not table structure.
        for k in ["TDESC1", "TWAVE1", "TDET1", "TDMEAN1", "TSR1", "ZNAXIS_X"] {
            assert!(!is_container_key(k), "{k}");
        }
        assert!(is_data_statistic("DATAP99") && is_data_statistic("CHECKSUM"));
        assert!(!is_data_statistic("DATAP1") && !is_data_statistic("DATE"));
    }

    #[test]
    fn aligned_header_takes_the_grid_from_the_reference_and_the_rest_from_the_frame() {
        let s = |k: &str, v: HeaderValue| (k.to_string(), v);
        let reference = vec![
            s("CRPIX1", HeaderValue::Float(512.5)),
            s("CDELT1", HeaderValue::Float(0.5)),
            s("PC1_2", HeaderValue::Float(0.01)),
            s("WCSAXES", HeaderValue::Int(3)),
            s("DATE-OBS", HeaderValue::Str("2000-01-01T00:00:00".into())),
        ];
        let frame = vec![
            s("CRPIX1", HeaderValue::Float(64.5)),
            s("CROTA2", HeaderValue::Float(180.0)),
            s("DATE-OBS", HeaderValue::Str("2011-02-15T00:00:01".into())),
            s("DATAMAX", HeaderValue::Float(9.0)),
            s("EXPTIME", HeaderValue::Float(2.0)),
        ];
        let cards = aligned_header_cards(&reference, &frame, &[], &["did it".to_string()]);
        let get = |k: &str| {
            let v: Vec<_> = cards.iter().filter(|(c, _)| c == k).collect();
            assert!(v.len() <= 1, "{k} twice");
            v.first().map(|(_, v)| v.clone())
        };
        assert_eq!(get("CRPIX1"), Some(HeaderValue::Float(512.5)));
        assert_eq!(get("CDELT1"), Some(HeaderValue::Float(0.5)));
        assert_eq!(get("PC1_2"), Some(HeaderValue::Float(0.01)));
        assert_eq!(get("WCSAXES"), Some(HeaderValue::Int(2)));
        assert_eq!(get("CROTA2"), None, "the frame's roll must not survive");
        assert_eq!(get("DATAMAX"), None);
        assert_eq!(
            get("DATE-OBS"),
            Some(HeaderValue::Str("2011-02-15T00:00:01".into()))
        );
        assert_eq!(get("EXPTIME"), Some(HeaderValue::Float(2.0)));
        assert_eq!(get("HISTORY"), Some(HeaderValue::Str("did it".into())));
    }

    /// Pearson correlation of the red and green channels of one panel, inside a circle.
    fn panel_rg_correlation(look: &Quicklook, panel: usize, center: [f64; 2], r: f64) -> f64 {
        let panel_width = (look.width - GAP_PX) / 2;
        let x0 = panel * (panel_width + GAP_PX);
        let (mut n, mut sr, mut sg, mut srr, mut sgg, mut srg) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for y in 0..look.height {
            for x in 0..panel_width {
                if (x as f64 - center[0]).hypot(y as f64 - center[1]) > r {
                    continue;
                }
                let i = 3 * (y * look.width + x0 + x);
                let (a, b) = (look.rgb[i] as f64, look.rgb[i + 1] as f64);
                n += 1.0;
                sr += a;
                sg += b;
                srr += a * a;
                sgg += b * b;
                srg += a * b;
            }
        }
        let cov = srg / n - sr * sg / n / n;
        cov / ((srr / n - (sr / n).powi(2)) * (sgg / n - (sg / n).powi(2))).sqrt()
    }

    /// Truth: a real full-disk AIA image and a copy moved by a known similarity. The fine panel
    /// renders the frame through that very transform, the coarse panel through the identity:
    /// the fine panel must show the two images in register (red = cyan), the coarse one not.
    #[test]
    fn fine_panel_registers_a_known_misaligned_pair_better_than_the_coarse_panel() {
        let reference = read_real("aia_171_20110215T000000_128.fits");
        let (h, w) = reference.dim();
        let center = Similarity::array_center(w, h);
        let truth = Similarity {
            scale: 1.003,
            rotation_rad: 0.02,
            dx: 2.6,
            dy: -1.7,
            center,
        };
        let frame = SplineImage::new(reference.view()).warp_similarity(&truth.inverse(), w, h);
        let identity = Similarity::identity(center);
        let look = quicklook_rgb(reference.view(), frame.view(), &identity, &truth).unwrap();

        // 128 px → replicated 4× to 512 px panels; two panels and the gap.
        assert_eq!((look.width, look.height), (2 * 512 + GAP_PX, 512));
        assert_eq!(look.rgb.len(), look.width * look.height * 3);
        // Green and blue carry the same frame.
        assert!(look.rgb.chunks(3).all(|p| p[1] == p[2]));

        // Inside the disk (AIA: 19.2″/px, R☉ ≈ 975″ → ~50 px; use 40 px, ×4 on screen).
        let disk = [255.5, 255.5];
        let coarse = panel_rg_correlation(&look, 0, disk, 160.0);
        let fine = panel_rg_correlation(&look, 1, disk, 160.0);
        // Measured: coarse 0.51, fine 0.990 (not 1: the frame went through two spline
        // resamplings, which smooth pixel-scale structure, and 8-bit quantisation).
        assert!(fine > 0.97, "fine panel correlation {fine}");
        assert!(fine > coarse + 0.3, "fine {fine} vs coarse {coarse}");
    }

    #[test]
    fn big_images_are_block_averaged_small_ones_replicated() {
        let big = Array2::from_shape_fn((3000, 2100), |(y, _)| y as f32);
        let small = resize(&big);
        // ⌈3000 / 1024⌉ = 3: 1000 × 700, each pixel the mean of a 3×3 block.
        assert_eq!(small.dim(), (1000, 700));
        assert_eq!(small[[10, 5]], 31.0);
        let tiny = Array2::from_shape_fn((100, 110), |(y, x)| (y * 1000 + x) as f32);
        let up = resize(&tiny);
        assert_eq!(up.dim(), (400, 440));
        assert_eq!(up[[7, 9]], tiny[[1, 2]]);
    }
}
