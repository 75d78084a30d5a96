//! Farneback iterations solved on a grid of window centres (stride `s`), with an optional
//! affine motion model inside the window.
//!
//! Why: with the constant-displacement model of Farnebäck/OpenCV, the flow at `x` is the
//! structure-tensor-weighted mean of the true displacement over the window, i.e. the
//! displacement at the window's *texture centroid*, not at `x`. Wherever texture is unevenly
//! spread (active regions, the limb, image or NaN edges) the centroid is pulled towards the
//! texture, and a rotation or scale change is under-measured
//! (docs/validation.md#affine-window-model). Fitting `d(x') = a + B (x' − x)` in the window
//! instead makes the estimate `a` exact for any affine field whatever the texture layout, and
//! windows may then be simply truncated at the domain's edges (no replicated border rows).
//!
//! The window sums are separable moments `Σ M·ξ^i·η^j` (i + j ≤ 2), kept as running sums down
//! the rows and prefix sums along a grid row, so the cost per pixel does not depend on the
//! window size. The per-pixel normal matrices still use every pixel (flow at a pixel is the
//! bilinear interpolation of the grid), only the solve runs on the grid.

use super::simd;
use super::solve::{matrices_row, FieldMut, FieldView, Level};
use rayon::prelude::*;

/// Positions of grid nodes along one axis of a domain of `len` pixels starting at level pixel
/// `origin`: the level pixels `s/2 + j·s` (the same nodes whatever the domain, so a ROI run
/// matches a whole-image run) plus the domain's first and last pixels, so that every pixel is
/// interpolated, never extrapolated.
pub(crate) fn axis(origin: usize, len: usize, s: usize) -> Vec<usize> {
    let first = (s / 2 + s - origin % s) % s;
    let mut v: Vec<usize> = (0..)
        .map(|j| first + j * s)
        .take_while(|&p| p < len)
        .collect();
    if v.is_empty() {
        v.push(0);
    }
    if *v.last().unwrap_or(&0) != len - 1 {
        v.push(len - 1);
    }
    if v[0] != 0 {
        v.insert(0, 0);
    }
    v
}

/// Interpolation taps for every pixel `0..len` on `nodes`: (node index, next node index, weight).
pub(crate) fn taps(nodes: &[usize], len: usize) -> Vec<(u32, u32, f32)> {
    let mut out = Vec::with_capacity(len);
    let mut j = 0;
    for p in 0..len {
        while j + 1 < nodes.len() && nodes[j + 1] <= p {
            j += 1;
        }
        if j + 1 >= nodes.len() {
            out.push((j as u32, j as u32, 0.0));
        } else {
            let (a, b) = (nodes[j], nodes[j + 1]);
            out.push((j as u32, j as u32 + 1, (p - a) as f32 / (b - a) as f32));
        }
    }
    out
}

/// Bilinear sample of a grid field at fractional pixel position (x, y) of its domain.
pub(crate) fn sample(g: &[f32], xs: &[usize], ys: &[usize], x: f64, y: f64) -> f32 {
    let locate = |nodes: &[usize], p: f64| -> (usize, usize, f64) {
        let last = nodes.len() - 1;
        let p = p.clamp(0.0, nodes[last] as f64);
        let j = nodes.partition_point(|&n| n as f64 <= p).saturating_sub(1);
        if j >= last {
            (last, last, 0.0)
        } else {
            let (a, b) = (nodes[j] as f64, nodes[j + 1] as f64);
            (j, j + 1, (p - a) / (b - a))
        }
    };
    let (x0, x1, wx) = locate(xs, x);
    let (y0, y1, wy) = locate(ys, y);
    let nx = xs.len();
    let at = |j: usize, i: usize| g[i * nx + j] as f64;
    let top = at(x0, y0) + wx * (at(x1, y0) - at(x0, y0));
    let bot = at(x0, y1) + wx * (at(x1, y1) - at(x0, y1));
    (top + wy * (bot - top)) as f32
}

