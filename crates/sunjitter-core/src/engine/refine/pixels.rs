//! Which reference pixels the refinement fits: the flow's grid of cells, the lattice that
//! thins them, and the region where both images can be read.

use crate::flow::Roi;
use crate::geometry::Similarity;
use crate::sampling::Correspondence;
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

/// The grid of cells the flow sampling used, over the bounding box of its mask
/// (`crate::sampling::grid_median_sample_cells`): cell column of each x, cell row of each y.
pub struct CellGrid {
    x0: usize,
    y0: usize,
    col_of: Vec<usize>,
    row_of: Vec<usize>,
    sample: usize,
}

impl CellGrid {
    /// The grid over the bounding box of `mask`, `sample × sample` cells.
    pub fn new(mask: ArrayView2<bool>, sample: usize) -> Option<CellGrid> {
        Some(CellGrid::over_box(
            crate::sampling::mask_bounding_box(mask)?,
            sample,
        ))
    }

    /// The grid over the box (x0, y0, x1, y1, inclusive), `sample × sample` cells.
    pub fn over_box(bbox: (usize, usize, usize, usize), sample: usize) -> CellGrid {
        let (x0, y0, x1, y1) = bbox;
        let sample = sample.max(1);
        let split = |lo: usize, hi: usize| -> Vec<usize> {
            let n = hi - lo + 1;
            let mut of = vec![0; n];
            for i in 0..sample {
                for o in &mut of[i * n / sample..(i + 1) * n / sample] {
                    *o = i;
                }
            }
            of
        };
        CellGrid {
            x0,
            y0,
            col_of: split(x0, x1.max(x0)),
            row_of: split(y0, y1.max(y0)),
            sample,
        }
    }

    /// Cell index (row-major) of a pixel; pixels outside the grid belong to the nearest cell.
    pub fn cell_of(&self, x: usize, y: usize) -> Option<usize> {
        let clamp = |v: usize, lo: usize, of: &[usize]| {
            of.get(v.saturating_sub(lo).min(of.len().saturating_sub(1)))
                .copied()
        };
        let c = clamp(x, self.x0, &self.col_of)?;
        let r = clamp(y, self.y0, &self.row_of)?;
        Some(r * self.sample + c)
    }

    /// The cell holding a (real-valued) sample point.
    pub fn cell_of_point(&self, p: &Correspondence) -> Option<usize> {
        if !(p.x >= 0.0 && p.y >= 0.0) {
            return None;
        }
        self.cell_of(p.x.round() as usize, p.y.round() as usize)
    }

    /// The 2 × 2 group of cells a cell belongs to.
    pub(super) fn group_of(&self, cell: usize) -> usize {
        let (r, c) = (cell / self.sample, cell % self.sample);
        (r / 2) * self.sample.div_ceil(2) + c / 2
    }
}

/// Pixels of an `h × w` grid that are `usable`, inside the cells that hold at least one of
/// `inliers`, with their cell, on a regular lattice (every `k`-th row and column) that keeps
/// them to about `max`.
pub fn inlier_cell_pixels(
    (h, w): (usize, usize),
    usable: impl Fn(usize, usize) -> bool + Sync,
    grid: &CellGrid,
    inliers: &[Correspondence],
    max: usize,
) -> Vec<(usize, usize, usize)> {
    let mut keep = vec![false; grid.sample * grid.sample];
    for p in inliers {
        if let Some(c) = grid.cell_of_point(p) {
            keep[c] = true;
        }
    }
    lattice_pixels((h, w), usable, grid, max, |c| keep[c])
}

