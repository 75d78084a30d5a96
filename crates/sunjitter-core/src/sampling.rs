//! Grid sampling of a dense flow field (paper §3.2): one representative flow vector per
//! grid cell, so that every part of the disk weighs the same in the fit and no densely
//! textured region dominates it.
//!
//! Points are taken inside the mask on a `stride` lattice anchored at the top-left corner of
//! the mask's bounding box. The box is split into `sample × sample` cells (integer
//! boundaries `x0 + ⌊i·W/sample⌋`), and each cell contributes one *actual* lattice point:
//! the one whose displacement (u, v) is nearest (Euclidean) to the component-wise median of
//! the cell's displacements. Ties go to the first point in row-major order, so the result is
//! deterministic. The component-wise median is O(n) per cell and robust to up to half the
//! cell being outliers; the chosen point is a real pixel, so its (x, y) is exact.
//! Points whose flow is not finite are skipped; cells with no valid point contribute nothing.

use ndarray::ArrayView2;
use rayon::prelude::*;

/// A reference-grid point `(x, y)` whose content appears in the frame at `(x + u, y + v)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Correspondence {
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
}

impl Correspondence {
    pub fn reference_point(&self) -> [f64; 2] {
        [self.x, self.y]
    }

    pub fn frame_point(&self) -> [f64; 2] {
        [self.x + self.u, self.y + self.v]
    }

    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.u.is_finite() && self.v.is_finite()
    }
}

/// One cell's representative, with the cell it came from and how many valid points the cell had
/// (useful for weighting, or for discarding cells that are mostly outside the mask).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellSample {
    pub point: Correspondence,
    /// (column, row) of the cell in the `sample × sample` grid.
    pub cell: [usize; 2],
    pub count: usize,
}

/// Inclusive bounding box `(x0, y0, x1, y1)` of the true pixels of a mask.
pub fn mask_bounding_box(mask: ArrayView2<bool>) -> Option<(usize, usize, usize, usize)> {
    use rayon::prelude::*;
    // Row by row, each row's first and last set pixel: a frame-sized mask is tens of MB.
    mask.axis_iter(ndarray::Axis(0))
        .into_par_iter()
        .enumerate()
        .filter_map(|(y, row)| {
            let first = row.iter().position(|&m| m)?;
            let last = row.iter().rposition(|&m| m)?;
            Some((first, y, last, y))
        })
        .reduce_with(|(ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1)| {
            (ax0.min(bx0), ay0.min(by0), ax1.max(bx1), ay1.max(by1))
        })
}

/// Per-cell representatives, cells in row-major order. Returns an empty vector when the
/// shapes of `u`, `v` and `mask` differ, when `stride` or `sample` is 0, or when the mask is empty.
pub fn grid_median_sample_cells(
    u: ArrayView2<f32>,
    v: ArrayView2<f32>,
    mask: ArrayView2<bool>,
    stride: usize,
    sample: usize,
) -> Vec<CellSample> {
    if u.dim() != v.dim() || u.dim() != mask.dim() || stride == 0 || sample == 0 {
        return Vec::new();
    }
    let Some((x0, y0, x1, y1)) = mask_bounding_box(mask) else {
        return Vec::new();
    };
    let (w, h) = (x1 - x0 + 1, y1 - y0 + 1);
    let edge_x = |i: usize| x0 + i * w / sample;
    let edge_y = |j: usize| y0 + j * h / sample;
    // First lattice coordinate ≥ lo on the lattice origin + k·stride.
    let first_on_lattice =
        |lo: usize, origin: usize| origin + (lo - origin).div_ceil(stride) * stride;

    (0..sample * sample)
        .into_par_iter()
        .map_init(Vec::<(usize, usize, f64, f64)>::new, |pts, cell_index| {
            let (ci, cj) = (cell_index % sample, cell_index / sample);
            let (xa, xb) = (edge_x(ci), edge_x(ci + 1));
            let (ya, yb) = (edge_y(cj), edge_y(cj + 1));
            pts.clear();
            let mut y = first_on_lattice(ya, y0);
            while y < yb {
                let mut x = first_on_lattice(xa, x0);
                while x < xb {
                    let (uu, vv) = (u[[y, x]], v[[y, x]]);
                    if mask[[y, x]] && uu.is_finite() && vv.is_finite() {
                        pts.push((x, y, uu as f64, vv as f64));
                    }
                    x += stride;
                }
                y += stride;
            }
            let (x, y, uu, vv, count) = median_representative(pts)?;
            Some(CellSample {
                point: Correspondence {
                    x: x as f64,
                    y: y as f64,
                    u: uu,
                    v: vv,
                },
                cell: [ci, cj],
                count,
            })
        })
        .flatten()
        .collect()
}

/// One representative per cell; see the module documentation for the definition.
pub fn grid_median_sample(
    u: ArrayView2<f32>,
    v: ArrayView2<f32>,
    mask: ArrayView2<bool>,
    stride: usize,
    sample: usize,
) -> Vec<Correspondence> {
    grid_median_sample_cells(u, v, mask, stride, sample)
        .into_iter()
        .map(|c| c.point)
        .collect()
}

