//! Writing f32 images, and the header cards of one cube frame as a file of its own.

use super::layout::utf8_path;
use super::pixels::{cfitsio_error, CFITSIO};
use ndarray::ArrayView2;
use std::ffi::CString;
use std::path::Path;
use sunjitter_core::header::{Header, HeaderValue};
use sunjitter_core::meta::{self, FrameMeta};
use sunjitter_core::{Error, Result};

/// Cards `write_image` sets itself (structure and scaling of the f32 array it writes).
const STRUCTURAL_KEYS: [&str; 11] = [
    "SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BSCALE", "BZERO", "BLANK", "XTENSION", "PCOUNT",
    "GCOUNT", "END",
];

fn is_structural(key: &str) -> bool {
    STRUCTURAL_KEYS.contains(&key)
        || (key.starts_with("NAXIS") && key[5..].bytes().all(|b| b.is_ascii_digit()))
}

/// Write a 2-D f32 image (shape `(height, width)`) as a FITS primary HDU with header cards.
///
/// Structural cards in `cards` (`BITPIX`, `NAXISn`, `BSCALE`, …) are skipped: the file holds the
/// f32 values as given. Keys must be standard FITS keywords (≤ 8 characters). The file is
/// written under a temporary name and renamed into place
/// ([`crate::outputs::write_atomically`]), so a directory watcher never sees a half-written
/// file and a failed write leaves nothing behind.
pub fn write_image(
    path: &Path,
    data: ArrayView2<f32>,
    cards: &[(String, HeaderValue)],
) -> Result<()> {
    let out_err = |reason: String| Error::output(path, reason);
    for (key, _) in cards {
        if key.is_empty()
            || key.len() > 8
            || !key
                .bytes()
                .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
        {
            return Err(out_err(format!("{key:?} is not a FITS keyword")));
        }
    }
    let pixels: Vec<f32> = data.iter().copied().collect();
    let (height, width) = data.dim();
    // Under a temporary name, removed again whatever fails (a full disk, say).
    crate::outputs::write_atomically(path, |tmp| {
        let ctmp = CString::new(utf8_path(tmp).map_err(|_| out_err("not a UTF-8 path".into()))?)
            .map_err(|_| out_err("the path contains a NUL byte".into()))?;
        let _guard = CFITSIO
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        write_with_cfitsio(&ctmp, width, height, pixels, cards).map_err(out_err)
    })
}

/// The cfitsio part of [`write_image`] (caller holds the lock).
fn write_with_cfitsio(
    cpath: &CString,
    width: usize,
    height: usize,
    mut pixels: Vec<f32>,
    cards: &[(String, HeaderValue)],
) -> std::result::Result<(), String> {
    use fitsio::sys;
    let mut status = 0;
    let mut fptr: *mut sys::fitsfile = std::ptr::null_mut();
    // SAFETY: cfitsio calls on the pointer it returned; strings are NUL-terminated CStrings that
    // outlive the calls; `pixels` holds width·height floats; the file is closed on every path.
    unsafe {
        sys::ffdkinit(&mut fptr, cpath.as_ptr(), &mut status);
        if status != 0 {
            return Err(cfitsio_error(status));
        }
        let mut naxes = [
            width as std::os::raw::c_long,
            height as std::os::raw::c_long,
        ];
        sys::ffcrim(fptr, -32, 2, naxes.as_mut_ptr(), &mut status);
        for (key, value) in cards.iter().filter(|(k, _)| !is_structural(k)) {
            if status != 0 {
                break;
            }
            let ckey = CString::new(key.as_str()).unwrap_or_default();
            let empty = CString::default();
            match value {
                HeaderValue::Bool(b) => sys::ffpkyl(
                    fptr,
                    ckey.as_ptr(),
                    i32::from(*b),
                    empty.as_ptr(),
                    &mut status,
                ),
                HeaderValue::Int(i) => {
                    sys::ffpkyj(fptr, ckey.as_ptr(), *i, empty.as_ptr(), &mut status)
                }
                // G format, 15 significant digits.
                HeaderValue::Float(f) if f.is_finite() => {
                    sys::ffpkyd(fptr, ckey.as_ptr(), *f, -15, empty.as_ptr(), &mut status)
                }
                HeaderValue::Float(_) => 0,
                // Commentary cards: no value indicator (cfitsio splits long text over cards).
                HeaderValue::Str(s) if key == "HISTORY" || key == "COMMENT" => {
                    let printable: String = s
                        .chars()
                        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
                        .collect();
                    let text = CString::new(printable).unwrap_or_default();
                    if key == "HISTORY" {
                        sys::ffphis(fptr, text.as_ptr(), &mut status)
                    } else {
                        sys::ffpcom(fptr, text.as_ptr(), &mut status)
                    }
                }
                HeaderValue::Str(s) => {
                    let printable: String = s
                        .chars()
                        .map(|c| if (' '..='~').contains(&c) { c } else { '?' })
                        .collect();
                    let cval = CString::new(printable).unwrap_or_default();
                    sys::ffpkls(
                        fptr,
                        ckey.as_ptr(),
                        cval.as_ptr(),
                        empty.as_ptr(),
                        &mut status,
                    )
                }
            };
        }
        if status == 0 {
            sys::ffppre(
                fptr,
                1,
                1,
                pixels.len() as i64,
                pixels.as_mut_ptr(),
                &mut status,
            );
        }
        let write_status = status;
        let mut close_status = 0;
        sys::ffclos(fptr, &mut close_status);
        match (write_status, close_status) {
            (0, 0) => Ok(()),
            (0, s) | (s, _) => Err(cfitsio_error(s)),
        }
    }
}

