//! Dense optical flow: Farnebäck (2003) two-frame motion estimation with the semantics of
//! OpenCV's `calcOpticalFlowFarneback`, written for f32, rayon and reuse between frames.
//!
//! Same as OpenCV: pyramid construction (every level blurred and resized from full
//! resolution), polynomial expansion (`poly_n`, `poly_sigma`), `iterations` of matrix update +
//! window averaging per level (box window, or the Gaussian window with σ = 0.3·(winsize/2)),
//! flow convention `prev[y, x] ≈ next[y + v, x + u]`, border replicate/taper.
//!
//! Different from OpenCV, on purpose:
//! - **No intensity-dependent regulariser.** OpenCV adds 1e-3 to a determinant that scales as
//!   intensity⁴ (on images of mean ≈ 1 it returns ≈ zero flow). Here both images are first
//!   mapped to `(I − mean(prev)) / std(prev)` and the averaged 2×2 system is solved as
//!   `(G + λI)·d = h` with `λ = 1e-6·T + 1e-9·trace(G)`, `T` the level's mean matrix trace.
//!   The flow therefore does not depend on the images' intensity units or offset.
//! - **Missing data.** NaN pixels are missing: they propagate through the pyramid blur and the
//!   polynomial expansion (a coefficient whose support touches a NaN is NaN), and every pixel
//!   whose expansion is NaN — in `prev`, or in `next` where the flow points — or whose flow
//!   points outside the computed domain gets zero weight in the window average. OpenCV instead
//!   keeps a one-sided equation for such pixels, which drags the flow. Windows with no data
//!   left give NaN; so do pixels where `prev` itself is NaN.
//! - **Region of interest.** With a [`Roi`], each level is computed only on the ROI mapped to
//!   that level plus a margin of `winsize/2 + poly_n + 3` level pixels (clamped to the image);
//!   output pixels outside the ROI are NaN. Inside the ROI the result differs from the
//!   whole-image flow only through the truncated outer margin (measured in the tests).
//!
//! Two ways to run it:
//! - [`FlowOptions::default()`]: OpenCV's algorithm, checked against OpenCV itself
//!   (`tests/flow_oracle.rs`; docs/validation.md#agreement-with-opencv). Its
//!   constant-displacement window is *biased*: the flow at `x` is the displacement at the
//!   window's texture centroid, so rotation and scale come out a few percent short on solar
//!   images (the "gain" of the paper's method).
//! - [`FlowOptions::affine_grid`]: the window fits an affine motion (unbiased for any affine
//!   field whatever the texture layout), solved on a grid of stride `winsize/8` and
//!   interpolated, with 3 coarse / 2 finest iterations: gains within a fraction of a percent
//!   of 1 and a far smaller flow error, at less cost (docs/validation.md#affine-window-model).
//!   This is the one the engine should use; a second pass (resample, measure the residual)
//!   removes the remaining gain.
//!
//! Hot loops are compiled twice (baseline and AVX2+FMA, chosen at run time; see `simd`),
//! work is split into row strips for rayon, and a [`Farneback`] keeps its buffers between
//! calls.

mod grid;
mod poly;
mod pyramid;
pub(crate) mod simd;
mod solve;

use crate::error::{Error, Result};
use crate::pages::{fill_vec, filled};
use ndarray::{Array2, ArrayView2};
use pyramid::cv_round;
use rayon::prelude::*;

/// Farneback parameters (OpenCV's names and meanings).
#[derive(Debug, Clone, PartialEq)]
pub struct FarnebackParams {
    /// Scale between pyramid levels (< 1); 0.5 is the classical pyramid.
    pub pyr_scale: f64,
    /// Number of levels above the full-resolution one (levels smaller than 32 px are dropped).
    pub levels: usize,
    /// Averaging window size in pixels (odd; an even value acts as the next odd one).
    pub winsize: usize,
    /// Matrix-update + averaging iterations per level.
    pub iterations: usize,
    /// Radius of the polynomial-expansion neighbourhood (5 or 7 typical).
    pub poly_n: usize,
    /// σ of the polynomial expansion's Gaussian applicability.
    pub poly_sigma: f64,
    /// Gaussian window (OpenCV `OPTFLOW_FARNEBACK_GAUSSIAN`) instead of the box window.
    pub gaussian_window: bool,
}

impl Default for FarnebackParams {
    /// The paper's settings (levels 5, winsize 101, 10 iterations, poly_n 5, poly_sigma 1.1,
    /// pyr_scale 0.5, box window). winsize 101 is the paper's ~63″ at AIA's 0.6″/px; callers
    /// that know the plate scale should set it with [`winsize_from_arcsec`].
    fn default() -> Self {
        FarnebackParams {
            pyr_scale: 0.5,
            levels: 5,
            winsize: 101,
            iterations: 10,
            poly_n: 5,
            poly_sigma: 1.1,
            gaussian_window: false,
        }
    }
}

