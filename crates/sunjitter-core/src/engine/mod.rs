//! One alignment: coarse (headers) → flow → sampling → fit → σ. No I/O here.
//!
//! The fine stage iterates: resample the frame onto the reference grid through the current
//! estimate, measure the residual motion with dense flow, fit a similarity to grid-median
//! vectors with RANSAC, compose, repeat until the update is negligible. Iterating drives the
//! residual motion towards zero, where the flow's gain errors (a window measures a little
//! less than the true rotation or scale) do not matter; the σ come from the last pass.

pub mod quality;

pub mod derotate;
mod flow_check;
mod geometry_check;
mod photometry;
pub mod refine;
mod sigma;

use crate::fit::{fit_similarity, FitFailure, RansacParams, SimilarityFit};
use crate::flow::{Farneback, FarnebackParams, FlowOptions, Roi};
use crate::geometry::{compose_with_covariance, sigmas, Covariance4, Similarity};
use crate::meta::FrameMeta;
use crate::preprocess;
use crate::record::{AlignResult, Status, TransformFields};
use crate::resample::HighOrderSpline;
use crate::sampling::grid_median_sample;
use ndarray::{s, Array2, ArrayView2, Zip};
use serde::{Deserialize, Serialize};
use std::ops::Range;
use std::time::Instant;

pub use refine::RefineMode;
pub use sigma::SigmaMethod;

/// An image and what its header says about it.
#[derive(Debug, Clone)]
pub struct Image {
    /// Pixel values, shape `(height, width)`, indexed `[y, x]`; NaN where blank.
    pub data: Array2<f32>,
    pub meta: FrameMeta,
}

/// Engine settings (from the configuration file's `[engine]` table). Every default is meant
/// to work on any solar imager; sizes are derived from the plate scale and the image itself.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EngineConfig {
    /// Farneback averaging window in arcsec (the paper uses about 63″), converted with the
    /// reference plate scale. `None` (the default): sized for the image's structure,
    /// `window_structure_lengths` texture correlation lengths (measured in the reference).
    /// Either way kept within `min_window_px` and a third of the disk radius (a quarter of the
    /// image without a disk).
    pub window_arcsec: Option<f64>,
    /// Explicit window in pixels (overrides everything else).
    pub window_px: Option<usize>,
    pub min_window_px: usize,
    pub window_structure_lengths: f64,
    /// Fraction of the solar radius kept in the disk mask (excludes the limb).
    pub mask_radius_fraction: f64,
    /// `sample × sample` grid of median vectors.
    pub sample: usize,
    /// RANSAC inlier threshold, px.
    pub ransac_threshold_px: f64,
    pub ransac_max_trials: usize,
    pub seed: u64,
    /// Pyramid levels of the first pass (`None`: as many as keep the coarsest level ≥ 64 px,
    /// at most 4). Later passes measure a small residual and use one level.
    pub pyramid_levels: Option<usize>,
    pub iterations: usize,
    /// Polynomial expansion neighbourhood (Farneback `poly_n`) and its Gaussian σ.
    pub poly_n: usize,
    pub poly_sigma: f64,
    /// Fine passes at most; stop when the update moves no point of the mask by more than
    /// `convergence_px`.
    pub max_passes: usize,
    pub convergence_px: f64,
    /// Replace pixels deviating from their 3×3 median by more than this fraction of it
    /// (cosmic rays, hot pixels); 0 disables.
    pub hot_pixel_fraction: f32,
    /// Systematic floor of the method, px (resampling and f32 arithmetic; measured with
    /// `simulate` as the bias left when the random error vanishes). Added in quadrature to the
    /// translation σ, and as `floor / rms radius of the vectors` to scale and rotation.
    pub systematic_floor_px: f64,
    /// Which σ is reported as `sigma_*` (the paper's plain UABJM is always reported too).
    pub sigma: SigmaMethod,
    /// Below this Bhattacharyya coefficient the result is `degraded`.
    pub min_similarity: f64,
    /// Below this structural correlation after alignment the result is `degraded`; below a
    /// third of it, `failed`.
    pub min_correlation: f64,
    /// Below this fraction of RANSAC inliers the result is `degraded`.
    pub min_inlier_fraction: f64,
    /// Final direct intensity refinement (Gauss–Newton on the RANSAC-inlier cells).
    pub refine: RefineMode,
    /// Gaussian σ applied to both images before the refinement, px: it takes the
    /// interpolation error of sharp structure out of the match (on the TRACE Monte Carlo,
    /// docs/validation.md: 0.7 px is best under noise and 5× better than none without noise).
    pub refine_smoothing_px: f64,
    /// Further Gaussian σ of the reference whose gradient weighs the refinement's residuals, px.
    pub refine_gradient_smoothing_px: f64,
    /// When the refinement follows, the flow seeds it on copies binned to the pyramid level
    /// where the mask spans at least this many pixels (full resolution below twice that).
    pub seed_extent_px: usize,
    /// The Sun's differential rotation taken out between the reference's and the frame's
    /// times (`howard`, `snodgrass`, `allen`, or `none` to keep it in the answer).
    pub solar_rotation: crate::solar_rotation::Profile,
}

impl Default for EngineConfig {
    fn default() -> Self {
        EngineConfig {
            window_arcsec: None,
            window_px: None,
            min_window_px: 15,
            window_structure_lengths: 10.0,
            mask_radius_fraction: 0.9,
            sample: 20,
            ransac_threshold_px: 1.0,
            ransac_max_trials: 2000,
            seed: 0,
            pyramid_levels: None,
            iterations: 10,
            poly_n: 5,
            poly_sigma: 1.1,
            max_passes: 4,
            convergence_px: 2e-4,
            hot_pixel_fraction: 1.0,
            systematic_floor_px: 3e-5,
            sigma: SigmaMethod::default(),
            min_similarity: 0.3,
            min_correlation: 0.3,
            min_inlier_fraction: 0.5,
            refine: RefineMode::default(),
            refine_smoothing_px: 0.7,
            refine_gradient_smoothing_px: 0.0,
            seed_extent_px: SEED_EXTENT_PX,
            solar_rotation: crate::solar_rotation::Profile::default(),
        }
    }
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

/// What the fine stage measured.
struct FineResult {
    transform: Similarity,
    covariance: Covariance4,
    uabjm_covariance: Covariance4,
    fit: SimilarityFit,
    points: usize,
    /// The frame resampled onto the reference grid through the final estimate, on `crop`
    /// only (the mask's box plus every later filter's reach).
    /// For a seed on binned copies, on the binned grid (and `crop` too).
    warped: Option<Array2<f32>>,
    crop: Crop,
    passes: usize,
    converged: bool,
    /// The last pass's motion (px at the mask's radius) when the passes ran out before it
    /// became negligible and it exceeded the answer's σ: the estimate was still moving.
    unsettled_px: Option<f64>,
    /// `Some(level)` for a seed for the refinement measured on images binned to that pyramid
    /// level.
    seed_level: Option<usize>,
    /// What the refinement needs: the bounding box (x0, y0, x1, y1, inclusive, reference
    /// grid) of the sampling mask, over which the sampling grid's cells lie, and the inliers.
    sample_box: Option<(usize, usize, usize, usize)>,
    inliers: Vec<crate::sampling::Correspondence>,
}

impl FineResult {
    /// `warped` at reference-grid rows and columns (which must lie inside the crop).
    fn warped_at(&self, rows: Range<usize>, cols: Range<usize>) -> Option<ArrayView2<'_, f32>> {
        let (y0, x0) = (self.crop.rows.start, self.crop.cols.start);
        let inside = rows.start >= y0
            && cols.start >= x0
            && rows.end <= self.crop.rows.end
            && cols.end <= self.crop.cols.end;
        let warped = self.warped.as_ref().filter(|_| inside)?;
        Some(warped.slice(s![
            rows.start - y0..rows.end - y0,
            cols.start - x0..cols.end - x0
        ]))
    }
}

/// Align `frame` to `reference`: where reference content appears in the frame.
/// To align several frames to one reference, prepare it once with [`PreparedReference`].
pub fn align_images(reference: &Image, frame: &Image, cfg: &EngineConfig) -> AlignOutcome {
    let started = Instant::now();
    let mut outcome = PreparedReference::new(reference, cfg).align(frame);
    outcome.result.elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
    outcome
}

