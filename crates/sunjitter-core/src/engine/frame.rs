//! The frame's stage before the flow: its own preparation (cleaning, disk check), then against
//! the reference the coarse transform from the headers, the Sun's rotation and the intensity
//! match.

use super::config::EngineConfig;
use super::prepared::ReferenceWork;
use super::{check_usable, cleaned_from, derotate, geometry_check, photometry};
use crate::geometry::Similarity;
use crate::meta::FrameMeta;
use crate::preprocess::BlockMeans;
use crate::record::SolarRotationFields;
use ndarray::Array2;
use std::sync::Arc;
use std::time::Instant;

/// The frame's own preparation, which needs nothing of the reference: cleaned, and its disk
/// checked against its header. A caller holding both images makes it while the reference is
/// prepared.
pub(super) struct FrameOwn {
    cleaned: Array2<f32>,
    fill: Option<super::FillSeen>,
    check: geometry_check::Checked,
    notes: Vec<String>,
    cleaned_in: std::time::Duration,
    checked_in: std::time::Duration,
}

impl FrameOwn {
    pub(super) fn new(
        frame: &FrameMeta,
        data: super::Pixels<'_>,
        hot_pixel_fraction: f32,
    ) -> Result<FrameOwn, String> {
        check_usable("frame", &data)?;
        let started = Instant::now();
        let (cleaned, fill) = cleaned_from(data, hot_pixel_fraction);
        let cleaned_in = started.elapsed();
        let mut notes = Vec::new();
        let check = geometry_check::checked(frame, &cleaned, &mut notes);
        Ok(FrameOwn {
            cleaned,
            fill,
            check,
            notes,
            cleaned_in,
            checked_in: started.elapsed(),
        })
    }
}

/// The frame as the measurement reads it, with what the coarse stage found.
pub(super) struct FrameSide {
    /// The frame's header, checked against its disk and the reference's.
    pub(super) meta: FrameMeta,
    /// Cleaned, in the reference's intensity units.
    pub(super) data: Array2<f32>,
    /// `data` binned by its disk check, unless the intensity match changed it since.
    pub(super) block_means: Option<Arc<BlockMeans>>,
    pub(super) coarse: Similarity,
    pub(super) carried: Option<derotate::Carried>,
    pub(super) solar_rotation: Option<SolarRotationFields>,
    /// The reference's notes and the frame's checks'.
    pub(super) notes: Vec<String>,
    /// The frame's border fill, taken as missing data.
    pub(super) fill: Option<super::FillSeen>,
    /// With `keep`: the frame's own disk check and its notes, and the cleaned frame where
    /// the intensity match changed `data`.
    pub(super) kept_check: Option<(geometry_check::Checked, Vec<String>)>,
    pub(super) kept_cleaned: Option<Array2<f32>>,
}

/// From the frame's own preparation: the coarse transform from the headers (checked against
/// the reference's), the Sun's rotation and the intensity match: everything before the flow.
pub(super) fn prepare_frame(
    work: &ReferenceWork,
    frame: &FrameMeta,
    own: FrameOwn,
    cfg: &EngineConfig,
    keep: bool,
    started: Instant,
) -> Result<FrameSide, String> {
    let mut notes: Vec<String> = work.notes.clone();
    let FrameOwn {
        cleaned: mut frame_data,
        fill,
        check: own,
        notes: own_notes,
        cleaned_in,
        checked_in,
    } = own;
    notes.extend(super::fill_note(work.fill, fill));

    let mut block_means = own.block_means.clone();
    // Coarse: headers, checked against the disks the images show.
    let kept_check = keep.then(|| (own.clone(), own_notes.clone()));
    let frame_meta = geometry_check::frame_against_reference(
        frame,
        own,
        own_notes,
        &work.meta,
        &work.reference_check,
        &mut notes,
    );
    tracing::debug!(?cleaned_in, ?checked_in, "frame prepared");
    let coarse = crate::coarse::coarse_transform(&work.reference_check.meta, &frame_meta)
        .map_err(|e| format!("coarse alignment: {e}"))?;
    if let Some(e) = &work.mask_error {
        return Err(e.clone());
    }

    // The Sun's rotation between the two times: the frame is carried back to the reference's
    // time, so that what is measured is the telescope.
    let rotation = derotate::derotate(
        &derotate::ReferenceSide {
            meta: &work.reference_check.meta,
            disk_px: work.reference_check.disk_px,
            mask: &work.mask,
            mask_box: work.mask_box,
            mask_fraction: cfg.mask_radius_fraction,
        },
        &frame_meta,
        coarse,
        cfg.solar_rotation,
    );
    let (carried, coarse, solar_rotation) = match rotation {
        derotate::Rotation::Removed(d) => {
            notes.extend(d.notes);
            (Some(d.carried), d.coarse, Some(d.fields))
        }
        derotate::Rotation::Kept { fields, note } => {
            notes.extend(note);
            (None, coarse, fields)
        }
        derotate::Rotation::Refused(why) => return Err(why),
    };
    tracing::debug!(?solar_rotation, carried_at = ?started.elapsed(), "solar rotation");
    // An exposure change is no motion: the frame in the reference's intensity units.
    let photometry = photometry::Photometry::estimate(
        work.cleaned.view(),
        &work.mask,
        frame_data.view(),
        &coarse,
    );
    // The frame as cleaned, for its preparation as a reference.
    let mut kept_cleaned = None;
    if let Some(p) = photometry.filter(|p| !p.is_identity()) {
        if keep {
            kept_cleaned = Some(frame_data.clone());
        }
        p.remove(&mut frame_data);
        block_means = None;
    }
    tracing::debug!(?photometry, "frame intensities matched");
    Ok(FrameSide {
        meta: frame_meta,
        data: frame_data,
        block_means,
        coarse,
        carried,
        solar_rotation,
        notes,
        fill,
        kept_check,
        kept_cleaned,
    })
}