/// Motion model inside the averaging window.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WindowModel {
    /// One displacement per window (Farnebäck/OpenCV). The estimate is the displacement at the
    /// window's texture centroid, which under-measures rotation and scale where texture is
    /// unevenly spread (see [`FlowOptions`]).
    Constant,
    /// `d(x') = a + B (x' − x)` fitted in the window; the estimate `a` is exact for any affine
    /// motion whatever the texture layout. Windows are truncated (not replicated) at edges.
    Affine,
}

/// Departures from OpenCV's algorithm, for accuracy and speed. The default is OpenCV's
/// algorithm (dense constant-model solve, same iterations on every level).
#[derive(Debug, Clone, PartialEq)]
pub struct FlowOptions {
    pub model: WindowModel,
    /// Solve the window system every `grid_stride` pixels (per level) and interpolate the flow
    /// bilinearly in between; the normal equations still use every pixel. 1 = every pixel.
    /// Any value other than 1, or the affine model, uses the grid solver (box window only;
    /// windows truncated at the domain's edges instead of OpenCV's replicated border).
    pub grid_stride: usize,
    /// Iterations on the finest level (`None`: `FarnebackParams::iterations`). The finest
    /// level starts from the upsampled coarse flow and needs few Gauss–Newton steps.
    pub finest_iterations: Option<usize>,
    /// Iterations on every coarser level (`None`: `FarnebackParams::iterations`). Coarse levels
    /// only seed the next one; their flow is refined again below.
    pub coarse_iterations: Option<usize>,
    /// Pyramid level the flow is finished on (0 = full resolution); its result is upsampled
    /// bilinearly to full resolution. Levels below it are never built (a level-1 finish costs
    /// about 60 %), but accuracy suffers: the flow is measured at a coarser sampling and
    /// interpolated (docs/validation.md#flow-finished-at-full-resolution). Keep 0 for
    /// measurements. "Finest" in the other options means this level.
    pub finest_level: usize,
}

impl Default for FlowOptions {
    fn default() -> Self {
        FlowOptions {
            model: WindowModel::Constant,
            grid_stride: 1,
            finest_iterations: None,
            coarse_iterations: None,
            finest_level: 0,
        }
    }
}

impl FlowOptions {
    /// The unbiased fast setting: affine window model, solved on a grid of stride
    /// `winsize/8` (the flow is smooth on the window's scale: strides from winsize/17 to
    /// winsize/4 give the same accuracy), 3 iterations on coarse levels and 2 on the finest.
    /// Its rotation and scale gains are within a fraction of a percent of 1, where OpenCV's
    /// algorithm falls a few percent short (docs/validation.md#affine-window-model).
    pub fn affine_grid(winsize: usize) -> Self {
        FlowOptions {
            model: WindowModel::Affine,
            grid_stride: (winsize / 8).max(1),
            finest_iterations: Some(2),
            coarse_iterations: Some(3),
            finest_level: 0,
        }
    }

    fn uses_grid(&self) -> bool {
        self.model == WindowModel::Affine || self.grid_stride > 1
    }
}

/// Smallest window [`winsize_from_arcsec`] returns: below this the 2×2 system rests on too few
/// polynomial fits (the expansion itself spans 11 px at poly_n 5).
pub const MIN_WINSIZE: usize = 7;

/// Window size in pixels for a window of `window_arcsec` at `plate_scale_arcsec` per pixel:
/// the nearest odd integer, at least [`MIN_WINSIZE`]. Non-finite or non-positive inputs give
/// the minimum.
pub fn winsize_from_arcsec(window_arcsec: f64, plate_scale_arcsec: f64) -> usize {
    let px = window_arcsec / plate_scale_arcsec;
    if !px.is_finite() || px <= 0.0 {
        return MIN_WINSIZE;
    }
    let n = px.round().min(1e6) as usize;
    let odd = if n.is_multiple_of(2) {
        // Round to the nearer odd neighbour.
        if px >= n as f64 {
            n + 1
        } else {
            n.saturating_sub(1)
        }
    } else {
        n
    };
    odd.max(MIN_WINSIZE)
}

/// A pixel rectangle `[x, x + width) × [y, y + height)` (x = column, y = row).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

/// Dense flow: `prev[y, x] ≈ next[y + v[y, x], x + u[y, x]]`, in pixels; NaN where unknown.
#[derive(Debug, Clone)]
pub struct Flow {
    pub u: Array2<f32>,
    pub v: Array2<f32>,
}

/// Half-open rectangle in some level's pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn width(&self) -> usize {
        self.x1 - self.x0
    }
    pub fn height(&self) -> usize {
        self.y1 - self.y0
    }
}