/// Working memory kept from one alignment to the next: the flow solver, whose buffers
/// (≈ 35 bytes per pixel of the crop) are the largest of an alignment. Faulting them in again
/// for every frame costs more than the flow's arithmetic on the coarse levels, so a caller
/// aligning many frames, against one reference or many, shares one `Workspace` between its
/// prepared references ([`PreparedReference::sharing`]). It holds one solver; an alignment
/// that finds it taken makes its own.
#[derive(Default)]
pub struct Workspace {
    spare: std::sync::Mutex<Option<Farneback>>,
}

impl Workspace {
    fn take(&self) -> Option<Farneback> {
        match self.spare.lock() {
            Ok(mut g) => g.take(),
            Err(poisoned) => poisoned.into_inner().take(),
        }
    }

    fn give(&self, solver: Farneback) {
        match self.spare.lock() {
            Ok(mut g) => *g = Some(solver),
            Err(poisoned) => *poisoned.into_inner() = Some(solver),
        }
    }
}

impl std::fmt::Debug for Workspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Workspace")
    }
}

/// The reference's share of an alignment (hot-pixel cleaning, disk check, mask, window,
/// resolution-matched copies and their high-pass), computed once and reused for every frame
/// aligned to it: the daemon aligns many frames to one reference. `align` gives exactly what
/// [`align_images`] gives.
pub struct PreparedReference {
    cfg: EngineConfig,
    file: String,
    work: Result<ReferenceWork, String>,
    workspace: std::sync::Arc<Workspace>,
}

struct ReferenceWork {
    /// The header's metadata, and as checked against the image.
    meta: FrameMeta,
    reference_check: geometry_check::Checked,
    notes: Vec<String>,
    cleaned: Array2<f32>,
    mask: Array2<bool>,
    /// Why the mask cannot be used (raised after the frame's own checks).
    mask_error: Option<String>,
    mask_box: Roi,
    winsize: usize,
    /// Resolution-matched versions by smoothing σ (few: one per partner plate scale).
    matched: std::sync::Mutex<Vec<std::sync::Arc<Matched>>>,
}

/// The reference smoothed to a frame's resolution, and its high-pass for the structure check.
struct Matched {
    sigma_px: f64,
    /// `None`: no smoothing (the cleaned reference itself).
    data: Option<Array2<f32>>,
    /// High-pass of `data` on `quality_crop`.
    high_pass: Array2<f32>,
    quality_crop: Crop,
    /// The refinement's systematic floor on this reference (measured on first use).
    self_test: std::sync::OnceLock<Option<refine::SelfTest>>,
    /// Binned copies for seed flows on large frames (made on first use).
    binned: std::sync::OnceLock<Binned>,
    /// The reference as the refinement reads it (made on the first refinement).
    refine_reference: std::sync::OnceLock<refine::RefineReference>,
    /// Radial power spectrum at the mask's centre, for the blur difference (first use).
    spectrum: std::sync::OnceLock<Option<crate::blur::RadialSpectrum>>,
}

/// At most this many resolution-matched versions are kept per reference.
const MATCHED_CACHE: usize = 4;

/// A frame's cleaned image and its own disk check, as preparing it as a reference makes them:
/// a frame that becomes the next reference (`previous`) is not cleaned and checked twice.
pub struct FrameWork {
    cleaned: Array2<f32>,
    check: geometry_check::Checked,
    notes: Vec<String>,
    hot_pixel_fraction: f32,
}

impl PreparedReference {
    pub fn new(reference: &Image, cfg: &EngineConfig) -> PreparedReference {
        PreparedReference::prepare(reference, cfg, None)
    }

    /// As [`PreparedReference::new`], reusing the work done on `reference` when it was
    /// aligned as a frame ([`PreparedReference::align_keeping`] of this same image).
    pub fn from_frame_work(
        reference: &Image,
        cfg: &EngineConfig,
        work: FrameWork,
    ) -> PreparedReference {
        PreparedReference::prepare(reference, cfg, Some(work))
    }

    fn prepare(
        reference: &Image,
        cfg: &EngineConfig,
        kept: Option<FrameWork>,
    ) -> PreparedReference {
        PreparedReference {
            cfg: cfg.clone(),
            file: crate::text::path(&reference.meta.file).into_owned(),
            work: ReferenceWork::new(reference, cfg, kept),
            workspace: Default::default(),
        }
    }

    /// Align with `workspace`, shared with other references, instead of one of its own.
    pub fn sharing(mut self, workspace: std::sync::Arc<Workspace>) -> PreparedReference {
        self.workspace = workspace;
        self
    }

    /// The configuration the reference was prepared with (and frames are aligned with).
    pub fn config(&self) -> &EngineConfig {
        &self.cfg
    }

    /// The reference's geometry as alignments to it use it; `None` when it cannot be used.
    pub fn geometry(&self) -> Option<UsedGeometry> {
        self.work.as_ref().ok().map(ReferenceWork::geometry)
    }

    /// Align `frame` to the prepared reference.
    pub fn align(&self, frame: &Image) -> AlignOutcome {
        self.align_with(frame, self.cfg.solar_rotation)
    }

    /// Align `frame`, taking out the Sun's rotation by `profile` (a channel's own setting).
    pub fn align_with(
        &self,
        frame: &Image,
        profile: crate::solar_rotation::Profile,
    ) -> AlignOutcome {
        self.align_inner(frame, profile, false).0
    }

    /// As [`PreparedReference::align_with`], and the work done on `frame` that preparing it
    /// as a reference would repeat (`None` when the alignment failed).
    pub fn align_keeping(
        &self,
        frame: &Image,
        profile: crate::solar_rotation::Profile,
    ) -> (AlignOutcome, Option<FrameWork>) {
        self.align_inner(frame, profile, true)
    }

    fn align_inner(
        &self,
        frame: &Image,
        profile: crate::solar_rotation::Profile,
        keep: bool,
    ) -> (AlignOutcome, Option<FrameWork>) {
        let started = Instant::now();
        let cfg = EngineConfig {
            solar_rotation: profile,
            ..self.cfg.clone()
        };
        let result = match &self.work {
            Ok(work) => align_inner(work, frame, &cfg, keep, &self.workspace),
            Err(reason) => Err(reason.clone()),
        };
        let (result, kept) = match result {
            Ok((outcome, kept)) => (Ok(outcome), kept),
            Err(e) => (Err(e), None),
        };
        let mut outcome = result.unwrap_or_else(|reason| {
            AlignOutcome::failed(&self.file, &crate::text::path(&frame.meta.file), &reason)
        });
        outcome.reference_geometry = self.geometry();
        outcome.result.elapsed_ms = started.elapsed().as_secs_f64() * 1e3;
        (outcome, kept)
    }
}

impl ReferenceWork {
    fn geometry(&self) -> UsedGeometry {
        let used = &self.reference_check.meta;
        UsedGeometry {
            plate_scale_arcsec: used.plate_scale_arcsec,
            sun_center_px: used.sun_center_px,
            from_disk: self.reference_check.corrected,
        }
    }

