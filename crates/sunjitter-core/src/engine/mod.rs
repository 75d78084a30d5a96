//! One alignment: coarse (headers) → flow → sampling → fit → σ. No I/O here.
//!
//! The fine stage iterates: resample the frame onto the reference grid through the current
//! estimate, measure the residual motion with dense flow, fit a similarity to grid-median
//! vectors with RANSAC, compose, repeat until the update is negligible. Iterating drives the
//! residual motion towards zero, where the flow's gain errors (a window measures a little
//! less than the true rotation or scale) do not matter; the σ come from the last pass.
//!
//! Modules, one per stage: `config` (settings), `workspace` (working memory shared between
//! alignments), `prepared` (the reference's share, kept for every frame), `frame` (the frame's
//! own preparation, the coarse transform, the Sun's rotation, intensities), `seed` (the flow on
//! binned copies), `fine` (flow passes and their crops), `refine` (the intensity refinement),
//! `sigma`, `verdict` (status and reasons), `align` (one alignment through them), and the
//! checks and corrections they call (`region`: masks, crops and filter reaches).

mod align;
mod config;
pub mod derotate;
mod fine;
mod flow_check;
mod frame;
mod geometry_check;
mod model;
mod photometry;
mod prepared;
pub mod quality;
pub mod refine;
mod region;
mod seed;
mod sigma;
mod verdict;
mod workspace;

use crate::geometry::{Covariance4, Similarity};
use crate::meta::FrameMeta;
use crate::preprocess;
use crate::record::{AlignResult, Status};
use ndarray::{Array2, ArrayView2};
use std::time::Instant;

pub use config::RefineMode;
pub use config::{ChannelSettings, EngineConfig};
pub use model::{Model, ModelChoice, ModelPrior};
pub use prepared::{FrameWork, PreparedReference};
pub use sigma::SigmaMethod;
pub use workspace::Workspace;

/// An image's pixels as the engine takes them: its own (cleaned in place) or borrowed.
pub type Pixels<'a> = ndarray::CowArray<'a, f32, ndarray::Ix2>;

/// An image and what its header says about it.
#[derive(Debug, Clone)]
pub struct Image {
    /// Pixel values, shape `(height, width)`, indexed `[y, x]`; NaN where blank.
    pub data: Array2<f32>,
    pub meta: FrameMeta,
}

/// The engine's full answer: the contract record plus what chained policies need.
#[derive(Debug, Clone)]
pub struct AlignOutcome {
    pub result: AlignResult,
    /// Whole grid-to-grid transform (coarse then fine), `None` when failed.
    pub transform: Option<Similarity>,
    /// The header-predicted (coarse) transform, when the headers could be used.
    pub coarse: Option<Similarity>,
    /// Calibrated covariance of (scale, rotation_rad, dx_px, dy_px), `None` when failed.
    pub covariance: Option<Covariance4>,
    /// Plain UABJM covariance of the same parameters.
    pub uabjm_covariance: Option<Covariance4>,
    /// The solar-disk mask used on the reference grid.
    pub mask: Option<Array2<bool>>,
    /// The reference's geometry as the alignment used it, when it was prepared.
    pub reference_geometry: Option<UsedGeometry>,
}

/// A reference's plate scale and Sun centre as used: the header's, or the disk-checked ones
/// where the header disagreed with the disk the image shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UsedGeometry {
    /// Arcsec per pixel along x and y, signed as the header's.
    pub plate_scale_arcsec: [f64; 2],
    /// Where helioprojective (0″, 0″) falls, 0-based px.
    pub sun_center_px: [f64; 2],
    /// Whether these differ from the header's (it was refused for the image's disk).
    pub from_disk: bool,
}

/// Align `frame` to `reference`: where reference content appears in the frame.
/// To align several frames to one reference, prepare it once with [`PreparedReference`].
pub fn align_images(reference: &Image, frame: &Image, cfg: &EngineConfig) -> AlignOutcome {
    align_images_in(reference, frame, cfg, Default::default())
}

/// [`align_images`] with `workspace` (one that keeps self-tests between runs, say).
pub fn align_images_in(
    reference: &Image,
    frame: &Image,
    cfg: &EngineConfig,
    workspace: std::sync::Arc<Workspace>,
) -> AlignOutcome {
    align_views_in(
        (&reference.meta, reference.data.view()),
        (&frame.meta, frame.data.view()),
        cfg,
        workspace,
    )
}

