//! Header metadata, normalised across instruments (the `info` command's fields).
//!
//! Everything here is a pure function of a parsed [`Header`]; the file reading is in
//! sunjitter-io's `fits`. Conventions (see the contract, "Geometry and units"):
//! plate scale in arcsec/pixel, roll in degrees in the `CROTA2` sense (solar north points to
//! pixel direction (sin ρ, cos ρ)), sun centre as 0-based pixel coordinates.

use crate::header::{Header, HeaderValue};
use crate::time::{self, TimeScale};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Where the observer was, as the header says (any part may be missing).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Observer {
    /// Stonyhurst longitude, degrees (`HGLN_OBS`).
    pub hgln_deg: Option<f64>,
    /// Heliographic latitude, degrees (`HGLT_OBS`, `CRLT_OBS`, EIT's `SOLAR_B0`).
    pub hglt_deg: Option<f64>,
    /// Carrington longitude, degrees (`CRLN_OBS`), used when `HGLN_OBS` is missing.
    pub crln_deg: Option<f64>,
    /// Distance to the Sun's centre, m (`DSUN_OBS`).
    pub dsun_m: Option<f64>,
    /// The solar radius the header's geometry uses, m (`RSUN_REF`).
    pub rsun_ref_m: Option<f64>,
}

/// What sunjitter understood of one image (or one frame of a cube).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    pub file: PathBuf,
    /// 0-based HDU index holding the image.
    pub hdu: usize,
    /// Frame index within a 3-D cube; `None` for a 2-D image.
    pub frame: Option<usize>,
    pub width: usize,
    pub height: usize,
    pub bitpix: i32,
    /// e.g. `AIA_171`, `EIT_195`, `HMI_6173`, `SJI_1400`, `TRACE_171`.
    pub channel: String,
    pub instrument: Option<String>,
    /// Wavelength in the header's unit (Å for EUV/UV imagers).
    pub wavelength: Option<f64>,
    /// Observation time, ns since the Unix epoch, UTC.
    pub obs_time_ns: Option<i64>,
    pub exptime_s: Option<f64>,
    /// Arcsec per pixel along x and y (`CDELT1`, `CDELT2` in arcsec).
    pub plate_scale_arcsec: [f64; 2],
    /// Image roll relative to solar north, degrees, in the `CROTA2` sense.
    pub rotation_deg: f64,
    /// 0-based pixel where helioprojective (0″, 0″) falls.
    pub sun_center_px: [f64; 2],
    pub rsun_arcsec: Option<f64>,
    /// Where the observer was (`HGLN_OBS`, `HGLT_OBS`, `DSUN_OBS`, …), for the Sun's rotation.
    #[serde(default)]
    pub observer: Observer,
}

impl FrameMeta {
    /// Observation time as ISO 8601 UTC (`YYYY-MM-DDTHH:MM:SS.sssZ`), if known.
    pub fn obs_time_iso(&self) -> Option<String> {
        self.obs_time_ns.map(time::format_iso_utc)
    }
}

/// Where the image sits in its file and how big it is (what the header alone cannot say).
#[derive(Debug, Clone, PartialEq)]
pub struct ImagePlace {
    pub file: PathBuf,
    pub hdu: usize,
    pub frame: Option<usize>,
    pub width: usize,
    pub height: usize,
    pub bitpix: i32,
}

/// Normalise one image's header. `Err` carries a one-line reason (a `BadHeader`).
///
/// The observation time here is the header's; cube readers replace it per frame.
pub fn from_header(header: &Header, place: ImagePlace) -> Result<FrameMeta, String> {
    let wcs = CelestialWcs::from_header(header)?;
    check_observer(header)?;
    let instrument = instrument(header);
    let wavelength = wavelength(header);
    Ok(FrameMeta {
        channel: channel(header, instrument.as_deref(), wavelength),
        instrument,
        wavelength,
        obs_time_ns: obs_time_ns(header),
        exptime_s: exptime_s(header),
        plate_scale_arcsec: wcs.plate_scale_arcsec(),
        rotation_deg: wcs.rotation_deg,
        sun_center_px: wcs.sun_center_px()?,
        rsun_arcsec: rsun_arcsec(header, wcs.cdelt_arcsec[0]),
        observer: observer(header),
        file: place.file,
        hdu: place.hdu,
        frame: place.frame,
        width: place.width,
        height: place.height,
        bitpix: place.bitpix,
    })
}

/// Give `h` the plate scale `arcsec` (arcsec/px along axes 1 and 2, positive) in place of its
/// own, for headers known to state a wrong one (binned data whose `CDELTi` were left at the
/// native pixel): `CDELTi` in the header's `CUNITi`, signs kept, or the columns of `CDi_j`
/// scaled to it. `CRPIXi`, `CRVALi` and the roll stay, so the reference pixel keeps its
/// coordinates and the Sun centre moves accordingly. Returns the plate scale the header gave.
pub fn set_plate_scale(h: &mut Header, arcsec: [f64; 2]) -> Result<[f64; 2], String> {
    if !arcsec.iter().all(|v| PLATE_SCALE_ARCSEC.contains(v)) {
        return Err(format!(
            "a plate scale of {:e}, {:e} arcsec/px is not physical",
            arcsec[0], arcsec[1]
        ));
    }
    let unit = [
        angle_unit_arcsec(h.str("CUNIT1"))?,
        angle_unit_arcsec(h.str("CUNIT2"))?,
    ];
    let old = CelestialWcs::from_header(h)?.cdelt_arcsec;
    if let Some(cd) = cd_matrix(h) {
        for (i, row) in cd.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let factor = arcsec[j] / old[j].abs();
                h.set(
                    &format!("CD{}_{}", i + 1, j + 1),
                    HeaderValue::Float(v * factor),
                );
            }
        }
    } else {
        for (j, key) in ["CDELT1", "CDELT2"].into_iter().enumerate() {
            let sign = if old[j] < 0.0 { -1.0 } else { 1.0 };
            h.set(key, HeaderValue::Float(sign * arcsec[j] / unit[j]));
        }
    }
    Ok(old.map(f64::abs))
}

/// Arcsec per unit of a `CUNITi` value; missing or blank means arcsec (solar convention).
fn angle_unit_arcsec(unit: Option<&str>) -> Result<f64, String> {
    let u = unit.unwrap_or("").trim().to_ascii_lowercase();
    Ok(match u.as_str() {
        "" | "arcsec" | "arcsecs" | "asec" | "arcseconds" => 1.0,
        "arcmin" | "amin" => 60.0,
        "deg" | "degree" | "degrees" => 3600.0,
        "rad" | "radian" | "radians" => 180.0 * 3600.0 / std::f64::consts::PI,
        "mas" => 1e-3,
        other => return Err(format!("CUNIT '{other}' is not an angle unit")),
    })
}