/// The grid and model for one level.
pub(crate) struct Grid<'a> {
    pub xs: &'a [usize],
    pub ys: &'a [usize],
    pub ytaps: &'a [(u32, u32, f32)],
    pub affine: bool,
}

#[derive(Default)]
pub(crate) struct GridScratch {
    /// One row of normal matrices (5 planes).
    ring: Vec<f32>,
    /// Cumulative vertical moment sums down the strip, and snapshots at window tops.
    cum: Vec<f64>,
    snaps: Vec<f64>,
    /// Vertical moment sums, channel-major (`nch` planes of `w`).
    vs: Vec<f64>,
    /// Prefix sums along the row at the window edges `stops` (`nh` channels each).
    pre: Vec<f64>,
    /// The columns where a grid window starts or ends, ascending: where the prefix sums
    /// are read.
    stops: Vec<usize>,
    /// Each grid column's window as indices into `stops` (start, end).
    edges: Vec<(usize, usize)>,
    urow: Vec<f32>,
    vrow: Vec<f32>,
}

/// A table of (channel, moment order) pairs.
type Channels = &'static [(usize, usize)];

/// Vertical moment channels: for G11, G12, G22 the orders η⁰, η¹, η²; for h1, h2 η⁰, η¹.
/// `(matrix channel, η order)`.
const VCH_AFFINE: [(usize, usize); 13] = [
    (0, 0),
    (0, 1),
    (0, 2),
    (1, 0),
    (1, 1),
    (1, 2),
    (2, 0),
    (2, 1),
    (2, 2),
    (3, 0),
    (3, 1),
    (4, 0),
    (4, 1),
];
const VCH_CONST: [(usize, usize); 5] = [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)];

/// Horizontal prefix channels: (vertical channel index, ξ order).
const HCH_AFFINE: [(usize, usize); 24] = [
    // G11: η⁰ with ξ⁰ ξ¹ ξ², η¹ with ξ⁰ ξ¹, η² with ξ⁰
    (0, 0),
    (0, 1),
    (0, 2),
    (1, 0),
    (1, 1),
    (2, 0),
    // G12
    (3, 0),
    (3, 1),
    (3, 2),
    (4, 0),
    (4, 1),
    (5, 0),
    // G22
    (6, 0),
    (6, 1),
    (6, 2),
    (7, 0),
    (7, 1),
    (8, 0),
    // h1: η⁰ ξ⁰ ξ¹, η¹ ξ⁰
    (9, 0),
    (9, 1),
    (10, 0),
    // h2
    (11, 0),
    (11, 1),
    (12, 0),
];
const HCH_CONST: [(usize, usize); 5] = [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0)];

/// One iteration on the grid: new grid flow from the old one.
pub(crate) fn iterate(
    lv: &Level,
    grid: &Grid,
    old: FieldView,
    new: FieldMut,
    scratch: &mut Vec<GridScratch>,
    last: bool,
) {
    let (gu_new, gv_new) = (new.u, new.v);
    let nx = grid.xs.len();
    let ny = grid.ys.len();
    let threads = rayon::current_num_threads().max(1);
    // Strips of grid rows; each recomputes the matrix rows of its halo.
    let per = ((2 * lv.m + 1) * 4 / (grid.ys.get(1).copied().unwrap_or(1).max(1))).max(1);
    let n = (ny / per).clamp(1, 2 * threads);
    let n = if n > threads && n < 2 * threads {
        threads
    } else {
        n
    };
    let bounds: Vec<(usize, usize)> = (0..n).map(|i| (i * ny / n, (i + 1) * ny / n)).collect();
    if scratch.len() < n {
        scratch.resize_with(n, GridScratch::default);
    }
    let mut u_parts = Vec::with_capacity(n);
    let mut v_parts = Vec::with_capacity(n);
    let (mut ur, mut vr) = (gu_new, gv_new);
    for &(a, b) in &bounds {
        let (uh, ut) = ur.split_at_mut((b - a) * nx);
        let (vh, vt) = vr.split_at_mut((b - a) * nx);
        u_parts.push(uh);
        v_parts.push(vh);
        ur = ut;
        vr = vt;
    }
    bounds
        .par_iter()
        .zip(scratch.par_iter_mut())
        .zip(u_parts.into_par_iter().zip(v_parts.into_par_iter()))
        .for_each(|((&(ia, ib), sc), (uo, vo))| {
            let out = FieldMut { u: uo, v: vo };
            if grid.affine {
                grid_strip_affine(lv, grid, old, (ia, ib), out, sc, last);
            } else {
                grid_strip_const(lv, grid, old, (ia, ib), out, sc, last);
            }
        });
}

