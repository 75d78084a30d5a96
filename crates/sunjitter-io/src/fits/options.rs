//! What a read is told: limits on what a file may claim, and plate scales given for channels.

use std::collections::BTreeMap;
use std::path::Path;
use sunjitter_core::header::{Header, ImageGeometry};
use sunjitter_core::meta;
use sunjitter_core::{Error, Result};

/// Plate scales (arcsec/px) given for channels whose headers state a wrong one, by the channel
/// the header names (`SJI_1400`; before `[channel_names]` renames it): applied to the header
/// where it is read, so the plate scale, the Sun centre and per-frame pointing all follow it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PlateScales(pub BTreeMap<String, f64>);

impl PlateScales {
    /// Give `header` its channel's plate scale, if one is given. Returns the header's own
    /// (arcsec/px) when replaced; a header whose WCS cannot be read is left as it is (reading
    /// it says why).
    pub fn apply(&self, header: &mut Header) -> Option<[f64; 2]> {
        if self.0.is_empty() {
            return None;
        }
        let instrument = meta::instrument(header);
        let channel = meta::channel(header, instrument.as_deref(), meta::wavelength(header));
        let scale = *self.0.get(&channel)?;
        meta::set_plate_scale(header, [scale, scale]).ok()
    }
}

/// How frames are read: limits on what a file may claim, and plate scales given for channels.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadOptions {
    pub limits: ReadLimits,
    pub plate_scales: PlateScales,
}

/// What a file may claim before its pixels are read: a header is free to announce any size,
/// and a sparse file occupies nothing on disk whatever length it reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Pixels in one image (one frame of a cube).
    pub max_frame_pixels: u64,
}

/// Admits any frame of today's solar imagers (4096² and their cubes) with margin: 8192².
pub const DEFAULT_MAX_FRAME_PIXELS: u64 = 8192 * 8192;

impl Default for ReadLimits {
    fn default() -> Self {
        ReadLimits {
            max_frame_pixels: DEFAULT_MAX_FRAME_PIXELS,
        }
    }
}

impl ReadLimits {
    pub(super) fn check(&self, path: &Path, g: &ImageGeometry) -> Result<()> {
        let pixels = g.width() as u64 * g.height() as u64;
        if pixels > self.max_frame_pixels {
            return Err(Error::bad_input(
                path,
                format!(
                    "the header announces {}×{} = {pixels} pixels per image, more than the limit of {} (`[daemon] max_frame_pixels`)",
                    g.width(),
                    g.height(),
                    self.max_frame_pixels
                ),
            ));
        }
        Ok(())
    }
}
