//! The reference's share of an alignment, prepared once for every frame aligned to it, and
//! the working memory alignments share.

use super::config::EngineConfig;
use super::fine::Crop;
use super::region::{grown, mask_roi};
use super::seed::Binned;
use super::workspace::Workspace;
use super::{check_usable, cleaned_from, geometry_check, quality, refine, Pixels};
use super::{Image, UsedGeometry};
use crate::flow::Roi;
use crate::meta::FrameMeta;
use crate::preprocess::{self, BlockMeans};
use ndarray::{s, Array2, ArrayView2, Zip};
use rayon::prelude::*;
use std::borrow::Cow;
use std::time::Instant;

/// The reference's share of an alignment (hot-pixel cleaning, disk check, mask, window,
/// resolution-matched copies and their high-pass), computed once and reused for every frame
/// aligned to it: the daemon aligns many frames to one reference. `align` gives exactly what
/// [`align_images`](super::align_images) gives.
pub struct PreparedReference {
    pub(super) cfg: EngineConfig,
    pub(super) file: String,
    pub(super) work: Result<ReferenceWork, String>,
    pub(super) workspace: std::sync::Arc<Workspace>,
    /// Frames aligned to it so far: only a reference that served one frame, as each does
    /// along a `previous` chain, hands its self-test on to that frame.
    pub(super) aligned: std::sync::atomic::AtomicUsize,
}

pub(super) struct ReferenceWork {
    /// The header's metadata, and as checked against the image.
    pub(super) meta: FrameMeta,
    pub(super) reference_check: geometry_check::Checked,
    pub(super) notes: Vec<String>,
    pub(super) cleaned: Array2<f32>,
    /// Its border fill, taken as missing data.
    pub(super) fill: Option<super::FillSeen>,
    pub(super) mask: Array2<bool>,
    /// Why the mask cannot be used (raised after the frame's own checks).
    pub(super) mask_error: Option<String>,
    pub(super) mask_box: Roi,
    pub(super) winsize: usize,
    /// Correlation length of the texture inside the mask, px (`structure_length_px`).
    pub(super) structure_px: Option<f64>,
    /// The self-test cases of the reference this one was aligned to as a frame, and that
    /// reference's smoothing σ, px: along a chain most of them still apply here.
    pub(super) handed_on: Option<(f64, refine::SelfTestCases)>,
    /// The reference's position along its chain (its sequence number in the log), which
    /// picks the self-test cases it renews ([`refine::HandedOn`]).
    pub(super) position: Option<u64>,
    /// Resolution-matched versions by smoothing σ (few: one per partner plate scale).
    matched: std::sync::Mutex<Vec<std::sync::Arc<Matched>>>,
}

/// The reference smoothed to a frame's resolution, and its high-pass for the structure check.
/// What it makes on first use is made by [`made_once`]: several frames may read one version
/// at once (channels that follow one partner), each on rayon's threads.
pub(super) struct Matched {
    sigma_px: f64,
    /// `None`: no smoothing (the cleaned reference itself).
    data: Option<Array2<f32>>,
    /// High-pass of `data` on the crop it covers, for the structure check on the full grid
    /// (made on first use: a seed's checks compare on its binned copies instead).
    high_pass: std::sync::OnceLock<(Array2<f32>, Crop)>,
    /// The refinement's self-test on this reference (run on first use).
    pub(super) self_test: std::sync::OnceLock<Option<refine::SelfTestCases>>,
    /// Binned copies for seed flows on large frames (made on first use).
    pub(super) binned: std::sync::OnceLock<Binned>,
    /// Binned copies on which a final flow answer is measured on large frames (first use).
    pub(super) binned_final: std::sync::OnceLock<Binned>,
    /// The reference as the refinement reads it (made on the first refinement).
    pub(super) refine_reference: std::sync::OnceLock<refine::RefineReference>,
    /// Radial power spectrum at the mask's centre, for the blur difference (first use).
    pub(super) spectrum: std::sync::OnceLock<Option<crate::blur::RadialSpectrum>>,
}

/// At most this many resolution-matched versions are kept per reference.
const MATCHED_CACHE: usize = 4;

/// A frame's cleaned image and its own disk check, as preparing it as a reference makes them:
/// a frame that becomes the next reference (`previous`) is not cleaned and checked twice.
pub struct FrameWork {
    pub(super) cleaned: Array2<f32>,
    pub(super) fill: Option<super::FillSeen>,
    pub(super) check: geometry_check::Checked,
    pub(super) notes: Vec<String>,
    pub(super) hot_pixel_fraction: f32,
    /// The self-test cases of the reference the frame was aligned to (with its smoothing
    /// σ, px), when that alignment was `ok` and the reference's first.
    pub(super) self_test: Option<(f64, refine::SelfTestCases)>,
}