/// Reusable solver: holds every buffer, so repeated calls on same-sized frames do not allocate.
pub struct Farneback {
    params: FarnebackParams,
    options: FlowOptions,
    grid_scratch: Vec<grid::GridScratch>,
    grid_xs: Vec<usize>,
    grid_ys: Vec<usize>,
    prev_grid_xs: Vec<usize>,
    prev_grid_ys: Vec<usize>,
    poly: poly::PolyKernel,
    gauss: Option<Vec<f32>>,
    /// The two images' polynomial expansions at the current level (the levels themselves are
    /// made band by band as they are expanded, and not kept).
    r0: Vec<f32>,
    r1: Vec<f32>,
    /// What `r0` was expanded from, and whether the next computation's first image is the
    /// last one's ([`Farneback::next_prev_unchanged`]).
    r0_key: Option<ExpansionKey>,
    prev_unchanged: bool,
    /// The output rows the next computation's caller reads ([`Farneback::next_rows`]).
    next_rows: Option<RowLattice>,
    u: [Vec<f32>; 2],
    v: [Vec<f32>; 2],
    prev_u: Vec<f32>,
    prev_v: Vec<f32>,
    scratch: Vec<solve::StripScratch>,
}

/// Pyramid bookkeeping for one level.
#[derive(Debug, Clone, Copy)]
struct LevelGeom {
    scale: f64,
    h: usize,
    w: usize,
    dom: Rect,
}

/// Validate parameters; the messages name the field.
fn check_params(p: &FarnebackParams) -> Result<()> {
    if !(p.pyr_scale > 0.0 && p.pyr_scale < 1.0) {
        return Err(Error::Usage(format!(
            "flow: pyr_scale must be in (0, 1), got {}",
            p.pyr_scale
        )));
    }
    if p.winsize == 0 || p.winsize > 4095 {
        return Err(Error::Usage(format!(
            "flow: winsize must be in 1..=4095, got {}",
            p.winsize
        )));
    }
    if p.poly_n == 0 || p.poly_n > 32 {
        return Err(Error::Usage(format!(
            "flow: poly_n must be in 1..=32, got {}",
            p.poly_n
        )));
    }
    if !p.poly_sigma.is_finite() || p.poly_sigma < 0.0 {
        return Err(Error::Usage(format!(
            "flow: poly_sigma must be finite and ≥ 0, got {}",
            p.poly_sigma
        )));
    }
    if p.iterations == 0 {
        return Err(Error::Usage("flow: iterations must be ≥ 1".into()));
    }
    Ok(())
}

/// Mean and standard deviation of the finite pixels (f64 accumulation), over `roi` rows/cols.
fn finite_stats(img: ArrayView2<f32>, rect: Rect) -> Option<(f64, f64)> {
    use rayon::prelude::*;
    let (s, s2, n) = (rect.y0..rect.y1)
        .into_par_iter()
        .map(|y| {
            let (mut s, mut s2, mut n) = (0f64, 0f64, 0usize);
            for x in rect.x0..rect.x1 {
                let v = img[[y, x]];
                if v.is_finite() {
                    let v = v as f64;
                    s += v;
                    s2 += v * v;
                    n += 1;
                }
            }
            (s, s2, n)
        })
        .reduce(|| (0.0, 0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    if n < 2 {
        return None;
    }
    let mean = s / n as f64;
    // Second pass for the spread would be exact; the shifted formula is enough for a scale.
    let var = (s2 / n as f64 - mean * mean).max(0.0);
    let sd = var.sqrt();
    if sd > 0.0 && sd.is_finite() {
        Some((mean, sd))
    } else {
        None
    }
}

/// Every `step`-th row from row `first`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RowLattice {
    pub first: usize,
    pub step: usize,
}

impl RowLattice {
    fn holds(&self, y: usize) -> bool {
        y >= self.first && (y - self.first).is_multiple_of(self.step.max(1))
    }
}

/// What an expansion depends on besides the image's pixels: its size and level, the domain,
/// the normalisation and the kernel.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ExpansionKey {
    image: (usize, usize),
    level: (usize, usize),
    dom: Rect,
    offset: f32,
    gain: f32,
    poly: (usize, f64),
}

impl Farneback {
    pub fn new(params: FarnebackParams) -> Result<Self> {
        check_params(&params)?;
        let poly = poly::PolyKernel::new(params.poly_n, params.poly_sigma);
        let gauss = params
            .gaussian_window
            .then(|| solve::gaussian_window(params.winsize / 2));
        Ok(Farneback {
            params,
            options: FlowOptions::default(),
            grid_scratch: Vec::new(),
            grid_xs: Vec::new(),
            grid_ys: Vec::new(),
            prev_grid_xs: Vec::new(),
            prev_grid_ys: Vec::new(),
            poly,
            gauss,
            r0: Vec::new(),
            r1: Vec::new(),
            r0_key: None,
            prev_unchanged: false,
            next_rows: None,
            u: [Vec::new(), Vec::new()],
            v: [Vec::new(), Vec::new()],
            prev_u: Vec::new(),
            prev_v: Vec::new(),
            scratch: Vec::new(),
        })
    }

