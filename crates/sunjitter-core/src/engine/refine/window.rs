//! The frame as the refinement samples it: windows of its grid, prefiltered for the model
//! spline.

use super::reference::Pixel;
use super::MODEL;
use crate::engine::derotate::Carried;
use crate::engine::region::gaussian_reach;
use crate::geometry::Similarity;
use crate::resample::HighOrderSpline;
use ndarray::{s, ArrayView2};
use rayon::prelude::*;

/// The frame as the refinement compares it: smoothed, prefiltered for spline sampling, on
/// the window of its grid that the pixels map into. Smoothing before the warp instead of
/// after is the same to first order in the scale change (a Gaussian is isotropic), and lets
/// every iteration sample only the pixels the fit uses instead of warping the whole box.
pub struct FrameWindow {
    /// One tile for a pair's refinement; several, far apart, for a self-test on tiles.
    pub(super) tiles: Vec<WindowTile>,
    /// The Sun's motion between the two times: pixels are sampled at `T(S(p))`.
    pub(super) carried: Option<Carried>,
}

/// A part of the frame, prefiltered for spline sampling.
pub(super) struct WindowTile {
    pub(super) spline: HighOrderSpline,
    /// Frame-grid position of the tile's first column and row.
    pub(super) origin: [f64; 2],
    /// Frame-grid position of its last column and row.
    pub(super) end: [f64; 2],
}

impl WindowTile {
    /// How far `(x, y)` lies inside the tile, px (negative outside).
    fn depth(&self, x: f64, y: f64) -> f64 {
        (x - self.origin[0])
            .min(self.end[0] - x)
            .min(y - self.origin[1])
            .min(self.end[1] - y)
    }
}

/// Pixels sampled per task.
pub(super) const SAMPLE_CHUNK: usize = 4096;

/// Room around the pixels' image in the frame: the smoothing's reach, the model spline's
/// support (3 px) and prefilter border transient (0.431^17 < 1e-6), and the motion of the
/// iterations.
pub(super) fn window_margin(sigma_px: f64) -> f64 {
    (gaussian_reach(sigma_px) + 3 + 17 + 8) as f64
}

impl FrameWindow {
    /// The part of `frame` that the pixels in `bbox` (reference grid) map into through `t`,
    /// smoothed by `sigma_px`; `None` when that lies outside the frame.
    pub fn new(
        frame: ArrayView2<f32>,
        bbox: (usize, usize, usize, usize),
        t: &Similarity,
        sigma_px: f64,
        carried: Option<&Carried>,
    ) -> Option<FrameWindow> {
        let (h, w) = frame.dim();
        let moved = carried.map_or(0.0, |c| c.max_px.ceil());
        let (x0, y0, x1, y1) = mapped_window(bbox, t, window_margin(sigma_px) + moved, w, h)?;
        let smoothed =
            crate::preprocess::gaussian_smooth(frame.slice(s![y0..=y1, x0..=x1]), sigma_px);
        Some(FrameWindow {
            tiles: vec![WindowTile {
                spline: HighOrderSpline::new(smoothed.view(), MODEL),
                origin: [x0 as f64, y0 as f64],
                end: [x1 as f64, y1 as f64],
            }],
            carried: carried.cloned(),
        })
    }

    /// Where the Sun carried each pixel (`None`: no rotation to follow); the same for every
    /// iteration.
    pub(super) fn carried_positions(&self, pixels: &[Pixel]) -> Option<Vec<(f64, f64)>> {
        let c = self.carried.as_ref()?;
        Some(c.at_pixels(pixels, |p| (p.x, p.y)))
    }

    /// Whether no two tiles' interiors overlap (a self-test's tiles lie far apart).
    fn tiles_disjoint(&self) -> bool {
        let apart = |a: &WindowTile, b: &WindowTile| {
            (0..2).any(|k| a.end[k] <= b.origin[k] || b.end[k] <= a.origin[k])
        };
        self.tiles
            .iter()
            .enumerate()
            .all(|(i, a)| self.tiles[i + 1..].iter().all(|b| apart(a, b)))
    }

    /// The tile that frame position `p` lies deepest in.
    fn tile_of(&self, p: [f64; 2]) -> usize {
        if self.tiles.len() == 1 {
            return 0;
        }
        let depth = |k: usize| self.tiles[k].depth(p[0], p[1]);
        let first = (0, depth(0));
        (1..self.tiles.len())
            .fold(first, |best, k| {
                let d = depth(k);
                if d > best.1 {
                    (k, d)
                } else {
                    best
                }
            })
            .0
    }