/// Usable pixels of an `h × w` grid in the cells `wanted`, thinned to a lattice of about `max`
/// of them. The lattice step is chosen from their count first (estimated on every second row
/// and column of a large grid), so that no full-size array is made.
pub(super) fn lattice_pixels(
    (h, w): (usize, usize),
    usable: impl Fn(usize, usize) -> bool + Sync,
    grid: &CellGrid,
    max: usize,
    wanted: impl Fn(usize) -> bool + Sync,
) -> Vec<(usize, usize, usize)> {
    let take = |x: usize, y: usize| {
        if usable(x, y) {
            grid.cell_of(x, y).filter(|&c| wanted(c))
        } else {
            None
        }
    };
    let count_every = |step: usize| -> usize {
        (0..h)
            .into_par_iter()
            .step_by(step)
            .map(|y| {
                (0..w)
                    .step_by(step)
                    .filter(|&x| take(x, y).is_some())
                    .count()
            })
            .sum()
    };
    let count = if h * w <= 4 * max {
        count_every(1)
    } else {
        4 * count_every(2)
    };
    let k = lattice_step(count, max);
    let rows: Vec<Vec<_>> = (0..h)
        .into_par_iter()
        .step_by(k)
        .map(|y| {
            (0..w)
                .step_by(k)
                .filter_map(|x| take(x, y).map(|c| (x, y, c)))
                .collect()
        })
        .collect();
    crate::pages::concat(&rows)
}

/// Lattice step (every `k`-th row and column) that brings `count` pixels to at most about `max`.
pub(super) fn lattice_step(count: usize, max: usize) -> usize {
    if count <= max {
        1
    } else {
        ((count as f64 / max.max(1) as f64).sqrt().ceil() as usize).max(2)
    }
}

/// Reference pixels the refinement may use: inside `mask`, with a finite reference, and at
/// least `margin` px (the smoothing's and the spline's reach) from the edges of both images
/// (the frame's through `t`) and from the frame's blanks. This is wider than the flow's
/// sample mask, which keeps half a window (60 px and more) from every edge: scale and
/// rotation are measured best at the largest lever arm.
pub(super) struct RefinementRegion<'a, M: Fn(f64, f64) -> (f64, f64)> {
    mask: &'a Array2<bool>,
    reference: ArrayView2<'a, f32>,
    frame_dim: (usize, usize),
    /// Frame pixels at least `margin` from any blank (`None`: the frame has none).
    frame_blank_free: Option<Array2<bool>>,
    map: M,
    margin: f64,
    /// Every mask pixel maps at least `margin` inside the frame, which has no blanks: the
    /// frame side needs no test.
    frame_side_holds: bool,
}

pub(super) fn refinement_region<'a>(
    mask: &'a Array2<bool>,
    mask_box: Roi,
    reference: ArrayView2<'a, f32>,
    frame: ArrayView2<f32>,
    t: &Similarity,
    carried: Option<&'a crate::engine::derotate::Carried>,
    margin: usize,
) -> RefinementRegion<'a, impl Fn(f64, f64) -> (f64, f64) + 'a> {
    let frame_blank_free = if crate::stats::all_finite(frame) {
        None
    } else {
        Some(crate::engine::region::erode(
            &frame.mapv(f32::is_finite),
            margin,
        ))
    };
    let frame_side_holds = frame_blank_free.is_none()
        && mask_maps_inside(mask_box, t, carried, margin as f64, frame.dim());
    RefinementRegion {
        mask,
        reference,
        frame_dim: frame.dim(),
        frame_blank_free,
        frame_side_holds,
        map: {
            let map = crate::resample::similarity_map(t);
            move |x, y| {
                let (sx, sy) = carried.map_or((x, y), |c| c.at(x, y));
                map(sx, sy)
            }
        },
        margin: margin as f64,
    }
}

impl<M: Fn(f64, f64) -> (f64, f64)> RefinementRegion<'_, M> {
    fn inside(&self, v: f64, n: usize) -> bool {
        v >= self.margin && v <= n as f64 - 1.0 - self.margin
    }

    pub(super) fn usable(&self, x: usize, y: usize) -> bool {
        let (h, w) = self.reference.dim();
        let (fh, fw) = self.frame_dim;
        if !(self.inside(x as f64, w)
            && self.inside(y as f64, h)
            && self.mask[[y, x]]
            && self.reference[[y, x]].is_finite())
        {
            return false;
        }
        if self.frame_side_holds {
            return true;
        }
        let (fx, fy) = (self.map)(x as f64, y as f64);
        self.inside(fx, fw)
            && self.inside(fy, fh)
            && self
                .frame_blank_free
                .as_ref()
                .is_none_or(|ok| ok[[fy.round() as usize, fx.round() as usize]])
    }
}