/// The helioprojective part of the WCS, in arcsec: the linear map from pixel offsets to
/// intermediate coordinates, `M = diag(CDELT) · PC` (or `CD`), plus the reference point.
#[derive(Debug, Clone, PartialEq)]
pub struct CelestialWcs {
    /// 1-based reference pixel (`CRPIX1`, `CRPIX2`).
    pub crpix: [f64; 2],
    /// Reference value, arcsec.
    pub crval_arcsec: [f64; 2],
    /// Pixel spacing, arcsec (`CDELTi`, or the column norms of `CD`).
    pub cdelt_arcsec: [f64; 2],
    /// Arcsec per pixel matrix `M[i][j]` (world axis i, pixel axis j).
    pub matrix: [[f64; 2]; 2],
    /// Roll in degrees, `CROTA2` sense.
    pub rotation_deg: f64,
    /// The zenithal projection of the axes (`-TAN`, `-ARC`, …); `None`: treated as linear.
    pub projection: Option<Zenithal>,
    /// Native longitude of the celestial pole, degrees (`LONPOLE`; 180° for zenithal).
    pub lonpole_deg: f64,
}

/// Zenithal projections (Calabretta & Greisen 2002, §5.1): `R_θ` as a function of the native
/// latitude θ, in radians of the intermediate plane.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Zenithal {
    /// Gnomonic: `R = cot θ`.
    Tan,
    /// Zenithal equidistant: `R = π/2 − θ`.
    Arc,
    /// Orthographic (no slant): `R = cos θ`.
    Sin,
    /// Zenithal equal-area: `R = √(2(1 − sin θ))`.
    Zea,
    /// Stereographic: `R = 2 cos θ / (1 + sin θ)`.
    Stg,
    /// Zenithal perspective with `μ = PV2_1` (no tilt): `R = (μ + 1) cos θ / (μ + sin θ)`.
    Azp { mu: f64 },
}

impl Zenithal {
    /// The projection named by `CTYPE1`/`CTYPE2` (both must agree), `Ok(None)` for linear axes
    /// (no code, as in old `SOLAR-X` headers), `Err` for a projection not handled here.
    fn from_header(h: &Header) -> Result<Option<Zenithal>, String> {
        let code = |k: &str| {
            h.str(k).and_then(|t| {
                let t = t.to_ascii_uppercase();
                (t.len() == 8 && t.as_bytes()[4] == b'-').then(|| t[5..].to_string())
            })
        };
        let (c1, c2) = (code("CTYPE1"), code("CTYPE2"));
        if c1 != c2 {
            return Ok(None);
        }
        let Some(c) = c1 else { return Ok(None) };
        Ok(Some(match c.as_str() {
            "TAN" => Zenithal::Tan,
            "ARC" => Zenithal::Arc,
            "SIN"
                if h.f64("PV2_1").unwrap_or(0.0) == 0.0 && h.f64("PV2_2").unwrap_or(0.0) == 0.0 =>
            {
                Zenithal::Sin
            }
            "ZEA" => Zenithal::Zea,
            "STG" => Zenithal::Stg,
            "AZP" if h.f64("PV2_2").unwrap_or(0.0) == 0.0 => Zenithal::Azp {
                mu: h.f64("PV2_1").unwrap_or(0.0),
            },
            other => {
                return Err(format!(
                    "the '{other}' projection (CTYPE1 = '{}') is not supported: only TAN, ARC, \
                     SIN, ZEA, STG and untilted AZP are",
                    h.str("CTYPE1").unwrap_or("")
                ))
            }
        }))
    }

    /// `R_θ` for native latitude `theta` (radians); `None` where the projection diverges.
    fn radius(self, theta: f64) -> Option<f64> {
        let (s, c) = theta.sin_cos();
        let r = match self {
            Zenithal::Tan => (s > 0.0).then(|| c / s)?,
            Zenithal::Arc => std::f64::consts::FRAC_PI_2 - theta,
            Zenithal::Sin => (s >= 0.0).then_some(c)?,
            Zenithal::Zea => (2.0 * (1.0 - s)).max(0.0).sqrt(),
            Zenithal::Stg => (1.0 + s > 0.0).then(|| 2.0 * c / (1.0 + s))?,
            Zenithal::Azp { mu } => (mu + s > 0.0).then(|| (mu + 1.0) * c / (mu + s))?,
        };
        r.is_finite().then_some(r)
    }
}

/// Plate scales any solar image can have, with margin: from a hundredth of the finest
/// (DKIST, about 0.01″/px) to some hundred times the coarsest (LASCO C3, 56″/px). A value
/// outside is a broken header, and every arcsecond reported from it would be wrong.
const PLATE_SCALE_ARCSEC: std::ops::RangeInclusive<f64> = 1e-4..=1e4;

impl CelestialWcs {
    /// Read `CRPIX`/`CRVAL`/`CDELT`/`CUNIT` and the rotation (`PCi_j`, `CDi_j`, `CROTA2`, or
    /// `SC_ROLL` for raw SOHO files that carry none of those).
    pub fn from_header(h: &Header) -> Result<Self, String> {
        let unit = [
            angle_unit_arcsec(h.str("CUNIT1"))?,
            angle_unit_arcsec(h.str("CUNIT2"))?,
        ];
        let crpix = [
            h.f64("CRPIX1")
                .ok_or("CRPIX1 is missing: no reference pixel")?,
            h.f64("CRPIX2")
                .ok_or("CRPIX2 is missing: no reference pixel")?,
        ];
        // FITS default for a missing CRVAL is 0.
        let crval_arcsec = [
            h.f64("CRVAL1").unwrap_or(0.0) * unit[0],
            h.f64("CRVAL2").unwrap_or(0.0) * unit[1],
        ];
        refuse_heliographic(h)?;
        let projection = Zenithal::from_header(h)?;
        let (cdelt_arcsec, matrix, rotation_deg) = match cd_matrix(h) {
            Some(cd) => from_cd(cd, unit)?,
            None => from_cdelt_and_rotation(h, unit)?,
        };
        for (axis, scale) in cdelt_arcsec.iter().enumerate() {
            if !PLATE_SCALE_ARCSEC.contains(&scale.abs()) {
                return Err(format!(
                    "a plate scale of {scale:e} arcsec/px along axis {} is not physical \
                     (CDELT{0}/CD{0}_{0}; expected {:e} to {:e} arcsec/px)",
                    axis + 1,
                    PLATE_SCALE_ARCSEC.start(),
                    PLATE_SCALE_ARCSEC.end()
                ));
            }
        }
        Ok(CelestialWcs {
            crpix,
            crval_arcsec,
            cdelt_arcsec,
            matrix,
            rotation_deg,
            projection,
            lonpole_deg: h.f64("LONPOLE").unwrap_or(180.0),
        })
    }

    /// `[CDELT1, CDELT2]` in arcsec.
    pub fn plate_scale_arcsec(&self) -> [f64; 2] {
        self.cdelt_arcsec
    }