simd::multiversion!(fn grid_strip_affine(
    lv: &Level,
    grid: &Grid,
    old: FieldView,
    rows: (usize, usize),
    out: FieldMut,
    sc: &mut GridScratch,
    last: bool,
) => grid_strip::<true>);

simd::multiversion!(fn grid_strip_const(
    lv: &Level,
    grid: &Grid,
    old: FieldView,
    rows: (usize, usize),
    out: FieldMut,
    sc: &mut GridScratch,
    last: bool,
) => grid_strip::<false>);

/// Interpolate the grid flow onto pixel row `y`: vertical blend of the two grid rows, then a
/// linear ramp across each grid interval (contiguous, vectorisable).
#[inline(always)]
pub(crate) fn flow_row(
    grid: &Grid,
    gu: &[f32],
    gv: &[f32],
    y: usize,
    u: &mut [f32],
    v: &mut [f32],
) {
    let nx = grid.xs.len();
    let (i0, i1, wy) = grid.ytaps[y];
    let (ua, ub) = (&gu[i0 as usize * nx..][..nx], &gu[i1 as usize * nx..][..nx]);
    let (va, vb) = (&gv[i0 as usize * nx..][..nx], &gv[i1 as usize * nx..][..nx]);
    let node = |a: &[f32], b: &[f32], j: usize| a[j] + wy * (b[j] - a[j]);
    for j in 0..nx {
        let (x0, cu, cv) = (grid.xs[j], node(ua, ub, j), node(va, vb, j));
        if j + 1 == nx {
            u[x0] = cu;
            v[x0] = cv;
            break;
        }
        let x1 = grid.xs[j + 1];
        let inv = 1.0 / (x1 - x0) as f32;
        let su = (node(ua, ub, j + 1) - cu) * inv;
        let sv = (node(va, vb, j + 1) - cv) * inv;
        let (us, vs) = (&mut u[x0..x1], &mut v[x0..x1]);
        for (k, (uo, vo)) in us.iter_mut().zip(vs.iter_mut()).enumerate() {
            *uo = cu + su * k as f32;
            *vo = cv + sv * k as f32;
        }
    }
}

