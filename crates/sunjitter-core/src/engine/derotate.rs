//! The Sun's rotation taken out of a pair: the reference is carried to the frame's time, so
//! that the engine measures only the telescope.
//!
//! With `C` the header-predicted (coarse) map reference → frame and `F` the solar-surface map
//! reference pixel → frame pixel at the frame's time ([`SurfaceMotion`]), the surface motion
//! on the reference grid is `S = C⁻¹∘F`. Every stage samples the frame at `T(S(p))` where it
//! sampled `T(p)`; for a frame moved by the telescope `J` on top of the headers
//! (`frame(J(F(p))) = ref(p)`) the answer is `T = J∘C` exactly. The surface motion costs a
//! few thousand evaluations of the model per pair, read by cubic convolution between them.
//!
//! A field that does not hold the whole disk (IRIS, TRACE, DKIST) is taken to follow the
//! Sun at its centre, as such instruments do: the headers' pointing (per frame where they give
//! it) plus the rotation predict the image, and without per-frame pointing only the rotation
//! relative to the field's centre is removed. Full-disk images are not tracked.

use crate::geometry::Similarity;
use crate::meta::FrameMeta;
pub use crate::record::SolarRotationFields;
use crate::solar_rotation::{grid_step_px, DisplacementGrid, Moved, Profile, SurfaceMotion, View};
use ndarray::Array2;
use std::sync::Arc;

/// A pair with the rotation to take out: the surface motion, the coarse map to start from,
/// and what was done.
pub(crate) struct Derotated {
    pub carried: Carried,
    pub coarse: Similarity,
    pub fields: SolarRotationFields,
    pub notes: Vec<String>,
}

/// Where the engine stands on the Sun's rotation for one pair.
pub(crate) enum Rotation {
    /// Taken out.
    Removed(Derotated),
    /// Nothing to take out (profile `none`, equal times), or not possible (said in `note`).
    Kept {
        fields: Option<SolarRotationFields>,
        note: Option<String>,
    },
    /// The two images were taken from different places: no similarity relates them.
    Refused(String),
}

/// Observers further apart than this (seen from the Sun) see different faces of it: STEREO
/// and SDO, or a spacecraft and the Earth. One observer moves far less between its frames.
pub const MAX_VIEWPOINT_SEPARATION_DEG: f64 = 5.0;

/// Inputs of [`derotate`] that describe the reference side.
pub(crate) struct ReferenceSide<'a> {
    pub meta: &'a FrameMeta,
    pub disk_px: Option<([f64; 2], f64)>,
    pub mask: &'a Array2<bool>,
    pub mask_box: crate::flow::Roi,
    pub mask_fraction: f64,
}