/// Whether every pixel of the mask whose bounding box is `mask_box`, carried by the Sun and
/// mapped through `t`, lands at least `margin` inside an `fh × fw` frame. A similarity maps
/// the box, grown by the largest
/// motion the Sun's field can interpolate to (and a pixel for round-off), into the hull of its
/// corners' images, so the corners decide.
fn mask_maps_inside(
    mask_box: Roi,
    t: &Similarity,
    carried: Option<&crate::engine::derotate::Carried>,
    margin: f64,
    (fh, fw): (usize, usize),
) -> bool {
    let motion = match carried.map(|c| c.motion_bound_px()) {
        None => 0.0,
        Some(Some(bound)) => bound,
        Some(None) => return false,
    };
    let grow = motion + 1.0;
    let (lo_x, hi_x) = (
        mask_box.x as f64 - grow,
        (mask_box.x + mask_box.width) as f64 - 1.0 + grow,
    );
    let (lo_y, hi_y) = (
        mask_box.y as f64 - grow,
        (mask_box.y + mask_box.height) as f64 - 1.0 + grow,
    );
    let map = crate::resample::similarity_map(t);
    let inside = |v: f64, n: usize| v >= margin && v <= n as f64 - 1.0 - margin;
    [(lo_x, lo_y), (hi_x, lo_y), (lo_x, hi_y), (hi_x, hi_y)]
        .into_iter()
        .all(|(x, y)| {
            let (fx, fy) = map(x, y);
            inside(fx, fw) && inside(fy, fh)
        })
}

/// The pixels inside the `side`×`side` square at the centre of `bbox` (all of them when the
/// box is no larger).
pub(super) fn central_pixels(
    pixels: &[(usize, usize, usize)],
    (x0, y0, x1, y1): (usize, usize, usize, usize),
    side: usize,
) -> Vec<(usize, usize, usize)> {
    let span = |a: usize, b: usize| {
        let extent = b - a + 1;
        let start = a + extent.saturating_sub(side) / 2;
        start..start + side.min(extent)
    };
    let (xs, ys) = (span(x0, x1), span(y0, y1));
    pixels
        .iter()
        .filter(|&&(x, y, _)| xs.contains(&x) && ys.contains(&y))
        .copied()
        .collect()
}