/// Grid rows `rows.0 .. rows.1` of the new grid flow, into `out` (those rows only).
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn grid_strip<const AFF: bool>(
    lv: &Level,
    grid: &Grid,
    old: FieldView,
    rows: (usize, usize),
    out: FieldMut,
    sc: &mut GridScratch,
    last: bool,
) {
    let FieldView { u: gu, v: gv } = old;
    let FieldMut { u: u_out, v: v_out } = out;
    let (ia, ib) = rows;
    let (w, h, m) = (lv.w, lv.h, lv.m);
    let nx = grid.xs.len();
    let rw = 5 * w;
    // Constant tables per model, so the channel loops unroll with fixed indices.
    let (vch, hch): (Channels, Channels) = if AFF {
        (&VCH_AFFINE, &HCH_AFFINE)
    } else {
        (&VCH_CONST, &HCH_CONST)
    };
    let nv = vch.len();
    let nh = hch.len();
    // Vertical window sums come from cumulative sums down the strip: every matrix row is
    // computed and added once; the cumulative sums are snapshotted at each grid row's window
    // top and subtracted at its bottom (f64: the cancellation costs a few digits of 16).
    let top_of = |i: usize| grid.ys[i].saturating_sub(m);
    let bot_of = |i: usize| (grid.ys[i] + m).min(h - 1);
    let lo = top_of(ia);
    // Most windows open at once (snapshots pending).
    let mut pending = 1;
    {
        let mut j = ia;
        for i in ia..ib {
            while j < ib && top_of(j) <= bot_of(i) {
                j += 1;
            }
            pending = pending.max(j - i);
        }
    }
    sc.ring.resize(rw, 0.0);
    sc.urow.resize(w, 0.0);
    sc.vrow.resize(w, 0.0);
    sc.cum.clear();
    sc.cum.resize(nv * w, 0.0);
    sc.snaps.resize(pending * nv * w, 0.0);
    sc.vs.resize(nv * w, 0.0);
    // Window edges along the row, the same for every grid row.
    let span = |xc: usize| (xc.saturating_sub(m), (xc + m + 1).min(w));
    sc.stops.clear();
    sc.stops
        .extend(grid.xs.iter().flat_map(|&xc| <[usize; 2]>::from(span(xc))));
    sc.stops.sort_unstable();
    sc.stops.dedup();
    sc.edges.clear();
    sc.edges.extend(grid.xs.iter().map(|&xc| {
        let (l, r) = span(xc);
        let at = |p: usize| sc.stops.partition_point(|&q| q < p);
        (at(l), at(r))
    }));
    sc.pre.resize(nh * sc.stops.len(), 0.0);

    let norm = 1.0 / ((2 * m + 1) * (2 * m + 1)) as f64;
    let sig2 = (m * (m + 1)) as f64 / 3.0;
    let (mut next_top, mut next_bot) = (ia, ia);
    let last_bot = bot_of(ib - 1);
    for y in lo..=last_bot {
        while next_top < ib && top_of(next_top) == y {
            let slot = next_top % pending;
            sc.snaps[slot * nv * w..][..nv * w].copy_from_slice(&sc.cum);
            next_top += 1;
        }
        add_row::<AFF>(lv, grid, gu, gv, sc, y, lo);
        while next_bot < ib && bot_of(next_bot) == y {
            let i = next_bot;
            next_bot += 1;
            {
                let slot = i % pending;
                let snap = &sc.snaps[slot * nv * w..][..nv * w];
                for ((d, &c), &p) in sc.vs.iter_mut().zip(&sc.cum).zip(snap) {
                    *d = c - p;
                }
            }
            // Centred on the grid row's yc, and summed along the row up to each window edge.
            let c = grid.ys[i] as f64 - lo as f64;
            if AFF {
                centred_prefix(
                    &sc.vs,
                    w,
                    c,
                    &VCH_AFFINE,
                    &HCH_AFFINE,
                    &sc.stops,
                    &mut sc.pre,
                );
            } else {
                centred_prefix(&sc.vs, w, c, &VCH_CONST, &HCH_CONST, &sc.stops, &mut sc.pre);
            }
            // Solve at every grid column.
            let row = i - ia;
            // Window sum of prefix channel k at column j, centred in ξ up to its order.
            let ws = |j: usize, k: usize| {
                let (l, r) = sc.edges[j];
                sc.pre[r * nh + k] - sc.pre[l * nh + k]
            };
            if AFF {
                // The columns' systems made one by one, solved SOLVE_LANES at a time.
                for j0 in (0..nx).step_by(SOLVE_LANES) {
                    let group = j0..(j0 + SOLVE_LANES).min(nx);
                    let mut systems = Lanes::identity();
                    let mut fallback = [None; SOLVE_LANES];
                    for (lane, j) in group.clone().enumerate() {
                        let m = affine_moments(|k| ws(j, k), grid.xs[j] as f64);
                        if let Some((k, rhs)) = affine_system(lv, &m, norm, sig2) {
                            systems.set(lane, &k, &rhs);
                            fallback[lane] = Some(m.constant());
                        }
                    }
                    let solved = cholesky_solve_lanes(&mut systems.a, &mut systems.b);
                    for (lane, j) in group.enumerate() {
                        let (uu, vv) = match fallback[lane] {
                            None => empty_window(last),
                            Some(_) if solved[lane] => {
                                (systems.b[1][lane] as f32, systems.b[0][lane] as f32)
                            }
                            // Degenerate window for the affine model: the constant one.
                            Some(g) => solve_const(lv, &g, norm, last),
                        };
                        u_out[row * nx + j] = uu;
                        v_out[row * nx + j] = vv;
                    }
                }
            } else {
                for j in 0..nx {
                    let g = [ws(j, 0), ws(j, 1), ws(j, 2), ws(j, 3), ws(j, 4)];
                    let (uu, vv) = solve_const(lv, &g, norm, last);
                    u_out[row * nx + j] = uu;
                    v_out[row * nx + j] = vv;
                }
            }
        }
    }
}