    /// 0-based pixel of helioprojective (0″, 0″): project it to intermediate coordinates
    /// around the reference point (the zenithal projection of `CTYPE`), then invert `M`.
    pub fn sun_center_px(&self) -> Result<[f64; 2], String> {
        let [x, y] = self.intermediate_of_sun_centre()?;
        let [[a, b], [c, d]] = self.matrix;
        let det = a * d - b * c;
        if det.abs() < 1e-300 || !det.is_finite() {
            return Err("the CDELT/PC matrix is singular".into());
        }
        let dx = (d * x - b * y) / det;
        let dy = (-c * x + a * y) / det;
        Ok([self.crpix[0] - 1.0 + dx, self.crpix[1] - 1.0 + dy])
    }

    /// Intermediate world coordinates (arcsec) of (0″, 0″) relative to the reference point.
    fn intermediate_of_sun_centre(&self) -> Result<[f64; 2], String> {
        let [lon0, lat0] = self.crval_arcsec;
        let Some(projection) = self.projection else {
            return Ok([-lon0, -lat0]);
        };
        let rad = std::f64::consts::PI / (180.0 * 3600.0);
        let (a0, d0) = (lon0 * rad, lat0 * rad);
        // Native coordinates of (α, δ) = (0, 0) with the reference point at the native pole
        // (Calabretta & Greisen 2002, eq. 5).
        let theta = (d0.cos() * a0.cos()).clamp(-1.0, 1.0).asin();
        let phi = self.lonpole_deg.to_radians() + a0.sin().atan2(-d0.sin() * a0.cos());
        let r = projection
            .radius(theta)
            .ok_or("the disk centre falls outside the projection (too far from CRVAL)")?;
        Ok([r * phi.sin() / rad, -r * phi.cos() / rad])
    }
}

/// Heliographic maps (Carrington or Stonyhurst longitude, synoptic maps) are not images of the
/// sky: their axes are degrees on the Sun, and there is no disk or pointing to align.
fn refuse_heliographic(h: &Header) -> Result<(), String> {
    for key in ["CTYPE1", "CTYPE2"] {
        let Some(t) = h.str(key) else { continue };
        let upper = t.to_ascii_uppercase();
        if ["CRLN", "CRLT", "HGLN", "HGLT", "LON", "LAT"]
            .iter()
            .any(|p| upper.starts_with(p))
        {
            return Err(format!(
                "{key} = '{t}' is a heliographic (longitude/latitude) map, not a helioprojective \
                 image of the Sun"
            ));
        }
    }
    Ok(())
}

/// `CDi_j` if present (already in CUNIT per pixel).
fn cd_matrix(h: &Header) -> Option<[[f64; 2]; 2]> {
    let keys = ["CD1_1", "CD1_2", "CD2_1", "CD2_2"];
    if !keys.iter().any(|k| h.contains(k)) {
        return None;
    }
    let v = |k: &str| h.f64(k).unwrap_or(0.0);
    Some([[v("CD1_1"), v("CD1_2")], [v("CD2_1"), v("CD2_2")]])
}

type LinearPart = ([f64; 2], [[f64; 2]; 2], f64);

/// From a `CD` matrix: scales are the column norms, roll from the matrix (CDELT > 0 assumed).
fn from_cd(cd: [[f64; 2]; 2], unit: [f64; 2]) -> Result<LinearPart, String> {
    let m = [
        [cd[0][0] * unit[0], cd[0][1] * unit[0]],
        [cd[1][0] * unit[1], cd[1][1] * unit[1]],
    ];
    let scale = [m[0][0].hypot(m[1][0]), m[0][1].hypot(m[1][1])];
    if scale[0] == 0.0 || scale[1] == 0.0 {
        return Err("the CD matrix is singular".into());
    }
    Ok((scale, m, roll_from_matrix(m, scale)))
}

/// From `CDELTi` with `PCi_j`, else `CROTA2`, else `SC_ROLL`, else no roll.
fn from_cdelt_and_rotation(h: &Header, unit: [f64; 2]) -> Result<LinearPart, String> {
    let cdelt = match (h.f64("CDELT1"), h.f64("CDELT2")) {
        (Some(x), Some(y)) => [x * unit[0], y * unit[1]],
        _ => match limb_plate_scale(h) {
            Some(scale) => scale,
            None if h.contains("CDELT1") => return Err("CDELT2 is missing: no plate scale".into()),
            None => return Err("CDELT1 is missing: no plate scale".into()),
        },
    };
    if cdelt[0] == 0.0 || cdelt[1] == 0.0 {
        return Err("CDELT1/CDELT2 is zero".into());
    }
    let crota = h
        .f64("CROTA2")
        .or_else(|| h.f64("CROTA1"))
        .or_else(|| h.f64("CROTA"));
    if let Some(pc) = pc_matrix(h) {
        let m = [
            [cdelt[0] * pc[0][0], cdelt[0] * pc[0][1]],
            [cdelt[1] * pc[1][0], cdelt[1] * pc[1][1]],
        ];
        let roll = roll_from_matrix(m, cdelt);
        if let Some(c) = crota {
            if angle_difference_deg(c, roll).abs() > 0.01 {
                return Err(format!(
                    "CROTA2 = {c}° disagrees with the PCi_j matrix ({roll:.4}°)"
                ));
            }
        }
        return Ok((cdelt, m, roll));
    }
    // SOHO raw files: no CROTA, the spacecraft roll is SC_ROLL ("solar north + CCW from
    // nominal", i.e. the camera turned CCW, which is the CROTA2 sense). sunpy ignores it.
    let roll = crota.or_else(|| h.f64("SC_ROLL")).unwrap_or(0.0);
    let (s, c) = roll.to_radians().sin_cos();
    // CROTA2 → M (Calabretta & Greisen 2002, eq. 189 with CDELT applied).
    let m = [[cdelt[0] * c, -cdelt[1] * s], [cdelt[0] * s, cdelt[1] * c]];
    Ok((cdelt, m, roll))
}

/// Plate scale (arcsec/px) from the solar semi-diameter and the limb fit's radii, for headers
/// that give no `CDELT` (GONG: `SOLAR-R` in arcsec or `SEMIDIAM` in radians, over the fitted
/// limb's minor and major axes `FNDLMBMI`/`FNDLMBMA` in pixels, as sunpy reads them).
fn limb_plate_scale(h: &Header) -> Option<[f64; 2]> {
    let semi_diameter = h
        .f64("SOLAR-R")
        .or_else(|| h.f64("SEMIDIAM").map(|r| r.to_degrees() * 3600.0))
        .filter(|r| *r > 0.0)?;
    let radius = |k: &str| h.f64(k).filter(|r| *r > 0.0);
    Some([
        semi_diameter / radius("FNDLMBMI")?,
        semi_diameter / radius("FNDLMBMA")?,
    ])
}

/// `PCi_j` (or the older `PC00i00j`) if any element is present; missing ones default to identity.
fn pc_matrix(h: &Header) -> Option<[[f64; 2]; 2]> {
    let get = |i: usize, j: usize| {
        h.f64(&format!("PC{i}_{j}"))
            .or_else(|| h.f64(&format!("PC{i:03}{j:03}")))
    };
    let present = (1..=2).any(|i| (1..=2).any(|j| get(i, j).is_some()));
    if !present {
        return None;
    }
    let v = |i, j| get(i, j).unwrap_or(if i == j { 1.0 } else { 0.0 });
    Some([[v(1, 1), v(1, 2)], [v(2, 1), v(2, 2)]])
}