impl PreparedReference {
    pub fn new(reference: &Image, cfg: &EngineConfig) -> PreparedReference {
        PreparedReference::of(Cow::Borrowed(reference), cfg, None)
    }

    /// [`PreparedReference::new`] for a caller done with the image: its pixels are cleaned in
    /// place. The numbers are the same.
    pub fn from_image(reference: Image, cfg: &EngineConfig) -> PreparedReference {
        PreparedReference::of(Cow::Owned(reference), cfg, None)
    }

    /// As [`PreparedReference::new`], reusing the work done on `reference` when it was
    /// aligned as a frame ([`PreparedReference::align_keeping`] of this same image).
    pub fn from_frame_work(
        reference: &Image,
        cfg: &EngineConfig,
        work: FrameWork,
    ) -> PreparedReference {
        PreparedReference::of(Cow::Borrowed(reference), cfg, Some(work))
    }

    fn of(
        reference: Cow<'_, Image>,
        cfg: &EngineConfig,
        kept: Option<FrameWork>,
    ) -> PreparedReference {
        let (meta, data) = match reference {
            Cow::Borrowed(image) => (Cow::Borrowed(&image.meta), Pixels::from(image.data.view())),
            Cow::Owned(Image { meta, data }) => (Cow::Owned(meta), Pixels::from(data)),
        };
        PreparedReference::of_parts(meta, data, cfg, kept)
    }

    /// A reference from its metadata and pixels, owned (cleaned in place) or borrowed.
    pub(super) fn of_pixels(
        meta: Cow<'_, FrameMeta>,
        data: Pixels<'_>,
        cfg: &EngineConfig,
    ) -> PreparedReference {
        PreparedReference::of_parts(meta, data, cfg, None)
    }

    fn of_parts(
        meta: Cow<'_, FrameMeta>,
        data: Pixels<'_>,
        cfg: &EngineConfig,
        kept: Option<FrameWork>,
    ) -> PreparedReference {
        PreparedReference {
            cfg: cfg.clone(),
            file: crate::text::path(&meta.file).into_owned(),
            work: ReferenceWork::new(meta, data, cfg, kept),
            workspace: Default::default(),
            aligned: Default::default(),
        }
    }

    /// Align with `workspace`, shared with other references, instead of one of its own.
    pub fn sharing(mut self, workspace: std::sync::Arc<Workspace>) -> PreparedReference {
        self.workspace = workspace;
        self
    }

    /// The reference at `position` along its chain (its sequence number in the log): along a
    /// `previous` chain that picks the self-test cases it renews, so that a chain started a few
    /// references earlier (a shard's overlap) gives the same σ as a single run.
    pub fn at_position(mut self, position: u64) -> PreparedReference {
        if let Ok(work) = &mut self.work {
            work.position = Some(position);
        }
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
}

impl ReferenceWork {
    pub(super) fn geometry(&self) -> UsedGeometry {
        let used = &self.reference_check.meta;
        UsedGeometry {
            plate_scale_arcsec: used.plate_scale_arcsec,
            sun_center_px: used.sun_center_px,
            from_disk: self.reference_check.corrected,
        }
    }