/// The prefix sums along a row at each of `stops` (ascending, at most `w`) into `pre`
/// (`NH` channels a stop): at stop `p`, over the pixels `x < p`, each horizontal channel
/// `(vertical channel, ξ order)` of `hch` the vertical channel's moment centred on `c`,
/// times `x^order`. The vertical moments `vs` are channel-major (`NV` planes of `w`), their
/// orders in `vch`. Each pixel's centred moments are made as it is summed, and the sums are
/// stored only where the windows read them; fixed sizes keep them in registers.
#[inline(always)]
fn centred_prefix<const NV: usize, const NH: usize>(
    vs: &[f64],
    w: usize,
    c: f64,
    vch: &[(usize, usize); NV],
    hch: &[(usize, usize); NH],
    stops: &[usize],
    pre: &mut [f64],
) {
    let planes: [&[f64]; NV] = std::array::from_fn(|k| &vs[k * w..][..w]);
    let mut acc = [0f64; NH];
    let mut x = 0;
    for (&stop, out) in stops.iter().zip(pre.chunks_exact_mut(NH)) {
        while x < stop {
            // The moment of order `ord` about `c` from the raw ones below it.
            let mut cm = [0f64; NV];
            for (k, (m, &(_, ord))) in cm.iter_mut().zip(vch).enumerate() {
                *m = match ord {
                    0 => planes[k][x],
                    1 => planes[k][x] - c * planes[k - 1][x],
                    _ => planes[k][x] - 2.0 * c * planes[k - 1][x] + c * c * planes[k - 2][x],
                };
            }
            let xf = x as f64;
            let pw = [1.0, xf, xf * xf];
            for (a, &(vk, ord)) in acc.iter_mut().zip(hch) {
                *a += cm[vk] * pw[ord];
            }
            x += 1;
        }
        out.copy_from_slice(&acc);
    }
}

/// Add pixel row `y` (its normal matrices at the interpolated grid flow) to the cumulative
/// vertical moment sums, with row weight `(y − lo)^order`.
#[inline(always)]
fn add_row<const AFF: bool>(
    lv: &Level,
    grid: &Grid,
    gu: &[f32],
    gv: &[f32],
    sc: &mut GridScratch,
    y: usize,
    lo: usize,
) {
    let vch: &[(usize, usize)] = if AFF { &VCH_AFFINE } else { &VCH_CONST };
    let w = lv.w;
    flow_row(grid, gu, gv, y, &mut sc.urow, &mut sc.vrow);
    matrices_row(lv, y, &sc.urow, &sc.vrow, &mut sc.ring[..5 * w]);
    let yy = y as f64 - lo as f64;
    let pw = [1.0, yy, yy * yy];
    let row = &sc.ring[..5 * w];
    for (k, &(c, ord)) in vch.iter().enumerate() {
        let f = pw[ord];
        let src = &row[c * w..][..w];
        let dst = &mut sc.cum[k * w..][..w];
        for (d, &s) in dst.iter_mut().zip(src) {
            *d += f * s as f64;
        }
    }
}

/// Constant model (OpenCV's equations) from window sums.
#[inline(always)]
fn solve_const(lv: &Level, s: &[f64; 5], norm: f64, last: bool) -> (f32, f32) {
    let (g11, g12, g22, h1, h2) = (
        s[0] * norm,
        s[1] * norm,
        s[2] * norm,
        s[3] * norm,
        s[4] * norm,
    );
    let tr = g11 + g22;
    if tr <= lv.empty_trace {
        return empty_window(last);
    }
    let l = lv.reg_abs + lv.reg_rel * tr;
    let (a, c) = (g11 + l, g22 + l);
    let idet = 1.0 / (a * c - g12 * g12);
    (
        ((a * h2 - g12 * h1) * idet) as f32,
        ((c * h1 - g12 * h2) * idet) as f32,
    )
}