/// Roll (CROTA2 sense) of an arcsec/pixel matrix: mean of the two column estimates,
/// `atan2(M21/CDELT1, M11/CDELT1)` and `atan2(−M12/CDELT2, M22/CDELT2)`.
fn roll_from_matrix(m: [[f64; 2]; 2], cdelt: [f64; 2]) -> f64 {
    let (s1, c1) = (m[1][0] / cdelt[0], m[0][0] / cdelt[0]);
    let (s2, c2) = (-m[0][1] / cdelt[1], m[1][1] / cdelt[1]);
    let r1 = s1.atan2(c1);
    let r2 = s2.atan2(c2);
    (r1.sin() + r2.sin())
        .atan2(r1.cos() + r2.cos())
        .to_degrees()
}

/// a − b wrapped into (−180°, 180°].
fn angle_difference_deg(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(360.0);
    if d > 180.0 {
        d - 360.0
    } else {
        d
    }
}

/// The header's observation time in UTC ns.
///
/// Preference: `T_OBS` (the observation's mid-time; SDO writes it, in TAI for HMI), then
/// `DATE-OBS`, then `DATE_OBS` (start of exposure), each combined with `TIME-OBS`/`TIME_OBS`
/// when it holds a date only. `TIMESYS = 'TAI'` applies where a string names no scale.
/// Unparseable values are skipped with a warning.
pub fn obs_time_ns(h: &Header) -> Option<i64> {
    let scale = match h.str("TIMESYS").map(str::to_ascii_uppercase).as_deref() {
        Some("TAI") => TimeScale::Tai,
        _ => TimeScale::Utc,
    };
    let time_of_day = h.str("TIME-OBS").or_else(|| h.str("TIME_OBS"));
    // A date without a time of day is midnight; a later keyword may hold the full time (the
    // Nançay files give `DATE-OBS = '2012-07-01'` and `DATE_OBS = '…T09:10:58.200Z'`).
    let mut date_only = None;
    for key in ["T_OBS", "DATE-OBS", "DATE_OBS"] {
        let Some(text) = h.str(key) else { continue };
        let parsed = match time_of_day {
            Some(tod) if is_date_only(text) => time::parse_date_and_time(text, tod, scale),
            _ => time::parse_fits_time(text, scale),
        };
        match parsed {
            Ok(ns) if time_of_day.is_none() && is_date_only(text) => {
                date_only = date_only.or(Some(ns))
            }
            Ok(ns) => return Some(ns),
            Err(e) => tracing::warn!("{key}: {e}; trying the next time keyword"),
        }
    }
    date_only
}

fn is_date_only(text: &str) -> bool {
    !text.contains(':')
}

/// A reference time for a cube's time axis or table: `DATEREF`, `STARTOBS`, else the obs time.
pub fn time_reference_ns(h: &Header) -> Option<i64> {
    ["DATEREF", "STARTOBS"]
        .iter()
        .find_map(|k| {
            h.str(k)
                .and_then(|t| time::parse_fits_time(t, TimeScale::Utc).ok())
        })
        .or_else(|| obs_time_ns(h))
}

/// Seconds of frame `frame` (0-based) on a cube's time axis (`CTYPEk = 'TIME'`, k ≥ 3),
/// `CRVALk + (frame + 1 − CRPIXk)·CDELTk` in `CUNITk` (seconds when missing).
pub fn time_axis_seconds(h: &Header, frame: usize) -> Option<f64> {
    // Tile-compressed images describe the image in ZNAXIS (NAXIS is the table's).
    let naxis = h.i64("ZNAXIS").or_else(|| h.i64("NAXIS")).unwrap_or(0);
    (3..=naxis.clamp(0, 999)).find_map(|k| {
        let ctype = h.str(&format!("CTYPE{k}"))?.to_ascii_uppercase();
        if !(ctype.starts_with("TIME") || ctype == "UTC") {
            return None;
        }
        let unit_s = match h
            .str(&format!("CUNIT{k}"))
            .unwrap_or("s")
            .to_ascii_lowercase()
            .as_str()
        {
            "s" | "sec" | "secs" | "second" | "seconds" => 1.0,
            "min" => 60.0,
            "h" | "hr" | "hour" | "hours" => 3600.0,
            "d" | "day" | "days" => 86_400.0,
            _ => return None,
        };
        let crval = h.f64(&format!("CRVAL{k}")).unwrap_or(0.0);
        let crpix = h.f64(&format!("CRPIX{k}")).unwrap_or(0.0);
        let cdelt = h.f64(&format!("CDELT{k}")).unwrap_or(1.0);
        Some((crval + (frame as f64 + 1.0 - crpix) * cdelt) * unit_s)
    })
}

/// Exposure time in seconds: the standard `XPOSURE` (FITS 4.0; EUI, EIT level 1), `EXPTIME`,
/// `EXPOSURE`, else TRACE's measured `SHT_MDUR`.
pub fn exptime_s(h: &Header) -> Option<f64> {
    ["XPOSURE", "EXPTIME", "EXPOSURE", "SHT_MDUR"]
        .iter()
        .find_map(|k| h.f64(k))
}

/// Refuse an observer position no observer can have: a latitude (`HGLT_OBS`, `CRLT_OBS`,
/// `SOLAR_B0`) beyond ±90°, a longitude (`HGLN_OBS`, `CRLN_OBS`) beyond ±360°. The Sun's
/// rotation is taken out with them, so a wrong one would bias every shift.
pub fn check_observer(h: &Header) -> Result<(), String> {
    for (keys, limit, what) in [
        (
            &["HGLT_OBS", "CRLT_OBS", "SOLAR_B0"][..],
            90.0,
            "a latitude (−90° to 90°)",
        ),
        (
            &["HGLN_OBS", "CRLN_OBS"][..],
            360.0,
            "a longitude (−360° to 360°)",
        ),
    ] {
        for key in keys {
            if let Some(v) = h.f64(key) {
                if v.abs() > limit {
                    return Err(format!("{key} = {v} is not {what}"));
                }
            }
        }
    }
    Ok(())
}

/// The observer's position from the header: Stonyhurst (`HGLN_OBS`, `HGLT_OBS`), else
/// Carrington (`CRLN_OBS`, `CRLT_OBS`), else EIT's `SOLAR_B0`; distance `DSUN_OBS`.
pub fn observer(h: &Header) -> Observer {
    let finite = |k: &str| h.f64(k).filter(|v| v.is_finite());
    Observer {
        hgln_deg: finite("HGLN_OBS"),
        hglt_deg: ["HGLT_OBS", "CRLT_OBS", "SOLAR_B0"]
            .iter()
            .find_map(|k| finite(k)),
        crln_deg: finite("CRLN_OBS"),
        dsun_m: finite("DSUN_OBS").filter(|d| *d > 0.0),
        rsun_ref_m: finite("RSUN_REF").filter(|r| *r > 0.0),
    }
}

