//! Seeds for the refinement and for full-resolution passes: the flow stage on copies binned to
//! a coarser pyramid level, its answer carried back to the full grid.

use super::config::EngineConfig;
use super::fine::{
    auto_levels, fine_alignment, flow_reach_px, Crop, FineResult, FlowRegion, FlowSetup, PassStart,
};
use super::quality;
use super::region::{grown, mask_roi};
use crate::flow::Roi;
use crate::geometry::{compose_with_covariance, Covariance4, Similarity};
use crate::preprocess::{self, BlockMeans};
use ndarray::{s, Array2, ArrayView2, Axis};
use rayon::prelude::*;

/// How far a seed on `level` may be from the full-resolution flow, px: a level-1 finish's RMS
/// flow error, growing with each further level, and none at full resolution
/// (docs/validation.md#flow-finished-at-full-resolution).
pub(super) fn seed_slack_px(level: usize) -> f64 {
    0.05 * ((1usize << level.min(16)) - 1) as f64
}

/// Gaussian σ, in units of the binning factor, both images are smoothed by before they are
/// binned for a final answer. A 2×2 mean alone passes 38 % of the amplitude at 3/8 cycles per
/// pixel, which aliases on the binned grid and moves band-limited structure differently from
/// the true shift; with this σ first, 2.4 %
/// (docs/validation.md#between-channels-the-answer-on-binned-copies).
pub(super) const FINAL_ANTIALIAS: f64 = 0.5;

/// The pyramid level a seed flow works on: where the mask spans at least
/// `cfg.seed_extent_px` (64 at the least), within the pyramid the flow would build.
pub(super) fn seed_level(roi: Roi, cfg: &EngineConfig) -> usize {
    level_spanning(roi, cfg, cfg.seed_extent_px.max(64))
}

/// The pyramid level a final flow answer is measured on: where the mask spans at least
/// `cfg.final_extent_px` (64 at the least); 0 keeps full resolution.
pub(super) fn final_level(roi: Roi, cfg: &EngineConfig) -> usize {
    match cfg.final_extent_px {
        0 => 0,
        px => level_spanning(roi, cfg, px.max(64)),
    }
}

/// The coarsest level, within the pyramid the flow would build, where the mask still spans
/// `extent_px`.
fn level_spanning(roi: Roi, cfg: &EngineConfig, extent_px: usize) -> usize {
    let extent = roi.width.min(roi.height);
    let levels = cfg.pyramid_levels.unwrap_or_else(|| auto_levels(extent));
    let mut level = 0;
    while level < levels && (extent >> (level + 1)) >= extent_px {
        level += 1;
    }
    level
}

/// The reference and its mask binned `2^level`× for flows on binned copies: seeds, and final
/// answers on large frames.
pub(super) struct Binned {
    level: usize,
    /// Gaussian σ, full-grid px, both images are smoothed by before binning (0: none).
    antialias_px: f64,
    pub(super) reference: Array2<f32>,
    pub(super) mask: Array2<bool>,
    pub(super) mask_box: Roi,
    /// High-pass of `reference` on `quality_crop`, as `Matched` has for the full grid.
    pub(super) high_pass: Array2<f32>,
    pub(super) quality_crop: Crop,
}

impl Binned {
    /// `known`: `reference` binned already by some factor, used when it is this one.
    pub(super) fn new(
        reference: ArrayView2<f32>,
        known: Option<&BlockMeans>,
        mask: &Array2<bool>,
        level: usize,
        trend_px: f64,
        antialias_px: f64,
    ) -> Binned {
        let factor = 1usize << level;
        let reference = bin(reference, known, factor, antialias_px);
        let mask = all_binned(mask, factor);
        let mask_box = mask_roi(&mask);
        let (h, w) = reference.dim();
        let (rows, cols) = grown(mask_box, trend_px, w, h);
        let high_pass =
            quality::high_pass(reference.slice(s![rows.clone(), cols.clone()]), trend_px);
        Binned {
            level,
            antialias_px,
            reference,
            mask,
            mask_box,
            high_pass,
            quality_crop: Crop { rows, cols },
        }
    }

    pub(super) fn level(&self) -> usize {
        self.level
    }