/// A window without structure: no flow on the last iteration, none added before it.
#[inline(always)]
fn empty_window(last: bool) -> (f32, f32) {
    if last {
        (f32::NAN, f32::NAN)
    } else {
        (0.0, 0.0)
    }
}

/// A window's centred moments for the affine model: per matrix channel (G11, G12, G22)
/// `[ξ⁰η⁰, ξ¹η⁰, ξ²η⁰, ξ⁰η¹, ξ¹η¹, ξ⁰η²]`, per right-hand side (h1, h2) `[ξ⁰η⁰, ξ¹η⁰, ξ⁰η¹]`.
struct AffineMoments {
    g11: [f64; 6],
    g12: [f64; 6],
    g22: [f64; 6],
    h1: [f64; 3],
    h2: [f64; 3],
}

impl AffineMoments {
    /// The constant model's sums (G11, G12, G22, h1, h2).
    fn constant(&self) -> [f64; 5] {
        [
            self.g11[0],
            self.g12[0],
            self.g22[0],
            self.h1[0],
            self.h2[0],
        ]
    }
}

/// [`AffineMoments`] of the window at column `xf` from its sums `ws(k)` of the horizontal
/// prefix channels ([`HCH_AFFINE`]), centred in ξ up to each channel's order.
#[inline(always)]
fn affine_moments(ws: impl Fn(usize) -> f64, xf: f64) -> AffineMoments {
    let mom = |base: usize| -> [f64; 6] {
        let (a0, a1, a2) = (ws(base), ws(base + 1), ws(base + 2));
        let (b0, b1) = (ws(base + 3), ws(base + 4));
        let c0 = ws(base + 5);
        [
            a0,
            a1 - xf * a0,
            a2 - 2.0 * xf * a1 + xf * xf * a0,
            b0,
            b1 - xf * b0,
            c0,
        ]
    };
    let hm = |base: usize| -> [f64; 3] {
        let (a0, a1, b0) = (ws(base), ws(base + 1), ws(base + 2));
        [a0, a1 - xf * a0, b0]
    };
    AffineMoments {
        g11: mom(0),
        g12: mom(6),
        g22: mom(12),
        h1: hm(18),
        h2: hm(21),
    }
}

/// The affine model's regularised normal equations for one window, in the unknowns (d_y,
/// d_x, ∂d_y/∂ξ, ∂d_x/∂ξ, ∂d_y/∂η, ∂d_x/∂η); `None` for a window without structure.
#[inline(always)]
fn affine_system(
    lv: &Level,
    m: &AffineMoments,
    norm: f64,
    sig2: f64,
) -> Option<([[f64; 6]; 6], [f64; 6])> {
    let tr = (m.g11[0] + m.g22[0]) * norm;
    if tr <= lv.empty_trace {
        return None;
    }
    // Moment index of φ_i·φ_j for φ = (1, ξ, η): into [1, ξ, ξ², η, ξη, η²].
    const IDX: [[usize; 3]; 3] = [[0, 1, 3], [1, 2, 4], [3, 4, 5]];
    let mut k = [[0f64; 6]; 6];
    let mut rhs = [0f64; 6];
    for bi in 0..3 {
        for bj in 0..3 {
            let q = IDX[bi][bj];
            k[2 * bi][2 * bj] = m.g11[q] * norm;
            k[2 * bi][2 * bj + 1] = m.g12[q] * norm;
            k[2 * bi + 1][2 * bj] = m.g12[q] * norm;
            k[2 * bi + 1][2 * bj + 1] = m.g22[q] * norm;
        }
        let q = [0usize, 1, 2][bi];
        rhs[2 * bi] = m.h1[q] * norm;
        rhs[2 * bi + 1] = m.h2[q] * norm;
    }
    let l = lv.reg_abs + lv.reg_rel * tr;
    for (i, row) in k.iter_mut().enumerate() {
        row[i] += if i < 2 { l } else { l * sig2 };
    }
    Some((k, rhs))
}

