//! Headers against images: where the disk a header predicts disagrees with the disk the
//! image shows (rebinned files whose CDELT/SOLAR_R were never updated, wrong CRPIX), say
//! so and trust the image.

use crate::coarse::{check_header, header_radius_px};
use crate::meta::FrameMeta;
use crate::preprocess::{detect_disk_keeping_copy, BlockMeans, DiskFit};
use ndarray::Array2;
use std::sync::Arc;

/// A header radius off by more than this fraction of the measured one is wrong.
const RADIUS_TOLERANCE: f64 = 0.1;
/// A header centre off by more than this fraction of the measured radius (and 3 px) is wrong.
const CENTER_TOLERANCE: f64 = 0.1;

/// One image's header as checked against the disk its image shows.
#[derive(Debug, Clone)]
pub(super) struct Checked {
    /// The metadata to use.
    pub meta: FrameMeta,
    /// The disk (centre, radius in px) for the mask, when known.
    pub disk_px: Option<([f64; 2], f64)>,
    /// Whether a disk was seen in the image at all.
    pub seen: bool,
    /// Whether the header was corrected from it.
    pub corrected: bool,
    /// The binned copy of the image the disk was measured on, if one was made.
    pub block_means: Option<Arc<BlockMeans>>,
}

/// One image's header against its disk: the metadata to use, the disk for the mask.
pub(super) fn checked(meta: &FrameMeta, data: &Array2<f32>, notes: &mut Vec<String>) -> Checked {
    let header_radius = header_radius_px(meta);
    let header_disk = header_radius.map(|r| (meta.sun_center_px, r));
    let (seen, block_means) = detect_disk_keeping_copy(data.view());
    let block_means = block_means.map(Arc::new);
    let Some(seen) = seen else {
        return Checked {
            meta: meta.clone(),
            disk_px: header_disk,
            seen: false,
            corrected: false,
            block_means,
        };
    };
    let check = check_header(meta, &seen);
    let centre_wrong = check.center_offset_px > (CENTER_TOLERANCE * seen.radius_px).max(3.0);
    let radius_wrong = check
        .radius_ratio
        .map(|q| (q - 1.0).abs() > RADIUS_TOLERANCE)
        .unwrap_or(false);
    if !(centre_wrong || radius_wrong) {
        return Checked {
            meta: meta.clone(),
            disk_px: header_disk,
            seen: true,
            corrected: false,
            block_means,
        };
    }
    let mut fixed = meta.clone();
    fixed.sun_center_px = seen.center_px;
    let mut note = describe(meta, header_radius, &seen);
    if let (true, Some(rsun)) = (radius_wrong, meta.rsun_arcsec) {
        let rebinned = header_radius.and_then(|r| rebinning_factor(r, seen.radius_px));
        fixed.plate_scale_arcsec = match rebinned {
            Some(k) => {
                note.push_str(&format!(
                    ", whose disk is the header's {}; plate scale the header's {}",
                    k.describe(),
                    k.applied()
                ));
                meta.plate_scale_arcsec.map(|p| p * k.factor())
            }
            None => {
                let plate = rsun / seen.radius_px;
                note.push_str(&format!(
                    "; plate scale {plate:.4}″/px from its radius (a limb seen above the \
                     photosphere, as in EUV, makes it too small by as much)"
                ));
                [
                    plate.copysign(meta.plate_scale_arcsec[0]),
                    plate.copysign(meta.plate_scale_arcsec[1]),
                ]
            }
        };
    }
    notes.push(note);
    Checked {
        meta: fixed,
        disk_px: Some((seen.center_px, seen.radius_px)),
        seen: true,
        corrected: true,
        block_means,
    }
}

/// A frame's header against its disk, kept consistent with the reference's check when both
/// headers claim the same geometry (one instrument's series, one stale header):
/// - no disk seen in the frame (noise or a data gap can hide it): corrected as the
///   reference was; a frame corrected while its reference is not would put the header's
///   error into the coarse transform (EIT 128² pairs under noise: coarse scale 0.13);
/// - both corrected, with radii that agree within [`RADIUS_TOLERANCE`]: the reference's plate
///   scale and the frame's own centre. Two noisy radius measurements of one instrument would
///   otherwise differ by a few tenths of a percent, and that difference would be taken as a
///   resolution difference and smoothed away;
/// - no disk seen in the reference, so its header stands: the frame keeps its header too.
#[cfg(test)]
pub(super) fn checked_frame(
    frame: &FrameMeta,
    frame_data: &Array2<f32>,
    reference_header: &FrameMeta,
    reference: &Checked,
    notes: &mut Vec<String>,
) -> FrameMeta {
    let mut own_notes = Vec::new();
    let own = checked(frame, frame_data, &mut own_notes);
    frame_against_reference(frame, own, own_notes, reference_header, reference, notes)
}