    pub fn params(&self) -> &FarnebackParams {
        &self.params
    }

    /// Declare that the next computation's first image holds the same pixels as the last
    /// one's: its expansion is kept where the level, domain and normalisation are the same
    /// too (successive passes against one reference).
    pub fn next_prev_unchanged(&mut self) {
        self.prev_unchanged = true;
    }

    /// Declare that the caller of the next computation reads only the output rows `rows`
    /// (a sampling lattice's): the dense flow is made there alone, the other rows are left
    /// NaN. Every row is made without it.
    pub fn next_rows(&mut self, rows: Option<RowLattice>) {
        self.next_rows = rows;
    }

    /// Change the parameters and options, keeping every buffer (a solver reused for another
    /// pass or frame does not page-fault its working memory in again).
    pub fn reconfigure(&mut self, params: FarnebackParams, options: FlowOptions) -> Result<()> {
        check_params(&params)?;
        let fresh = Farneback::new(params)?.with_options(options)?;
        self.params = fresh.params;
        self.options = fresh.options;
        self.poly = fresh.poly;
        self.gauss = fresh.gauss;
        Ok(())
    }

    /// Use `options` (see [`FlowOptions`]); errors on a zero stride or zero iterations.
    pub fn with_options(mut self, options: FlowOptions) -> Result<Self> {
        if options.grid_stride == 0
            || options.finest_iterations == Some(0)
            || options.coarse_iterations == Some(0)
        {
            return Err(Error::Usage(
                "flow: grid_stride and iteration counts must be ≥ 1".into(),
            ));
        }
        if options.uses_grid() && self.params.gaussian_window {
            return Err(Error::Usage(
                "flow: the grid/affine solver has the box window only (set gaussian_window false)"
                    .into(),
            ));
        }
        self.options = options;
        Ok(self)
    }

    pub fn options(&self) -> &FlowOptions {
        &self.options
    }

    /// Pyramid levels as OpenCV crops them (none smaller than 32 px) and their domains.
    fn geometry(&self, h: usize, w: usize, roi: Rect) -> Vec<LevelGeom> {
        const MIN_SIZE: f64 = 32.0;
        let p = &self.params;
        let mut levels = 0;
        let mut scale = 1.0;
        while levels < p.levels {
            scale *= p.pyr_scale;
            if w as f64 * scale < MIN_SIZE || h as f64 * scale < MIN_SIZE {
                break;
            }
            levels += 1;
        }
        let margin = p.winsize / 2 + p.poly_n + 3;
        let mut out: Vec<LevelGeom> = Vec::with_capacity(levels + 1);
        for k in 0..=levels {
            let mut s = 1.0;
            for _ in 0..k {
                s *= p.pyr_scale;
            }
            let lh = (cv_round(h as f64 * s) as usize).max(1);
            let lw = (cv_round(w as f64 * s) as usize).max(1);
            // Map a full-resolution span into this level, expand by the margin.
            let map = |lo: usize, hi: usize, full: usize, lev: usize| -> (usize, usize) {
                let r = lev as f64 / full as f64;
                let a = ((lo as f64 + 0.5) * r - 0.5).floor() as isize - margin as isize;
                let b = ((hi as f64 - 0.5) * r - 0.5).ceil() as isize + 1 + margin as isize;
                (a.max(0) as usize, (b.max(0) as usize).min(lev))
            };
            let (mut x0, mut x1) = map(roi.x0, roi.x1, w, lw);
            let (mut y0, mut y1) = map(roi.y0, roi.y1, h, lh);
            // Must also cover where the finer level's domain samples this level's flow.
            if let Some(f) = out.last() {
                let cover = |lo: usize, hi: usize, fine: usize, lev: usize| -> (usize, usize) {
                    let r = lev as f64 / fine as f64;
                    let a = ((lo as f64 + 0.5) * r - 0.5).floor() as isize - 2;
                    let b = ((hi as f64 - 0.5) * r - 0.5).ceil() as isize + 3;
                    (a.max(0) as usize, (b.max(0) as usize).min(lev))
                };
                let (cx0, cx1) = cover(f.dom.x0, f.dom.x1, f.w, lw);
                let (cy0, cy1) = cover(f.dom.y0, f.dom.y1, f.h, lh);
                x0 = x0.min(cx0);
                x1 = x1.max(cx1);
                y0 = y0.min(cy0);
                y1 = y1.max(cy1);
            }
            out.push(LevelGeom {
                scale: s,
                h: lh,
                w: lw,
                dom: Rect { x0, y0, x1, y1 },
            });
        }
        out
    }

