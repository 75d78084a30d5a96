//! The interpolating B-spline prefilter (recursive, whole-sample mirror) and the filling of
//! non-finite pixels before it.

use super::mirror;
use ndarray::{Array2, ArrayView2, ArrayViewMut2, Axis, Zip};
use rayon::prelude::*;

/// Pole of the cubic B-spline prefilter, √3 − 2.
const POLE: f64 = -0.267_949_192_431_122_7;
/// Beyond this many samples the pole's powers are below f64 precision (|z|^28 < 1e-16).
const HORIZON: usize = 30;

pub(super) fn non_finite_mask(src: &ArrayView2<f32>) -> Option<Array2<bool>> {
    if crate::stats::all_finite(src.view()) {
        None
    } else {
        Some(Zip::from(src).par_map_collect(|v| !v.is_finite()))
    }
}

/// `out[y, x]` = any `bad` within rows `y−before..=y+after` and the same columns, mirrored.
pub(super) fn dilate_support(bad: &Array2<bool>, before: isize, after: isize) -> Array2<bool> {
    let (h, w) = bad.dim();
    let along_x = Array2::from_shape_fn((h, w), |(y, x)| {
        (-before..=after).any(|d| bad[[y, mirror(x as isize + d, w)]])
    });
    Array2::from_shape_fn((h, w), |(y, x)| {
        (-before..=after).any(|d| along_x[[mirror(y as isize + d, h), x]])
    })
}

/// Replace the pixels flagged in `bad` with a smooth local mean (push-pull pyramid:
/// NaN-aware 2×2 means up to a level without holes, then bilinear back down).
pub(super) fn fill_non_finite(img: &mut Array2<f32>, bad: &Array2<bool>) {
    let mut levels: Vec<Array2<f64>> =
        vec![Zip::from(&*img)
            .and(bad)
            .map_collect(|&v, &b| if b { f64::NAN } else { v as f64 })];
    loop {
        let top = levels.last().expect("pyramid has a level");
        if !top.iter().any(|v| v.is_nan()) {
            break;
        }
        let (h, w) = top.dim();
        if h == 1 && w == 1 {
            // Nothing finite at all: a neutral constant, every output is masked anyway.
            levels.last_mut().expect("pyramid has a level")[[0, 0]] = 0.0;
            break;
        }
        let (nh, nw) = (h.div_ceil(2), w.div_ceil(2));
        let next = Array2::from_shape_fn((nh, nw), |(y, x)| {
            let (mut sum, mut n) = (0.0, 0u32);
            for yy in 2 * y..(2 * y + 2).min(h) {
                for xx in 2 * x..(2 * x + 2).min(w) {
                    let v = top[[yy, xx]];
                    if !v.is_nan() {
                        sum += v;
                        n += 1;
                    }
                }
            }
            if n > 0 {
                sum / n as f64
            } else {
                f64::NAN
            }
        });
        levels.push(next);
    }
    for k in (0..levels.len() - 1).rev() {
        let (upper, lower) = levels.split_at_mut(k + 1);
        let (fine, coarse) = (&mut upper[k], &lower[0]);
        let (ch, cw) = coarse.dim();
        for ((y, x), v) in fine.indexed_iter_mut() {
            if v.is_nan() {
                // Child pixel centre in parent coordinates.
                let py = ((y as f64 + 0.5) / 2.0 - 0.5).clamp(0.0, ch as f64 - 1.0);
                let px = ((x as f64 + 0.5) / 2.0 - 0.5).clamp(0.0, cw as f64 - 1.0);
                let (y0, x0) = (py.floor() as usize, px.floor() as usize);
                let (y1, x1) = ((y0 + 1).min(ch - 1), (x0 + 1).min(cw - 1));
                let (ty, tx) = (py - y0 as f64, px - x0 as f64);
                *v = (coarse[[y0, x0]] * (1.0 - tx) + coarse[[y0, x1]] * tx) * (1.0 - ty)
                    + (coarse[[y1, x0]] * (1.0 - tx) + coarse[[y1, x1]] * tx) * ty;
            }
        }
    }
    Zip::from(img)
        .and(&levels[0])
        .for_each(|v, &f| *v = f as f32);
}

/// Exact causal initial values for the mirror boundary (scipy's `_init_causal_mirror`), per
/// lane, truncated after `horizon` samples, where the pole's powers vanish in f64.
#[inline(always)]
fn init_causal_mirror<const L: usize>(c: &[[f64; L]], z: f64, horizon: usize) -> [f64; L] {
    let n = c.len();
    if n > horizon {
        let mut acc = c[0];
        let mut zi = z;
        for v in &c[1..horizon] {
            for l in 0..L {
                acc[l] += zi * v[l];
            }
            zi *= z;
        }
        return acc;
    }
    let zn1 = z.powi(n as i32 - 1);
    let mut acc: [f64; L] = std::array::from_fn(|l| c[0][l] + zn1 * c[n - 1][l]);
    let mut zi = z;
    for i in 1..n - 1 {
        for l in 0..L {
            acc[l] += zi * (c[i][l] + zn1 * c[n - 1 - i][l]);
        }
        zi *= z;
    }
    acc.map(|a| a / (1.0 - zn1 * zn1))
}

