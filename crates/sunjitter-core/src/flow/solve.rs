//! One Farneback iteration over a level: update the per-pixel normal equations from the current
//! flow (OpenCV `FarnebackUpdateMatrices`), average them over the window (box via running sums,
//! or the separable Gaussian), and solve the 2×2 system per pixel.
//!
//! The three steps are fused and streamed row by row inside horizontal strips: a strip keeps a
//! ring of the `2m+2` matrix rows its vertical window needs, so the 5-channel matrix image is
//! never stored whole (memory and bandwidth stay small). Strips run in parallel with rayon; each
//! recomputes the `m` rows of halo it shares with its neighbours, which keeps the iteration a
//! plain Jacobi step (identical to OpenCV's, whose in-place update never reads a row it changed).

use super::simd;
use rayon::prelude::*;

/// OpenCV's border taper for the 5 outermost pixels of a level.
const BORDER: [f32; 5] = [0.14, 0.14, 0.4472, 0.4472, 0.4472];

/// Everything an iteration needs about the level, read-only.
pub(crate) struct Level<'a> {
    /// Domain size.
    pub h: usize,
    pub w: usize,
    /// Domain's first row and the level's height (for OpenCV's border taper at true edges).
    pub y0: usize,
    pub level_h: usize,
    pub r0: &'a [f32],
    pub r1: &'a [f32],
    /// OpenCV's border taper per domain column.
    pub col_taper: &'a [f32],
    /// Half window.
    pub m: usize,
    /// Gaussian window kernel (`m+1` taps, centre first); `None` = box window.
    pub gauss: Option<&'a [f32]>,
    /// Tikhonov term added to the averaged matrix's diagonal: `reg_abs + reg_rel·trace`.
    pub reg_abs: f64,
    pub reg_rel: f64,
    /// Averaged trace below which a window holds no data (→ NaN on the last iteration).
    pub empty_trace: f64,
}

/// Per-strip working memory, reused across iterations and frames.
#[derive(Default)]
pub(crate) struct StripScratch {
    ring: Vec<f32>,
    ring_row: Vec<usize>,
    vsum: Vec<f64>,
    pad: Vec<f64>,
    hsum: Vec<f64>,
    vconv: Vec<f32>,
    hconv: Vec<f32>,
}

#[inline]
fn taper(pos: usize, len: usize) -> f32 {
    let mut s = 1.0;
    if pos < 5 {
        s *= BORDER[pos];
    }
    if pos + 5 >= len {
        s *= BORDER[len - pos - 1];
    }
    s
}

/// OpenCV's taper for every column of the domain (1 away from the level's true edges).
pub(crate) fn column_taper(x0: usize, w: usize, level_w: usize) -> Vec<f32> {
    (0..w).map(|x| taper(x0 + x, level_w)).collect()
}

const LANES: usize = 8;