/// [`checked_frame`] from the frame's own check (`checked` of its header and image, with the
/// notes that check made).
pub(super) fn frame_against_reference(
    frame: &FrameMeta,
    own: Checked,
    own_notes: Vec<String>,
    reference_header: &FrameMeta,
    reference: &Checked,
    notes: &mut Vec<String>,
) -> FrameMeta {
    let (reference_corrected, frame_corrected) = (reference.corrected, own.corrected);
    let name = frame
        .file
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if !same_claimed_geometry(frame, reference_header) {
        notes.extend(own_notes);
        return own.meta;
    }
    if reference_corrected && !own.seen {
        let mut fixed = frame.clone();
        fixed.plate_scale_arcsec = reference.meta.plate_scale_arcsec;
        for axis in 0..2 {
            fixed.sun_center_px[axis] +=
                reference.meta.sun_center_px[axis] - reference_header.sun_center_px[axis];
        }
        notes.push(format!(
            "{name}: no disk seen; its header repeats the reference's, so it is corrected as the reference's was"
        ));
        return fixed;
    }
    if reference_corrected && frame_corrected {
        let same_radius = match (own.disk_px, reference.disk_px) {
            (Some((_, a)), Some((_, b))) => (a / b - 1.0).abs() <= RADIUS_TOLERANCE,
            _ => false,
        };
        notes.extend(own_notes);
        let mut fixed = own.meta;
        if same_radius {
            fixed.plate_scale_arcsec = reference.meta.plate_scale_arcsec;
        }
        return fixed;
    }
    if frame_corrected && !reference.seen {
        notes.push(format!(
            "{name}: its header disagrees with its disk, but no disk was seen in the reference, whose header repeats it; using both headers as they are"
        ));
        return frame.clone();
    }
    notes.extend(own_notes);
    own.meta
}

/// Whether two headers claim the same plate scale and, within 1 % (it follows the Earth's
/// orbit, about 0.005 % a day), the same solar radius: one instrument's series.
fn same_claimed_geometry(a: &FrameMeta, b: &FrameMeta) -> bool {
    let close = |x: f64, y: f64, tolerance: f64| (x - y).abs() <= tolerance * x.abs().max(y.abs());
    close(a.plate_scale_arcsec[0], b.plate_scale_arcsec[0], 1e-9)
        && close(a.plate_scale_arcsec[1], b.plate_scale_arcsec[1], 1e-9)
        && match (a.rsun_arcsec, b.rsun_arcsec) {
            (Some(x), Some(y)) => close(x, y, 0.01),
            (None, None) => true,
            _ => false,
        }
}

/// A whole-number resampling of the image that its header was not updated for.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Rebinned {
    /// Binned `k`×: pixels `k` times larger.
    Binned(u32),
    /// Upsampled `k`×.
    Upsampled(u32),
}

impl Rebinned {
    /// The factor on the header's plate scale.
    fn factor(self) -> f64 {
        match self {
            Rebinned::Binned(k) => k as f64,
            Rebinned::Upsampled(k) => 1.0 / k as f64,
        }
    }

    fn describe(self) -> String {
        match self {
            Rebinned::Binned(k) => format!("binned {k}×"),
            Rebinned::Upsampled(k) => format!("upsampled {k}×"),
        }
    }

    fn applied(self) -> String {
        match self {
            Rebinned::Binned(k) => format!("× {k}"),
            Rebinned::Upsampled(k) => format!("÷ {k}"),
        }
    }
}

/// The largest whole-number resampling [`rebinning_factor`] recognises.
const MAX_REBINNING: u32 = 64;
/// How far the disk seen may stand beyond the photospheric one its header describes
/// (fraction of the radius): the EUV limb stands above the photosphere, by 2–5 % on 128²
/// EIT and AIA images, and a coarse grid blurs it outwards.
const LIMB_ABOVE: f64 = 0.07;
/// How far it may fall inside it: the limb fit's own error.
const LIMB_BELOW: f64 = 0.03;