    /// Flow from `prev` to `next` (same shape) inside `roi` (whole image if `None`), optionally
    /// starting from `init` (full-resolution flow; NaN counts as 0).
    pub fn compute(
        &mut self,
        prev: ArrayView2<f32>,
        next: ArrayView2<f32>,
        roi: Option<Roi>,
        init: Option<&Flow>,
    ) -> Result<Flow> {
        let mut out = Flow {
            u: Array2::zeros((0, 0)),
            v: Array2::zeros((0, 0)),
        };
        self.compute_into(prev, next, roi, init, &mut out)?;
        Ok(out)
    }

    /// [`Farneback::compute`] writing into `out`, whose arrays are reused when they already
    /// have the images' shape (no page-faulting fresh 2×4·H·W bytes per frame).
    pub fn compute_into(
        &mut self,
        prev: ArrayView2<f32>,
        next: ArrayView2<f32>,
        roi: Option<Roi>,
        init: Option<&Flow>,
        out: &mut Flow,
    ) -> Result<()> {
        let (h, w) = prev.dim();
        let reuse = std::mem::take(&mut self.prev_unchanged);
        let rows = self.next_rows.take();
        let roi_rect = checked_domain(prev.dim(), next.dim(), roi, init)?;
        for a in [&mut out.u, &mut out.v] {
            if a.dim() == (h, w) {
                a.par_mapv_inplace(|_| f32::NAN);
            } else {
                *a = filled(h, w, f32::NAN);
            }
        }
        let (out_u, out_v) = (&mut out.u, &mut out.v);

        let geoms = self.geometry(h, w, roi_rect);
        // Normalisation: statistics of prev over the finest domain (offset and unit free).
        let Some((mean, sd)) = finite_stats(prev, geoms[0].dom) else {
            // Constant or empty image: nothing to measure.
            return Ok(());
        };
        let (offset, gain) = (mean as f32, (1.0 / sd) as f32);
        let norm0 = pyramid::Normalised {
            img: prev,
            offset,
            gain,
        };
        let norm1 = pyramid::Normalised { img: next, ..norm0 };

        let m = self.params.winsize / 2;
        let use_grid = self.options.uses_grid();
        let mut prev_geom: Option<LevelGeom> = None;
        let finest = self.options.finest_level.min(geoms.len() - 1);
        for (k, g) in geoms.iter().enumerate().rev() {
            if k < finest {
                break;
            }
            let dom = g.dom;
            let (dh, dw) = (dom.height(), dom.width());
            let key = ExpansionKey {
                image: (h, w),
                level: (g.h, g.w),
                dom,
                offset,
                gain,
                poly: (self.params.poly_n, self.params.poly_sigma),
            };
            let expand = |img, r: &mut Vec<f32>| {
                let level = pyramid::LevelRows::new(img, g.scale, (g.h, g.w), dom);
                poly::expand(&self.poly, &level, r);
            };
            if !(reuse && self.r0_key == Some(key)) {
                expand(norm0, &mut self.r0);
            }
            expand(norm1, &mut self.r1);
            self.r0_key = Some(key);

            // Initial flow for this level (dense, or on the grid).
            if use_grid {
                self.grid_start(g, prev_geom, init);
            } else {
                let n = dh * dw;
                for b in 0..2 {
                    fill_vec(&mut self.u[b], n, 0.0);
                    fill_vec(&mut self.v[b], n, 0.0);
                }
                if let Some(pg) = prev_geom {
                    upsample(
                        &self.prev_u,
                        &self.prev_v,
                        pg,
                        *g,
                        1.0 / self.params.pyr_scale,
                        &mut self.u[0],
                        &mut self.v[0],
                    );
                } else if let Some(f) = init {
                    sample_init(f, g, &mut self.u[0], &mut self.v[0]);
                }
            }
            prev_geom = Some(*g);

            let t = solve::typical_trace(&self.r0, dw);
            if !(t > 0.0 && t.is_finite()) {
                // No usable texture at this level: keep the flow as it is.
                std::mem::swap(&mut self.prev_u, &mut self.u[0]);
                std::mem::swap(&mut self.prev_v, &mut self.v[0]);
                if use_grid {
                    std::mem::swap(&mut self.prev_grid_xs, &mut self.grid_xs);
                    std::mem::swap(&mut self.prev_grid_ys, &mut self.grid_ys);
                }
                continue;
            }
            let col_taper = solve::column_taper(dom.x0, dw, g.w);
            let lv = solve::Level {
                h: dh,
                w: dw,
                y0: dom.y0,
                level_h: g.h,
                r0: &self.r0,
                r1: &self.r1,
                col_taper: &col_taper,
                m,
                gauss: self.gauss.as_deref(),
                reg_abs: 1e-6 * t,
                reg_rel: 1e-9,
                empty_trace: 1e-9 * t,
            };
            let iters = match (
                k,
                self.options.finest_iterations,
                self.options.coarse_iterations,
            ) {
                (0, Some(n), _) => n,
                (1.., _, Some(n)) => n,
                _ => self.params.iterations,
            };
            let ytaps = if use_grid {
                grid::taps(&self.grid_ys, dh)
            } else {
                Vec::new()
            };
            let gr = grid::Grid {
                xs: &self.grid_xs,
                ys: &self.grid_ys,
                ytaps: &ytaps,
                affine: self.options.model == WindowModel::Affine,
            };
            let mut cur = 0;
            for it in 0..iters {
                let last = k == finest && it + 1 == iters;
                let (ua, ub) = self.u.split_at_mut(1);
                let (va, vb) = self.v.split_at_mut(1);
                let (u_old, u_new, v_old, v_new) = if cur == 0 {
                    (&ua[0], &mut ub[0], &va[0], &mut vb[0])
                } else {
                    (&ub[0], &mut ua[0], &vb[0], &mut va[0])
                };
                if use_grid {
                    u_new.resize(u_old.len(), 0.0);
                    v_new.resize(v_old.len(), 0.0);
                }
                let old = solve::FieldView { u: u_old, v: v_old };
                let new = solve::FieldMut { u: u_new, v: v_new };
                if use_grid {
                    grid::iterate(&lv, &gr, old, new, &mut self.grid_scratch, last);
                } else {
                    solve::iterate(&lv, old, new, &mut self.scratch, last);
                }
                cur = 1 - cur;
            }
            std::mem::swap(&mut self.prev_u, &mut self.u[cur]);
            std::mem::swap(&mut self.prev_v, &mut self.v[cur]);
            if use_grid {
                std::mem::swap(&mut self.prev_grid_xs, &mut self.grid_xs);
                std::mem::swap(&mut self.prev_grid_ys, &mut self.grid_ys);
            }
        }

        // Copy the ROI out of the finest domain.
        let d0 = geoms[0].dom;
        let dw = d0.width();
        if finest > 0 {
            self.upsample_finish(&geoms, finest);
        } else if self.options.uses_grid() {
            self.densify(d0, roi_rect, rows, prev, out_u, out_v);
            return Ok(());
        }
        let (pu, pv) = (&self.prev_u, &self.prev_v);
        out_u
            .axis_iter_mut(ndarray::Axis(0))
            .into_par_iter()
            .zip(out_v.axis_iter_mut(ndarray::Axis(0)).into_par_iter())
            .enumerate()
            .skip(roi_rect.y0)
            .take(roi_rect.y1 - roi_rect.y0)
            .filter(|(y, _)| rows.is_none_or(|r| r.holds(*y)))
            .for_each(|(y, (mut ur, mut vr))| {
                for x in roi_rect.x0..roi_rect.x1 {
                    if prev[[y, x]].is_finite() {
                        let i = (y - d0.y0) * dw + (x - d0.x0);
                        ur[x] = pu[i];
                        vr[x] = pv[i];
                    }
                }
            });
        Ok(())
    }
}