/// Windows whose 6×6 systems are solved side by side, one per vector lane.
const SOLVE_LANES: usize = 4;

/// [`SOLVE_LANES`] systems, element by element across the lanes.
struct Lanes {
    a: [[[f64; SOLVE_LANES]; 6]; 6],
    b: [[f64; SOLVE_LANES]; 6],
}

impl Lanes {
    /// Identity systems: a lane left so solves trivially.
    fn identity() -> Lanes {
        let mut a = [[[0.0; SOLVE_LANES]; 6]; 6];
        for (i, row) in a.iter_mut().enumerate() {
            row[i] = [1.0; SOLVE_LANES];
        }
        Lanes {
            a,
            b: [[0.0; SOLVE_LANES]; 6],
        }
    }

    fn set(&mut self, lane: usize, k: &[[f64; 6]; 6], rhs: &[f64; 6]) {
        for ((row, krow), (b, &r)) in self.a.iter_mut().zip(k).zip(self.b.iter_mut().zip(rhs)) {
            for (a, &v) in row.iter_mut().zip(krow) {
                a[lane] = v;
            }
            b[lane] = r;
        }
    }
}

/// In-place Cholesky solves of [`SOLVE_LANES`] 6×6 SPD systems side by side; per lane,
/// false if its matrix is not positive definite (its results are then meaningless). Each
/// lane takes exactly the steps of a scalar solve, so the lanes' answers are its own.
#[allow(clippy::needless_range_loop)]
#[inline(always)]
fn cholesky_solve_lanes(
    a: &mut [[[f64; SOLVE_LANES]; 6]; 6],
    b: &mut [[f64; SOLVE_LANES]; 6],
) -> [bool; SOLVE_LANES] {
    let mut ok = [true; SOLVE_LANES];
    for j in 0..6 {
        let mut d = a[j][j];
        for k in 0..j {
            for l in 0..SOLVE_LANES {
                d[l] -= a[j][k][l] * a[j][k][l];
            }
        }
        for l in 0..SOLVE_LANES {
            ok[l] &= d[l] > 0.0;
            d[l] = d[l].sqrt();
        }
        a[j][j] = d;
        for i in j + 1..6 {
            let mut s = a[i][j];
            for k in 0..j {
                for l in 0..SOLVE_LANES {
                    s[l] -= a[i][k][l] * a[j][k][l];
                }
            }
            for l in 0..SOLVE_LANES {
                a[i][j][l] = s[l] / d[l];
            }
        }
    }
    for i in 0..6 {
        let mut s = b[i];
        for k in 0..i {
            for l in 0..SOLVE_LANES {
                s[l] -= a[i][k][l] * b[k][l];
            }
        }
        for l in 0..SOLVE_LANES {
            b[i][l] = s[l] / a[i][i][l];
        }
    }
    for i in (0..6).rev() {
        let mut s = b[i];
        for k in i + 1..6 {
            for l in 0..SOLVE_LANES {
                s[l] -= a[k][i][l] * b[k][l];
            }
        }
        for l in 0..SOLVE_LANES {
            b[i][l] = s[l] / a[i][i][l];
        }
    }
    ok
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axis_covers_every_pixel() {
        assert_eq!(axis(0, 10, 4), vec![0, 2, 6, 9]);
        assert_eq!(axis(3, 10, 4), vec![0, 3, 7, 9]);
        assert_eq!(axis(7, 5, 1), vec![0, 1, 2, 3, 4]);
        let t = taps(&axis(0, 10, 4), 10);
        assert_eq!(t[4], (1, 2, 0.5));
        assert_eq!(t[9], (3, 3, 0.0));
    }

    /// The textbook Cholesky solve, one system at a time: what each lane must reproduce.
    #[allow(clippy::needless_range_loop)]
    fn cholesky_one(a: &mut [[f64; 6]; 6], b: &mut [f64; 6]) -> bool {
        for j in 0..6 {
            let mut d = a[j][j];
            for k in 0..j {
                d -= a[j][k] * a[j][k];
            }
            if d.is_nan() || d <= 0.0 {
                return false;
            }
            let d = d.sqrt();
            a[j][j] = d;
            for i in j + 1..6 {
                let mut s = a[i][j];
                for k in 0..j {
                    s -= a[i][k] * a[j][k];
                }
                a[i][j] = s / d;
            }
        }
        for i in 0..6 {
            let mut s = b[i];
            for k in 0..i {
                s -= a[i][k] * b[k];
            }
            b[i] = s / a[i][i];
        }
        for i in (0..6).rev() {
            let mut s = b[i];
            for k in i + 1..6 {
                s -= a[k][i] * b[k];
            }
            b[i] = s / a[i][i];
        }
        true
    }

    #[test]
    fn lanes_solve_each_system_as_one_solve_does_bit_for_bit() {
        // Random SPD systems (MᵀM + εI, ill-conditioned ones among them) and one that is not
        // positive definite, four to a group.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut systems = Vec::new();
        for n in 0..24 {
            let m: [[f64; 6]; 6] = std::array::from_fn(|_| std::array::from_fn(|_| next()));
            let eps = [1e-9, 1e-3, 1.0][n % 3];
            let a: [[f64; 6]; 6] = std::array::from_fn(|i| {
                std::array::from_fn(|j| {
                    (0..6).map(|k| m[k][i] * m[k][j]).sum::<f64>() + if i == j { eps } else { 0.0 }
                })
            });
            let b: [f64; 6] = std::array::from_fn(|_| 1e3 * next());
            systems.push((a, b));
        }
        let (mut bad, b) = systems[5];
        bad[3][3] = -1.0;
        systems.insert(7, (bad, b));
        for group in systems.chunks(SOLVE_LANES) {
            let mut lanes = Lanes::identity();
            for (lane, (a, b)) in group.iter().enumerate() {
                lanes.set(lane, a, b);
            }
            let ok = cholesky_solve_lanes(&mut lanes.a, &mut lanes.b);
            for (lane, (a, b)) in group.iter().enumerate() {
                let (mut a, mut b) = (*a, *b);
                let expected = cholesky_one(&mut a, &mut b);
                assert_eq!(ok[lane], expected);
                if expected {
                    for (got, want) in lanes.b.iter().zip(&b) {
                        assert_eq!(got[lane].to_bits(), want.to_bits());
                    }
                }
            }
        }
    }

    #[test]
    #[allow(clippy::needless_range_loop)]
    fn cholesky_solves_spd() {
        // A = LLᵀ with L lower-triangular ones → A x = b, x known.
        let mut a = [[0f64; 6]; 6];
        for i in 0..6 {
            for j in 0..6 {
                a[i][j] = (i.min(j) + 1) as f64;
            }
        }
        let x = [1.0, -2.0, 0.5, 3.0, 0.0, -1.0];
        let mut b = [0f64; 6];
        for i in 0..6 {
            b[i] = (0..6).map(|j| a[i][j] * x[j]).sum();
        }
        // Lane 0 holds the system, lane 1 its negative (not positive definite), lane 2 the
        // system scaled by 4 (x/… unchanged: the same x), lane 3 the identity.
        let mut lanes = Lanes::identity();
        let neg = a.map(|row| row.map(|v| -v));
        let four = a.map(|row| row.map(|v| 4.0 * v));
        lanes.set(0, &a, &b);
        lanes.set(1, &neg, &b);
        lanes.set(2, &four, &b.map(|v| 4.0 * v));
        let ok = cholesky_solve_lanes(&mut lanes.a, &mut lanes.b);
        assert_eq!(ok, [true, false, true, true]);
        for i in 0..6 {
            assert!((lanes.b[i][0] - x[i]).abs() < 1e-12);
            assert!((lanes.b[i][2] - x[i]).abs() < 1e-12);
            assert_eq!(lanes.b[i][3], 0.0);
        }
    }
}