/// The whole-number factor `k ≥ 2` by which the image was binned (or upsampled) without its
/// header being updated, when the disk it shows (`seen_px`) is the header's (`header_px`)
/// resampled by `k`, with the limb between [`LIMB_BELOW`] inside and [`LIMB_ABOVE`] outside
/// the photosphere's. The header's plate scale times `k` is then exact, where a plate scale
/// from the radius carries the limb's height (EIT 195 rebinned 8×: 4 % small).
fn rebinning_factor(header_px: f64, seen_px: f64) -> Option<Rebinned> {
    if !(header_px > 0.0 && seen_px > 0.0) {
        return None;
    }
    // seen = header · scale · (1 + h), h ∈ [−LIMB_BELOW, LIMB_ABOVE].
    let fits = |scale: f64| {
        let h = seen_px / (header_px * scale) - 1.0;
        (-LIMB_BELOW..=LIMB_ABOVE).contains(&h)
    };
    let ratio = header_px / seen_px;
    (2..=MAX_REBINNING)
        .map(Rebinned::Binned)
        .chain((2..=MAX_REBINNING).map(Rebinned::Upsampled))
        .filter(|k| fits(1.0 / k.factor()))
        .min_by(|a, b| {
            let off = |k: &Rebinned| (k.factor() / ratio).ln().abs();
            off(a).total_cmp(&off(b))
        })
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

#[cfg(test)]
mod tests {
    use super::*;

    /// EIT 195 rebinned 8× without updating its header: CDELT1 says 2.63″/px, the disk says
    /// about 8 × 2.63 = 21″/px (data README). A second image with the same header but no disk
    /// to be seen (a uniform frame, as a dropout or heavy noise would leave) must be corrected
    /// the same way, or the coarse transform would carry the 8× error.
    #[test]
    fn a_frame_repeating_a_corrected_header_is_corrected_the_same_way() {
        let (data, meta) = crate::test_data::read_real_image("eit_195_20040301T000010_128.fits");
        let eit = crate::engine::Image { data, meta };
        assert!((eit.meta.plate_scale_arcsec[0].abs() - 2.63).abs() < 0.01);
        let mut notes = Vec::new();
        let reference = checked(&eit.meta, &eit.data, &mut notes);
        assert!(reference.seen);
        // Binned 8× from 1024²: 8 × 2.63″ exactly, where the EUV limb's radius gives 4 % less.
        let plate = reference.meta.plate_scale_arcsec[0].abs();
        assert!((plate - 8.0 * 2.63).abs() < 1e-9, "reference plate {plate}");

        let blank = Array2::from_elem(eit.data.dim(), 900.0f32);
        let frame = checked_frame(&eit.meta, &blank, &eit.meta, &reference, &mut notes);
        assert_eq!(frame.plate_scale_arcsec, reference.meta.plate_scale_arcsec);
        assert_eq!(frame.sun_center_px, reference.meta.sun_center_px);

        // The reverse: no disk seen in the reference, so its header stands, and the frame
        // that repeats it keeps it too, although its own disk disagrees.
        let unseen = checked(&eit.meta, &blank, &mut notes);
        assert!(!unseen.seen);
        let frame = checked_frame(&eit.meta, &eit.data, &eit.meta, &unseen, &mut notes);
        assert_eq!(frame.plate_scale_arcsec, eit.meta.plate_scale_arcsec);
        assert!(notes
            .iter()
            .any(|n| n.contains("no disk was seen in the reference")));
    }

    #[test]
    fn whole_number_rebinnings_are_recognised_with_the_limb_above_the_photosphere() {
        // The header's radius over the seen one, the EUV limb 0–7 % above.
        assert_eq!(rebinning_factor(371.1, 48.5), Some(Rebinned::Binned(8)));
        assert_eq!(rebinning_factor(371.1, 47.4), Some(Rebinned::Binned(8)));
        assert_eq!(
            rebinning_factor(400.0, 200.0 * 1.03),
            Some(Rebinned::Binned(2))
        );
        assert_eq!(
            rebinning_factor(50.0, 200.0 * 1.02),
            Some(Rebinned::Upsampled(4))
        );
        // A radius 30 % off is no rebinning, nor is a ratio between two whole numbers.
        assert_eq!(rebinning_factor(100.0, 130.0), None);
        assert_eq!(rebinning_factor(250.0, 100.0), None);
    }
}