impl Farneback {
    /// Grid flow for level `g` at its start: from the coarser level's grid, from `init`, or 0.
    fn grid_start(&mut self, g: &LevelGeom, from: Option<LevelGeom>, init: Option<&Flow>) {
        let s = self.options.grid_stride;
        let xs = grid::axis(g.dom.x0, g.dom.width(), s);
        let ys = grid::axis(g.dom.y0, g.dom.height(), s);
        let (nx, ny) = (xs.len(), ys.len());
        for b in 0..2 {
            self.u[b].clear();
            self.u[b].resize(nx * ny, 0.0);
            self.v[b].clear();
            self.v[b].resize(nx * ny, 0.0);
        }
        if let Some(c) = from {
            let f = (1.0 / self.params.pyr_scale) as f32;
            let (rx, ry) = (c.w as f64 / g.w as f64, c.h as f64 / g.h as f64);
            for (i, &y) in ys.iter().enumerate() {
                let cy = ((g.dom.y0 + y) as f64 + 0.5) * ry - 0.5 - c.dom.y0 as f64;
                for (j, &x) in xs.iter().enumerate() {
                    let cx = ((g.dom.x0 + x) as f64 + 0.5) * rx - 0.5 - c.dom.x0 as f64;
                    let (pxs, pys) = (&self.prev_grid_xs, &self.prev_grid_ys);
                    self.u[0][i * nx + j] = grid::sample(&self.prev_u, pxs, pys, cx, cy) * f;
                    self.v[0][i * nx + j] = grid::sample(&self.prev_v, pxs, pys, cx, cy) * f;
                }
            }
        } else if let Some(fl) = init {
            let (dw, dh) = (g.dom.width(), g.dom.height());
            let mut du = vec![0f32; dw * dh];
            let mut dv = vec![0f32; dw * dh];
            sample_init(fl, g, &mut du, &mut dv);
            for (i, &y) in ys.iter().enumerate() {
                for (j, &x) in xs.iter().enumerate() {
                    self.u[0][i * nx + j] = du[y * dw + x];
                    self.v[0][i * nx + j] = dv[y * dw + x];
                }
            }
        }
        self.grid_xs = xs;
        self.grid_ys = ys;
    }