/// Bounding box (x0, y0, x1, y1), inclusive, of `pixels`; `None` when there are none.
pub(super) fn pixel_box(pixels: &[(usize, usize, usize)]) -> Option<(usize, usize, usize, usize)> {
    let (&(x, y, _), rest) = pixels.split_first()?;
    Some(
        rest.iter()
            .fold((x, y, x, y), |(x0, y0, x1, y1), &(x, y, _)| {
                (x0.min(x), y0.min(y), x1.max(x), y1.max(y))
            }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::region::mask_roi;

    #[test]
    fn a_mask_said_to_map_inside_maps_inside_pixel_by_pixel() {
        // The shortcut may only hold where every mask pixel's image does (the definition);
        // it must hold for a disk well inside the frame and fail once one pixel leaves.
        let (h, w, margin) = (200, 220, 10.0);
        let mask = Array2::from_shape_fn((h, w), |(y, x)| {
            (x as f64 - 110.0).hypot(y as f64 - 100.0) <= 70.0
        });
        let each_inside = |t: &Similarity| {
            let map = crate::resample::similarity_map(t);
            mask.indexed_iter().filter(|(_, &m)| m).all(|((y, x), _)| {
                let (fx, fy) = map(x as f64, y as f64);
                fx >= margin
                    && fx <= w as f64 - 1.0 - margin
                    && fy >= margin
                    && fy <= h as f64 - 1.0 - margin
            })
        };
        let mut held = 0;
        for (dx, rotation_rad, scale) in [
            (0.3, 0.0, 1.0),
            (-12.0, 0.02, 1.01),
            (15.0, -0.05, 0.98),
            (25.0, 0.0, 1.0),
            (30.0, 0.1, 1.05),
        ] {
            let t = Similarity {
                scale,
                rotation_rad,
                dx,
                dy: -0.4 * dx,
                center: [109.5, 99.5],
            };
            let said = mask_maps_inside(mask_roi(&mask), &t, None, margin, (h, w));
            if said {
                held += 1;
                assert!(each_inside(&t), "{t:?}");
            }
            if !each_inside(&t) {
                assert!(!said, "{t:?}");
            }
        }
        assert!(held >= 2, "held {held} times");
        assert!(!mask_maps_inside(
            mask_roi(&mask),
            &Similarity {
                dx: 40.0,
                ..Similarity::identity([109.5, 99.5])
            },
            None,
            margin,
            (h, w)
        ));
    }

    #[test]
    fn the_region_keeps_the_margin_from_both_images_edges() {
        // 40 × 30 reference, the same frame shifted by +3.4 px in x: pixel x maps to x + 3.4,
        // so with a 4 px margin x must satisfy 4 ≤ x and x + 3.4 ≤ 39 − 4 (x ≤ 31), 4 ≤ y ≤ 25.
        let (h, w) = (30, 40);
        let reference = Array2::from_elem((h, w), 1.0f32);
        let mut frame = Array2::from_elem((h, w), 1.0f32);
        let mask = Array2::from_elem((h, w), true);
        let t = Similarity {
            dx: 3.4,
            ..Similarity::identity(Similarity::array_center(w, h))
        };
        let mask_box = mask_roi(&mask);
        let region_of = |frame: &Array2<f32>| {
            refinement_region(&mask, mask_box, reference.view(), frame.view(), &t, None, 4)
        };
        let region = region_of(&frame);
        for ((y, x), _) in mask.indexed_iter() {
            assert_eq!(
                region.usable(x, y),
                (4..=31).contains(&x) && (4..=25).contains(&y),
                "({x}, {y})"
            );
        }
        // A blank in the frame at (20, 15) removes the pixels mapping within 4 px of it.
        frame[[15, 20]] = f32::NAN;
        let region = region_of(&frame);
        // Pixel (x, y) maps to round(x + 3.4) = x + 3: excluded when |x + 3 − 20| ≤ 4 and
        // |y − 15| ≤ 4.
        for ((y, x), _) in mask.indexed_iter() {
            let r = region.usable(x, y);
            let inside = (4..=31).contains(&x) && (4..=25).contains(&y);
            let near_blank = (x + 3).abs_diff(20) <= 4 && y.abs_diff(15) <= 4;
            assert_eq!(r, inside && !near_blank, "({x}, {y})");
        }
    }

    #[test]
    fn the_check_region_is_the_central_square_of_the_box() {
        let pixels: Vec<(usize, usize, usize)> = (0..10)
            .flat_map(|y| (0..20).map(move |x| (x, y, 0)))
            .collect();
        // Box 20 wide, 10 high; a 4 px square starts at (20 − 4)/2 = 8 and (10 − 4)/2 = 3.
        let inner = central_pixels(&pixels, (0, 0, 19, 9), 4);
        assert_eq!(inner.len(), 16);
        assert!(inner
            .iter()
            .all(|&(x, y, _)| (8..12).contains(&x) && (3..7).contains(&y)));
        // A box no larger than the square keeps everything.
        assert_eq!(central_pixels(&pixels, (0, 0, 19, 9), 64).len(), 200);
    }

    #[test]
    fn the_lattice_keeps_every_kth_row_and_column_under_the_cap() {
        let region = Array2::from_elem((100, 100), true);
        let grid = CellGrid::new(region.view(), 4).expect("grid");
        // Under the cap: all 10 000.
        assert_eq!(
            lattice_pixels((100, 100), |_, _| true, &grid, 10_000, |_| true).len(),
            10_000
        );
        // Cap 2 500: every 2nd row and column, exactly 50 × 50.
        let kept = lattice_pixels((100, 100), |_, _| true, &grid, 2_500, |_| true);
        assert_eq!(kept.len(), 2_500);
        assert!(kept.iter().all(|&(x, y, _)| x % 2 == 0 && y % 2 == 0));
        // Cap 1 000: k = ⌈√10⌉ = 4, 25 × 25.
        assert_eq!(
            lattice_pixels((100, 100), |_, _| true, &grid, 1_000, |_| true).len(),
            625
        );
        // Only the wanted cells: one of 16 (25 × 25 px), all of it under the cap.
        let one = lattice_pixels((100, 100), |_, _| true, &grid, 10_000, |c| c == 5);
        assert_eq!(one.len(), 625);
        assert!(one
            .iter()
            .all(|&(x, y, c)| c == 5 && (25..50).contains(&x) && (25..50).contains(&y)));
    }
}