/// Normal-equation row `y` (5 planes of `w`: G11, G12, G22, h1, h2 in (y, x) order) from the
/// current flow `u`, `v` of that row. Missing data (NaN expansion at the pixel, or at the place
/// the flow points to, or that place outside the domain) gets zero weight.
///
/// Pixels go by groups of 8; when the flow's integer part is the same across a group (the
/// usual case: flow is smooth) the bilinear taps are contiguous loads and the group is
/// computed as straight-line lane arithmetic the compiler vectorises.
#[inline(always)]
pub(crate) fn matrices_row(lv: &Level, y: usize, u: &[f32], v: &[f32], out: &mut [f32]) {
    let (w, h) = (lv.w, lv.h);
    let gy = lv.y0 + y;
    let row_taper = if gy < 5 || gy + 5 >= lv.level_h {
        taper(gy, lv.level_h)
    } else {
        1.0
    };
    let (o0, rest) = out.split_at_mut(w);
    let (o1, rest) = rest.split_at_mut(w);
    let (o2, rest) = rest.split_at_mut(w);
    let (o3, o4) = rest.split_at_mut(w);
    let o4 = &mut o4[..w];
    // Expansions are stored row by row, the 5 channels of a row one after the other.
    let stride = 5 * w;
    let q: [&[f32]; 5] = std::array::from_fn(|c| &lv.r0[y * stride + c * w..][..w]);
    let r1 = lv.r1;
    let yf = y as f32;
    let mut x = 0;
    while x < w {
        let n = LANES.min(w - x);
        // The group's flow, expansion and taper, lane by lane; a group cut by the row's end
        // repeats its last pixel. Whole groups are contiguous loads.
        let mut du = [0f32; LANES];
        let mut dv = [0f32; LANES];
        let mut q8 = [[0f32; LANES]; 5];
        let mut ct = [0f32; LANES];
        if n == LANES {
            du.copy_from_slice(&u[x..x + LANES]);
            dv.copy_from_slice(&v[x..x + LANES]);
            for (qc, src) in q8.iter_mut().zip(&q) {
                qc.copy_from_slice(&src[x..x + LANES]);
            }
            ct.copy_from_slice(&lv.col_taper[x..x + LANES]);
        } else {
            for i in 0..LANES {
                let j = (x + i).min(w - 1);
                du[i] = u[j];
                dv[i] = v[j];
                for c in 0..5 {
                    q8[c][i] = q[c][j];
                }
                ct[i] = lv.col_taper[j];
            }
        }
        let mut fx = [0f32; LANES];
        let mut fy = [0f32; LANES];
        let mut ixs = [0i32; LANES];
        let mut iys = [0i32; LANES];
        for i in 0..LANES {
            let px = (x + i) as f32 + du[i];
            let py = yf + dv[i];
            let flx = floor_fast(px);
            let fly = floor_fast(py);
            fx[i] = px - flx;
            fy[i] = py - fly;
            ixs[i] = flx as i32;
            iys[i] = fly as i32;
        }
        let off = ixs[0] - x as i32;
        let row = iys[0];
        let uniform = n == LANES
            && (0..LANES).all(|i| ixs[i] - (x + i) as i32 == off && iys[i] == row)
            && ixs[0] >= 0
            && ixs[LANES - 1] < w as i32 - 1
            && row >= 0
            && row < h as i32 - 1;
        // Interpolated R1 channels per lane.
        let mut s = [[0f32; LANES]; 5];
        if uniform {
            for (c, sc) in s.iter_mut().enumerate() {
                let base = row as usize * stride + c * w + ixs[0] as usize;
                let top = &r1[base..base + LANES + 1];
                let bot = &r1[base + stride..base + stride + LANES + 1];
                for i in 0..LANES {
                    let t = top[i] + fx[i] * (top[i + 1] - top[i]);
                    let b = bot[i] + fx[i] * (bot[i + 1] - bot[i]);
                    sc[i] = t + fy[i] * (b - t);
                }
            }
        } else {
            for i in 0..n {
                let (ix, iy) = (ixs[i], iys[i]);
                let inside = ix >= 0 && iy >= 0 && ix < w as i32 - 1 && iy < h as i32 - 1;
                for (c, sc) in s.iter_mut().enumerate() {
                    sc[i] = if inside {
                        let p = iy as usize * stride + c * w + ix as usize;
                        let pl = r1;
                        let t = pl[p] + fx[i] * (pl[p + 1] - pl[p]);
                        let b = pl[p + stride] + fx[i] * (pl[p + stride + 1] - pl[p + stride]);
                        t + fy[i] * (b - t)
                    } else {
                        f32::NAN
                    };
                }
            }
        }
        // Lane arithmetic on fixed-size arrays (vectorised), then store the valid lanes.
        let tp = ct.map(|c| row_taper * c);
        let mut mo = [[0f32; LANES]; 5];
        for i in 0..LANES {
            let (dx, dy) = (du[i], dv[i]);
            let r4 = (q8[2][i] + s[2][i]) * 0.5;
            let r5 = (q8[3][i] + s[3][i]) * 0.5;
            let r6 = (q8[4][i] + s[4][i]) * 0.25;
            let r2 = (q8[0][i] - s[0][i]) * 0.5 + r4 * dy + r6 * dx;
            let r3 = (q8[1][i] - s[1][i]) * 0.5 + r6 * dy + r5 * dx;
            let t = tp[i];
            let (r2, r3, r4, r5, r6) = (r2 * t, r3 * t, r4 * t, r5 * t, r6 * t);
            let m = [
                r4 * r4 + r6 * r6,
                (r4 + r5) * r6,
                r5 * r5 + r6 * r6,
                r4 * r2 + r6 * r3,
                r6 * r2 + r5 * r3,
            ];
            // NaN anywhere (missing data, outside) means zero weight.
            let sum = m[0] + m[1] + m[2] + m[3] + m[4];
            let keep = !sum.is_nan();
            for c in 0..5 {
                mo[c][i] = if keep { m[c] } else { 0.0 };
            }
        }
        for (c, o) in [&mut *o0, &mut *o1, &mut *o2, &mut *o3, &mut *o4]
            .into_iter()
            .enumerate()
        {
            o[x..x + n].copy_from_slice(&mo[c][..n]);
        }
        x += n;
    }
}