/// Apparent solar radius in arcsec: `RSUN_OBS`, `RSUN_ARC` (PROBA2, PUNCH) or `RSUN` (STEREO,
/// LASCO, K-Cor), all in arcsec; else `SOLAR_R` (GONG: `SOLAR-R`), in pixels in EIT files
/// (×|CDELT1|) but in arcsec in Yohkoh's and GONG's, told apart by its comment or, without
/// one, by which reading gives a radius the Sun can have; else GONG's `SEMIDIAM` (radians);
/// else `asin(RSUN_REF / DSUN_OBS)` (the sphere's apparent radius, as sunpy computes it); else
/// unknown.
pub fn rsun_arcsec(h: &Header, cdelt1_arcsec: f64) -> Option<f64> {
    if let Some(r) = ["RSUN_OBS", "RSUN_ARC", "RSUN"]
        .iter()
        .find_map(|k| h.f64(k).filter(|r| *r > 0.0))
    {
        return Some(r);
    }
    // GONG writes `SOLAR-R` ("[arcsec] solar semi-diameter").
    let solar_r = ["SOLAR_R", "SOLAR-R"]
        .into_iter()
        .find_map(|k| h.f64(k).filter(|r| *r > 0.0).map(|r| (k, r)));
    if let Some((key, r)) = solar_r {
        let comment = h.comment(key).unwrap_or("").to_ascii_lowercase();
        let in_pixels = r * cdelt1_arcsec.abs();
        return Some(if comment.contains("arcsec") {
            r
        } else if comment.contains("pix") || APPARENT_RSUN_ARCSEC.contains(&in_pixels) {
            in_pixels
        } else if APPARENT_RSUN_ARCSEC.contains(&r) {
            r
        } else {
            in_pixels
        });
    }
    // GONG magnetograms: the semi-diameter in radians.
    if let Some(r) = h.f64("SEMIDIAM").filter(|r| *r > 0.0 && *r < 0.1) {
        return Some(r.to_degrees() * 3600.0);
    }
    let (rsun_m, dsun_m) = (h.f64("RSUN_REF")?, h.f64("DSUN_OBS")?);
    (rsun_m > 0.0 && dsun_m > rsun_m).then(|| (rsun_m / dsun_m).asin().to_degrees() * 3600.0)
}

/// Angular radii (arcsec) the Sun can have as seen by a solar observatory: from beyond Jupiter's
/// orbit (5.5 AU, 175″) to Solar Orbiter's perihelion (0.28 AU, 3430″) and a little closer.
const APPARENT_RSUN_ARCSEC: std::ops::RangeInclusive<f64> = 150.0..=4000.0;

/// Short instrument name: an abbreviation in parentheses (`Extreme-ultraviolet Imaging
/// Telescope (EIT)` → `EIT`), else the first token of `INSTRUME` (`AIA_3` → `AIA`,
/// `HMI_FRONT2` → `HMI`), else the last part of `TELESCOP` (`SDO/AIA` → `AIA`).
pub fn instrument(h: &Header) -> Option<String> {
    let abbreviation = |text: &str| {
        let inner = text.rsplit_once('(')?.1.split_once(')')?.0.trim();
        (!inner.is_empty() && !inner.contains(' ')).then(|| sanitise(inner))
    };
    if let Some(i) = h.str("INSTRUME") {
        if let Some(a) = abbreviation(i) {
            return Some(a);
        }
        let token = i.split(['_', ' ']).find(|t| !t.is_empty())?;
        return Some(sanitise(token));
    }
    let t = h.str("TELESCOP")?;
    if let Some(a) = abbreviation(t) {
        return Some(a);
    }
    t.rsplit('/').find(|t| !t.trim().is_empty()).map(sanitise)
}

/// Wavelength in the header's unit: `WAVELNTH`, IRIS's `TWAVE1`, TRACE's `WAVE_LEN`. Zero is
/// not a wavelength (white-light coronagraphs and heliospheric imagers write `WAVELNTH = 0`).
pub fn wavelength(h: &Header) -> Option<f64> {
    ["WAVELNTH", "TWAVE1", "WAVE_LEN"]
        .iter()
        .find_map(|k| h.f64(k).filter(|w| *w > 0.0))
}

/// The telescope within a multi-telescope instrument, when the header names one that is not
/// the instrument itself: `DETECTOR` (SECCHI's `EUVI`, `COR1`, `HI2`; LASCO's `C2`, `C3`;
/// EUI's `FSI`, `HRI_EUV`), with STEREO's spacecraft letter (`EUVI-A`), whose two copies of
/// each telescope must not share a channel.
fn telescope_within(h: &Header, instrument: Option<&str>) -> Option<String> {
    let detector = sanitise(h.str("DETECTOR")?);
    if instrument.is_some_and(|i| i == detector || detector.contains(i) || i.contains(&detector)) {
        return None;
    }
    let spacecraft = match h.str("OBSRVTRY").map(sanitise).as_deref() {
        Some("STEREO_A") => "-A",
        Some("STEREO_B") => "-B",
        _ => "",
    };
    Some(format!("{detector}{spacecraft}"))
}

/// Channel name: IRIS's `TDESC1` (`SJI_1400`), else instrument + wavelength (`AIA_171`),
/// else instrument + a non-numeric wavelength label (`TRACE_WL`), else what is known. The
/// instrument part names the telescope within a multi-telescope instrument
/// (`SECCHI-EUVI-A_171`, `LASCO-C2`, `EUI-FSI_174`).
pub fn channel(h: &Header, instrument: Option<&str>, wavelength: Option<f64>) -> String {
    if let Some(desc) = h.str("TDESC1") {
        return sanitise(desc);
    }
    let label = match wavelength {
        Some(w) => Some(format!("{}", w.round() as i64)),
        None => ["WAVELNTH", "WAVE_LEN"]
            .iter()
            .find_map(|k| h.str(k))
            .map(sanitise),
    };
    let qualified = match (instrument, telescope_within(h, instrument)) {
        (Some(i), Some(t)) => Some(format!("{i}-{t}")),
        (None, Some(t)) => Some(t),
        (i, None) => i.map(str::to_string),
    };
    let instrument = qualified.as_deref();
    match (instrument, label) {
        (Some(i), Some(l)) => format!("{i}_{l}"),
        (Some(i), None) => i.to_string(),
        (None, Some(l)) => format!("UNKNOWN_{l}"),
        (None, None) => "UNKNOWN".to_string(),
    }
}