    fn new(
        meta: Cow<'_, FrameMeta>,
        data: Pixels<'_>,
        cfg: &EngineConfig,
        kept: Option<FrameWork>,
    ) -> Result<ReferenceWork, String> {
        let (h, w) = data.dim();
        let started = Instant::now();
        check_usable("reference", &data)?;
        let (cleaned, fill, reference_check, notes, handed_on) = match kept {
            Some(k) if k.hot_pixel_fraction.to_bits() == cfg.hot_pixel_fraction.to_bits() => {
                (k.cleaned, k.fill, k.check, k.notes, k.self_test)
            }
            _ => {
                let (cleaned, fill) = cleaned_from(data, cfg.hot_pixel_fraction);
                let mut notes = Vec::new();
                let check = geometry_check::checked(&meta, &cleaned, &mut notes);
                (cleaned, fill, check, notes, None)
            }
        };
        let checked_at = started.elapsed();
        let (checked, disk_px) = (&reference_check.meta, reference_check.disk_px);

        // Mask on the reference grid: the disk without its limb, or the whole valid field.
        let mut mask = match disk_px {
            Some((c, r)) => preprocess::disk_mask(w, h, c, r, cfg.mask_radius_fraction),
            None => Array2::from_elem((h, w), true),
        };
        Zip::from(&mut mask)
            .and(&cleaned)
            .par_for_each(|m, v| *m = *m && v.is_finite());
        let mask_pixels = crate::stats::count_set(mask.view());
        let mask_error = (mask_pixels < 64).then(|| {
            format!(
                "the solar-disk mask holds {mask_pixels} usable pixels of the reference; nothing to align"
            )
        });
        // Filters and statistics below only matter inside the mask: run them on its bounding
        // box plus the filter's reach (the disk covers under half of a full-disk frame).
        let mask_box = mask_roi(&mask);
        let masked_at = started.elapsed();

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
        tracing::debug!(?structure, winsize, plate, ?checked_at, ?masked_at, chosen_at = ?started.elapsed(), "window chosen");
        Ok(ReferenceWork {
            meta: meta.into_owned(),
            reference_check,
            notes,
            cleaned,
            fill,
            mask,
            mask_error,
            mask_box,
            winsize,
            structure_px: structure,
            handed_on,
            position: None,
            matched: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// The reference smoothed by `sigma_px` (cached).
    pub(super) fn matched(&self, sigma_px: f64) -> std::sync::Arc<Matched> {
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
        let made = std::sync::Arc::new(Matched {
            sigma_px,
            data,
            high_pass: std::sync::OnceLock::new(),
            self_test: std::sync::OnceLock::new(),
            binned: std::sync::OnceLock::new(),
            binned_final: std::sync::OnceLock::new(),
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
    pub(super) fn trend_px(&self) -> f64 {
        self.winsize as f64 / 4.0
    }
}

/// `cell`'s value, made by `make` when it has none yet; never waiting for another thread to
/// make it. A rayon thread that waits for its own work runs other jobs meanwhile, another
/// frame's among them: had it waited on a cell, it could be the very thread making that
/// cell further up its own stack, and never return. Two threads that find the cell empty
/// make it both; the first value set stands, and the other is the same (the making is
/// deterministic).
pub(super) fn made_once<T>(cell: &std::sync::OnceLock<T>, make: impl FnOnce() -> T) -> &T {
    if let Some(value) = cell.get() {
        return value;
    }
    // Err: another thread set it first, with the same value.
    let _ = cell.set(make());
    cell.get()
        .expect("set just above, or by another thread before")
}

impl Matched {
    pub(super) fn view<'a>(&'a self, work: &'a ReferenceWork) -> ArrayView2<'a, f32> {
        self.data.as_ref().map_or(work.cleaned.view(), |d| d.view())
    }

    /// [`Self::view`] binned by the disk check, where this version is the cleaned reference.
    pub(super) fn block_means<'a>(&self, work: &'a ReferenceWork) -> Option<&'a BlockMeans> {
        match self.data {
            None => work.reference_check.block_means.as_deref(),
            Some(_) => None,
        }
    }

    /// The high-pass of this version on the mask's box and the trend's reach, and that crop.
    pub(super) fn high_pass(&self, work: &ReferenceWork) -> &(Array2<f32>, Crop) {
        made_once(&self.high_pass, || {
            // Structure only: the large-scale disk brightness correlates even for unrelated
            // images.
            let (h, w) = work.cleaned.dim();
            let trend_px = work.trend_px();
            let (rows, cols) = grown(work.mask_box, trend_px, w, h);
            let crop = self.view(work).slice_move(s![rows.clone(), cols.clone()]);
            (quality::high_pass(crop, trend_px), Crop { rows, cols })
        })
    }

    /// The binned copies at `level`, if made.
    pub(super) fn binned_at(&self, level: usize) -> Option<&Binned> {
        [&self.binned, &self.binned_final]
            .into_iter()
            .find_map(|b| b.get().filter(|b| b.level() == level))
    }

    /// The self-test cases handed on to this version of the reference, if any.
    pub(super) fn handed_on<'a>(&self, work: &'a ReferenceWork) -> Option<refine::HandedOn<'a>> {
        work.handed_on
            .as_ref()
            .filter(|(sigma_px, _)| sigma_px.to_bits() == self.sigma_px.to_bits())
            .map(|(_, cases)| refine::HandedOn {
                cases,
                position: work.position,
            })
    }

    /// This version's self-test cases with its smoothing σ, to hand on along a chain.
    pub(super) fn self_test_to_hand_on(&self) -> Option<(f64, refine::SelfTestCases)> {
        let cases = self.self_test.get()?.as_ref()?;
        Some((self.sigma_px, cases.clone()))
    }
}

/// Gaussian σ of the trend removed in `structure_length_px`, px.
const STRUCTURE_TREND_SIGMA_PX: f64 = 8.0;

/// Pixels of the mask's box `structure_length_px` reads at most: beyond that, every k-th row.
/// A million pixels of texture fix the length far inside the window's rounding
/// (docs/validation.md#the-structure-length-on-sampled-rows).
const STRUCTURE_MAX_PIXELS: usize = 1 << 20;

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
    // Every `step`-th row: the trend is made only on those and the rows either side of them.
    let step = (h * w).div_ceil(STRUCTURE_MAX_PIXELS).max(1);
    let sampled: Vec<usize> = (1..h - 1).step_by(step).collect();
    let trend = if step == 1 {
        preprocess::gaussian_smooth(img, STRUCTURE_TREND_SIGMA_PX)
    } else {
        let around: Vec<usize> = sampled.iter().flat_map(|&y| [y - 1, y, y + 1]).collect();
        preprocess::gaussian_smooth_rows(img, STRUCTURE_TREND_SIGMA_PX, &around)
    };
    // Row `y - 1 + d` of the image is row `trend_row(i, d)` of `trend` (`y` the `i`-th sampled).
    let trend_row = |i: usize, d: usize| {
        if step == 1 {
            sampled[i] - 1 + d
        } else {
            3 * i + d
        }
    };
    // Row sums in parallel, added in row order: the same figure whatever the thread count.
    let rows: Vec<[f64; 4]> = (0..sampled.len())
        .into_par_iter()
        .map(|i| {
            let y = sampled[i];
            let hp_row = |d: usize| {
                let (row, t) = (img.row(y - 1 + d), trend.row(trend_row(i, d)));
                move |xx: usize| (row[xx] - t[xx]) as f64
            };
            let (above, here, below) = (hp_row(0), hp_row(1), hp_row(2));
            let m = mask.row(y);
            let mut sums = [0.0f64; 4];
            for x in 1..w - 1 {
                if !m[x] {
                    continue;
                }
                let v = here(x);
                let gx = (here(x + 1) - here(x - 1)) / 2.0;
                let gy = (below(x) - above(x)) / 2.0;
                if !(v.is_finite() && gx.is_finite() && gy.is_finite()) {
                    continue;
                }
                sums[0] += 1.0;
                sums[1] += v;
                sums[2] += v * v;
                sums[3] += (gx * gx + gy * gy) / 2.0;
            }
            sums
        })
        .collect();
    let [n, s, s2, g2] = rows.iter().fold([0.0f64; 4], |a, r| {
        [a[0] + r[0], a[1] + r[1], a[2] + r[2], a[3] + r[3]]
    });
    if n < 64.0 {
        return None;
    }
    let var = s2 / n - (s / n).powi(2);
    let grad = g2 / n;
    (var > 0.0 && grad > 0.0).then(|| (var / grad).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cell made while its maker, on the same thread, needs it again (as a rayon thread
    /// that runs another frame's job while it waits does): the inner call makes it rather
    /// than wait for the outer one, which would never finish, and every caller reads the
    /// first value set. On a cell already made, nothing is made again.
    #[test]
    fn a_cell_needed_again_while_it_is_made_is_made_not_waited_for() {
        let cell = std::sync::OnceLock::new();
        let mut inner = None;
        let outer = *made_once(&cell, || {
            inner = Some(*made_once(&cell, || 2));
            1
        });
        assert_eq!((inner, outer), (Some(2), 2));
        assert_eq!(*made_once(&cell, || unreachable!("the cell is made")), 2);
    }

    /// A plane wave `sin(kx·x + ky·y)` over `h × w` with a mask `margin` px inside its edges:
    /// its central differences have the mean square `(sin²kx + sin²ky)/2` of its variance, so
    /// the length is `√(2 / (sin²kx + sin²ky))` exactly, and the trend (a Gaussian of the wave)
    /// scales it uniformly away from the edges.
    fn wave(h: usize, w: usize, k: [f64; 2], margin: usize) -> (Array2<f32>, Array2<bool>, f64) {
        let img = Array2::from_shape_fn((h, w), |(y, x)| {
            (100.0 + (k[0] * x as f64 + k[1] * y as f64).sin()) as f32
        });
        let mask = Array2::from_shape_fn((h, w), |(y, x)| {
            (margin..h - margin).contains(&y) && (margin..w - margin).contains(&x)
        });
        let truth = (2.0 / (k[0].sin().powi(2) + k[1].sin().powi(2))).sqrt();
        (img, mask, truth)
    }

    #[test]
    fn the_structure_length_of_a_plane_wave_on_every_row_and_on_sampled_rows() {
        // 600 × 700: every row; 1500 × 2100: every 4th row.
        for (h, w) in [(600, 700), (1500, 2100)] {
            for k in [[0.31, 0.17], [0.9, 0.05], [0.12, 0.55]] {
                let (img, mask, truth) = wave(h, w, k, 40);
                let got = structure_length_px(img.view(), mask.view()).expect("a length");
                assert!(
                    (got / truth - 1.0).abs() < 2e-3,
                    "{h}×{w}, k {k:?}: {got} vs {truth}"
                );
            }
        }
    }
}