/// The Sun's motion between the reference's time and the frame's, and the coarse map that
/// goes with it (see the module documentation).
pub(crate) fn derotate(
    reference: &ReferenceSide,
    frame_meta: &FrameMeta,
    coarse: Similarity,
    profile: Profile,
) -> Rotation {
    let kept = |note: Option<String>| Rotation::Kept { fields: None, note };
    let views = View::new(reference.meta).zip(View::new(frame_meta));
    if let Some((from, to)) = &views {
        let apart =
            SurfaceMotion::new(from.clone(), to.clone(), Profile::None).viewpoint_separation_deg();
        if apart > MAX_VIEWPOINT_SEPARATION_DEG {
            return Rotation::Refused(format!(
                "the images were taken from viewpoints {apart:.1}° apart (HGLN_OBS/HGLT_OBS): \
                 no similarity maps one onto the other"
            ));
        }
    }
    let nothing = |dt_s: f64| SolarRotationFields {
        profile,
        dt_s,
        dx_px: 0.0,
        dy_px: 0.0,
        tracked: false,
    };
    if profile == Profile::None {
        return Rotation::Kept {
            fields: dt_s(reference.meta, frame_meta).map(nothing),
            note: None,
        };
    }
    let Some((from, to)) = views else {
        return kept(Some(
            "solar rotation not removed: no observation time or no usable WCS".into(),
        ));
    };
    let motion = SurfaceMotion::new(from, to, profile);
    if motion.dt_s() == 0.0 {
        return Rotation::Kept {
            fields: Some(nothing(0.0)),
            note: None,
        };
    }
    let (h, w) = reference.mask.dim();
    let full_disk = holds_the_disk(reference.disk_px, w, h);
    let inverse = coarse.inverse();
    // G = C⁻¹∘F on the reference grid: the surface motion as the reference's pixels see it.
    let on_reference = |p: [f64; 2]| match motion.map(p) {
        Moved::To(q) => Some(inverse.apply(q)),
        _ => None,
    };
    let centre = if full_disk {
        reference.meta.sun_center_px
    } else {
        let b = reference.mask_box;
        [
            b.x as f64 + (b.width as f64 - 1.0) / 2.0,
            b.y as f64 + (b.height as f64 - 1.0) / 2.0,
        ]
    };
    let found = on_reference(centre)
        .map(|m| (centre, m))
        .or_else(|| mask_point_on_disk(reference, &on_reference));
    let Some((centre, moved_centre)) = found else {
        return kept(Some(
            "solar rotation not removed: no part of the field lies on the solar disk".into(),
        ));
    };
    let removed = [moved_centre[0] - centre[0], moved_centre[1] - centre[1]];
    // A tracked field: the centre's motion belongs to the pointing, C_eff(p) = C(p + τ).
    let (tau, coarse_eff) = if full_disk {
        ([0.0, 0.0], coarse)
    } else {
        let c = coarse.center;
        let [ax, ay] = coarse.apply([c[0] + removed[0], c[1] + removed[1]]);
        let [bx, by] = coarse.apply(c);
        (
            removed,
            Similarity {
                dx: coarse.dx + (ax - bx),
                dy: coarse.dy + (ay - by),
                ..coarse
            },
        )
    };
    let eff_inverse = coarse_eff.inverse();
    // S(p) − p on the reference grid: C_eff⁻¹(F(p)) on the disk, C_eff⁻¹(C(p)) on the sky.
    let displacement = |p: [f64; 2]| -> [f64; 2] {
        let q = match motion.map(p) {
            Moved::To(q) => q,
            Moved::Hidden => return [f64::NAN; 2],
            Moved::OffDisk => coarse.apply(p),
        };
        let s = eff_inverse.apply(q);
        [s[0] - p[0], s[1] - p[1]]
    };
    let radius_px = reference.disk_px.map_or(w.max(h) as f64, |(_, r)| r);
    let largest = (moved_centre[0] - centre[0]).hypot(moved_centre[1] - centre[1]);
    let step = grid_step_px(
        largest.max(1e-6),
        radius_px,
        reference.mask_fraction.max(0.9),
    );
    let grid = DisplacementGrid::sample(w, h, step, displacement);
    let mut notes = Vec::new();
    if motion.observer_assumed() {
        notes
            .push("solar rotation: observer keywords missing, the Earth's position assumed".into());
    }
    Rotation::Removed(Derotated {
        carried: Carried::new(grid),
        coarse: coarse_eff,
        fields: SolarRotationFields {
            profile,
            dt_s: motion.dt_s(),
            dx_px: removed[0] - tau[0],
            dy_px: removed[1] - tau[1],
            tracked: !full_disk,
        },
        notes,
    })
}

/// The Sun's motion between the two times on the reference grid, `S(p) = p + field(p)`: the
/// frame is sampled at `T(S(p))` instead of `T(p)`. On binned copies (`factor` 2^level) the
/// same field in binned pixels.
#[derive(Debug, Clone)]
pub struct Carried {
    grid: Arc<DisplacementGrid>,
    factor: f64,
    /// Largest motion, px of this grid.
    pub max_px: f64,
    /// Whether every point of the grid has a motion (none is hidden).
    all_finite: bool,
}

/// Largest `Σ|w|` of the 4 × 4 cubic convolution weights (Keys, a = −½): 1.25 per axis, at a
/// fraction of ½. An interpolated motion is at most this times the largest node's.
const CUBIC_CONVOLUTION_GAIN: f64 = 1.25 * 1.25;

impl Carried {
    fn new(grid: DisplacementGrid) -> Carried {
        let max_px = grid.max_norm();
        let all_finite = grid.all_finite();
        Carried {
            grid: Arc::new(grid),
            factor: 1.0,
            max_px,
            all_finite,
        }
    }