/// Upper-case, with anything but letters, digits and `-` turned into `_` (safe in topic names).
fn sanitise(text: &str) -> String {
    text.trim()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c.to_ascii_uppercase()
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(cards: &[(&str, HeaderValue)]) -> Header {
        let mut h = Header::new();
        for (k, v) in cards {
            h.push(k, v.clone());
        }
        h
    }

    fn f(v: f64) -> HeaderValue {
        HeaderValue::Float(v)
    }

    fn s(v: &str) -> HeaderValue {
        HeaderValue::Str(v.into())
    }

    #[test]
    fn a_given_plate_scale_replaces_the_headers_and_moves_the_sun_centre_with_it() {
        // A 10× binned field whose CDELT stayed at the native 0.16635″ (IRIS SJI, binned): the
        // reference pixel keeps its coordinates, so the disk centre, 505.392″ west and
        // 279.88″ north of it, is 505.392 / 1.6635 px away along x (linear axes, no roll).
        let mut h = header(&[
            ("CRPIX1", f(55.15)),
            ("CRPIX2", f(54.75)),
            ("CRVAL1", f(505.392)),
            ("CRVAL2", f(279.88)),
            ("CDELT1", f(0.16635)),
            ("CDELT2", f(0.16635)),
        ]);
        let old = set_plate_scale(&mut h, [1.6635, 1.6635]).unwrap();
        assert_eq!(old, [0.16635, 0.16635]);
        let wcs = CelestialWcs::from_header(&h).unwrap();
        assert_eq!(wcs.plate_scale_arcsec(), [1.6635, 1.6635]);
        let c = wcs.sun_center_px().unwrap();
        assert!((c[0] - (54.15 - 505.392 / 1.6635)).abs() < 1e-9, "{c:?}");
        assert!((c[1] - (53.75 - 279.88 / 1.6635)).abs() < 1e-9, "{c:?}");

        // CDELT in degrees with a flipped axis: the sign and the unit are kept.
        let mut h = header(&[
            ("CRPIX1", f(1.0)),
            ("CRPIX2", f(1.0)),
            ("CUNIT1", s("deg")),
            ("CUNIT2", s("deg")),
            ("CDELT1", f(-0.5 / 3600.0)),
            ("CDELT2", f(0.5 / 3600.0)),
        ]);
        set_plate_scale(&mut h, [2.0, 2.0]).unwrap();
        assert!((h.f64("CDELT1").unwrap() + 2.0 / 3600.0).abs() < 1e-15);
        assert!((h.f64("CDELT2").unwrap() - 2.0 / 3600.0).abs() < 1e-15);

        // A CD matrix (30° roll, 0.6″/px) keeps its roll at the new scale.
        let (sn, cs) = 30f64.to_radians().sin_cos();
        let mut h = header(&[
            ("CRPIX1", f(1.0)),
            ("CRPIX2", f(1.0)),
            ("CD1_1", f(0.6 * cs)),
            ("CD1_2", f(-0.6 * sn)),
            ("CD2_1", f(0.6 * sn)),
            ("CD2_2", f(0.6 * cs)),
        ]);
        set_plate_scale(&mut h, [1.2, 1.2]).unwrap();
        let wcs = CelestialWcs::from_header(&h).unwrap();
        assert!((wcs.plate_scale_arcsec()[0] - 1.2).abs() < 1e-12);
        assert!((wcs.rotation_deg - 30.0).abs() < 1e-9);
        assert!(set_plate_scale(&mut h, [0.0, 1.0]).is_err());
    }

    #[test]
    fn crota2_and_equivalent_pc_give_the_same_geometry() {
        // A 30° roll written both ways (PC from CROTA2 by Calabretta & Greisen eq. 189).
        let (sn, cs) = 30f64.to_radians().sin_cos();
        let base = [
            ("CRPIX1", f(10.0)),
            ("CRPIX2", f(20.0)),
            ("CRVAL1", f(100.0)),
            ("CRVAL2", f(-50.0)),
            ("CDELT1", f(2.0)),
            ("CDELT2", f(1.0)),
        ];
        let mut a = header(&base);
        a.push("CROTA2", f(30.0));
        let mut b = header(&base);
        for (k, v) in [
            ("PC1_1", cs),
            ("PC1_2", -sn * 1.0 / 2.0),
            ("PC2_1", sn * 2.0 / 1.0),
            ("PC2_2", cs),
        ] {
            b.push(k, f(v));
        }
        let (wa, wb) = (
            CelestialWcs::from_header(&a).unwrap(),
            CelestialWcs::from_header(&b).unwrap(),
        );
        assert!((wb.rotation_deg - 30.0).abs() < 1e-12);
        let (ca, cb) = (wa.sun_center_px().unwrap(), wb.sun_center_px().unwrap());
        assert!((ca[0] - cb[0]).abs() < 1e-9 && (ca[1] - cb[1]).abs() < 1e-9);
        // Hand computation, linear axes: offset = R(−30°)·(−100/2, 50/1) in pixels… via M⁻¹.
        // M = [[2c, −s],[2s, c]], det = 2; M⁻¹·(−100, 50) = ((c·−100 + s·50)/2, (−2s·−100 + 2c·50)/2).
        let expect = [
            9.0 + (cs * -100.0 + sn * 50.0) / 2.0,
            19.0 + (200.0 * sn + 100.0 * cs) / 2.0,
        ];
        assert!(
            (ca[0] - expect[0]).abs() < 1e-9 && (ca[1] - expect[1]).abs() < 1e-9,
            "{ca:?} vs {expect:?}"
        );
        // Both present and agreeing is fine; disagreeing is a bad header.
        let mut agreeing = b.clone();
        agreeing.push("CROTA2", f(30.0));
        assert!(CelestialWcs::from_header(&agreeing).is_ok());
        let mut contradicting = b;
        contradicting.push("CROTA2", f(31.0));
        assert!(CelestialWcs::from_header(&contradicting)
            .unwrap_err()
            .contains("disagrees"));
    }

    /// Far from the reference point the projection matters (3.6′ off-centre: ≈ 4 px at
    /// 0.1″/px, and the projections differ by a few px there).
    #[test]
    fn zenithal_projections_match_astropy_far_from_the_reference() {
        // astropy.wcs.WCS(header).wcs_world2pix([[0, 0]], 0) for the same cards.
        let truths = [
            ("TAN", None, [-33011.7774183, -14467.71473282]),
            ("ARC", None, [-33008.414173, -14466.239226]),
            ("SIN", None, [-33006.732782, -14465.501574]),
            ("ZEA", None, [-33007.993820, -14466.054811]),
            ("STG", None, [-33009.254907, -14466.608069]),
            ("AZP", Some(0.82), [-33009.504369, -14466.717512]),
        ];
        for (code, mu, truth) in truths {
            let mut h = header(&[
                ("CTYPE1", s(&format!("HPLN-{code}"))),
                ("CTYPE2", s(&format!("HPLT-{code}"))),
                ("CRVAL1", f(3000.0)),
                ("CRVAL2", f(2000.0)),
                ("CDELT1", f(0.1)),
                ("CDELT2", f(0.1)),
                ("CRPIX1", f(10.0)),
                ("CRPIX2", f(20.0)),
                ("CROTA2", f(10.0)),
            ]);
            if let Some(mu) = mu {
                h.push("PV2_1", f(mu));
            }
            let c = CelestialWcs::from_header(&h)
                .unwrap()
                .sun_center_px()
                .unwrap();
            assert!((c[0] - truth[0]).abs() < 1e-4, "{code}: {c:?}");
            assert!((c[1] - truth[1]).abs() < 1e-4, "{code}: {c:?}");
        }
    }

    #[test]
    fn stereo_hi2_perspective_projection_matches_astropy() {
        // sunpy's test header hi_20110910_114721_s7h2A: the Sun is 53° from the reference
        // point, where a linear reading of the axes is 20 px off. Truth: astropy.wcs.
        let h = header(&[
            ("CRPIX1", f(128.5)),
            ("CRPIX2", f(128.5)),
            ("CTYPE1", s("HPLN-AZP")),
            ("CTYPE2", s("HPLT-AZP")),
            ("CRVAL1", f(-53.4739394881)),
            ("CRVAL2", f(5.62052403739)),
            ("PC1_1", f(0.997349787778)),
            ("PC1_2", f(0.0727557614094)),
            ("PC2_1", f(-0.0727557614094)),
            ("PC2_2", f(0.997349787778)),
            ("CUNIT1", s("deg")),
            ("CUNIT2", s("deg")),
            ("CDELT1", f(0.288381416267)),
            ("CDELT2", f(0.288381416267)),
            ("PV2_1", f(0.819999992847)),
            ("LONPOLE", f(180.0)),
        ]);
        let c = CelestialWcs::from_header(&h)
            .unwrap()
            .sun_center_px()
            .unwrap();
        assert!((c[0] - 333.783085).abs() < 1e-4, "{c:?}");
        assert!((c[1] - 127.583883).abs() < 1e-4, "{c:?}");
    }

    #[test]
    fn unsupported_projections_and_heliographic_maps_are_refused() {
        let mut h = header(&[
            ("CRPIX1", f(1.0)),
            ("CRPIX2", f(1.0)),
            ("CDELT1", f(1.0)),
            ("CDELT2", f(1.0)),
            ("CTYPE1", s("HPLN-AIT")),
            ("CTYPE2", s("HPLT-AIT")),
        ]);
        assert!(CelestialWcs::from_header(&h).unwrap_err().contains("'AIT'"));
        for (x, y) in [
            ("CRLN-CEA", "CRLT-CEA"),
            ("HGLN-CAR", "HGLT-CAR"),
            ("Long", "Lat"),
        ] {
            h = header(&[
                ("CRPIX1", f(1.0)),
                ("CRPIX2", f(1.0)),
                ("CDELT1", f(1.0)),
                ("CDELT2", f(1.0)),
                ("CTYPE1", s(x)),
                ("CTYPE2", s(y)),
            ]);
            let e = CelestialWcs::from_header(&h).unwrap_err();
            assert!(e.contains("heliographic"), "{x}: {e}");
        }
    }

    #[test]
    fn sc_roll_is_used_only_without_crota_or_pc() {
        let base = [
            ("CRPIX1", f(64.5)),
            ("CRPIX2", f(64.5)),
            ("CDELT1", f(2.63)),
            ("CDELT2", f(2.63)),
            ("SC_ROLL", f(180.0)),
        ];
        let w = CelestialWcs::from_header(&header(&base)).unwrap();
        assert_eq!(w.rotation_deg, 180.0);
        let mut with_crota = header(&base);
        with_crota.push("CROTA2", f(0.5));
        assert_eq!(
            CelestialWcs::from_header(&with_crota).unwrap().rotation_deg,
            0.5
        );
    }

    #[test]
    fn units_and_missing_keys() {
        let h = header(&[
            ("CRPIX1", f(1.0)),
            ("CRPIX2", f(1.0)),
            ("CDELT1", f(1.0 / 3600.0)),
            ("CDELT2", f(1.0 / 3600.0)),
            ("CUNIT1", s("deg")),
            ("CUNIT2", s("deg")),
        ]);
        let w = CelestialWcs::from_header(&h).unwrap();
        assert!((w.cdelt_arcsec[0] - 1.0).abs() < 1e-12);
        let bad = header(&[
            ("CRPIX1", f(1.0)),
            ("CRPIX2", f(1.0)),
            ("CDELT1", f(1.0)),
            ("CDELT2", f(1.0)),
            ("CUNIT1", s("m")),
        ]);
        assert!(CelestialWcs::from_header(&bad)
            .unwrap_err()
            .contains("CUNIT"));
        let none = header(&[("CRPIX1", f(1.0)), ("CRPIX2", f(1.0))]);
        assert!(CelestialWcs::from_header(&none)
            .unwrap_err()
            .contains("CDELT1 is missing"));
    }

    #[test]
    fn rsun_from_reference_radius_and_distance() {
        // sunpy.coordinates.sun._angular_radius(696000 km, 1 AU) = 959.645″.
        let h = header(&[
            ("RSUN_REF", f(696_000_000.0)),
            ("DSUN_OBS", f(149_597_870_700.0)),
        ]);
        let r = rsun_arcsec(&h, 1.0).unwrap();
        assert!((r - 959.645).abs() < 0.001, "{r}");
        assert_eq!(
            rsun_arcsec(&header(&[("SOLAR_R", f(372.27))]), 2.63),
            Some(372.27 * 2.63)
        );
        assert_eq!(rsun_arcsec(&header(&[("DSUN_OBS", f(1.5e11))]), 1.0), None);
    }

    #[test]
    fn gong_halpha_plate_scale_from_the_limb_fit() {
        // sunpy's test header gong_halpha.header (no CDELT): sunpy's GONGHalphaMap gives scale
        // 1.07949397″/px (SOLAR-R / FNDLMBMI), sun centre (1023, 1023), rsun 971.544571″.
        let mut h = header(&[
            ("CTYPE1", s("GONGX")),
            ("CTYPE2", s("GONGY")),
            ("CRVAL1", f(0.0)),
            ("CRVAL2", f(0.0)),
            ("CRPIX1", f(1024.0)),
            ("CRPIX2", f(1024.0)),
            ("FNDLMBMI", f(900.0)),
            ("FNDLMBMA", f(900.0)),
        ]);
        h.push_with_comment(
            "SOLAR-R",
            f(971.544571353755),
            "[arcsec] solar semi-diameter",
        );
        let wcs = CelestialWcs::from_header(&h).unwrap();
        for v in wcs.plate_scale_arcsec() {
            assert!((v - 1.07949397).abs() < 1e-8, "{v}");
        }
        let c = wcs.sun_center_px().unwrap();
        assert!((c[0] - 1023.0).abs() < 1e-9 && (c[1] - 1023.0).abs() < 1e-9);
        assert_eq!(rsun_arcsec(&h, wcs.cdelt_arcsec[0]), Some(971.544571353755));
    }

    #[test]
    fn radius_keywords_of_other_instruments() {
        let c = |k: &str, v: f64, comment: &str| {
            let mut h = Header::new();
            h.push_with_comment(k, f(v), comment);
            h
        };
        // PROBA2/SWAP, PUNCH: RSUN_ARC; STEREO, LASCO, K-Cor: RSUN; both in arcsec.
        assert_eq!(
            rsun_arcsec(&c("RSUN_ARC", 945.771838956, ""), 3.16),
            Some(945.771838956)
        );
        assert_eq!(
            rsun_arcsec(&c("RSUN", 978.572578766, ""), 11.9),
            Some(978.572578766)
        );
        // Yohkoh SXT: "Solar radius in arcsec (geocentric)"; EIT: "Solar radius, EIT pixels".
        let sxt = c(
            "SOLAR_R",
            967.151,
            "ssw: Solar radius in arcsec (geocentric)",
        );
        assert_eq!(rsun_arcsec(&sxt, 9.82), Some(967.151));
        let eit = c("SOLAR_R", 188.11, "Solar radius, EIT pixels");
        assert!((rsun_arcsec(&eit, 5.26).unwrap() - 989.4586).abs() < 1e-9);
        // No comment: the reading the Sun's size allows.
        assert_eq!(rsun_arcsec(&c("SOLAR_R", 967.151, ""), 9.82), Some(967.151));
        assert!((rsun_arcsec(&c("SOLAR_R", 372.27, ""), 2.63).unwrap() - 979.0701).abs() < 1e-9);
    }

    #[test]
    fn exposure_and_time_keywords_of_other_instruments() {
        // FITS 4.0's XPOSURE (EUI, EIT level 1) before the older EXPTIME.
        let h = header(&[("XPOSURE", f(6.0)), ("EXPTIME", f(5.0))]);
        assert_eq!(exptime_s(&h), Some(6.0));
        // Nançay: a date-only DATE-OBS, the full time in DATE_OBS.
        let nrh = header(&[
            ("DATE-OBS", s("2012-07-01")),
            ("DATE_OBS", s("2012-07-01T09:10:58.200Z")),
        ]);
        assert_eq!(
            obs_time_ns(&nrh).map(time::format_iso_utc).as_deref(),
            Some("2012-07-01T09:10:58.200Z")
        );
        // A date alone is still midnight when nothing better is given.
        let date = header(&[("DATE-OBS", s("2012-07-01"))]);
        assert_eq!(
            obs_time_ns(&date).map(time::format_iso_utc).as_deref(),
            Some("2012-07-01T00:00:00.000Z")
        );
    }

    #[test]
    fn channels_of_multi_telescope_instruments() {
        let name = |cards: &[(&str, HeaderValue)]| {
            let h = header(cards);
            let i = instrument(&h);
            channel(&h, i.as_deref(), wavelength(&h))
        };
        let euvi = name(&[
            ("INSTRUME", s("SECCHI")),
            ("DETECTOR", s("EUVI")),
            ("OBSRVTRY", s("STEREO_A")),
            ("WAVELNTH", HeaderValue::Int(171)),
        ]);
        assert_eq!(euvi, "SECCHI-EUVI-A_171");
        let cor1 = name(&[
            ("INSTRUME", s("SECCHI")),
            ("DETECTOR", s("COR1")),
            ("OBSRVTRY", s("STEREO_B")),
            ("WAVELNTH", HeaderValue::Int(0)),
        ]);
        assert_eq!(cor1, "SECCHI-COR1-B");
        let c2 = name(&[("INSTRUME", s("LASCO")), ("DETECTOR", s("C2"))]);
        assert_eq!(c2, "LASCO-C2");
        let fsi = name(&[
            ("INSTRUME", s("EUI")),
            ("DETECTOR", s("FSI")),
            ("WAVELNTH", HeaderValue::Int(304)),
        ]);
        assert_eq!(fsi, "EUI-FSI_304");
        let aia = name(&[
            ("INSTRUME", s("AIA_3")),
            ("DETECTOR", s("AIA")),
            ("WAVELNTH", HeaderValue::Int(171)),
        ]);
        assert_eq!(aia, "AIA_171");
        let eit_l1 = name(&[
            ("TELESCOP", s("Extreme-ultraviolet Imaging Telescope (EIT)")),
            ("WAVELNTH", HeaderValue::Int(171)),
        ]);
        assert_eq!(eit_l1, "EIT_171");
    }

    #[test]
    fn channel_names() {
        let aia = header(&[
            ("INSTRUME", s("AIA_3")),
            ("WAVELNTH", HeaderValue::Int(171)),
        ]);
        assert_eq!(
            channel(&aia, instrument(&aia).as_deref(), wavelength(&aia)),
            "AIA_171"
        );
        let trace_wl = header(&[("INSTRUME", s("TRACE")), ("WAVE_LEN", s("WL"))]);
        assert_eq!(
            channel(
                &trace_wl,
                instrument(&trace_wl).as_deref(),
                wavelength(&trace_wl)
            ),
            "TRACE_WL"
        );
        let iris = header(&[
            ("INSTRUME", s("SJI")),
            ("TDESC1", s("SJI_1400")),
            ("TWAVE1", f(1400.0)),
        ]);
        assert_eq!(
            channel(&iris, instrument(&iris).as_deref(), wavelength(&iris)),
            "SJI_1400"
        );
        let tel = header(&[("TELESCOP", s("SDO/HMI"))]);
        assert_eq!(instrument(&tel).as_deref(), Some("HMI"));
        assert_eq!(channel(&Header::new(), None, None), "UNKNOWN");
    }

    #[test]
    fn time_preference_and_time_axis() {
        let h = header(&[
            ("DATE-OBS", s("2014-03-01T00:00:27.90")),
            ("T_OBS", s("2014.03.01_00:01:25_TAI")),
        ]);
        assert_eq!(
            time::format_iso_utc(obs_time_ns(&h).unwrap()),
            "2014-03-01T00:00:50.000Z"
        );
        let split = header(&[("DATE-OBS", s("2004-03-01")), ("TIME-OBS", s("00:00:10"))]);
        assert_eq!(
            time::format_iso_utc(obs_time_ns(&split).unwrap()),
            "2004-03-01T00:00:10.000Z"
        );
        let garbled = header(&[
            ("T_OBS", s("soon")),
            ("DATE_OBS", s("1998-05-19T22:21:43.000")),
        ]);
        assert_eq!(
            time::format_iso_utc(obs_time_ns(&garbled).unwrap()),
            "1998-05-19T22:21:43.000Z"
        );
        let cube = header(&[
            ("NAXIS", HeaderValue::Int(3)),
            ("CTYPE3", s("Time")),
            ("CUNIT3", s("seconds")),
            ("CRPIX3", f(27.0)),
            ("CRVAL3", f(6726.79)),
            ("CDELT3", f(21.4087)),
        ]);
        assert!((time_axis_seconds(&cube, 26).unwrap() - 6726.79).abs() < 1e-9);
        assert!((time_axis_seconds(&cube, 0).unwrap() - (6726.79 - 26.0 * 21.4087)).abs() < 1e-9);
    }
}