/// The point nearest the component-wise median of `pts` (row-major order, first wins ties).
fn median_representative(
    pts: &[(usize, usize, f64, f64)],
) -> Option<(usize, usize, f64, f64, usize)> {
    if pts.is_empty() {
        return None;
    }
    let mut scratch: Vec<f64> = pts.iter().map(|p| p.2).collect();
    let mu = median_in_place(&mut scratch);
    scratch.clear();
    scratch.extend(pts.iter().map(|p| p.3));
    let mv = median_in_place(&mut scratch);
    let mut best = 0;
    let mut best_d2 = f64::INFINITY;
    for (i, p) in pts.iter().enumerate() {
        let d2 = (p.2 - mu).powi(2) + (p.3 - mv).powi(2);
        if d2 < best_d2 {
            best_d2 = d2;
            best = i;
        }
    }
    let p = pts[best];
    Some((p.0, p.1, p.2, p.3, pts.len()))
}

/// Median of a non-empty slice (mean of the middle pair for an even count); reorders it.
fn median_in_place(v: &mut [f64]) -> f64 {
    let n = v.len();
    let (_, &mut upper, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        upper
    } else {
        // The lower middle is the largest of the elements left of n/2.
        let lower = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lower + upper)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn one_point_per_cell_with_the_median_displacement() {
        // 8×8 field, 2×2 cells of 4×4 pixels. Top-left cell: displacement (x, 0) for x = 0..3,
        // i.e. u values 0,1,2,3 on each row; component-wise median (1.5, 0) → the nearest points
        // have u = 1 or u = 2 (equal distance); the first in row-major order is (x=1, y=0).
        let (h, w) = (8, 8);
        let u = Array2::from_shape_fn((h, w), |(_, x)| (x % 4) as f32);
        let v = Array2::<f32>::zeros((h, w));
        let mask = Array2::from_elem((h, w), true);
        let s = grid_median_sample_cells(u.view(), v.view(), mask.view(), 1, 2);
        assert_eq!(s.len(), 4);
        assert_eq!(s[0].cell, [0, 0]);
        assert_eq!(s[0].count, 16);
        assert_eq!((s[0].point.x, s[0].point.y, s[0].point.u), (1.0, 0.0, 1.0));
        assert_eq!((s[1].point.x, s[1].point.y, s[1].point.u), (5.0, 0.0, 1.0));
        assert_eq!(s[3].cell, [1, 1]);
        assert_eq!((s[3].point.x, s[3].point.y), (5.0, 4.0));
    }

    #[test]
    fn outliers_nan_and_mask_are_respected() {
        // One 5×5 cell (sample = 1) of displacement (2, −1) with two gross outliers, a NaN and a
        // masked-out pixel carrying an absurd value: the representative must carry (2, −1).
        let mut u = Array2::from_elem((5, 5), 2.0f32);
        let mut v = Array2::from_elem((5, 5), -1.0f32);
        let mut mask = Array2::from_elem((5, 5), true);
        u[[0, 0]] = 50.0;
        v[[4, 4]] = -80.0;
        u[[2, 2]] = f32::NAN;
        u[[1, 1]] = 1e6;
        mask[[1, 1]] = false;
        let s = grid_median_sample_cells(u.view(), v.view(), mask.view(), 1, 1);
        assert_eq!(s.len(), 1);
        assert_eq!(s[0].count, 23);
        assert_eq!((s[0].point.u, s[0].point.v), (2.0, -1.0));
        // First valid inlier in row-major order is (1, 0).
        assert_eq!((s[0].point.x, s[0].point.y), (1.0, 0.0));
    }

    #[test]
    fn stride_lattice_is_anchored_at_the_mask_box() {
        // Mask covers x, y ∈ [3, 10]; stride 4 → lattice x, y ∈ {3, 7}.
        let u = Array2::from_shape_fn((12, 12), |(y, x)| (100 * y + x) as f32);
        let v = Array2::<f32>::zeros((12, 12));
        let mask = Array2::from_shape_fn((12, 12), |(y, x)| {
            (3..=10).contains(&x) && (3..=10).contains(&y)
        });
        let s = grid_median_sample(u.view(), v.view(), mask.view(), 4, 1);
        // u = 303, 307, 703, 707; median 505; nearest is 307 (|−198|) then 703 (198): tie → first.
        assert_eq!(s.len(), 1);
        assert_eq!((s[0].x, s[0].y, s[0].u), (7.0, 3.0, 307.0));
        assert_eq!(s[0].frame_point(), [314.0, 3.0]);
    }

    #[test]
    fn bad_arguments_give_nothing_rather_than_panic() {
        let a = Array2::<f32>::zeros((4, 4));
        let m = Array2::from_elem((4, 4), true);
        let m_small = Array2::from_elem((3, 4), true);
        let empty = Array2::from_elem((4, 4), false);
        assert!(grid_median_sample(a.view(), a.view(), m.view(), 0, 2).is_empty());
        assert!(grid_median_sample(a.view(), a.view(), m.view(), 1, 0).is_empty());
        assert!(grid_median_sample(a.view(), a.view(), m_small.view(), 1, 2).is_empty());
        assert!(grid_median_sample(a.view(), a.view(), empty.view(), 1, 2).is_empty());
        // More cells than pixels: empty cells are skipped, every pixel is its own cell.
        assert_eq!(
            grid_median_sample(a.view(), a.view(), m.view(), 1, 9).len(),
            16
        );
    }
}