    /// Bring the flow finished on level `finest` to full resolution (dense, in `prev_u/v`).
    fn upsample_finish(&mut self, geoms: &[LevelGeom], finest: usize) {
        let from = geoms[finest];
        let (fw, fh) = (from.dom.width(), from.dom.height());
        if self.options.uses_grid() {
            // Grid → dense on the level's domain first.
            let ytaps = grid::taps(&self.prev_grid_ys, fh);
            let gr = grid::Grid {
                xs: &self.prev_grid_xs,
                ys: &self.prev_grid_ys,
                ytaps: &ytaps,
                affine: false,
            };
            fill_vec(&mut self.u[0], fw * fh, 0.0);
            fill_vec(&mut self.v[0], fw * fh, 0.0);
            let (pu, pv) = (&self.prev_u, &self.prev_v);
            self.u[0]
                .par_chunks_mut(fw)
                .zip(self.v[0].par_chunks_mut(fw))
                .enumerate()
                .for_each(|(y, (ur, vr))| grid::flow_row(&gr, pu, pv, y, ur, vr));
            std::mem::swap(&mut self.prev_u, &mut self.u[0]);
            std::mem::swap(&mut self.prev_v, &mut self.v[0]);
        }
        let to = geoms[0];
        let n = to.dom.width() * to.dom.height();
        fill_vec(&mut self.u[0], n, 0.0);
        fill_vec(&mut self.v[0], n, 0.0);
        upsample(
            &self.prev_u,
            &self.prev_v,
            from,
            to,
            1.0 / from.scale,
            &mut self.u[0],
            &mut self.v[0],
        );
        std::mem::swap(&mut self.prev_u, &mut self.u[0]);
        std::mem::swap(&mut self.prev_v, &mut self.v[0]);
    }

    /// Interpolate the finest level's grid flow onto the ROI's pixels (NaN next to a NaN grid
    /// node, and where `prev` is NaN).
    fn densify(
        &self,
        d0: Rect,
        roi: Rect,
        rows: Option<RowLattice>,
        prev: ArrayView2<f32>,
        out_u: &mut Array2<f32>,
        out_v: &mut Array2<f32>,
    ) {
        use rayon::prelude::*;
        let (xs, ys) = (&self.prev_grid_xs, &self.prev_grid_ys);
        let ytaps = grid::taps(ys, d0.height());
        let gr = grid::Grid {
            xs,
            ys,
            ytaps: &ytaps,
            affine: false,
        };
        let (gu, gv) = (&self.prev_u, &self.prev_v);
        let dw = d0.width();
        out_u
            .axis_iter_mut(ndarray::Axis(0))
            .into_par_iter()
            .zip(out_v.axis_iter_mut(ndarray::Axis(0)).into_par_iter())
            .enumerate()
            .filter(|(y, _)| (roi.y0..roi.y1).contains(y) && rows.is_none_or(|r| r.holds(*y)))
            .for_each_init(
                || (vec![0f32; dw], vec![0f32; dw]),
                |(ru, rv), (y, (mut ou, mut ov))| {
                    grid::flow_row(&gr, gu, gv, y - d0.y0, ru, rv);
                    let p = prev.row(y);
                    for x in roi.x0..roi.x1 {
                        if p[x].is_finite() {
                            ou[x] = ru[x - d0.x0];
                            ov[x] = rv[x - d0.x0];
                        }
                    }
                },
            );
    }
}

