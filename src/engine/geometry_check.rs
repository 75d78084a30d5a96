//! Headers against images: where the disk a header predicts disagrees with the disk the
//! image shows (rebinned files whose CDELT/SOLAR_R were never updated, wrong CRPIX), say
//! so and trust the image.

use super::Image;
use crate::coarse::{check_header, header_radius_px};
use crate::meta::FrameMeta;
use crate::preprocess::{detect_disk, DiskFit};
use ndarray::Array2;

/// The metadata the coarse stage should use, after checking it against the images.
#[derive(Debug, Clone)]
pub struct EffectiveGeometry {
    pub reference: FrameMeta,
    pub frame: FrameMeta,
    /// The reference disk (centre, radius in px) for the mask, when known.
    pub reference_disk_px: Option<([f64; 2], f64)>,
    pub notes: Vec<String>,
}

/// A header radius off by more than this fraction of the measured one is wrong.
const RADIUS_TOLERANCE: f64 = 0.1;
/// A header centre off by more than this fraction of the measured radius (and 3 px) is wrong.
const CENTER_TOLERANCE: f64 = 0.1;

pub fn effective_geometry(
    reference: &Image,
    reference_data: &Array2<f32>,
    frame: &Image,
    frame_data: &Array2<f32>,
) -> EffectiveGeometry {
    let mut notes = Vec::new();
    let (ref_meta, ref_disk) = checked(&reference.meta, reference_data, &mut notes);
    let (frame_meta, _) = checked(&frame.meta, frame_data, &mut notes);
    EffectiveGeometry {
        reference: ref_meta,
        frame: frame_meta,
        reference_disk_px: ref_disk,
        notes,
    }
}

/// One image's header against its disk: the metadata to use, the disk for the mask.
pub(super) fn checked(
    meta: &FrameMeta,
    data: &Array2<f32>,
    notes: &mut Vec<String>,
) -> (FrameMeta, Option<([f64; 2], f64)>) {
    let header_radius = header_radius_px(meta);
    let header_disk = header_radius.map(|r| (meta.sun_center_px, r));
    let Some(seen) = detect_disk(data.view()) else {
        return (meta.clone(), header_disk);
    };
    let check = check_header(meta, &seen);
    let centre_wrong = check.center_offset_px > (CENTER_TOLERANCE * seen.radius_px).max(3.0);
    let radius_wrong = check
        .radius_ratio
        .map(|q| (q - 1.0).abs() > RADIUS_TOLERANCE)
        .unwrap_or(false);
    if !(centre_wrong || radius_wrong) {
        return (meta.clone(), header_disk);
    }
    let mut fixed = meta.clone();
    fixed.sun_center_px = seen.center_px;
    if let (true, Some(rsun)) = (radius_wrong, meta.rsun_arcsec) {
        let plate = rsun / seen.radius_px;
        fixed.plate_scale_arcsec = [
            plate.copysign(meta.plate_scale_arcsec[0]),
            plate.copysign(meta.plate_scale_arcsec[1]),
        ];
    }
    notes.push(describe(meta, header_radius, &seen));
    (fixed, Some((seen.center_px, seen.radius_px)))
}

fn describe(meta: &FrameMeta, header_radius: Option<f64>, seen: &DiskFit) -> String {
    let name = meta
        .file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let header = match header_radius {
        Some(r) => format!(
            "centre ({:.1}, {:.1}) px, radius {r:.1} px",
            meta.sun_center_px[0], meta.sun_center_px[1]
        ),
        None => format!(
            "centre ({:.1}, {:.1}) px",
            meta.sun_center_px[0], meta.sun_center_px[1]
        ),
    };
    format!(
        "{name}: header disk ({header}) disagrees with the image (centre ({:.1}, {:.1}) px, radius {:.1} px); using the image",
        seen.center_px[0], seen.center_px[1], seen.radius_px
    )
}