    /// `img` (full grid) binned as the reference was; `known`: `img` binned already by some
    /// factor, used when it is this one.
    pub(super) fn bin(&self, img: ArrayView2<f32>, known: Option<&BlockMeans>) -> Array2<f32> {
        bin(img, known, 1 << self.level, self.antialias_px)
    }

    fn factor(&self) -> f64 {
        (1usize << self.level) as f64
    }

    /// Binned pixel q covers full pixels b·q … b·q + b − 1: its centre is b·(q + 0.5) − 0.5.
    fn to_full(&self, q: f64) -> f64 {
        let b = self.factor();
        b * (q + 0.5) - 0.5
    }

    /// `t` (full grid) as the same motion on the binned grid, about the binned array's centre:
    /// a similarity about centre C with shift d is, there, the same scale and rotation about
    /// the binned C with shift d/b.
    pub(super) fn to_binned(&self, t: &Similarity) -> Similarity {
        let b = self.factor();
        let (sh, sw) = self.reference.dim();
        let small_center = Similarity::array_center(sw, sh);
        let about = [self.to_full(small_center[0]), self.to_full(small_center[1])];
        let c = t.recentered(about);
        Similarity {
            dx: c.dx / b,
            dy: c.dy / b,
            center: small_center,
            ..c
        }
    }

    /// Where the flow measures on the binned grid. Between channels `disk` is the reference's
    /// disk (centre, radius px, full grid), whose limb the flow's windows must stay clear of;
    /// the flow's reach is in binned pixels here.
    pub(super) fn region(
        &self,
        disk: Option<([f64; 2], f64)>,
        winsize: usize,
        cfg: &EngineConfig,
    ) -> FlowRegion<'_> {
        let b = self.factor();
        FlowRegion {
            mask: &self.mask,
            sample_within: disk.map(|([cx, cy], r)| {
                let to_binned = |v: f64| (v + 0.5) / b - 0.5;
                (
                    [to_binned(cx), to_binned(cy)],
                    r / b - flow_reach_px(winsize, cfg.poly_n),
                )
            }),
        }
    }
}

fn bin(
    img: ArrayView2<f32>,
    known: Option<&BlockMeans>,
    factor: usize,
    antialias_px: f64,
) -> Array2<f32> {
    match known {
        _ if antialias_px > 0.0 => preprocess::smooth_bin(img, factor, antialias_px),
        Some(known) if known.bin == factor => known.means.clone(),
        _ => preprocess::bin_mean(img, factor),
    }
}

/// `mask` binned `factor`×, the last blocks partial: a binned pixel is in the mask when all
/// its pixels are.
fn all_binned(mask: &Array2<bool>, factor: usize) -> Array2<bool> {
    let (h, w) = mask.dim();
    let (bh, bw) = (h.div_ceil(factor), w.div_ceil(factor));
    let mask = mask.as_standard_layout();
    let pixels = mask.as_slice().expect("a standard layout is contiguous");
    let mut out = Array2::from_elem((bh, bw), true);
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(by, mut row)| {
            for y in by * factor..((by + 1) * factor).min(h) {
                let blocks = pixels[y * w..(y + 1) * w].chunks(factor);
                for (o, block) in row.iter_mut().zip(blocks) {
                    *o = *o && !block.contains(&false);
                }
            }
        });
    out
}

/// What a run of the flow on binned copies is for.
#[derive(Clone, Copy, Debug)]
pub(super) enum BinnedRun {
    /// A seed, from the coarse alignment (full grid): the whole pyramid, then passes until
    /// the update is a tenth of the seed's own slack.
    Seed(Similarity),
    /// The flow's final answer, from a seed on a coarser level (full grid): passes on this
    /// level only, converged as at full resolution.
    Final(Similarity),
}

