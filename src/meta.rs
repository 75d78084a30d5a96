//! Header metadata, normalised across instruments (the `info` command's fields).

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

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
}