/// Mean trace of the normal matrices at zero flow from `R0` alone: the level's typical
/// "texture energy", the unit in which the regulariser is expressed (scale-free).
pub(crate) fn typical_trace(r0: &[f32], w: usize) -> f64 {
    let (sum, count) = r0
        .par_chunks(5 * w)
        .map(|row| {
            let (a, b, e) = (&row[2 * w..3 * w], &row[3 * w..4 * w], &row[4 * w..5 * w]);
            let mut s = 0f64;
            let mut n = 0usize;
            for i in 0..w {
                let (a, b, e) = (a[i] as f64, b[i] as f64, e[i] as f64 * 0.5);
                let t = a * a + b * b + 2.0 * e * e;
                if t.is_finite() {
                    s += t;
                    n += 1;
                }
            }
            (s, n)
        })
        .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if count == 0 {
        0.0
    } else {
        sum / count as f64
    }
}

/// Solve the averaged 2×2 system for one row; `sums` holds the 5 window-sum planes (`w` each).
#[inline(always)]
fn solve_row(lv: &Level, sums: &[f64], scale: f64, u: &mut [f32], v: &mut [f32], last: bool) {
    let w = u.len();
    let (s0, s1, s2, s3, s4) = (
        &sums[..w],
        &sums[w..2 * w],
        &sums[2 * w..3 * w],
        &sums[3 * w..4 * w],
        &sums[4 * w..5 * w],
    );
    let empty = if last {
        lv.empty_trace
    } else {
        f64::NEG_INFINITY
    };
    for x in 0..w {
        let g11 = s0[x] * scale;
        let g12 = s1[x] * scale;
        let g22 = s2[x] * scale;
        let h1 = s3[x] * scale;
        let h2 = s4[x] * scale;
        let tr = g11 + g22;
        let l = lv.reg_abs + lv.reg_rel * tr;
        let (a, c) = (g11 + l, g22 + l);
        let idet = 1.0 / (a * c - g12 * g12);
        let uu = ((a * h2 - g12 * h1) * idet) as f32;
        let vv = ((c * h1 - g12 * h2) * idet) as f32;
        let gone = tr <= empty;
        u[x] = if gone { f32::NAN } else { uu };
        v[x] = if gone { f32::NAN } else { vv };
    }
}

/// Row strips for parallel work: enough to keep every thread busy, few enough that the halo
/// (2m rows recomputed per strip) stays a small fraction.
pub(crate) fn strips(h: usize, m: usize) -> Vec<(usize, usize)> {
    let threads = rayon::current_num_threads().max(1);
    let min_rows = (4 * (2 * m + 1)).max(16);
    let n = (h / min_rows).clamp(1, 2 * threads);
    let n = if n > threads && n < 2 * threads {
        threads
    } else {
        n
    };
    (0..n).map(|i| (i * h / n, (i + 1) * h / n)).collect()
}

/// A flow field's two components on a level, row-major, as an iteration reads them.
#[derive(Clone, Copy)]
pub(crate) struct FieldView<'a> {
    pub(crate) u: &'a [f32],
    pub(crate) v: &'a [f32],
}

/// A flow field's two components (or the rows of a strip of them), as an iteration writes them.
pub(crate) struct FieldMut<'a> {
    pub(crate) u: &'a mut [f32],
    pub(crate) v: &'a mut [f32],
}

