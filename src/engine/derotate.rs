//! The Sun's rotation taken out of a pair: the frame is resampled so that every solar feature
//! sits where it would have been at the reference's time, and the engine then measures only
//! the telescope.
//!
//! With `C` the header-predicted (coarse) map reference → frame, `F` the solar-surface map
//! reference pixel → frame pixel at the frame's time ([`SurfaceMotion`]), the derotated frame
//! is `frame'(y) = frame(F(C⁻¹(y)))`. A frame moved by the telescope `J` on top of the
//! headers (`frame(J(F(p))) = ref(p)`) then gives `C⁻¹·J·C` up to a term of the rotation
//! field's gradient times `J`'s motion, which is added to σ.
//!
//! A field that does not hold the whole disk (IRIS, TRACE, DKIST) is taken to follow the
//! Sun at its centre, as such instruments do: the headers' pointing (per frame where they give
//! it) plus the rotation predict the image, and without per-frame pointing only the rotation
//! relative to the field's centre is removed. Full-disk images are not tracked.

use super::refine::MODEL;
use crate::geometry::Similarity;
use crate::meta::FrameMeta;
use crate::resample::HighOrderSpline;
use crate::solar_rotation::{grid_step_px, DisplacementGrid, Moved, Profile, SurfaceMotion, View};
use ndarray::{Array2, Axis};
use rayon::prelude::*;
pub use crate::record::SolarRotationFields;

/// A derotated pair: the frame to measure, the coarse map to start from, and what was done.
pub(super) struct Derotated {
    pub frame: Array2<f32>,
    pub coarse: Similarity,
    pub fields: SolarRotationFields,
    /// Largest gradient of the removed displacement (px/px): the error left is this times the
    /// telescope's motion beyond the coarse map.
    pub gradient: f64,
    pub notes: Vec<String>,
}

/// Where the engine stands on the Sun's rotation for one pair.
pub(super) enum Rotation {
    /// Taken out.
    Removed(Derotated),
    /// Nothing to take out (profile `none`, equal times), or not possible (said in `note`).
    Kept {
        fields: Option<SolarRotationFields>,
        note: Option<String>,
    },
}

/// Inputs of [`derotate`] that describe the reference side.
pub(super) struct ReferenceSide<'a> {
    pub meta: &'a FrameMeta,
    pub disk_px: Option<([f64; 2], f64)>,
    pub mask: &'a Array2<bool>,
    pub mask_box: crate::flow::Roi,
    pub mask_fraction: f64,
}

/// Take the rotation between the reference's time and the frame's out of `frame`.
pub(super) fn derotate(
    reference: &ReferenceSide,
    frame_meta: &FrameMeta,
    frame: &Array2<f32>,
    coarse: Similarity,
    profile: Profile,
) -> Rotation {
    let kept = |note: Option<String>| Rotation::Kept { fields: None, note };
    if profile == Profile::None {
        return Rotation::Kept {
            fields: dt_s(reference.meta, frame_meta).map(|dt_s| SolarRotationFields {
                profile,
                dt_s,
                dx_px: 0.0,
                dy_px: 0.0,
                tracked: false,
            }),
            note: None,
        };
    }
    let (Some(from), Some(to)) = (View::new(reference.meta), View::new(frame_meta)) else {
        return kept(Some(
            "solar rotation not removed: no observation time or no usable WCS".into(),
        ));
    };
    let motion = SurfaceMotion::new(from, to, profile);
    if motion.dt_s() == 0.0 {
        return Rotation::Kept {
            fields: Some(SolarRotationFields {
                profile,
                dt_s: 0.0,
                dx_px: 0.0,
                dy_px: 0.0,
                tracked: false,
            }),
            note: None,
        };
    }
    let inverse = coarse.inverse();
    // G = C⁻¹∘F on the reference grid: the surface motion as the reference's pixels see it.
    let on_reference = |p: [f64; 2]| match motion.map(p) {
        Moved::To(q) => Some(inverse.apply(q)),
        _ => None,
    };
    let (h, w) = reference.mask.dim();
    let full_disk = reference.disk_px.is_some_and(|(c, r)| {
        c[0] - r >= -0.5 && c[1] - r >= -0.5 && c[0] + r <= w as f64 - 0.5 && c[1] + r <= h as f64 - 0.5
    });
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
    // D(y) − y on the frame grid: F(C_eff⁻¹(y)) on the disk, C(C_eff⁻¹(y)) on the sky.
    let displacement = |y: [f64; 2]| -> [f64; 2] {
        let p = eff_inverse.apply(y);
        let q = match motion.map(p) {
            Moved::To(q) => q,
            Moved::Hidden => return [f64::NAN; 2],
            Moved::OffDisk => coarse.apply(p),
        };
        [q[0] - y[0], q[1] - y[1]]
    };
    let (fh, fw) = frame.dim();
    let radius_px = reference
        .disk_px
        .map(|(_, r)| r * coarse.scale)
        .unwrap_or((fw.max(fh)) as f64);
    let largest = (removed[0].hypot(removed[1])).max(1e-6);
    let step = grid_step_px(largest, radius_px, reference.mask_fraction.max(0.9));
    let grid = DisplacementGrid::sample(fw, fh, step, displacement);
    let in_mask = |y: [f64; 2]| {
        let p = eff_inverse.apply(y);
        let (x, y) = (p[0].round(), p[1].round());
        x >= 0.0
            && y >= 0.0
            && (x as usize) < w
            && (y as usize) < h
            && reference.mask[[y as usize, x as usize]]
    };
    let gradient = grid.max_gradient(in_mask);

    let spline = HighOrderSpline::new(frame.view(), MODEL);
    let mut out = Array2::<f32>::zeros((fh, fw));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(y, mut row)| {
            for (x, v) in row.iter_mut().enumerate() {
                let d = grid.at([x as f64, y as f64]);
                *v = if d[0] == 0.0 && d[1] == 0.0 {
                    frame[[y, x]]
                } else if d[0].is_finite() && d[1].is_finite() {
                    spline.sample_at(x as f64 + d[0], y as f64 + d[1])
                } else {
                    f32::NAN
                };
            }
        });
    let mut notes = Vec::new();
    if motion.observer_assumed() {
        notes.push("solar rotation: observer keywords missing, the Earth's position assumed".into());
    }
    Rotation::Removed(Derotated {
        frame: out,
        coarse: coarse_eff,
        fields: SolarRotationFields {
            profile,
            dt_s: motion.dt_s(),
            dx_px: removed[0] - tau[0],
            dy_px: removed[1] - tau[1],
            tracked: !full_disk,
        },
        gradient,
        notes,
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