/// The flow stage on `binned` copies, as a seed or as the flow's final answer (`run`): the
/// result in full-grid terms (transform, covariances, inliers, sampling mask), its warped
/// frame on the binned grid. Between channels `disk` is the reference's disk (centre, radius
/// px, full grid), whose limb the flow's windows must stay clear of. `frame`: its pixels and
/// block means, when it has them.
pub(super) fn binned_alignment(
    binned: &Binned,
    grid: (usize, usize),
    frame: (&Array2<f32>, Option<&BlockMeans>),
    run: BinnedRun,
    disk: Option<([f64; 2], f64)>,
    setup: FlowSetup,
) -> Result<FineResult, String> {
    let (frame, frame_means) = frame;
    let cfg = setup.cfg;
    let factor = 1usize << binned.level;
    let b = factor as f64;
    // The reference's grid (the frame may be of another size).
    let (h, w) = grid;
    let full_center = Similarity::array_center(w, h);
    let small_frame = binned.bin(frame.view(), frame_means);
    let (start, run_cfg) = match run {
        // Converged when the update is a tenth of the seed's own slack (in binned pixels).
        BinnedRun::Seed(coarse) => (
            PassStart::Coarse(binned.to_binned(&coarse)),
            EngineConfig {
                convergence_px: cfg
                    .convergence_px
                    .max(0.1 * seed_slack_px(binned.level) / b),
                ..cfg.clone()
            },
        ),
        BinnedRun::Final(seed) => (PassStart::Seed(binned.to_binned(&seed)), cfg.clone()),
    };
    let carried = setup.carried.map(|c| c.binned(factor));
    let mut fine = fine_alignment(
        binned.reference.view(),
        &small_frame,
        binned.region(disk, setup.winsize, cfg),
        start,
        run_cfg.max_passes,
        FlowSetup {
            frame_smoothing_px: setup.frame_smoothing_px / b,
            carried: carried.as_ref(),
            cfg: &run_cfg,
            ..setup
        },
    )
    .map_err(|e| e.to_string())?;
    let unbinned = |t: &Similarity, cov: &Covariance4| -> (Similarity, Covariance4) {
        let t_about = Similarity {
            dx: t.dx * b,
            dy: t.dy * b,
            center: [binned.to_full(t.center[0]), binned.to_full(t.center[1])],
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
    fine.unsettled_px = fine.unsettled_px.map(|px| px * b);
    for p in &mut fine.inliers {
        p.x = binned.to_full(p.x);
        p.y = binned.to_full(p.y);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_binned_pixel_is_in_the_mask_when_all_its_pixels_are() {
        // 10 × 7 with factor 4: partial blocks at the right and bottom edges.
        let mask = Array2::from_shape_fn((7, 10), |(y, x)| !(y == 1 && x == 2) && x != 9);
        let binned = all_binned(&mask, 4);
        // Blocks: rows 0–3 | 4–6, columns 0–3 | 4–7 | 8–9.
        let want = ndarray::arr2(&[[false, true, false], [true, true, false]]);
        assert_eq!(binned, want);
        // A whole mask stays whole, the partial blocks included.
        assert!(all_binned(&Array2::from_elem((7, 10), true), 4)
            .iter()
            .all(|&m| m));
    }

    /// A copy binned already stands in for the block means (bin × bin, from pixel 0, the last
    /// blocks partial) only at its own factor and without anti-aliasing.
    #[test]
    fn a_copy_binned_already_serves_only_its_own_factor() {
        let img = Array2::from_shape_fn((37, 45), |(y, x)| ((y * 45 + x) % 11) as f32);
        let mean_of_block = |b: usize, (by, bx): (usize, usize)| {
            let block = img.slice(s![
                by * b..((by + 1) * b).min(37),
                bx * b..((bx + 1) * b).min(45)
            ]);
            block.iter().map(|&v| f64::from(v)).sum::<f64>() / block.len() as f64
        };
        // A copy binned 4×, of some other image: what serves where it is used.
        let known = BlockMeans {
            bin: 4,
            means: Array2::from_elem((10, 12), -1.0),
        };
        let mask = Array2::from_elem((37, 45), true);
        for level in [1, 2, 3] {
            let binned = Binned::new(img.view(), Some(&known), &mask, level, 2.0, 0.0);
            let b = 1 << level;
            for ((by, bx), &v) in binned.reference.indexed_iter() {
                let want = if b == 4 {
                    -1.0
                } else {
                    mean_of_block(b, (by, bx))
                };
                assert!(
                    (f64::from(v) - want).abs() < 1e-5,
                    "{b}×: ({bx}, {by}) {v} vs {want}"
                );
            }
            assert_eq!(
                binned.bin(img.view(), Some(&known)),
                binned.reference,
                "{b}×"
            );
            // Smoothed first: the copy is not what is asked for.
            let smoothed = Binned::new(img.view(), Some(&known), &mask, level, 2.0, 1.0);
            assert!(
                smoothed.reference.iter().all(|&v| v >= 0.0),
                "{b}× smoothed"
            );
        }
    }
}