/// Header cards for frame `meta` of a cube written as a 2-D image: the cube's cards minus
/// structure, the third (time) axis and per-cube time keys, plus the frame's own `DATE-OBS`
/// (UTC), `EXPTIME`, and where it came from (`SRCFILE`, `SRCFRAME`). Keys that are not
/// standard 8-character keywords (HIERARCH) are dropped. A frame read at its own pointing
/// (per-frame table) gets `CRPIX1`/`CRPIX2` moved by its sun centre's move, and `XCEN`/`YCEN`
/// set to that pointing: the 2-D file has no table, so its header must carry the pointing.
pub fn frame_header_cards(cube_header: &Header, meta: &FrameMeta) -> Vec<(String, HeaderValue)> {
    let mut cards: Vec<(String, HeaderValue)> = cube_header
        .cards()
        .iter()
        .filter(|c| {
            is_standard_keyword(&c.key) && !is_structural(&c.key) && !is_per_cube_key(&c.key)
        })
        .filter_map(|c| Some((c.key.clone(), c.value.clone()?)))
        .collect();
    cards.retain(|(k, _)| {
        !matches!(
            k.as_str(),
            "DATE-OBS" | "EXPTIME" | "TIMESYS" | "SRCFILE" | "SRCFRAME"
        )
    });
    if let Some(t) = meta.obs_time_iso() {
        cards.push((
            "DATE-OBS".into(),
            HeaderValue::Str(t.trim_end_matches('Z').to_string()),
        ));
        cards.push(("TIMESYS".into(), HeaderValue::Str("UTC".into())));
    }
    if let Some(e) = meta.exptime_s {
        cards.push(("EXPTIME".into(), HeaderValue::Float(e)));
    }
    if let Some((crpix, offset)) = frame_pointing(cube_header, meta) {
        for (key, value) in cards.iter_mut() {
            let moved = match key.as_str() {
                "CRPIX1" => Some(crpix[0]),
                "CRPIX2" => Some(crpix[1]),
                "XCEN" => value.as_f64().map(|v| v + offset[0]),
                "YCEN" => value.as_f64().map(|v| v + offset[1]),
                _ => None,
            };
            if let Some(v) = moved {
                *value = HeaderValue::Float(v);
            }
        }
    }
    cards.push((
        "SRCFILE".into(),
        HeaderValue::Str(meta.file.display().to_string()),
    ));
    if let Some(f) = meta.frame {
        cards.push(("SRCFRAME".into(), HeaderValue::Int(f as i64)));
    }
    cards
}

/// For a cube frame whose sun centre the per-frame table moved
/// ([`FrameClock::apply`](super::cube::FrameClock::apply)): the frame's reference pixel
/// (1-based `CRPIX1`, `CRPIX2`, moved with the sun centre, which is exact whatever the
/// projection) and its pointing offset from the header's, arcsec (`d = −M·move`, the inverse
/// of [`pointing_shift_px`](super::cube::pointing_shift_px)). `None` at the header's pointing.
fn frame_pointing(cube_header: &Header, meta: &FrameMeta) -> Option<([f64; 2], [f64; 2])> {
    meta.frame?;
    let wcs = meta::CelestialWcs::from_header(cube_header).ok()?;
    let nominal = wcs.sun_center_px().ok()?;
    let moved = [
        meta.sun_center_px[0] - nominal[0],
        meta.sun_center_px[1] - nominal[1],
    ];
    if moved == [0.0, 0.0] || !moved.iter().all(|v| v.is_finite()) {
        return None;
    }
    let m = wcs.matrix;
    let offset = [
        -(m[0][0] * moved[0] + m[0][1] * moved[1]),
        -(m[1][0] * moved[0] + m[1][1] * moved[1]),
    ];
    Some(([wcs.crpix[0] + moved[0], wcs.crpix[1] + moved[1]], offset))
}

/// 1–8 characters of `A–Z 0–9 _ -`.
fn is_standard_keyword(key: &str) -> bool {
    !key.is_empty()
        && key.len() <= 8
        && key
            .bytes()
            .all(|b| b.is_ascii_uppercase() || b.is_ascii_digit() || b == b'_' || b == b'-')
}