    fn new(
        reference: &Image,
        cfg: &EngineConfig,
        kept: Option<FrameWork>,
    ) -> Result<ReferenceWork, String> {
        let (h, w) = reference.data.dim();
        check_usable("reference", &reference.data)?;
        let (cleaned, reference_check, notes) = match kept {
            Some(k) if k.hot_pixel_fraction.to_bits() == cfg.hot_pixel_fraction.to_bits() => {
                (k.cleaned, k.check, k.notes)
            }
            _ => {
                let cleaned = cleaned(&reference.data, cfg.hot_pixel_fraction);
                let mut notes = Vec::new();
                let check = geometry_check::checked(&reference.meta, &cleaned, &mut notes);
                (cleaned, check, notes)
            }
        };
        let (checked, disk_px) = (&reference_check.meta, reference_check.disk_px);

        // Mask on the reference grid: the disk without its limb, or the whole valid field.
        let mut mask = match disk_px {
            Some((c, r)) => preprocess::disk_mask(w, h, c, r, cfg.mask_radius_fraction),
            None => Array2::from_elem((h, w), true),
        };
        Zip::from(&mut mask)
            .and(&cleaned)
            .for_each(|m, v| *m = *m && v.is_finite());
        let mask_pixels = mask.iter().filter(|m| **m).count();
        let mask_error = (mask_pixels < 64).then(|| {
            format!(
                "the solar-disk mask holds {mask_pixels} usable pixels of the reference; nothing to align"
            )
        });
        // Filters and statistics below only matter inside the mask: run them on its bounding
        // box plus the filter's reach (the disk covers under half of a full-disk frame).
        let mask_box = mask_roi(&mask);

        // Window sized for the plate scale, bounded by what the image's structure supports.
        let plate = checked.plate_scale_arcsec[0].abs();
        let structure = if mask_error.is_none() {
            let (rows, cols) = grown(mask_box, STRUCTURE_TREND_SIGMA_PX, w, h);
            structure_length_px(
                cleaned.slice(s![rows.clone(), cols.clone()]),
                mask.slice(s![rows, cols]),
            )
        } else {
            None
        };
        let winsize = choose_window(cfg, plate, structure, disk_px.map(|d| d.1), w, h);
        tracing::debug!(?structure, winsize, plate, "window chosen");
        Ok(ReferenceWork {
            meta: reference.meta.clone(),
            reference_check,
            notes,
            cleaned,
            mask,
            mask_error,
            mask_box,
            winsize,
            matched: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// The reference smoothed by `sigma_px` (cached).
    fn matched(&self, sigma_px: f64) -> std::sync::Arc<Matched> {
        let sigma_px = if sigma_px > 0.0 { sigma_px } else { 0.0 };
        let lock = || match self.matched.lock() {
            Ok(g) => g,
            Err(poisoned) => poisoned.into_inner(),
        };
        if let Some(m) = lock()
            .iter()
            .find(|m| m.sigma_px.to_bits() == sigma_px.to_bits())
        {
            return m.clone();
        }
        let data =
            (sigma_px > 0.0).then(|| preprocess::gaussian_smooth(self.cleaned.view(), sigma_px));
        let view = data.as_ref().map_or(self.cleaned.view(), |d| d.view());
        // Structure only: the large-scale disk brightness correlates even for unrelated images.
        let (h, w) = self.cleaned.dim();
        let trend_px = self.trend_px();
        let (rows, cols) = grown(self.mask_box, trend_px, w, h);
        let high_pass = quality::high_pass(view.slice(s![rows.clone(), cols.clone()]), trend_px);
        let made = std::sync::Arc::new(Matched {
            sigma_px,
            data,
            high_pass,
            quality_crop: Crop { rows, cols },
            self_test: std::sync::OnceLock::new(),
            binned: std::sync::OnceLock::new(),
            refine_reference: std::sync::OnceLock::new(),
            spectrum: std::sync::OnceLock::new(),
        });
        let mut cache = lock();
        if cache.len() >= MATCHED_CACHE {
            cache.remove(0);
        }
        cache.push(made.clone());
        made
    }

    /// Scale of the trend removed before the structure check, px.
    fn trend_px(&self) -> f64 {
        self.winsize as f64 / 4.0
    }
}

impl Matched {
    fn view<'a>(&'a self, work: &'a ReferenceWork) -> ArrayView2<'a, f32> {
        self.data.as_ref().map_or(work.cleaned.view(), |d| d.view())
    }
}

fn align_inner(
    work: &ReferenceWork,
    frame: &Image,
    cfg: &EngineConfig,
    keep: bool,
    workspace: &Workspace,
) -> Result<(AlignOutcome, Option<FrameWork>), String> {
    check_usable("frame", &frame.data)?;
    let mut notes: Vec<String> = work.notes.clone();

    let started = Instant::now();
    let mut frame_data = cleaned(&frame.data, cfg.hot_pixel_fraction);
    let cleaned_at = started.elapsed();

    // Coarse: headers, checked against the disks the images show.
    let mut own_notes = Vec::new();
    let own = geometry_check::checked(&frame.meta, &frame_data, &mut own_notes);
    let kept_check = keep.then(|| (own.clone(), own_notes.clone()));
    let frame_meta = geometry_check::frame_against_reference(
        &frame.meta,
        own,
        own_notes,
        &work.meta,
        &work.reference_check,
        &mut notes,
    );
    tracing::debug!(?cleaned_at, checked_at = ?started.elapsed(), "frame prepared");
    let coarse = crate::coarse::coarse_transform(&work.reference_check.meta, &frame_meta)
        .map_err(|e| format!("coarse alignment: {e}"))?;
    if let Some(e) = &work.mask_error {
        return Err(e.clone());
    }
    let (mask, mask_box, winsize) = (&work.mask, work.mask_box, work.winsize);
    let ref_data = &work.cleaned;

    // The Sun's rotation between the two times: the frame is carried back to the reference's
    // time, so that what is measured is the telescope.
    let rotation = derotate::derotate(
        &derotate::ReferenceSide {
            meta: &work.reference_check.meta,
            disk_px: work.reference_check.disk_px,
            mask,
            mask_box,
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
    let photometry =
        photometry::Photometry::estimate(ref_data.view(), mask, frame_data.view(), &coarse);
    // The frame as cleaned, for its preparation as a reference.
    let mut kept_cleaned = None;
    if let Some(p) = photometry.filter(|p| !p.is_identity()) {
        if keep {
            kept_cleaned = Some(frame_data.clone());
        }
        p.remove(&mut frame_data);
    }
    tracing::debug!(?photometry, "frame intensities matched");
    let frame_data = frame_data;
    let (h, w) = work.cleaned.dim();
    let partial = !derotate::holds_the_disk(work.reference_check.disk_px, w, h);
    let measure = |coarse: Similarity,
                   carried: Option<&derotate::Carried>,
                   solar_rotation: Option<crate::record::SolarRotationFields>,
                   mut notes: Vec<String>|
     -> Result<AlignOutcome, String> {
        // Resolution matching: degrade the sharper image to the other's resolution.
        let plate = work.reference_check.meta.plate_scale_arcsec[0].abs();
        let grid_plate = plate;
        let frame_plate_on_grid = frame_meta.plate_scale_arcsec[0].abs();
        let (sig_ref, sig_frame) = preprocess::resolution_matching_sigmas(
            preprocess::nyquist_fwhm_arcsec(plate),
            preprocess::nyquist_fwhm_arcsec(frame_plate_on_grid),
            grid_plate,
        );
        let matched = work.matched(sig_ref);
        let ref_matched = matched.view(work);

        let refining = refine::wanted(cfg.refine, &work.meta, &frame.meta);
        // Between channels the limb is no common structure: each channel brightens towards it by
        // its own amount and shows it at its own height (EIT 171 and 195, one telescope, fit
        // disks 2.3 % apart). Windows that reach it read that as a scale change (EIT 195 against
        // 171: 0.9927 ± 0.0020, 3.7σ from 1; with the windows clear of it 0.9975 ± 0.0038).
        let limb_clear = match work.reference_check.disk_px {
            Some((centre, radius)) if work.meta.channel != frame.meta.channel => {
                Some((centre, radius - flow_reach_px(winsize, cfg.poly_n)))
            }
            _ => None,
        };
        let flow_from = |start: Similarity, max_passes: usize| {
            fine_alignment(
                ref_matched,
                &frame_data,
                FlowRegion {
                    mask,
                    sample_within: limb_clear,
                },
                start,
                winsize,
                sig_frame,
                max_passes,
                carried,
                cfg,
                workspace,
            )
            .map_err(|e| e.to_string())
        };
        let full_stage = || flow_from(coarse, cfg.max_passes);
        // When the refinement follows, the flow only seeds it, on binned copies of a large
        // frame; should the refinement not be taken, the flow runs at full resolution after all.
        let seed_level = if refining {
            seed_level(mask_box, cfg)
        } else {
            0
        };
        let mut fine = if seed_level > 0 {
            let binned = matched
                .binned
                .get_or_init(|| Binned::new(ref_matched, mask, seed_level, work.trend_px()));
            seed_alignment(
                binned,
                work.cleaned.dim(),
                &frame_data,
                coarse,
                winsize,
                sig_frame,
                carried,
                cfg,
                workspace,
            )
            // Binned copies can lack what the full frame has (too few vectors, say).
            .or_else(|_| full_stage())?
        } else {
            full_stage()?
        };
        let mut refine_note = None;
        let mut methods_disagree = false;
        let mut refinement_accepted = false;
        let mut refinement_ran_off = false;
        if refining {
            let prepared = matched.refine_reference.get_or_init(|| {
                refine::RefineReference::new(ref_matched, &refine::settings(cfg, 0.0))
            });
            let blur_of = |fine: &FineResult| {
                let centre = [
                    mask_box.x as f64 + (mask_box.width as f64 - 1.0) / 2.0,
                    mask_box.y as f64 + (mask_box.height as f64 - 1.0) / 2.0,
                ];
                let side = mask_box.width.min(mask_box.height);
                let reference = matched
                    .spectrum
                    .get_or_init(|| crate::blur::RadialSpectrum::around(ref_matched, centre, side))
                    .as_ref()?;
                let at = match carried {
                    Some(c) => {
                        let (x, y) = c.then(&fine.transform)(centre[0], centre[1]);
                        [x, y]
                    }
                    None => fine.transform.apply(centre),
                };
                let frame = crate::blur::RadialSpectrum::moved(
                    frame_data.view(),
                    reference,
                    [at[0] - centre[0], at[1] - centre[1]],
                )?;
                crate::blur::blur_difference(reference, &frame, fine.transform.scale)
            };
            let try_refine = |fine: &mut FineResult| {
                let measured = Instant::now();
                let blur = blur_of(fine);
                tracing::debug!(?blur, took = ?measured.elapsed(), "blur difference");
                refine::apply(
                    refine::FlowAnswer {
                        transform: &mut fine.transform,
                        covariance: &mut fine.covariance,
                        sample_box: fine.sample_box,
                        inliers: &fine.inliers,
                        slack_px: fine.seed_level.map_or(0.0, seed_slack_px),
                    },
                    &refine::RefineInputs {
                        reference: ref_matched,
                        prepared,
                        frame: frame_data.view(),
                        mask,
                        frame_smoothing_px: sig_frame,
                        blur,
                        carried,
                        cfg,
                    },
                    |settings| {
                        *matched.self_test.get_or_init(|| {
                            refine::self_test_floor(
                                ref_matched,
                                prepared,
                                mask,
                                cfg.sample,
                                settings,
                            )
                        })
                    },
                )
            };
            let mut outcome = try_refine(&mut fine);
            if outcome.is_err() {
                if fine.seed_level.is_some() {
                    fine = full_stage()?;
                }
                // A flow still moving by more than its σ when its passes ran out is mostly
                // converging slowly: weak or noisy structure lowers its gain, and each pass
                // recovers only part of what is left. More passes, then the refinement again
                // (tests/data/lasco_c3_noisy_drift: `ok` after 12 passes, within 1.7σ; stopped
                // after 4 passes it would be `degraded`, its rotation 7.3σ off).
                // Only here: on real frames that the refinement accepts after the first passes,
                // more passes can wander off (IRIS 1400 frames 22–24 under a brightening).
                if fine.unsettled_px.is_some() {
                    let mut more = flow_from(
                        fine.transform,
                        cfg.max_passes.max(1) * (UNSETTLED_PASS_FACTOR - 1),
                    )?;
                    more.passes += fine.passes;
                    fine = more;
                    outcome = try_refine(&mut fine);
                }
            }
            match outcome {
                Ok(note) => {
                    refine_note = Some(note);
                    fine.unsettled_px = None;
                    refinement_accepted = true;
                }
                Err(rejected) => {
                    refine_note = Some(rejected.note);
                    refinement_ran_off = rejected.ran_off;
                    // Two measurements of one motion that disagree beyond their σ: the flow's
                    // answer stays, and its σ grow to cover the refinement's (on LASCO C3 pairs
                    // under noise the flow can be 8σ off and the rejected refinement right).
                    if let Some(refined) = rejected.disagreeing {
                        let (a, b) = (fine.transform.params(), refined.params());
                        for k in 0..4 {
                            fine.covariance[k][k] += (a[k] - b[k]).powi(2);
                        }
                        methods_disagree = true;
                    }
                }
            }
        }
        // The flow's answer is final: its σ must cover its own interpolation bias, which the
        // scatter of its vectors does not show (see `flow_check`).
        if !refining && cfg.sigma == SigmaMethod::Calibrated {
            let checked = Instant::now();
            let region = FlowRegion {
                mask,
                sample_within: limb_clear,
            };
            match flow_check::flow_interpolation_check(
                ref_matched,
                region,
                &fine.transform,
                &coarse,
                winsize,
                cfg,
                workspace,
            ) {
                Some(term) => {
                    for (k, t) in term.iter().enumerate() {
                        fine.covariance[k][k] += t * t;
                    }
                    notes.push(format!(
                        "flow interpolation check {:.1e} / {:.3}″ / {:.1e} / {:.1e} px",
                        term[0],
                        term[1] * crate::geometry::ARCSEC_PER_RAD,
                        term[2],
                        term[3]
                    ));
                }
                None => notes.push("flow interpolation check could not run".to_string()),
            }
            tracing::debug!(took = ?checked.elapsed(), "flow interpolation check");
        }
        // Once the refinement has the last word, the flow only seeded it: its convergence is
        // no news to the user.
        if !fine.converged && !refinement_accepted {
            notes.push(format!(
                "fine alignment did not converge to {} px in {} passes",
                cfg.convergence_px, fine.passes
            ));
        }
        notes.extend(refine_note);
        let fine_at = started.elapsed();
        // Quality of the final match: on the full grid, or for a seed on binned copies on theirs
        // (the refinement moves the seed's answer by a small fraction of a binned pixel).
        let (similarity, correlation) = match (fine.seed_level, matched.binned.get()) {
            (Some(_), Some(binned)) => quality_of(
                &QualityGrid {
                    reference: binned.reference.view(),
                    mask: &binned.mask,
                    mask_box: binned.mask_box,
                    high_pass: &binned.high_pass,
                    quality_crop: &binned.quality_crop,
                    trend_px: work.trend_px(),
                },
                &fine,
            ),
            _ => quality_of(
                &QualityGrid {
                    reference: ref_data.view(),
                    mask,
                    mask_box,
                    high_pass: &matched.high_pass,
                    quality_crop: &matched.quality_crop,
                    trend_px: work.trend_px(),
                },
                &fine,
            ),
        };

        tracing::debug!(?fine_at, quality_at = ?started.elapsed(), "frame aligned");
        let t = fine.transform;
        let sig = sigmas(&fine.covariance);
        let usig = sigmas(&fine.uabjm_covariance);
        let header_residual = coarse.inverse().after(&t);
        let inlier_fraction = fine.fit.n_inliers as f64 / fine.points.max(1) as f64;

        let mut status = Status::Ok;
        let mut reasons: Vec<String> = Vec::new();
        if let Some(c) = correlation {
            if c < cfg.min_correlation / 3.0 {
                return Err(format!(
                "no common structure: correlation {c:.3} after alignment (frame unrelated to the reference?)"
            ));
            }
            if c < cfg.min_correlation {
                status = Status::Degraded;
                reasons.push(format!("weak common structure (correlation {c:.3})"));
            }
        }
        if let Some(s) = similarity {
            if s < cfg.min_similarity {
                status = Status::Degraded;
                reasons.push(format!("low histogram similarity {s:.3}"));
            }
        }
        // A flow that needs more than `max_passes`, or is still moving when its passes run out,
        // has a low gain. With weak common structure, or a flow field most of which fits no one
        // similarity, it may also settle on a wrong match far outside its σ, or stop short of the
        // right one (tests/data/lasco_c3_noisy_false_match: a −3.6° rotation, 26σ off;
        // tests/data/hmi_zero_sky_false_match: near no motion, 27σ off in dx). Without the
        // refinement's confirmation there is no reliable answer. Nor when the flow settles but
        // the refinement from its answer runs off: then both checks of that answer fail (HMI 100²
        // with a zero sky has pairs whose flow settles within 4 passes near no motion, 26–27σ
        // from the truth, and the refinement from there leaves the frame or goes singular).
        let slow_flow = fine.unsettled_px.is_some() || fine.passes > cfg.max_passes.max(1);
        let weak = correlation
            .filter(|&c| c < cfg.min_correlation)
            .map(|c| format!("the common structure is weak (correlation {c:.3})"));
        let incoherent = (inlier_fraction < cfg.min_inlier_fraction).then(|| {
            format!(
                "only {}/{} flow vectors agree with one similarity",
                fine.fit.n_inliers, fine.points
            )
        });
        if let (false, Some(why)) = (refinement_accepted, weak.or(incoherent)) {
            let unconfirmed = match fine.unsettled_px {
                Some(moved) => Some(format!(
                "the fine alignment was still moving after {} passes ({moved:.3} px in the last)",
                fine.passes
            )),
                None if slow_flow => Some(format!(
                    "the fine alignment needed {} passes to settle",
                    fine.passes
                )),
                None if refinement_ran_off => {
                    Some("the intensity refinement from the flow's answer ran off".to_string())
                }
                None => None,
            };
            if let Some(unconfirmed) = unconfirmed {
                return Err(format!("no reliable answer: {why}, and {unconfirmed}"));
            }
        }
        if let Some(moved) = fine.unsettled_px {
            status = Status::Degraded;
            reasons.push(format!(
                "the fine alignment was still moving ({moved:.3} px in its last pass); σ include \
             that step"
            ));
        }
        if methods_disagree {
            status = Status::Degraded;
            reasons.push(
                "the flow and the intensity refinement disagree; σ include their difference".into(),
            );
        }
        if inlier_fraction < cfg.min_inlier_fraction {
            status = Status::Degraded;
            reasons.push(format!(
                "only {}/{} flow vectors agree with one similarity",
                fine.fit.n_inliers, fine.points
            ));
        }
        reasons.extend(notes);
        reasons.push(match fine.seed_level {
            Some(level) if level > 0 => format!(
                "window {winsize} px, {} passes finished on pyramid level {level}",
                fine.passes
            ),
            _ => format!("window {winsize} px, {} passes", fine.passes),
        });

        // The plate scale the alignment used: the header's, or the disk-checked one where the
        // header's was refused.
        let ps = work.reference_check.meta.plate_scale_arcsec;
        let result = AlignResult {
            reference: crate::text::path(&work.meta.file).into_owned(),
            frame: crate::text::path(&frame.meta.file).into_owned(),
            scale: Some(t.scale),
            rotation_arcsec: Some(t.rotation_arcsec()),
            dx_px: Some(t.dx),
            dy_px: Some(t.dy),
            dx_arcsec: Some(t.dx * ps[0]),
            dy_arcsec: Some(t.dy * ps[1]),
            sigma_scale: Some(sig[0]),
            sigma_rotation_arcsec: Some(sig[1] * crate::geometry::ARCSEC_PER_RAD),
            sigma_dx_px: Some(sig[2]),
            sigma_dy_px: Some(sig[3]),
            sigma_dx_arcsec: Some(sig[2] * ps[0].abs()),
            sigma_dy_arcsec: Some(sig[3] * ps[1].abs()),
            uabjm_sigma_scale: Some(usig[0]),
            uabjm_sigma_rotation_arcsec: Some(usig[1] * crate::geometry::ARCSEC_PER_RAD),
            uabjm_sigma_dx_px: Some(usig[2]),
            uabjm_sigma_dy_px: Some(usig[3]),
            header_residual: Some(TransformFields {
                scale: header_residual.scale,
                rotation_arcsec: header_residual.rotation_arcsec(),
                dx_px: header_residual.dx,
                dy_px: header_residual.dy,
            }),
            solar_rotation,
            points: fine.points,
            inliers: fine.fit.n_inliers,
            residual_rms_px: Some(fine.fit.residual_rms_px),
            similarity,
            status,
            message: reasons.join("; "),
            elapsed_ms: 0.0,
        };
        Ok(AlignOutcome {
            result,
            transform: Some(t),
            coarse: Some(coarse),
            covariance: Some(fine.covariance),
            uabjm_covariance: Some(fine.uabjm_covariance),
            mask: Some(mask.clone()),
            reference_geometry: Some(work.geometry()),
        })
    };
    let first = measure(coarse, carried.as_ref(), solar_rotation, notes.clone());
    // A partial field has no disk to check its header pointing against: where that pointing
    // leads to no match, the frame is measured from the reference's pointing instead.
    let moved = max_motion_px(&coarse.recentered(Similarity::array_center(w, h)), 0.0);
    let outcome = match first {
        Err(why) if partial && moved > 1.0 => {
            let still = Similarity {
                dx: 0.0,
                dy: 0.0,
                ..coarse.recentered(Similarity::array_center(w, h))
            };
            notes.push(format!(
                "the header pointing ({moved:.1} px from the reference's) led to no match ({why}); \
                 measured from the reference's pointing, the Sun's rotation not removed"
            ));
            measure(still, None, None, notes).map_err(|_| why)
        }
        other => other,
    }?;
    let kept = kept_check.map(|(check, notes)| FrameWork {
        cleaned: kept_cleaned.unwrap_or(frame_data),
        check,
        notes,
        hot_pixel_fraction: cfg.hot_pixel_fraction,
    });
    Ok((outcome, kept))
}

/// The grid the quality checks compare on: the reference's, or binned copies of it.
struct QualityGrid<'a> {
    reference: ArrayView2<'a, f32>,
    mask: &'a Array2<bool>,
    mask_box: Roi,
    high_pass: &'a Array2<f32>,
    quality_crop: &'a Crop,
    trend_px: f64,
}

/// Bhattacharyya similarity of the histograms and rank correlation of the structure between
/// the reference and the frame as aligned (`fine.warped`, on the same grid).
fn quality_of(q: &QualityGrid, fine: &FineResult) -> (Option<f64>, Option<f64>) {
    let (h, w) = q.reference.dim();
    let (rows, cols) = grown(q.mask_box, 0.0, w, h);
    let similarity = || {
        fine.warped_at(rows.clone(), cols.clone())
            .and_then(|warped| {
                quality::bhattacharyya(
                    q.reference.slice(s![rows.clone(), cols.clone()]),
                    warped,
                    q.mask.slice(s![rows.clone(), cols.clone()]),
                )
            })
    };
    let crop = &q.quality_crop;
    let correlation = || {
        fine.warped_at(crop.rows.clone(), crop.cols.clone())
            .and_then(|warped| {
                quality::rank_correlation(
                    q.high_pass.view(),
                    quality::high_pass(warped, q.trend_px).view(),
                    q.mask.slice(s![crop.rows.clone(), crop.cols.clone()]),
                )
            })
    };
    // Independent, and each partly serial: side by side.
    rayon::join(similarity, correlation)
}

/// Errors of the fine stage.
#[derive(Debug, thiserror::Error)]
enum FineError {
    #[error("flow: {0}")]
    Flow(String),
    #[error("fit (pass {pass}): {source}")]
    Fit {
        pass: usize,
        #[source]
        source: FitFailure,
    },
}

/// Where the fine stage measures: the mask, and optionally a circle (centre, radius px on the
/// reference grid) its sampled points must also lie in.
#[derive(Clone, Copy)]
struct FlowRegion<'a> {
    mask: &'a Array2<bool>,
    sample_within: Option<([f64; 2], f64)>,
}

/// How far a point's flow sees, px (a point that far inside the limb sees none of it): half the
/// window, the polynomial expansion's reach (`poly_n` px each side, as in OpenCV) and two
/// strides of the affine grid. A point's flow is interpolated from the nodes around it, one
/// stride; and each iteration of the solver reads the previous flow across the window, so the
/// dependence reaches further. On AIA 171 128² between channels, with the frame's limb made
/// twice as bright (6 pairs), one stride leaves the scale 2.2e-4 short (1.65σ), two 4.2e-5,
/// and the bias keeps falling with the margin (6e-6 at 10 px more).
fn flow_reach_px(winsize: usize, poly_n: usize) -> f64 {
    (winsize / 2 + 2 * FlowOptions::affine_grid(winsize).grid_stride + poly_n) as f64
}

#[allow(clippy::too_many_arguments)]
fn fine_alignment(
    reference: ArrayView2<f32>,
    frame: &Array2<f32>,
    region: FlowRegion,
    coarse: Similarity,
    winsize: usize,
    frame_smoothing_px: f64,
    max_passes: usize,
    carried: Option<&derotate::Carried>,
    cfg: &EngineConfig,
    workspace: &Workspace,
) -> Result<FineResult, FineError> {
    let (h, w) = reference.dim();
    let mask = region.mask;
    let center = Similarity::array_center(w, h);
    // The refinement's model, so that the two answers share no interpolation bias the other
    // lacks (with a cubic spline here, the flow's answer on tests/data/trace_fourier_shift is
    // 9.6e-4 px off and the refinement's 7e-5 px: 7.5σ apart).
    let spline = HighOrderSpline::new(frame.view(), refine::MODEL);
    let roi = mask_roi(mask);
    let levels = cfg
        .pyramid_levels
        .unwrap_or_else(|| auto_levels(roi.width.min(roi.height)));
    let ransac = RansacParams {
        threshold_px: cfg.ransac_threshold_px,
        max_trials: cfg.ransac_max_trials,
        seed: cfg.seed,
        ..RansacParams::default()
    };
    let stride = (roi.width.min(roi.height) / cfg.sample.max(1) / 6).max(1);
    let radius = mask_extent_px(mask, roi);

    // Every pass works on a crop of the reference grid: the mask's box plus what the flow's
    // domain (at the pass's coarsest level), its border taper, the frame's smoothing and the
    // quality filters after the last pass read around it. Inside the mask the results equal
    // those of whole-frame arrays; outside nothing is computed (the disk covers under half of
    // a full-disk frame).
    let quality_reach = gaussian_reach(winsize as f64 / 4.0);
    let smoothing_reach = gaussian_reach(frame_smoothing_px);
    let crop_for = |levels: usize| -> Crop {
        // 2^16 px exceeds any image: more levels only clamp the crop to the whole image.
        let levels = levels.min(16);
        let flow = (winsize / 2 + cfg.poly_n + 3 + FLOW_TAPER_PX + 2) << levels;
        let blur = if levels > 0 {
            (5usize << levels) / 4 + 2
        } else {
            0
        };
        let margin = (flow + blur).max(quality_reach) + smoothing_reach;
        // Aligned so that every level's pixels and flow-grid nodes are those of the whole image.
        let grid_stride = FlowOptions::affine_grid(winsize).grid_stride;
        Crop::around(roi, margin, grid_stride << levels, w, h)
    };

    // The Sun's motion over the largest crop (the first pass's), read by every pass.
    let shifts = carried.map(|c| {
        let crop = crop_for(levels);
        let s = c.shifts(
            crop.cols.start,
            crop.rows.start,
            crop.cols.len(),
            crop.rows.len(),
        );
        (crop, s)
    });
    let mut estimate = coarse.recentered(center);
    let mut solver: Option<Farneback> = workspace.take();
    let mut pass = 0;
    loop {
        pass += 1;
        let pass_started = Instant::now();
        let first = pass == 1;
        let pass_levels = if first { levels } else { 0 };
        let crop = crop_for(pass_levels);
        let (x0, y0) = (crop.cols.start, crop.rows.start);
        let (ch, cw) = (crop.rows.len(), crop.cols.len());
        let mut warped = match (&shifts, carried) {
            (Some((outer, s)), _) if outer.contains(&crop) => {
                let (ox, oy) = (x0 - outer.cols.start, y0 - outer.rows.start);
                let window = s.slice(s![oy..oy + ch, ox..ox + cw]);
                spline.warp_similarity_window_shifted(&estimate, x0, y0, window)
            }
            (_, Some(c)) => spline.warp_similarity_window_shifted(
                &estimate,
                x0,
                y0,
                c.shifts(x0, y0, cw, ch).view(),
            ),
            _ => spline.warp_similarity_window(&estimate, x0, y0, cw, ch),
        };
        if frame_smoothing_px > 0.0 {
            warped = preprocess::gaussian_smooth(warped.view(), frame_smoothing_px);
        }
        let ref_crop = reference.slice(s![crop.rows.clone(), crop.cols.clone()]);
        let mask_crop = mask.slice(s![crop.rows.clone(), crop.cols.clone()]);
        let roi_crop = Roi {
            x: roi.x - x0,
            y: roi.y - y0,
            ..roi
        };
        let params = FarnebackParams {
            pyr_scale: 0.5,
            levels: pass_levels,
            winsize,
            iterations: if first {
                cfg.iterations
            } else {
                cfg.iterations.min(4)
            },
            poly_n: cfg.poly_n,
            poly_sigma: cfg.poly_sigma,
            gaussian_window: false,
        };
        let options = FlowOptions {
            ..FlowOptions::affine_grid(winsize)
        };
        // The solver keeps its buffers between passes and frames.
        let mut s = match solver.take() {
            Some(mut s) => {
                if s.params() != &params || s.options() != &options {
                    s.reconfigure(params.clone(), options.clone())
                        .map_err(|e| FineError::Flow(e.to_string()))?;
                }
                s
            }
            None => Farneback::new(params.clone())
                .and_then(|f| f.with_options(options.clone()))
                .map_err(|e| FineError::Flow(e.to_string()))?,
        };
        let warped_at = pass_started.elapsed();
        let flow = s
            .compute(ref_crop, warped.view(), Some(roi_crop), None)
            .map_err(|e| FineError::Flow(e.to_string()))?;
        solver = Some(s);
        let flow_at = pass_started.elapsed();

        // Sample only where the whole window saw data: a window cut by the frame's edge
        // (or a blank region) measures a biased motion. The crop's own edge is further than
        // the window from the mask unless it is the image's edge, which erosion treats alike.
        let mut valid = warped.mapv(f32::is_finite);
        Zip::from(&mut valid)
            .and(&ref_crop)
            .for_each(|m, v| *m = *m && v.is_finite());
        let mut sample_mask = erode(&valid, winsize / 2);
        Zip::from(&mut sample_mask)
            .and(&mask_crop)
            .for_each(|a, b| *a = *a && *b);
        if let Some(([cx, cy], r)) = region.sample_within {
            let r2 = if r > 0.0 { r * r } else { -1.0 };
            Zip::indexed(&mut sample_mask).for_each(|(y, x), m| {
                let (dx, dy) = ((x + x0) as f64 - cx, (y + y0) as f64 - cy);
                *m = *m && dx * dx + dy * dy <= r2;
            });
        }
        let mut points = grid_median_sample(
            flow.u.view(),
            flow.v.view(),
            sample_mask.view(),
            stride,
            cfg.sample,
        );
        for p in &mut points {
            p.x += x0 as f64;
            p.y += y0 as f64;
        }
        let fit = fit_similarity(&points, center, &ransac)
            .map_err(|source| FineError::Fit { pass, source })?;
        tracing::debug!(pass, ?warped_at, ?flow_at, fitted_at = ?pass_started.elapsed(), crop = ?(cw, ch), "fine pass");
        let update = fit.transform;
        let previous = estimate;
        estimate = estimate.after(&update);
        // Converged when the update is negligible, or lost in this pass's own noise.
        let moved = max_motion_px(&update, radius);
        let noise = sigmas(&fit.covariance)[2].hypot(sigmas(&fit.covariance)[3]);
        let converged = moved < cfg.convergence_px.max(0.1 * noise);
        tracing::debug!(pass, moved, noise, estimate = ?estimate.params(), "fine pass estimate");
        if converged || pass >= max_passes.max(1) {
            let inliers = fit.inlier_points(&points);
            let uabjm = fit.covariance;
            let mut calibrated = sigma::calibrated_covariance(cfg.sigma, &inliers, &fit, winsize);
            if cfg.sigma == SigmaMethod::Calibrated {
                sigma::add_floor(&mut calibrated, &inliers, center, cfg.systematic_floor_px);
            }
            let zero = [[0.0; 4]; 4];
            let (_, mut cov) = compose_with_covariance(&previous, &zero, &update, &calibrated);
            // Still moving when the passes ran out: the last step is a measure of how far
            // from settled the answer is (on HMI 100² with a zero-filled sky it wanders by
            // pixels).
            let sigma_xy = sigmas(&cov)[2].hypot(sigmas(&cov)[3]);
            let unsettled_px = (!converged && moved > sigma_xy).then_some(moved);
            if let Some(solver) = solver.take() {
                workspace.give(solver);
            }
            if !converged {
                let step = update.params();
                for (k, d) in [step[0] - 1.0, step[1], step[2], step[3]]
                    .iter()
                    .enumerate()
                {
                    cov[k][k] += d * d;
                }
            }
            let (_, ucov) = compose_with_covariance(&previous, &zero, &update, &uabjm);
            let sample_box = crate::sampling::mask_bounding_box(sample_mask.view())
                .map(|(a, b, c, d)| (a + x0, b + y0, c + x0, d + y0));
            return Ok(FineResult {
                transform: estimate,
                covariance: cov,
                uabjm_covariance: ucov,
                points: points.len(),
                fit,
                warped: Some(warped),
                crop,
                passes: pass,
                converged,
                unsettled_px,
                seed_level: None,
                sample_box,
                inliers,
            });
        }
    }
}

/// How many times `max_passes` the fine passes may run in all when the flow is still moving
/// by more than its σ and the refinement did not take its answer.
const UNSETTLED_PASS_FACTOR: usize = 3;

/// Outermost pixels of a level that OpenCV's border taper weighs down.
const FLOW_TAPER_PX: usize = 5;

/// Rows and columns of the reference grid one pass works on.
#[derive(Debug, Clone, PartialEq)]
struct Crop {
    rows: Range<usize>,
    cols: Range<usize>,
}

impl Crop {
    fn contains(&self, other: &Crop) -> bool {
        self.rows.start <= other.rows.start
            && self.cols.start <= other.cols.start
            && self.rows.end >= other.rows.end
            && self.cols.end >= other.cols.end
    }

    /// `roi` grown by `margin`, its start rounded down and its end up to multiples of `align`,
    /// clamped to the `w × h` image.
    fn around(roi: Roi, margin: usize, align: usize, w: usize, h: usize) -> Crop {
        let span = |lo: usize, len: usize, n: usize| -> Range<usize> {
            let a = lo.saturating_sub(margin) / align * align;
            let b = (lo + len + margin).div_ceil(align) * align;
            a..b.min(n)
        };
        Crop {
            rows: span(roi.y, roi.height, h),
            cols: span(roi.x, roi.width, w),
        }
    }
}

/// Reach of `preprocess::gaussian_smooth` at σ = `sigma_px` (its truncation radius) plus one
/// pixel for a central difference; 0 when it does nothing.
pub(crate) fn gaussian_reach(sigma_px: f64) -> usize {
    if sigma_px > 0.0 && sigma_px.is_finite() {
        (4.0 * sigma_px + 0.5) as usize + 1
    } else {
        0
    }
}

/// Pixels whose `(2r+1)²` neighbourhood lies entirely inside the image and inside `valid`.
fn erode(valid: &Array2<bool>, r: usize) -> Array2<bool> {
    use rayon::prelude::*;
    let (h, w) = valid.dim();
    // Integral image of invalid pixels, row-major with a zero first row and column.
    let iw = w + 1;
    let mut integral = vec![0u32; (h + 1) * iw];
    for (y, row) in valid.rows().into_iter().enumerate() {
        let (above, below) = integral.split_at_mut((y + 1) * iw);
        let (prev, cur) = (&above[y * iw..], &mut below[..iw]);
        let mut count = 0u32;
        for (x, v) in row.iter().enumerate() {
            count += u32::from(!*v);
            cur[x + 1] = prev[x + 1] + count;
        }
    }
    let mut out = Array2::from_elem((h, w), false);
    out.axis_iter_mut(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut o)| {
            if y < r || y + r >= h {
                return;
            }
            let (top, bottom) = ((y - r) * iw, (y + r + 1) * iw);
            for x in r..w.saturating_sub(r) {
                let (x0, x1) = (x - r, x + r + 1);
                o[x] = integral[bottom + x1] + integral[top + x0]
                    == integral[top + x1] + integral[bottom + x0];
            }
        });
    out
}

/// Largest displacement the transform causes within `radius` of its centre.
fn max_motion_px(t: &Similarity, radius: f64) -> f64 {
    let (a, b) = t.ab();
    let linear = ((a - 1.0).powi(2) + b * b).sqrt() * radius;
    (t.dx * t.dx + t.dy * t.dy).sqrt() + linear
}

/// Largest distance of a mask pixel from the array centre (`roi`: the mask's bounding box).
fn mask_extent_px(mask: &Array2<bool>, roi: Roi) -> f64 {
    let (h, w) = mask.dim();
    let c = Similarity::array_center(w, h);
    let mut r2: f64 = 0.0;
    let boxed = mask.slice(s![roi.y..roi.y + roi.height, roi.x..roi.x + roi.width]);
    for ((y, x), &m) in boxed.indexed_iter() {
        if m {
            let (x, y) = ((x + roi.x) as f64, (y + roi.y) as f64);
            r2 = r2.max((x - c[0]).powi(2) + (y - c[1]).powi(2));
        }
    }
    r2.sqrt()
}

/// Gaussian σ of the trend removed in `structure_length_px`, px.
const STRUCTURE_TREND_SIGMA_PX: f64 = 8.0;

/// Rows and columns of `roi` grown by the reach of a Gaussian of `sigma_px` as
/// `preprocess::gaussian_smooth` truncates it, plus one pixel for a central difference,
/// clamped to the `w × h` image: inside `roi` such filters give the same values on this crop
/// as on the whole image.
fn grown(roi: Roi, sigma_px: f64, w: usize, h: usize) -> (Range<usize>, Range<usize>) {
    let reach = gaussian_reach(sigma_px);
    (
        roi.y.saturating_sub(reach)..(roi.y + roi.height + reach).min(h),
        roi.x.saturating_sub(reach)..(roi.x + roi.width + reach).min(w),
    )
}

fn mask_roi(mask: &Array2<bool>) -> Roi {
    let (h, w) = mask.dim();
    match crate::sampling::mask_bounding_box(mask.view()) {
        Some((x0, y0, x1, y1)) => Roi {
            x: x0,
            y: y0,
            width: x1 - x0 + 1,
            height: y1 - y0 + 1,
        },
        None => Roi {
            x: 0,
            y: 0,
            width: w,
            height: h,
        },
    }
}

/// Default mask extent, px, at the pyramid level a seed flow works on. The flow's cost and
/// memory grow with the pixel count while the refinement only needs a start near its answer:
/// on 4096² synthetic pairs a seed on 4× binned copies (750 px) gives the same refined answer
/// to 2e-5 px as one at full resolution. Not less: on TRACE 1024² a seed on 2× binned copies
/// (512 px) moves the refined dy by about 1e-4 px (2σ) — the refinement's reweighting settles
/// on slightly different weights from a coarser start. And a seed that converged on its level,
/// not one pass: on undersampled images the refinement's answer depends on its start (AIA 171
/// 128²: 40″ rotation RMSE from a one-pass seed, 9″ from the converged flow).
const SEED_EXTENT_PX: usize = 700;

/// How far a seed on `level` may be from the full-resolution flow, px: the RMS flow error of
/// a level-1 finish on TRACE 1024² warps is 0.05–0.06 px (0 at full resolution).
fn seed_slack_px(level: usize) -> f64 {
    0.05 * ((1usize << level.min(16)) - 1) as f64
}

/// The pyramid level a seed flow works on: where the mask spans at least
/// `cfg.seed_extent_px` (64 at the least), within the pyramid the flow would build.
fn seed_level(roi: Roi, cfg: &EngineConfig) -> usize {
    let extent = roi.width.min(roi.height);
    let levels = cfg.pyramid_levels.unwrap_or_else(|| auto_levels(extent));
    let mut level = 0;
    while level < levels && (extent >> (level + 1)) >= cfg.seed_extent_px.max(64) {
        level += 1;
    }
    level
}

/// The reference and its mask binned `2^level`× for seed flows.
struct Binned {
    level: usize,
    reference: Array2<f32>,
    mask: Array2<bool>,
    mask_box: Roi,
    /// High-pass of `reference` on `quality_crop`, as [`Matched`] has for the full grid.
    high_pass: Array2<f32>,
    quality_crop: Crop,
}

impl Binned {
    fn new(reference: ArrayView2<f32>, mask: &Array2<bool>, level: usize, trend_px: f64) -> Binned {
        let factor = 1usize << level;
        let inside = preprocess::bin_mean(mask.mapv(|m| m as u8 as f32).view(), factor);
        let reference = preprocess::bin_mean(reference, factor);
        // A binned pixel is in the mask when all its pixels are.
        let mask = inside.mapv(|v| v >= 1.0);
        let mask_box = mask_roi(&mask);
        let (h, w) = reference.dim();
        let (rows, cols) = grown(mask_box, trend_px, w, h);
        let high_pass =
            quality::high_pass(reference.slice(s![rows.clone(), cols.clone()]), trend_px);
        Binned {
            level,
            reference,
            mask,
            mask_box,
            high_pass,
            quality_crop: Crop { rows, cols },
        }
    }
}

/// The flow stage on `binned` copies, as a seed for the refinement: the result in full-grid
/// terms (transform, covariances, inliers, sampling mask), without a warped frame.
#[allow(clippy::too_many_arguments)]
fn seed_alignment(
    binned: &Binned,
    grid: (usize, usize),
    frame: &Array2<f32>,
    coarse: Similarity,
    winsize: usize,
    frame_smoothing_px: f64,
    carried: Option<&derotate::Carried>,
    cfg: &EngineConfig,
    workspace: &Workspace,
) -> Result<FineResult, String> {
    let factor = 1usize << binned.level;
    let b = factor as f64;
    // The reference's grid (the frame may be of another size).
    let (h, w) = grid;
    let (sh, sw) = binned.reference.dim();
    // Binned pixel q covers full pixels b·q … b·q + b − 1: its centre is b·(q + 0.5) − 0.5.
    let to_full = |q: f64| b * (q + 0.5) - 0.5;
    let small_center = Similarity::array_center(sw, sh);
    let full_center = Similarity::array_center(w, h);
    // A similarity about centre C with shift d is, on the binned grid, the same scale and
    // rotation about the binned C with shift d/b.
    let about = [to_full(small_center[0]), to_full(small_center[1])];
    let c = coarse.recentered(about);
    let coarse_small = Similarity {
        dx: c.dx / b,
        dy: c.dy / b,
        center: small_center,
        ..c
    };
    let small_frame = preprocess::bin_mean(frame.view(), factor);
    // Converged when the update is a tenth of the seed's own slack (in binned pixels).
    let seed_cfg = EngineConfig {
        convergence_px: cfg
            .convergence_px
            .max(0.1 * seed_slack_px(binned.level) / b),
        ..cfg.clone()
    };
    let mut fine = fine_alignment(
        binned.reference.view(),
        &small_frame,
        // Seeds run only within one channel, where the limb is common structure.
        FlowRegion {
            mask: &binned.mask,
            sample_within: None,
        },
        coarse_small,
        winsize,
        frame_smoothing_px / b,
        seed_cfg.max_passes,
        carried.map(|c| c.binned(factor)).as_ref(),
        &seed_cfg,
        workspace,
    )
    .map_err(|e| e.to_string())?;
    let unbinned = |t: &Similarity, cov: &Covariance4| -> (Similarity, Covariance4) {
        let t_about = Similarity {
            dx: t.dx * b,
            dy: t.dy * b,
            center: [to_full(t.center[0]), to_full(t.center[1])],
            ..*t
        };
        let d = [1.0, 1.0, b, b];
        let cov_about: Covariance4 =
            std::array::from_fn(|i| std::array::from_fn(|j| cov[i][j] * d[i] * d[j]));
        let zero = [[0.0; 4]; 4];
        compose_with_covariance(
            &t_about,
            &cov_about,
            &Similarity::identity(full_center),
            &zero,
        )
    };
    let (transform, covariance) = unbinned(&fine.transform, &fine.covariance);
    let (_, uabjm_covariance) = unbinned(&fine.transform, &fine.uabjm_covariance);
    fine.transform = transform;
    fine.covariance = covariance;
    fine.uabjm_covariance = uabjm_covariance;
    fine.fit.residual_rms_px *= b;
    for p in &mut fine.inliers {
        p.x = to_full(p.x);
        p.y = to_full(p.y);
        p.u *= b;
        p.v *= b;
    }
    // Binned pixel q covers full pixels b·q … b·q + b − 1.
    fine.sample_box = fine.sample_box.map(|(x0, y0, x1, y1)| {
        (
            x0 * factor,
            y0 * factor,
            (x1 * factor + factor - 1).min(w - 1),
            (y1 * factor + factor - 1).min(h - 1),
        )
    });
    fine.seed_level = Some(binned.level);
    Ok(fine)
}

/// Pyramid levels that keep the coarsest level at least 64 px across (at most 4).
fn auto_levels(extent_px: usize) -> usize {
    let mut levels = 0;
    let mut size = extent_px as f64;
    while levels < 4 && size / 2.0 >= 64.0 {
        size /= 2.0;
        levels += 1;
    }
    levels
}

/// The averaging window in pixels (odd).
fn choose_window(
    cfg: &EngineConfig,
    plate_arcsec: f64,
    structure_px: Option<f64>,
    disk_radius_px: Option<f64>,
    width: usize,
    height: usize,
) -> usize {
    let odd = |n: f64| -> usize {
        let n = n.round().max(3.0) as usize;
        if n.is_multiple_of(2) {
            n + 1
        } else {
            n
        }
    };
    if let Some(px) = cfg.window_px {
        return odd(px as f64);
    }
    let from_arcsec = cfg
        .window_arcsec
        .filter(|_| plate_arcsec > 0.0 && plate_arcsec.is_finite())
        .map(|a| a / plate_arcsec);
    let nominal = from_arcsec
        .or(structure_px.map(|l| l * cfg.window_structure_lengths))
        .unwrap_or(cfg.min_window_px as f64);
    let lo = cfg.min_window_px as f64;
    let hi = match disk_radius_px {
        Some(r) => r * cfg.mask_radius_fraction / 1.5,
        None => width.min(height) as f64 / 4.0,
    }
    .max(lo);
    odd(nominal.clamp(lo, hi))
}

/// Correlation length of the image's texture inside the mask, px:
/// `ℓ = √(var(I) / var(∇I))`, exact for a Gaussian-correlated random field. The large-scale
/// trend is removed first (a blur at 8 px would otherwise dominate var(I) on a full disk).
fn structure_length_px(img: ArrayView2<f32>, mask: ArrayView2<bool>) -> Option<f64> {
    let (h, w) = img.dim();
    if h < 8 || w < 8 {
        return None;
    }
    let trend = preprocess::gaussian_smooth(img, STRUCTURE_TREND_SIGMA_PX);
    let (mut n, mut s, mut s2, mut g2) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            if !mask[[y, x]] {
                continue;
            }
            let hp = |yy: usize, xx: usize| (img[[yy, xx]] - trend[[yy, xx]]) as f64;
            let v = hp(y, x);
            let gx = (hp(y, x + 1) - hp(y, x - 1)) / 2.0;
            let gy = (hp(y + 1, x) - hp(y - 1, x)) / 2.0;
            if !(v.is_finite() && gx.is_finite() && gy.is_finite()) {
                continue;
            }
            n += 1.0;
            s += v;
            s2 += v * v;
            g2 += (gx * gx + gy * gy) / 2.0;
        }
    }
    if n < 64.0 {
        return None;
    }
    let var = s2 / n - (s / n).powi(2);
    let grad = g2 / n;
    (var > 0.0 && grad > 0.0).then(|| (var / grad).sqrt())
}

