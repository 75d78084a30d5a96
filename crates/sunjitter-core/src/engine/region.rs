//! Where on the reference grid a stage works: the mask's bounding box, crops grown by a
//! filter's reach, pixels whose neighbourhood is all valid.

use crate::flow::Roi;
use ndarray::Array2;
use std::ops::Range;

/// Reach of `preprocess::gaussian_smooth` at σ = `sigma_px` (its truncation radius) plus one
/// pixel for a central difference; 0 when it does nothing.
pub(super) fn gaussian_reach(sigma_px: f64) -> usize {
    if sigma_px > 0.0 && sigma_px.is_finite() {
        (4.0 * sigma_px + 0.5) as usize + 1
    } else {
        0
    }
}

/// Pixels whose `(2r+1)²` neighbourhood lies entirely inside the image and inside `valid`.
/// Separable, with running counts: two boolean arrays the image's size and nothing larger.
pub(super) fn erode(valid: &Array2<bool>, r: usize) -> Array2<bool> {
    use ndarray::Axis;
    use rayon::prelude::*;
    let (h, w) = valid.dim();
    let mut out = Array2::from_elem((h, w), false);
    if 2 * r + 1 > w || 2 * r + 1 > h {
        return out;
    }
    // Across: the whole span [x − r, x + r] of the row is valid.
    let mut across = Array2::from_elem((h, w), false);
    across
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(valid.axis_iter(Axis(0)))
        .for_each(|(mut o, row)| {
            let mut invalid = row.iter().take(2 * r).filter(|v| !**v).count();
            for x in r..w - r {
                invalid += usize::from(!row[x + r]);
                o[x] = invalid == 0;
                invalid -= usize::from(!row[x - r]);
            }
        });
    // Down: the whole span [y − r, y + r] of the column is valid across; strips of columns,
    // each with its running counts.
    const STRIP: usize = 256;
    out.axis_chunks_iter_mut(Axis(1), STRIP)
        .into_par_iter()
        .zip(across.axis_chunks_iter(Axis(1), STRIP))
        .for_each(|(mut o, a)| {
            let mut invalid = vec![0usize; a.ncols()];
            for row in a.rows().into_iter().take(2 * r) {
                for (n, v) in invalid.iter_mut().zip(row) {
                    *n += usize::from(!*v);
                }
            }
            for y in r..h - r {
                for (n, v) in invalid.iter_mut().zip(a.row(y + r)) {
                    *n += usize::from(!*v);
                }
                for ((d, n), v) in o.row_mut(y).iter_mut().zip(&mut invalid).zip(a.row(y - r)) {
                    *d = *n == 0;
                    *n -= usize::from(!*v);
                }
            }
        });
    out
}

/// Rows and columns of `roi` grown by the reach of a Gaussian of `sigma_px` as
/// `preprocess::gaussian_smooth` truncates it, plus one pixel for a central difference,
/// clamped to the `w × h` image: inside `roi` such filters give the same values on this crop
/// as on the whole image.
pub(super) fn grown(roi: Roi, sigma_px: f64, w: usize, h: usize) -> (Range<usize>, Range<usize>) {
    let reach = gaussian_reach(sigma_px);
    (
        roi.y.saturating_sub(reach)..(roi.y + roi.height + reach).min(h),
        roi.x.saturating_sub(reach)..(roi.x + roi.width + reach).min(w),
    )
}

/// The bounding box of the mask's pixels; the whole grid when it has none.
pub(super) fn mask_roi(mask: &Array2<bool>) -> Roi {
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