/// One iteration: the new flow from the old one. `last` marks the final iteration of the
/// finest level (empty windows become NaN).
pub(crate) fn iterate(
    lv: &Level,
    old: FieldView,
    new: FieldMut,
    scratch: &mut Vec<StripScratch>,
    last: bool,
) {
    let (u_new, v_new) = (new.u, new.v);
    let w = lv.w;
    let bounds = strips(lv.h, lv.m);
    if scratch.len() < bounds.len() {
        scratch.resize_with(bounds.len(), StripScratch::default);
    }
    // Split output rows into the strips' disjoint chunks.
    let mut u_parts = Vec::with_capacity(bounds.len());
    let mut v_parts = Vec::with_capacity(bounds.len());
    let (mut ur, mut vr) = (u_new, v_new);
    for &(a, b) in &bounds {
        let (uh, ut) = ur.split_at_mut((b - a) * w);
        let (vh, vt) = vr.split_at_mut((b - a) * w);
        u_parts.push(uh);
        v_parts.push(vh);
        ur = ut;
        vr = vt;
    }
    bounds
        .par_iter()
        .zip(scratch.par_iter_mut())
        .zip(u_parts.into_par_iter().zip(v_parts.into_par_iter()))
        .for_each(|((&(ya, yb), sc), (uo, vo))| {
            run_strip_mv(lv, old, (ya, yb), FieldMut { u: uo, v: vo }, sc, last);
        });
}

simd::multiversion!(fn run_strip_mv(
    lv: &Level,
    old: FieldView,
    rows: (usize, usize),
    out: FieldMut,
    sc: &mut StripScratch,
    last: bool,
) => run_strip);

/// Make sure matrix row `c` is in the ring; returns its slot.
#[inline(always)]
fn ensure_row(
    lv: &Level,
    u_old: &[f32],
    v_old: &[f32],
    sc: &mut StripScratch,
    c: usize,
    slots: usize,
) -> usize {
    let (w, rw) = (lv.w, lv.w * 5);
    let slot = c % slots;
    if sc.ring_row[slot] != c {
        let (u, v) = (&u_old[c * w..][..w], &v_old[c * w..][..w]);
        matrices_row(lv, c, u, v, &mut sc.ring[slot * rw..][..rw]);
        sc.ring_row[slot] = c;
    }
    slot
}