/// [`align_images_in`] on pixels held elsewhere (another language's arrays, say), each with
/// its metadata: they are read where they lie, in any memory layout, and never written.
pub fn align_views_in(
    reference: (&FrameMeta, ArrayView2<'_, f32>),
    frame: (&FrameMeta, ArrayView2<'_, f32>),
    cfg: &EngineConfig,
    workspace: std::sync::Arc<Workspace>,
) -> AlignOutcome {
    let started = Instant::now();
    let reference = (
        std::borrow::Cow::Borrowed(reference.0),
        Pixels::from(reference.1),
    );
    let (prepared, own) = prepared_side_by_side(reference, frame.0, Pixels::from(frame.1), cfg);
    aligned_pair(prepared.sharing(workspace), frame.0, own, cfg, started)
}

/// [`align_images`] for a caller done with both images: each one's pixels are cleaned in
/// place, so a large pair holds two frames fewer at its peak. The numbers are the same.
pub fn align_images_owned(reference: Image, frame: Image, cfg: &EngineConfig) -> AlignOutcome {
    align_images_owned_in(reference, frame, cfg, Default::default())
}

/// [`align_images_owned`] with `workspace`.
pub fn align_images_owned_in(
    reference: Image,
    frame: Image,
    cfg: &EngineConfig,
    workspace: std::sync::Arc<Workspace>,
) -> AlignOutcome {
    let started = Instant::now();
    let Image { data, meta } = frame;
    let reference = (
        std::borrow::Cow::Owned(reference.meta),
        Pixels::from(reference.data),
    );
    let (prepared, own) = prepared_side_by_side(reference, &meta, Pixels::from(data), cfg);
    aligned_pair(prepared.sharing(workspace), &meta, own, cfg, started)
}

/// The reference prepared and the frame cleaned and disk-checked side by side: the frame's
/// own preparation needs nothing of the reference, and each fills the other's idle moments.
fn prepared_side_by_side(
    reference: (std::borrow::Cow<'_, FrameMeta>, Pixels<'_>),
    frame: &FrameMeta,
    data: Pixels<'_>,
    cfg: &EngineConfig,
) -> (PreparedReference, Result<frame::FrameOwn, String>) {
    rayon::join(
        || PreparedReference::of_pixels(reference.0, reference.1, cfg),
        || frame::FrameOwn::new(frame, data, cfg.hot_pixel_fraction),
    )
}

/// The frame aligned from its own preparation, timed from `started`.
fn aligned_pair(
    prepared: PreparedReference,
    frame: &FrameMeta,
    own: Result<frame::FrameOwn, String>,
    cfg: &EngineConfig,
    started: Instant,
) -> AlignOutcome {
    let (mut outcome, _) = prepared.align_own(frame, own, &cfg.channel_settings(), false, started);
    outcome.result.elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
    outcome
}

/// Whether an image can serve as a reference at all (size, finite pixels, structure).
pub fn usable_as_reference(image: &Image) -> Result<(), String> {
    check_usable("reference", &image.data)
}

fn check_usable<S: ndarray::Data<Elem = f32>>(
    which: &str,
    data: &ndarray::ArrayBase<S, ndarray::Ix2>,
) -> Result<(), String> {
    let (h, w) = data.dim();
    if h < 16 || w < 16 {
        return Err(format!("{which} image is {w}×{h} px; too small to align"));
    }
    // Rows a sixteenth at a time: an image that can be aligned shows enough finite pixels
    // and two different values within the first few, and is not read further. Only one
    // that may fail is read whole, for the figures its message gives.
    let need = (h * w) / 10;
    let rows = h.div_ceil(USABLE_CHECK_PARTS);
    let mut range = (0, f32::INFINITY, f32::NEG_INFINITY);
    for top in (0..h).step_by(rows) {
        let part =
            crate::stats::finite_range(data.slice(ndarray::s![top..(top + rows).min(h), ..]));
        range = (range.0 + part.0, range.1.min(part.1), range.2.max(part.2));
        if range.0 >= need && range.2 > range.1 {
            return Ok(());
        }
    }
    let (n_finite, lo, hi) = range;
    if n_finite < need {
        return Err(format!(
            "{which} image has {n_finite} finite pixels of {}; nothing to align",
            h * w
        ));
    }
    if hi <= lo {
        return Err(format!(
            "{which} image is constant ({lo}); no structure to align"
        ));
    }
    Ok(())
}

/// Parts (of rows) that [`check_usable`] reads one after the other.
const USABLE_CHECK_PARTS: usize = 16;

/// An image's border fill, taken as missing data: its value and pixel count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FillSeen {
    value: f32,
    pixels: usize,
}

/// What the record's message says of the fill of the reference and of the frame.
fn fill_note(reference: Option<FillSeen>, frame: Option<FillSeen>) -> Option<String> {
    let taken = "taken as missing data";
    Some(match (reference, frame) {
        (Some(r), Some(f)) if r.value.to_bits() == f.value.to_bits() => format!(
            "border fill {} {taken} ({} px of the reference, {} of the frame)",
            r.value, r.pixels, f.pixels
        ),
        (Some(r), Some(f)) => format!(
            "border fill {} of the reference ({} px) and {} of the frame ({} px) {taken}",
            r.value, r.pixels, f.value, f.pixels
        ),
        (Some(r), None) => format!(
            "border fill {} {taken} ({} px of the reference)",
            r.value, r.pixels
        ),
        (None, Some(f)) => format!(
            "border fill {} {taken} ({} px of the frame)",
            f.value, f.pixels
        ),
        (None, None) => return None,
    })
}

/// `data` with its border fill taken as missing (NaN) and cleaned of hot pixels (a copy when
/// nothing is to be cleaned), in place when it is owned: no second frame-sized array is
/// faulted in. Also what fill was found.
fn cleaned_from(data: Pixels<'_>, hot_pixel_fraction: f32) -> (Array2<f32>, Option<FillSeen>) {
    let fill = preprocess::find_fill(data.view());
    let data = match &fill {
        Some(fill) => {
            let mut d = data.into_owned();
            fill.blank(&mut d);
            Pixels::from(d)
        }
        None => data,
    };
    let seen = fill.map(|f| FillSeen {
        value: f.value,
        pixels: f.pixels,
    });
    if data.is_view() || !data.is_standard_layout() {
        let cleaned = if hot_pixel_fraction > 0.0 {
            preprocess::hot_pixels_removed(data.view(), hot_pixel_fraction)
        } else {
            // Copied in parallel: a frame is tens of MB, faulted in page by page.
            ndarray::Zip::from(&data).par_map_collect(|&v| v)
        };
        return (cleaned, seen);
    }
    let mut d = data.into_owned();
    if hot_pixel_fraction > 0.0 {
        preprocess::remove_hot_pixels(&mut d, hot_pixel_fraction);
    }
    (d, seen)
}

impl AlignOutcome {
    /// A `failed` outcome: no numbers, the reason in `message`.
    pub fn failed(reference: &str, frame: &str, reason: &str) -> AlignOutcome {
        AlignOutcome {
            result: AlignResult {
                reference: reference.into(),
                frame: frame.into(),
                scale: None,
                rotation_arcsec: None,
                dx_px: None,
                dy_px: None,
                dx_arcsec: None,
                dy_arcsec: None,
                sigma_scale: None,
                sigma_rotation_arcsec: None,
                sigma_dx_px: None,
                sigma_dy_px: None,
                sigma_dx_arcsec: None,
                sigma_dy_arcsec: None,
                uabjm_sigma_scale: None,
                uabjm_sigma_rotation_arcsec: None,
                uabjm_sigma_dx_px: None,
                uabjm_sigma_dy_px: None,
                header_residual: None,
                solar_rotation: None,
                points: 0,
                inliers: 0,
                residual_rms_px: None,
                model: None,
                similarity: None,
                status: Status::Failed,
                message: reason.into(),
                elapsed_ms: 0.0,
            },
            transform: None,
            coarse: None,
            covariance: None,
            uabjm_covariance: None,
            mask: None,
            reference_geometry: None,
        }
    }
}

/// The identity result of a frame aligned to itself (the first frame of a reference).
pub fn self_alignment(image: &Image) -> AlignOutcome {
    let (h, w) = image.data.dim();
    let t = Similarity::identity(Similarity::array_center(w, h));
    let zero = [[0.0; 4]; 4];
    let name = image.meta.file.display().to_string();
    AlignOutcome {
        result: AlignResult::identity(name.clone(), name, "reference frame (aligned to itself)"),
        transform: Some(t),
        coarse: Some(t),
        covariance: Some(zero),
        uabjm_covariance: Some(zero),
        mask: None,
        reference_geometry: None,
    }
}

#[cfg(test)]
mod tests {
    use super::check_usable;
    use ndarray::Array2;

    /// Pass or fail as the definition says, whatever part of the image holds what: 10 % of
    /// the pixels finite at least, two different finite values; a failure's figures are
    /// the whole image's.
    #[test]
    fn usability_follows_the_whole_image_wherever_its_pixels_lie() {
        let (h, w) = (64, 40);
        let image =
            |f: &dyn Fn(usize, usize) -> f32| Array2::from_shape_fn((h, w), |(y, x)| f(y, x));
        // Constant but for one pixel in the last row: usable.
        assert_eq!(
            check_usable(
                "frame",
                &image(&|y, x| if (y, x) == (63, 39) { 2.0 } else { 1.0 })
            ),
            Ok(())
        );
        // Blank but for the last 7 rows (10.9 % of the pixels), varying: usable.
        let tail = |y: usize, x: usize| if y >= 57 { (x + y) as f32 } else { f32::NAN };
        assert_eq!(check_usable("frame", &image(&tail)), Ok(()));
        // One row fewer (9.4 %): 240 finite pixels of 2560.
        let short = |y: usize, x: usize| if y >= 58 { (x + y) as f32 } else { f32::NAN };
        assert_eq!(
            check_usable("frame", &image(&short)),
            Err("frame image has 240 finite pixels of 2560; nothing to align".to_string())
        );
        // Constant where finite, infinities at the start: constant.
        let flat = |y: usize, _: usize| if y < 3 { f32::INFINITY } else { 5.5 };
        assert_eq!(
            check_usable("reference", &image(&flat)),
            Err("reference image is constant (5.5); no structure to align".to_string())
        );
        assert!(check_usable("frame", &Array2::from_elem((15, 40), 1.0)).is_err());
    }
}