    /// The same motion on copies binned by `factor`.
    pub fn binned(&self, factor: usize) -> Carried {
        let f = self.factor * factor as f64;
        Carried {
            grid: self.grid.clone(),
            factor: f,
            max_px: self.max_px * self.factor / f,
            all_finite: self.all_finite,
        }
    }

    /// A bound on `|S(p) − p|` over the image, px of this grid; `None` when some point is
    /// hidden (its `S(p)` is NaN).
    pub fn motion_bound_px(&self) -> Option<f64> {
        self.all_finite
            .then_some(CUBIC_CONVOLUTION_GAIN * self.max_px)
    }

    /// `S(p)`: where the surface point at `p` is at the frame's time (NaN: hidden).
    #[inline]
    pub fn at(&self, x: f64, y: f64) -> (f64, f64) {
        let b = self.factor;
        // Binned pixel q covers full pixels b·q … b·q + b − 1: its centre is b·(q + ½) − ½.
        let d = self.grid.at([b * (x + 0.5) - 0.5, b * (y + 0.5) - 0.5]);
        (x + d[0] / b, y + d[1] / b)
    }

    /// [`Carried::at`] at the whole pixel `xy(p)` of each of `pixels`: each column's and each
    /// row's interpolation weights are worked out once, not at every point (the same values).
    pub fn at_pixels<P: Sync>(
        &self,
        pixels: &[P],
        xy: impl Fn(&P) -> (usize, usize) + Sync,
    ) -> Vec<(f64, f64)> {
        use rayon::prelude::*;
        let (w, h) = pixels
            .iter()
            .map(&xy)
            .fold((0, 0), |(w, h), (x, y)| (w.max(x + 1), h.max(y + 1)));
        let b = self.factor;
        let (xt, yt) = (
            self.x_taps(0, w),
            self.grid.y_taps((0..h).map(|y| b * (y as f64 + 0.5) - 0.5)),
        );
        pixels
            .par_iter()
            .map(|p| {
                let (x, y) = xy(p);
                let d = self.grid.at_taps(xt[x].as_ref(), yt[y].as_ref());
                (x as f64 + d[0] / b, y as f64 + d[1] / b)
            })
            .collect()
    }

    /// `S(p) − p` over the `width × height` window at column `x0`, row `y0` (NaN: hidden).
    pub fn shifts(&self, x0: usize, y0: usize, width: usize, height: usize) -> Array2<[f32; 2]> {
        use ndarray::Axis;
        use rayon::prelude::*;
        let mut out = Array2::from_elem((height, width), [0.0f32; 2]);
        let taps = self.x_taps(x0, width);
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(y, mut row)| {
                let row = row
                    .as_slice_mut()
                    .expect("a new array's rows are contiguous");
                self.row_with(&taps, x0, y + y0, row);
            });
        out
    }

    /// `S(p) − p` along row `y` from column `x0`, one value per element of `out`.
    pub fn shifts_row(&self, x0: usize, y: usize, out: &mut [[f32; 2]]) {
        let taps = self.x_taps(x0, out.len());
        self.row_with(&taps, x0, y, out);
    }

    /// Where the grid is read for columns `x0 … x0 + width − 1`: the same for every row.
    fn x_taps(&self, x0: usize, width: usize) -> Vec<Option<crate::solar_rotation::GridTap>> {
        let b = self.factor;
        self.grid
            .x_taps((x0..x0 + width).map(|x| b * (x as f64 + 0.5) - 0.5))
    }

    /// `S(p) − p` along row `y`, as [`Carried::at`] gives it point by point.
    fn row_with(
        &self,
        taps: &[Option<crate::solar_rotation::GridTap>],
        x0: usize,
        y: usize,
        out: &mut [[f32; 2]],
    ) {
        let b = self.factor;
        let yf = y as f64;
        self.grid.row(taps, b * (yf + 0.5) - 0.5, |k, d| {
            let x = (x0 + k) as f64;
            let (sx, sy) = (x + d[0] / b, yf + d[1] / b);
            out[k] = [(sx - x) as f32, (sy - yf) as f32];
        });
    }

    /// `T∘S` as a coordinate map.
    pub fn then(&self, t: &Similarity) -> impl Fn(f64, f64) -> (f64, f64) + Sync + '_ {
        let map = crate::resample::similarity_map(t);
        move |x, y| {
            let (sx, sy) = self.at(x, y);
            map(sx, sy)
        }
    }
}