/// Floor that compiles to plain instructions on any x86-64 (|x| < 2³¹).
#[inline(always)]
fn floor_fast(x: f32) -> f32 {
    let t = x as i32 as f32;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// Rows `rows.0 .. rows.1` of the new flow, into `out` (those rows only).
#[inline(always)]
fn run_strip(
    lv: &Level,
    old: FieldView,
    rows: (usize, usize),
    out: FieldMut,
    sc: &mut StripScratch,
    last: bool,
) {
    let FieldView { u: u_old, v: v_old } = old;
    let FieldMut { u: u_out, v: v_out } = out;
    let (ya, yb) = rows;
    let (w, h, m) = (lv.w, lv.h, lv.m);
    let slots = 2 * m + 2;
    let rw = w * 5;
    sc.ring.resize(slots * rw, 0.0);
    sc.ring_row.clear();
    sc.ring_row.resize(slots, usize::MAX);
    let clamp = |r: isize| r.clamp(0, h as isize - 1) as usize;
    let ensure = |sc: &mut StripScratch, c: usize| ensure_row(lv, u_old, v_old, sc, c, slots);
    let wp = w + 2 * m + 1;
    match lv.gauss {
        None => {
            let scale = 1.0 / ((2 * m + 1) * (2 * m + 1)) as f64;
            sc.vsum.clear();
            sc.vsum.resize(rw, 0.0);
            for t in -(m as isize)..=(m as isize) {
                let slot = ensure(sc, clamp(ya as isize + t));
                let row = &sc.ring[slot * rw..][..rw];
                for (acc, &val) in sc.vsum.iter_mut().zip(row) {
                    *acc += val as f64;
                }
            }
            sc.pad.resize(5 * wp, 0.0);
            sc.hsum.resize(rw, 0.0);
            for y in ya..yb {
                // Replicate-padded vertical sums, then a running horizontal sum (5 chains).
                for c in 0..5 {
                    let src = &sc.vsum[c * w..][..w];
                    let dst = &mut sc.pad[c * wp..][..wp];
                    dst[..m].iter_mut().for_each(|d| *d = src[0]);
                    dst[m..m + w].copy_from_slice(src);
                    dst[m + w..].iter_mut().for_each(|d| *d = src[w - 1]);
                }
                {
                    let pad = &sc.pad;
                    let p: [&[f64]; 5] = std::array::from_fn(|c| &pad[c * wp..][..wp]);
                    let mut acc = [0f64; 5];
                    for (c, a) in acc.iter_mut().enumerate() {
                        *a = p[c][..2 * m + 1].iter().sum();
                    }
                    let (h0, rest) = sc.hsum.split_at_mut(w);
                    let (h1, rest) = rest.split_at_mut(w);
                    let (h2, rest) = rest.split_at_mut(w);
                    let (h3, h4) = rest.split_at_mut(w);
                    for x in 0..w {
                        h0[x] = acc[0];
                        h1[x] = acc[1];
                        h2[x] = acc[2];
                        h3[x] = acc[3];
                        h4[x] = acc[4];
                        let (add, sub) = (x + 2 * m + 1, x);
                        if add < wp {
                            for c in 0..5 {
                                acc[c] += p[c][add] - p[c][sub];
                            }
                        }
                    }
                }
                let r = y - ya;
                solve_row(
                    lv,
                    &sc.hsum,
                    scale,
                    &mut u_out[r * w..][..w],
                    &mut v_out[r * w..][..w],
                    last,
                );
                if y + 1 < yb {
                    let add = ensure(sc, clamp(y as isize + 1 + m as isize));
                    let sub = ensure(sc, clamp(y as isize - m as isize));
                    let (ring, vsum) = (&sc.ring, &mut sc.vsum);
                    let ra = &ring[add * rw..][..rw];
                    let rs = &ring[sub * rw..][..rw];
                    for ((acc, &a), &s) in vsum.iter_mut().zip(ra).zip(rs) {
                        *acc += a as f64 - s as f64;
                    }
                }
            }
        }
        Some(kernel) => {
            let wg = w + 2 * m;
            sc.vconv.resize(5 * wg, 0.0);
            sc.hconv.resize(rw, 0.0);
            sc.hsum.resize(rw, 0.0);
            for y in ya..yb {
                for t in -(m as isize)..=(m as isize) {
                    ensure(sc, clamp(y as isize + t));
                }
                // Vertical convolution into replicate-padded planar rows.
                for c in 0..5 {
                    let dst = &mut sc.vconv[c * wg + m..][..w];
                    let c0 = clamp(y as isize) % slots;
                    let k0 = kernel[0];
                    for (d, &s) in dst.iter_mut().zip(&sc.ring[c0 * rw + c * w..][..w]) {
                        *d = s * k0;
                    }
                    for (i, &ki) in kernel.iter().enumerate().skip(1) {
                        let a = clamp(y as isize + i as isize) % slots;
                        let b = clamp(y as isize - i as isize) % slots;
                        let ra = &sc.ring[a * rw + c * w..][..w];
                        let rb = &sc.ring[b * rw + c * w..][..w];
                        for ((d, &p), &q) in dst.iter_mut().zip(ra).zip(rb) {
                            *d += ki * (p + q);
                        }
                    }
                    let row = &mut sc.vconv[c * wg..][..wg];
                    let (first, lastv) = (row[m], row[m + w - 1]);
                    row[..m].iter_mut().for_each(|d| *d = first);
                    row[m + w..].iter_mut().for_each(|d| *d = lastv);
                    // Horizontal convolution.
                    let hc = &mut sc.hconv[c * w..][..w];
                    for (hv, &a) in hc.iter_mut().zip(&row[m..m + w]) {
                        *hv = a * k0;
                    }
                    for (t, &kt) in kernel.iter().enumerate().skip(1) {
                        let l = &row[m - t..][..w];
                        let r = &row[m + t..][..w];
                        for ((hv, &a), &b) in hc.iter_mut().zip(l).zip(r) {
                            *hv += kt * (a + b);
                        }
                    }
                }
                for (p, &hv) in sc.hsum.iter_mut().zip(&sc.hconv) {
                    *p = hv as f64;
                }
                let r = y - ya;
                solve_row(
                    lv,
                    &sc.hsum,
                    1.0,
                    &mut u_out[r * w..][..w],
                    &mut v_out[r * w..][..w],
                    last,
                );
            }
        }
    }
}

/// OpenCV's Gaussian window: σ = 0.3·m, taps `0..=m`, normalised over `−m..=m`.
pub(crate) fn gaussian_window(m: usize) -> Vec<f32> {
    let sigma = m as f64 * 0.3;
    let mut k = vec![1f64];
    let mut s = 1f64;
    for i in 1..=m {
        let t = (-((i * i) as f64) / (2.0 * sigma * sigma)).exp() as f32 as f64;
        k.push(t);
        s += 2.0 * t;
    }
    k.iter().map(|v| (v / s) as f32).collect()
}