/// Bilinear upsampling of the coarser level's flow into this level's domain (OpenCV's
/// `resize(..., INTER_LINEAR)` geometry), multiplied by `factor`.
fn upsample(
    pu: &[f32],
    pv: &[f32],
    from: LevelGeom,
    to: LevelGeom,
    factor: f64,
    u: &mut [f32],
    v: &mut [f32],
) {
    use rayon::prelude::*;
    let fw = from.dom.width();
    let f = factor as f32;
    let xt = pyramid::resize_taps(to.dom.x0..to.dom.x1, from.w, to.w);
    let yt = pyramid::resize_taps(to.dom.y0..to.dom.y1, from.h, to.h);
    // Positions outside the coarser domain clamp to it (it covers them except at image edges).
    let cx = |i: usize| i.clamp(from.dom.x0, from.dom.x1 - 1) - from.dom.x0;
    let cy = |i: usize| i.clamp(from.dom.y0, from.dom.y1 - 1) - from.dom.y0;
    let tw = to.dom.width();
    u.par_chunks_mut(tw)
        .zip(v.par_chunks_mut(tw))
        .zip(yt.par_iter())
        .for_each(|((ur, vr), &(y0, y1, wy))| {
            let (ra, rb) = (cy(y0) * fw, cy(y1) * fw);
            for ((uo, vo), &(x0, x1, wx)) in ur.iter_mut().zip(vr.iter_mut()).zip(&xt) {
                let (a, b) = (cx(x0), cx(x1));
                let lerp = |p: &[f32]| {
                    let top = p[ra + a] + wx * (p[ra + b] - p[ra + a]);
                    let bot = p[rb + a] + wx * (p[rb + b] - p[rb + a]);
                    top + wy * (bot - top)
                };
                *uo = lerp(pu) * f;
                *vo = lerp(pv) * f;
            }
        });
}

/// Initial flow for the coarsest level: bilinear samples of the full-resolution flow at the
/// level pixels' centres, scaled to level pixels; NaN counts as zero.
fn sample_init(init: &Flow, g: &LevelGeom, u: &mut [f32], v: &mut [f32]) {
    let (h, w) = init.u.dim();
    let xt = pyramid::resize_taps(g.dom.x0..g.dom.x1, w, g.w);
    let yt = pyramid::resize_taps(g.dom.y0..g.dom.y1, h, g.h);
    let s = g.scale as f32;
    let z = |x: f32| if x.is_finite() { x } else { 0.0 };
    let tw = g.dom.width();
    for (j, &(y0, y1, wy)) in yt.iter().enumerate() {
        for (i, &(x0, x1, wx)) in xt.iter().enumerate() {
            let lerp = |a: &Array2<f32>| {
                let top = z(a[[y0, x0]]) + wx * (z(a[[y0, x1]]) - z(a[[y0, x0]]));
                let bot = z(a[[y1, x0]]) + wx * (z(a[[y1, x1]]) - z(a[[y1, x0]]));
                top + wy * (bot - top)
            };
            u[j * tw + i] = lerp(&init.u) * s;
            v[j * tw + i] = lerp(&init.v) * s;
        }
    }
}

/// Dense Farneback flow from `prev` to `next` (see the module docs). One-shot convenience
/// around [`Farneback`]; keep a `Farneback` to reuse buffers between frames.
pub fn farneback(
    prev: ArrayView2<f32>,
    next: ArrayView2<f32>,
    params: &FarnebackParams,
    roi: Option<Roi>,
) -> Result<Flow> {
    Farneback::new(params.clone())?.compute(prev, next, roi, None)
}

/// [`farneback`] starting from an initial flow (e.g. a previous estimate).
pub fn farneback_with_init(
    prev: ArrayView2<f32>,
    next: ArrayView2<f32>,
    params: &FarnebackParams,
    roi: Option<Roi>,
    init: &Flow,
) -> Result<Flow> {
    Farneback::new(params.clone())?.compute(prev, next, roi, Some(init))
}

/// The rectangle of a `prev` of shape `prev` (height, width) the flow is measured on: the
/// whole image or `roi` clipped to it, once the shapes of `next` and `init` agree.
fn checked_domain(
    prev: (usize, usize),
    next: (usize, usize),
    roi: Option<Roi>,
    init: Option<&Flow>,
) -> Result<Rect> {
    let (h, w) = prev;
    if next != (h, w) {
        return Err(Error::Usage(format!(
            "flow: prev is {}×{} but next is {}×{} (width×height)",
            w, h, next.1, next.0
        )));
    }
    if h == 0 || w == 0 {
        return Err(Error::Usage("flow: empty image".into()));
    }
    if let Some(f) = init {
        if f.u.dim() != (h, w) || f.v.dim() != (h, w) {
            return Err(Error::Usage(
                "flow: initial flow has a different shape than the images".into(),
            ));
        }
    }
    Ok(match roi {
        None => Rect {
            x0: 0,
            y0: 0,
            x1: w,
            y1: h,
        },
        Some(r) => {
            let x1 = r.x.saturating_add(r.width).min(w);
            let y1 = r.y.saturating_add(r.height).min(h);
            if r.x >= x1 || r.y >= y1 {
                return Err(Error::Usage(format!(
                    "flow: ROI {r:?} does not intersect the {w}×{h} image"
                )));
            }
            Rect {
                x0: r.x,
                y0: r.y,
                x1,
                y1,
            }
        }
    })
}

#[cfg(test)]
mod tests;