    /// Value and reference-grid gradient of the frame at the image of each pixel through `t`
    /// (of each pixel's carried position, when given).
    pub(super) fn sample(
        &self,
        pixels: &[Pixel],
        carried: Option<&[(f64, f64)]>,
        t: &Similarity,
    ) -> Vec<[f64; 3]> {
        let mut out = vec![[0.0; 3]; pixels.len()];
        self.sample_into(pixels, carried, t, &mut out);
        out
    }

    /// [`Self::sample`] into `out` (one entry per pixel): iterations resample into the
    /// buffer they read last, instead of faulting in a new one.
    pub(super) fn sample_into(
        &self,
        pixels: &[Pixel],
        carried: Option<&[(f64, f64)]>,
        t: &Similarity,
        out: &mut [[f64; 3]],
    ) {
        assert_eq!(out.len(), pixels.len(), "one sample per pixel");
        let (a, b) = t.ab();
        let map = crate::resample::similarity_map(t);
        let disjoint = self.tiles_disjoint();
        out.par_chunks_mut(SAMPLE_CHUNK)
            .zip(pixels.par_chunks(SAMPLE_CHUNK))
            .enumerate()
            .for_each(|(k, (out, pixels))| {
                let moved = carried.map(|c| &c[k * SAMPLE_CHUNK..]);
                let mut positions: Vec<[f64; 2]> = pixels
                    .iter()
                    .enumerate()
                    .map(|(i, p)| {
                        let (px, py) = moved.map_or((p.x as f64, p.y as f64), |m| m[i]);
                        let (x, y) = map(px, py);
                        [x, y]
                    })
                    .collect();
                // Runs of positions in one tile, each sampled from the tile it lies deepest in.
                // Inside a tile that overlaps no other, a position lies deepest in it.
                let inside =
                    |tile: usize, [x, y]: [f64; 2]| disjoint && self.tiles[tile].depth(x, y) > 0.0;
                let mut start = 0;
                while start < positions.len() {
                    let tile = self.tile_of(positions[start]);
                    let mut stop = start + 1;
                    while stop < positions.len()
                        && (inside(tile, positions[stop]) || self.tile_of(positions[stop]) == tile)
                    {
                        stop += 1;
                    }
                    let t = &self.tiles[tile];
                    for q in &mut positions[start..stop] {
                        *q = [q[0] - t.origin[0], q[1] - t.origin[1]];
                    }
                    t.spline
                        .sample_with_gradient_at(&positions[start..stop], &mut out[start..stop]);
                    start = stop;
                }
                for s in out.iter_mut() {
                    let [v, fx, fy] = *s;
                    // ∇(frame ∘ T) = Jᵀ ∇frame with J = [[a, −b], [b, a]].
                    *s = [v, a * fx + b * fy, -b * fx + a * fy];
                }
            });
    }
}

/// Bounding box (inclusive) on a `w × h` grid of the image of `bbox` through `t`, grown by
/// `margin`; `None` when it misses the grid or the transform is not finite.
pub(super) fn mapped_window(
    bbox: (usize, usize, usize, usize),
    t: &Similarity,
    margin: f64,
    w: usize,
    h: usize,
) -> Option<(usize, usize, usize, usize)> {
    let (bx0, by0, bx1, by1) = bbox;
    let corners = [(bx0, by0), (bx1, by0), (bx0, by1), (bx1, by1)]
        .map(|(x, y)| t.apply([x as f64, y as f64]));
    if corners.iter().flatten().any(|v| !v.is_finite()) || w < 8 || h < 8 {
        return None;
    }
    let lo = |k: usize| corners.iter().map(|c| c[k]).fold(f64::INFINITY, f64::min) - margin;
    let hi = |k: usize| {
        corners
            .iter()
            .map(|c| c[k])
            .fold(f64::NEG_INFINITY, f64::max)
            + margin
    };
    let (x0, x1) = (lo(0).floor().max(0.0), hi(0).ceil().min(w as f64 - 1.0));
    let (y0, y1) = (lo(1).floor().max(0.0), hi(1).ceil().min(h as f64 - 1.0));
    (x1 - x0 >= 8.0 && y1 - y0 >= 8.0).then_some((
        x0 as usize,
        y0 as usize,
        x1 as usize,
        y1 as usize,
    ))
}