/// Whether an image can serve as a reference at all (size, finite pixels, structure).
pub fn usable_as_reference(image: &Image) -> Result<(), String> {
    check_usable("reference", &image.data)
}

fn check_usable(which: &str, data: &Array2<f32>) -> Result<(), String> {
    let (h, w) = data.dim();
    if h < 16 || w < 16 {
        return Err(format!("{which} image is {w}×{h} px; too small to align"));
    }
    use rayon::prelude::*;
    // Count and range of the finite pixels, row by row in parallel (no copy of the frame).
    let (n_finite, lo, hi) = data
        .axis_iter(ndarray::Axis(0))
        .into_par_iter()
        .map(|row| {
            row.iter().filter(|v| v.is_finite()).fold(
                (0usize, f32::INFINITY, f32::NEG_INFINITY),
                |(n, a, b), &v| (n + 1, a.min(v), b.max(v)),
            )
        })
        .reduce(
            || (0, f32::INFINITY, f32::NEG_INFINITY),
            |x, y| (x.0 + y.0, x.1.min(y.1), x.2.max(y.2)),
        );
    if n_finite < (h * w) / 10 {
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

fn cleaned(data: &Array2<f32>, hot_pixel_fraction: f32) -> Array2<f32> {
    let mut out = data.clone();
    if hot_pixel_fraction > 0.0 {
        preprocess::remove_hot_pixels(&mut out, hot_pixel_fraction);
    }
    out
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
    let fields = TransformFields {
        scale: 1.0,
        rotation_arcsec: 0.0,
        dx_px: 0.0,
        dy_px: 0.0,
    };
    AlignOutcome {
        result: AlignResult {
            reference: name.clone(),
            frame: name,
            scale: Some(1.0),
            rotation_arcsec: Some(0.0),
            dx_px: Some(0.0),
            dy_px: Some(0.0),
            dx_arcsec: Some(0.0),
            dy_arcsec: Some(0.0),
            sigma_scale: Some(0.0),
            sigma_rotation_arcsec: Some(0.0),
            sigma_dx_px: Some(0.0),
            sigma_dy_px: Some(0.0),
            sigma_dx_arcsec: Some(0.0),
            sigma_dy_arcsec: Some(0.0),
            uabjm_sigma_scale: Some(0.0),
            uabjm_sigma_rotation_arcsec: Some(0.0),
            uabjm_sigma_dx_px: Some(0.0),
            uabjm_sigma_dy_px: Some(0.0),
            header_residual: Some(fields),
            solar_rotation: None,
            points: 0,
            inliers: 0,
            residual_rms_px: Some(0.0),
            similarity: Some(1.0),
            status: Status::Ok,
            message: "reference frame (aligned to itself)".into(),
            elapsed_ms: 0.0,
        },
        transform: Some(t),
        coarse: Some(t),
        covariance: Some(zero),
        uabjm_covariance: Some(zero),
        mask: None,
        reference_geometry: None,
    }
}