/// Whether the disk (centre, radius in px) lies whole inside a `w × h` image.
pub(crate) fn holds_the_disk(disk_px: Option<([f64; 2], f64)>, w: usize, h: usize) -> bool {
    disk_px.is_some_and(|(c, r)| {
        c[0] - r >= -0.5
            && c[1] - r >= -0.5
            && c[0] + r <= w as f64 - 0.5
            && c[1] + r <= h as f64 - 0.5
    })
}

/// Frame time minus reference time, s, when both are known.
fn dt_s(reference: &FrameMeta, frame: &FrameMeta) -> Option<f64> {
    Some((frame.obs_time_ns? - reference.obs_time_ns?) as f64 * 1e-9)
}

/// The first mask pixel (scanning a coarse lattice) whose surface point is on the disk now,
/// and where it moves.
fn mask_point_on_disk(
    reference: &ReferenceSide,
    on_reference: &dyn Fn([f64; 2]) -> Option<[f64; 2]>,
) -> Option<([f64; 2], [f64; 2])> {
    let (h, w) = reference.mask.dim();
    let step = (w.max(h) / 32).max(1);
    (0..h).step_by(step).find_map(|y| {
        (0..w).step_by(step).find_map(|x| {
            let p = [x as f64, y as f64];
            reference.mask[[y, x]]
                .then(|| on_reference(p).map(|m| (p, m)))
                .flatten()
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::Roi;

    fn meta(time_s: i64, hgln_deg: f64, sun_center_px: [f64; 2]) -> FrameMeta {
        let cfg = crate::synth::SynthConfig::new(256, 1, 12.0);
        let mut m = cfg.meta(crate::synth::DEFAULT_START_NS + time_s * 1_000_000_000);
        m.observer.hgln_deg = Some(hgln_deg);
        m.sun_center_px = sun_center_px;
        m
    }

    fn side<'a>(
        m: &'a FrameMeta,
        mask: &'a Array2<bool>,
        disk: Option<([f64; 2], f64)>,
    ) -> ReferenceSide<'a> {
        ReferenceSide {
            meta: m,
            disk_px: disk,
            mask,
            mask_box: Roi {
                x: 0,
                y: 0,
                width: 256,
                height: 256,
            },
            mask_fraction: 0.9,
        }
    }

    #[test]
    fn images_from_two_viewpoints_are_refused() {
        // SDO (HGLN 0°) and STEREO-A in 2011 (HGLN about 90°).
        let c = [127.5, 127.5];
        let (r, f) = (meta(0, 0.0, c), meta(60, 90.0, c));
        let mask = Array2::from_elem((256, 256), true);
        let coarse = Similarity::identity(c);
        let got = derotate(
            &side(&r, &mask, Some((c, 100.0))),
            &f,
            coarse,
            Profile::Howard,
        );
        assert!(matches!(got, Rotation::Refused(ref why) if why.contains("90.0°")));
        // The same observer an hour later is measured.
        let f = meta(3600, 0.0, c);
        let got = derotate(
            &side(&r, &mask, Some((c, 100.0))),
            &f,
            coarse,
            Profile::Howard,
        );
        assert!(matches!(got, Rotation::Removed(_)));
    }

    #[test]
    fn pixels_carried_together_land_where_each_alone_does() {
        // `at_pixels` shares each row's and column's weights; every pixel must land exactly
        // where `at` puts it alone, hidden ones (NaN) included, in any order.
        let c = [127.5, 127.5];
        let r = meta(0, 0.0, c);
        let mask = Array2::from_elem((256, 256), true);
        for dt_s in [3600, 6 * 3600] {
            let f = meta(dt_s, 0.0, c);
            let Rotation::Removed(d) = derotate(
                &side(&r, &mask, Some((c, 100.0))),
                &f,
                Similarity::identity(c),
                Profile::Howard,
            ) else {
                panic!("rotation removed after {dt_s} s")
            };
            let pixels: Vec<(usize, usize)> = (0..256)
                .rev()
                .flat_map(|y| (0..256).step_by(3).map(move |x| (x, y)))
                .collect();
            let together = d.carried.at_pixels(&pixels, |&p| p);
            let mut hidden = 0;
            for (&(x, y), &(sx, sy)) in pixels.iter().zip(&together) {
                let (ax, ay) = d.carried.at(x as f64, y as f64);
                hidden += usize::from(ax.is_nan());
                assert_eq!(
                    (sx.to_bits(), sy.to_bits()),
                    (ax.to_bits(), ay.to_bits()),
                    "({x}, {y})"
                );
            }
            assert!(hidden < pixels.len(), "{dt_s} s: every pixel hidden");
        }
    }

    #[test]
    fn the_motion_bound_holds_every_points_motion_or_says_some_is_hidden() {
        // The bound is what lets the refinement skip testing where each pixel lands: every
        // point's |S(p) − p| must lie within it, and without one some point must be hidden.
        let c = [127.5, 127.5];
        let r = meta(0, 0.0, c);
        let mask = Array2::from_elem((256, 256), true);
        let coarse = Similarity::identity(c);
        let mut bounded = 0;
        for dt_s in [60, 3600, 6 * 3600] {
            let f = meta(dt_s, 0.0, c);
            let Rotation::Removed(d) = derotate(
                &side(&r, &mask, Some((c, 100.0))),
                &f,
                coarse,
                Profile::Howard,
            ) else {
                panic!("rotation removed after {dt_s} s")
            };
            let motions: Vec<f64> = (0..1024)
                .flat_map(|y| (0..1024).map(move |x| (x as f64 / 4.0, y as f64 / 4.0)))
                .map(|(x, y)| {
                    let (sx, sy) = d.carried.at(x, y);
                    (sx - x).hypot(sy - y)
                })
                .collect();
            match d.carried.motion_bound_px() {
                Some(bound) => {
                    bounded += 1;
                    let largest = motions.iter().fold(0.0f64, |a, &m| a.max(m));
                    assert!(largest <= bound, "{dt_s} s: {largest} px beyond {bound}");
                    assert!(largest > 0.0, "{dt_s} s: no motion");
                }
                None => assert!(motions.iter().any(|m| m.is_nan()), "{dt_s} s"),
            }
        }
        assert!(bounded > 0, "no bound at any interval");
    }

    #[test]
    fn a_tracked_field_keeps_only_the_rotation_relative_to_its_centre() {
        // A 256² field whose disk (radius 100 px) is mostly outside: the field's centre (on
        // the disk) is taken to follow the Sun, so the surface motion there is zero and the
        // coarse map carries the rotation of that point.
        let c = [-60.0, 127.5];
        let (r, f) = (meta(0, 0.0, c), meta(3600, 0.0, c));
        let mut mask = Array2::from_elem((256, 256), false);
        mask.slice_mut(ndarray::s![100..156, 0..20]).fill(true);
        let coarse = Similarity::identity([127.5, 127.5]);
        let mut s = side(&r, &mask, None);
        s.mask_box = Roi {
            x: 0,
            y: 100,
            width: 20,
            height: 56,
        };
        let Rotation::Removed(d) = derotate(&s, &f, coarse, Profile::Howard) else {
            panic!("rotation removed")
        };
        assert!(d.fields.tracked);
        let centre = [9.5, 127.5];
        let (x, y) = d.carried.at(centre[0], centre[1]);
        // Zero up to the grid's reading of the motion (cubic convolution, about 1e-4 px).
        assert!((x - centre[0]).hypot(y - centre[1]) < 1e-3, "({x}, {y})");
        // The coarse map moved by the centre's rotation: west, a fraction of a pixel per hour
        // at 38″/px (synth's plate scale at 256²: 9.6″, times the disk's 100/25 px ratio).
        assert!(d.coarse.dx > 0.0, "{:?}", d.coarse);
        // Leaving the rotation in the answer: the headers alone predict the image.
        assert!(matches!(
            derotate(&s, &f, coarse, Profile::None),
            Rotation::Kept { .. }
        ));
    }
}
