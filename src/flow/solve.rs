//! One Farneback iteration over a level: update the per-pixel normal equations from the current
//! flow (OpenCV `FarnebackUpdateMatrices`), average them over the window (box via running sums,
//! or the separable Gaussian), and solve the 2×2 system per pixel.
//!
//! The three steps are fused and streamed row by row inside horizontal strips: a strip keeps a
//! ring of the `2m+2` matrix rows its vertical window needs, so the 5-channel matrix image is
//! never stored whole (memory and bandwidth stay small). Strips run in parallel with rayon; each
//! recomputes the `m` rows of halo it shares with its neighbours, which keeps the iteration a
//! plain Jacobi step (identical to OpenCV's, whose in-place update never reads a row it changed).

use rayon::prelude::*;

/// OpenCV's border taper for the 5 outermost pixels of a level.
const BORDER: [f32; 5] = [0.14, 0.14, 0.4472, 0.4472, 0.4472];

/// Everything an iteration needs about the level, read-only.
pub(crate) struct Level<'a> {
    /// Domain size.
    pub h: usize,
    pub w: usize,
    /// Domain origin and whole level size (for OpenCV's border taper at true image edges).
    pub y0: usize,
    pub x0: usize,
    pub level_h: usize,
    pub level_w: usize,
    pub r0: &'a [f32],
    pub r1: &'a [f32],
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

/// Normal-equation row `y` (5 channels per pixel: G11, G12, G22, h1, h2 in (y, x) order)
/// from the current flow `u`, `v` of that row. Missing data (NaN expansion at the pixel, or at
/// the place the flow points to, or that place outside the domain) gets zero weight.
fn matrices_row(lv: &Level, y: usize, u: &[f32], v: &[f32], out: &mut [f32]) {
    let w = lv.w;
    let r0row = &lv.r0[y * w * 5..][..w * 5];
    let r1 = lv.r1;
    let gy = lv.y0 + y;
    let row_taper = if gy < 5 || gy + 5 >= lv.level_h {
        taper(gy, lv.level_h)
    } else {
        1.0
    };
    let stride = w * 5;
    let yf = y as f32;
    for x in 0..w {
        let (dx, dy) = (u[x], v[x]);
        let fx = x as f32 + dx;
        let fy = yf + dy;
        let x1 = fx.floor();
        let y1 = fy.floor();
        let ax = fx - x1;
        let ay = fy - y1;
        let (ix, iy) = (x1 as isize, y1 as isize);
        let q = &r0row[x * 5..x * 5 + 5];
        let o = &mut out[x * 5..x * 5 + 5];
        let inside = ix >= 0 && iy >= 0 && (ix as usize) < w - 1 && (iy as usize) < lv.h - 1;
        if !inside || q[0].is_nan() {
            o.iter_mut().for_each(|v| *v = 0.0);
            continue;
        }
        let p = (iy as usize) * stride + (ix as usize) * 5;
        let a00 = (1.0 - ax) * (1.0 - ay);
        let a01 = ax * (1.0 - ay);
        let a10 = (1.0 - ax) * ay;
        let a11 = ax * ay;
        let s = |c: usize| {
            a00 * r1[p + c] + a01 * r1[p + 5 + c] + a10 * r1[p + stride + c] + a11 * r1[p + stride + 5 + c]
        };
        let (mut r2, mut r3, mut r4, mut r5, mut r6) = (s(0), s(1), s(2), s(3), s(4));
        if r2.is_nan() {
            o.iter_mut().for_each(|v| *v = 0.0);
            continue;
        }
        r4 = (q[2] + r4) * 0.5;
        r5 = (q[3] + r5) * 0.5;
        r6 = (q[4] + r6) * 0.25;
        r2 = (q[0] - r2) * 0.5;
        r3 = (q[1] - r3) * 0.5;
        r2 += r4 * dy + r6 * dx;
        r3 += r6 * dy + r5 * dx;
        let gx = lv.x0 + x;
        let mut t = row_taper;
        if gx < 5 || gx + 5 >= lv.level_w {
            t *= taper(gx, lv.level_w);
        }
        if t != 1.0 {
            r2 *= t;
            r3 *= t;
            r4 *= t;
            r5 *= t;
            r6 *= t;
        }
        o[0] = r4 * r4 + r6 * r6;
        o[1] = (r4 + r5) * r6;
        o[2] = r5 * r5 + r6 * r6;
        o[3] = r4 * r2 + r6 * r3;
        o[4] = r6 * r2 + r5 * r3;
    }
}