/// Keys that describe the cube as a whole and would mislead on a single frame: the third WCS
/// axis (`CTYPE3`, `PC3_1`, `PC1_3`…), and the times that outrank `DATE-OBS` (`T_OBS`, `DATE_OBS`).
fn is_per_cube_key(key: &str) -> bool {
    const AXIS_KEYS: [&str; 9] = [
        "CTYPE", "CUNIT", "CRPIX", "CRVAL", "CDELT", "CROTA", "CNAME", "CRDER", "CSYSER",
    ];
    let third_axis = AXIS_KEYS.iter().any(|p| {
        key.strip_prefix(p)
            .is_some_and(|n| n.parse::<u32>().is_ok_and(|n| n >= 3))
    });
    let matrix = ["PC", "CD"].iter().any(|p| {
        key.strip_prefix(p)
            .and_then(|ij| ij.split_once('_'))
            .is_some_and(|(i, j)| {
                i.parse::<u32>().is_ok_and(|i| i >= 3) || j.parse::<u32>().is_ok_and(|j| j >= 3)
            })
    });
    third_axis
        || matrix
        || matches!(
            key,
            "T_OBS" | "DATE_OBS" | "TIME-OBS" | "TIME_OBS" | "DATE_END" | "DATEREF" | "MJDREF"
        )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fits::{read_frame, read_image_header, FrameSpec};
    use ndarray::Array2;

    const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../../data/real/");

    /// A cube frame written as a 2-D file with `frame_header_cards` reads back with the same
    /// metadata as the frame had in the cube (truth: the cube's values, checked against sunpy
    /// in tests/info.rs).
    #[test]
    fn cube_frame_round_trips_through_a_2d_file() {
        let cube = format!("{REAL}iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits");
        let frame = read_frame(&FrameSpec::cube_frame(&cube, 27)).unwrap();
        let (_, header) = read_image_header(Path::new(&cube)).unwrap();
        let cards = frame_header_cards(&header, &frame.meta);
        assert!(!cards
            .iter()
            .any(|(k, _)| k == "CTYPE3" || k == "PC3_1" || k == "NAXIS3" || k == "DATE_OBS"));
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("f27.fits");
        write_image(&out, frame.data.view(), &cards).unwrap();
        let back = read_frame(&FrameSpec::file(&out)).unwrap();
        assert_eq!(back.data, frame.data);
        let m = &back.meta;
        assert_eq!((m.frame, m.bitpix, m.hdu), (None, -32, 0));
        assert_eq!(m.obs_time_iso(), frame.meta.obs_time_iso());
        assert_eq!(
            (m.channel.as_str(), m.instrument.as_deref(), m.wavelength),
            ("SJI_1400", Some("SJI"), Some(1400.0))
        );
        assert_eq!(m.plate_scale_arcsec, frame.meta.plate_scale_arcsec);
        for k in 0..2 {
            assert!((m.sun_center_px[k] - frame.meta.sun_center_px[k]).abs() < 1e-9);
        }
        assert!((m.rotation_deg - frame.meta.rotation_deg).abs() < 1e-12);
        assert!((m.exptime_s.unwrap() - frame.meta.exptime_s.unwrap()).abs() < 1e-12);
    }

    #[test]
    fn write_image_round_trips_values_and_cards() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out [1].fits");
        let data = Array2::from_shape_fn((3, 4), |(y, x)| {
            if (y, x) == (1, 2) {
                f32::NAN
            } else {
                (y * 10 + x) as f32 + 0.25
            }
        });
        let cards = vec![
            ("CDELT1".to_string(), HeaderValue::Float(0.6)),
            ("CDELT2".to_string(), HeaderValue::Float(0.6)),
            ("CRPIX1".to_string(), HeaderValue::Float(2.5)),
            ("CRPIX2".to_string(), HeaderValue::Float(2.0)),
            ("BITPIX".to_string(), HeaderValue::Int(16)),
            ("BZERO".to_string(), HeaderValue::Float(32768.0)),
            (
                "DATE-OBS".to_string(),
                HeaderValue::Str("2020-01-02T03:04:05.678".into()),
            ),
            ("INSTRUME".to_string(), HeaderValue::Str("SYNTH".into())),
            ("WAVELNTH".to_string(), HeaderValue::Int(171)),
        ];
        write_image(&path, data.view(), &cards).unwrap();
        let back = read_frame(&FrameSpec::parse(path.to_str().unwrap())).unwrap();
        assert_eq!(back.data.dim(), (3, 4));
        assert!(back.data[[1, 2]].is_nan());
        assert_eq!(back.data[[2, 3]], 23.25);
        assert_eq!(back.meta.bitpix, -32);
        assert_eq!(back.meta.channel, "SYNTH_171");
        assert_eq!(
            back.meta.obs_time_iso().unwrap(),
            "2020-01-02T03:04:05.678Z"
        );
        assert_eq!(back.meta.sun_center_px, [1.5, 1.0]);
        assert!(write_image(&path, data.view(), &[("lower".into(), HeaderValue::Int(1))]).is_err());
        // No temporary file left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