/// One causal and one anti-causal recursion of pole `z` (mirror boundary) along `L`
/// interleaved lines, `c[i][l]` being sample `i` of line `l`. Each line is one long chain of
/// dependent multiply-adds; run side by side, they fill the vector units instead of waiting
/// on each other's latency. Per line, the arithmetic is that of a single line.
#[inline(always)]
fn apply_pole<const L: usize>(c: &mut [[f64; L]], z: f64, horizon: usize) {
    let n = c.len();
    c[0] = init_causal_mirror(c, z, horizon);
    for i in 1..n {
        let prev = c[i - 1];
        for l in 0..L {
            c[i][l] += z * prev[l];
        }
    }
    let before_last = c[n - 2];
    for (last, before) in c[n - 1].iter_mut().zip(before_last) {
        *last = (z * before + *last) * z / (z * z - 1.0);
    }
    for i in (0..n - 1).rev() {
        let next = c[i + 1];
        for l in 0..L {
            c[i][l] = z * (next[l] - c[i][l]);
        }
    }
}

/// A B-spline prefilter: its gain and its poles with their horizons.
#[derive(Clone, Copy)]
pub(super) struct Prefilter {
    pub(super) gain: f64,
    pub(super) poles: &'static [(f64, usize)],
}

/// The cubic B-spline's (gain 6, one pole).
pub(super) const CUBIC_PREFILTER: Prefilter = Prefilter {
    gain: 6.0,
    poles: &[(POLE, HORIZON)],
};

impl Prefilter {
    /// In place along `L` interleaved lines.
    #[inline(always)]
    fn lanes<const L: usize>(self, c: &mut [[f64; L]]) {
        if c.len() < 2 {
            return;
        }
        c.iter_mut().flatten().for_each(|v| *v *= self.gain);
        for &(z, horizon) in self.poles {
            apply_pole(c, z, horizon);
        }
    }
}

/// Rows per block in the horizontal pass, interleaved.
const ROW_BLOCK: usize = 8;
/// Columns per block in the vertical pass: contiguous reads, several lanes at once.
const COLUMN_BLOCK: usize = 32;

crate::flow::simd::multiversion!(fn filter_rows(
    filter: Prefilter,
    block: &mut [[f64; ROW_BLOCK]],
) => filter_rows_body);

#[inline(always)]
fn filter_rows_body(filter: Prefilter, block: &mut [[f64; ROW_BLOCK]]) {
    filter.lanes(block);
}

crate::flow::simd::multiversion!(fn filter_columns(
    filter: Prefilter,
    block: &mut [[f64; COLUMN_BLOCK]],
) => filter_columns_body);

#[inline(always)]
fn filter_columns_body(filter: Prefilter, block: &mut [[f64; COLUMN_BLOCK]]) {
    filter.lanes(block);
}

/// Separable prefilter: blocks of rows in parallel, then blocks of columns in parallel, each
/// block's lines interleaved in an f64 scratch.
pub(super) fn prefilter(img: &mut Array2<f32>, filter: Prefilter) {
    let (h, w) = img.dim();
    if w >= 2 {
        img.axis_chunks_iter_mut(Axis(0), ROW_BLOCK)
            .into_par_iter()
            .for_each(|rows| filter_block(rows.reversed_axes(), filter, filter_rows));
    }
    if h >= 2 {
        img.axis_chunks_iter_mut(Axis(1), COLUMN_BLOCK)
            .into_par_iter()
            .for_each(|columns| filter_block(columns, filter, filter_columns));
    }
}

/// Filter the lines of `block`, indexed `[position along the line, line]` (at most `L` lines;
/// the scratch's spare lanes stay zero), through `run`.
fn filter_block<const L: usize>(
    mut block: ArrayViewMut2<f32>,
    filter: Prefilter,
    run: fn(Prefilter, &mut [[f64; L]]),
) {
    let mut lanes = vec![[0.0f64; L]; block.nrows()];
    for (lane, line) in lanes.iter_mut().zip(block.rows()) {
        for (slot, v) in lane.iter_mut().zip(line) {
            *slot = *v as f64;
        }
    }
    run(filter, &mut lanes);
    for (lane, mut line) in lanes.iter().zip(block.rows_mut()) {
        for (slot, v) in lane.iter().zip(line.iter_mut()) {
            *v = *slot as f32;
        }
    }
}