/// Mean trace of the normal matrices at zero flow from `R0` alone: the level's typical
/// "texture energy", the unit in which the regulariser is expressed (scale-free).
pub(crate) fn typical_trace(r0: &[f32]) -> f64 {
    let (sum, count) = r0
        .par_chunks(5 * 1024)
        .map(|c| {
            let mut s = 0f64;
            let mut n = 0usize;
            for q in c.chunks_exact(5) {
                if q[0].is_finite() {
                    let (a, b, e) = (q[2] as f64, q[3] as f64, q[4] as f64 * 0.5);
                    s += a * a + b * b + 2.0 * e * e;
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

/// Solve the averaged 2×2 system for one row; `sums` holds the window-averaged 5 channels.
#[inline]
fn solve_row(lv: &Level, sums: &[f64], scale: f64, u: &mut [f32], v: &mut [f32], last: bool) {
    for x in 0..u.len() {
        let s = &sums[x * 5..x * 5 + 5];
        let g11 = s[0] * scale;
        let g12 = s[1] * scale;
        let g22 = s[2] * scale;
        let h1 = s[3] * scale;
        let h2 = s[4] * scale;
        let tr = g11 + g22;
        if last && tr <= lv.empty_trace {
            u[x] = f32::NAN;
            v[x] = f32::NAN;
            continue;
        }
        let l = lv.reg_abs + lv.reg_rel * tr;
        let (a, c) = (g11 + l, g22 + l);
        let idet = 1.0 / (a * c - g12 * g12);
        u[x] = ((a * h2 - g12 * h1) * idet) as f32;
        v[x] = ((c * h1 - g12 * h2) * idet) as f32;
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

/// One iteration: new flow (`u_new`, `v_new`) from the old one. `last` marks the level's final
/// iteration of the finest level (empty windows become NaN).
#[allow(clippy::too_many_arguments)]
pub(crate) fn iterate(
    lv: &Level,
    u_old: &[f32],
    v_old: &[f32],
    u_new: &mut [f32],
    v_new: &mut [f32],
    scratch: &mut Vec<StripScratch>,
    last: bool,
) {
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
            run_strip(lv, u_old, v_old, ya, yb, uo, vo, sc, last);
        });
}

#[allow(clippy::too_many_arguments)]
fn run_strip(
    lv: &Level,
    u_old: &[f32],
    v_old: &[f32],
    ya: usize,
    yb: usize,
    u_out: &mut [f32],
    v_out: &mut [f32],
    sc: &mut StripScratch,
    last: bool,
) {
    let (w, h, m) = (lv.w, lv.h, lv.m);
    let slots = 2 * m + 2;
    let rw = w * 5;
    sc.ring.resize(slots * rw, 0.0);
    sc.ring_row.clear();
    sc.ring_row.resize(slots, usize::MAX);
    let clamp = |r: isize| r.clamp(0, h as isize - 1) as usize;
    // Make sure matrix row `c` is in the ring.
    let ensure = |sc: &mut StripScratch, c: usize| {
        let slot = c % slots;
        if sc.ring_row[slot] != c {
            let (u, v) = (&u_old[c * w..][..w], &v_old[c * w..][..w]);
            matrices_row(lv, c, u, v, &mut sc.ring[slot * rw..][..rw]);
            sc.ring_row[slot] = c;
        }
        slot
    };
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
            sc.pad.resize((w + 2 * m + 1) * 5, 0.0);
            for y in ya..yb {
                // Replicate-padded copy of the vertical sums, then a running horizontal sum.
                {
                    let (vs, pad) = (&sc.vsum, &mut sc.pad);
                    for j in 0..w + 2 * m + 1 {
                        let src = (j as isize - m as isize).clamp(0, w as isize - 1) as usize;
                        pad[j * 5..j * 5 + 5].copy_from_slice(&vs[src * 5..src * 5 + 5]);
                    }
                    let mut acc = [0f64; 5];
                    for j in 0..2 * m + 1 {
                        for c in 0..5 {
                            acc[c] += pad[j * 5 + c];
                        }
                    }
                    // Reuse `vsum`-sized output by writing window sums in place into pad's head.
                    for x in 0..w {
                        let (add, sub) = ((x + 2 * m + 1) * 5, x * 5);
                        let cur = acc;
                        if x + 1 < w {
                            for c in 0..5 {
                                acc[c] += pad[add + c] - pad[sub + c];
                            }
                        }
                        pad[sub..sub + 5].copy_from_slice(&cur);
                    }
                }
                let r = y - ya;
                solve_row(
                    lv,
                    &sc.pad[..rw],
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
            sc.vconv.resize((w + 2 * m) * 5, 0.0);
            sc.hconv.resize(rw, 0.0);
            sc.pad.resize(rw, 0.0);
            for y in ya..yb {
                for t in -(m as isize)..=(m as isize) {
                    ensure(sc, clamp(y as isize + t));
                }
                // Vertical convolution into the padded row buffer.
                {
                    let dst = &mut sc.vconv[m * 5..m * 5 + rw];
                    let c0 = clamp(y as isize) % slots;
                    let k0 = kernel[0];
                    for (d, &s) in dst.iter_mut().zip(&sc.ring[c0 * rw..][..rw]) {
                        *d = s * k0;
                    }
                    for (i, &ki) in kernel.iter().enumerate().skip(1) {
                        let a = clamp(y as isize + i as isize) % slots;
                        let b = clamp(y as isize - i as isize) % slots;
                        let ra = &sc.ring[a * rw..][..rw];
                        let rb = &sc.ring[b * rw..][..rw];
                        for ((d, &p), &q) in dst.iter_mut().zip(ra).zip(rb) {
                            *d += ki * (p + q);
                        }
                    }
                }
                let vc = &mut sc.vconv;
                for j in 0..m {
                    for c in 0..5 {
                        vc[j * 5 + c] = vc[m * 5 + c];
                        vc[(m + w + j) * 5 + c] = vc[(m + w - 1) * 5 + c];
                    }
                }
                // Horizontal convolution.
                let k0 = kernel[0];
                for (i, hv) in sc.hconv.iter_mut().enumerate() {
                    *hv = vc[m * 5 + i] * k0;
                }
                for (t, &kt) in kernel.iter().enumerate().skip(1) {
                    let l = &vc[(m - t) * 5..][..rw];
                    let r = &vc[(m + t) * 5..][..rw];
                    for ((hv, &a), &b) in sc.hconv.iter_mut().zip(l).zip(r) {
                        *hv += kt * (a + b);
                    }
                }
                for (p, &hv) in sc.pad.iter_mut().zip(&sc.hconv) {
                    *p = hv as f64;
                }
                let r = y - ya;
                solve_row(
                    lv,
                    &sc.pad[..rw],
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
