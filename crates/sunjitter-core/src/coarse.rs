//! Coarse alignment from header metadata (paper §3.1): the similarity that maps the
//! reference pixel grid onto the frame pixel grid.
//!
//! # Derivation
//!
//! For a 0-based pixel `q` of an image with plate scale `D = diag(CDELT1, CDELT2)`,
//! roll `ρ` (`CROTA2`) and sun centre `q☉` (the pixel of helioprojective (0″, 0″)),
//! the FITS linear WCS (`CD = PC·D`, `PC(ρ) = R(ρ) = [[cos ρ, −sin ρ], [sin ρ, cos ρ]]`)
//! gives the helioprojective offset from disk centre
//!
//! ```text
//! w = R(ρ) · D · (q − q☉)                         (arcsec)
//! ```
//!
//! (the TAN projection differs from this by a relative θ²/3 ≈ 1e-5 at the limb: 0.01″).
//! A solar feature seen at `w_r` by the reference observer is seen at
//! `w_f = k · w_r` by the frame's observer, `k = R☉_f / R☉_r` the ratio of apparent
//! solar radii (1 when either is unknown; it is not 1 for observers at different
//! distances, e.g. SOHO at L1 and SDO). Equating and solving for the frame pixel, with
//! isotropic scales `D = d·I` (which commute with rotations):
//!
//! ```text
//! q − q☉_f = k · (d_r / d_f) · R(ρ_r − ρ_f) · (p − q☉_r)
//! ```
//!
//! so `s = k·d_r/d_f` (equivalently, the ratio of the solar radius in frame pixels to
//! that in reference pixels), `θ = ρ_r − ρ_f` (counter-clockwise, x right / y up, as
//! the contract's `R(θ)`), and about the reference array centre `c`:
//!
//! ```text
//! q = s·R(θ)·(p − c) + c + d,   d = q☉_f − c + s·R(θ)·(c − q☉_r).
//! ```
//!
//! Anisotropic pixels (`|CDELT1| ≠ |CDELT2|`) cannot be represented by a similarity: the
//! geometric mean is used and the fine alignment absorbs the rest. Two negative CDELTs
//! are a 180° rotation; exactly one negative CDELT is a mirror image and is refused.

use crate::geometry::Similarity;
use crate::meta::FrameMeta;
use crate::{Error, Result};

/// Where the Sun lies on one pixel grid: enough to map between two grids.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridGeometry {
    /// 0-based pixel of the disk centre.
    pub sun_center_px: [f64; 2],
    /// Pixels per unit length common to both grids: the solar radius in pixels, or pixels
    /// per arcsec when the radius is unknown for either image.
    pub px_per_unit: f64,
    /// Roll in degrees, `CROTA2` sense.
    pub roll_deg: f64,
}

impl GridGeometry {
    /// From a disk measured in the image itself (e.g. [`crate::preprocess::detect_disk`])
    /// and a roll angle from the header: the fallback when a header's scale or centre lies.
    pub fn from_disk(sun_center_px: [f64; 2], radius_px: f64, roll_deg: f64) -> Self {
        GridGeometry {
            sun_center_px,
            px_per_unit: radius_px,
            roll_deg,
        }
    }
}

/// The similarity taking grid `reference` onto grid `frame`, about `center`
/// (the reference array centre). See the module documentation for the derivation.
pub fn similarity_between(
    reference: &GridGeometry,
    frame: &GridGeometry,
    center: [f64; 2],
) -> Similarity {
    let scale = frame.px_per_unit / reference.px_per_unit;
    let rotation_rad = (reference.roll_deg - frame.roll_deg).to_radians();
    let mut t = Similarity {
        scale,
        rotation_rad,
        dx: 0.0,
        dy: 0.0,
        center,
    };
    // d = q☉_f − c + s·R(θ)·(c − q☉_r): with d = 0, apply() gives s·R(θ)·(q☉_r − c) + c.
    let moved = t.apply(reference.sun_center_px);
    t.dx = frame.sun_center_px[0] - moved[0];
    t.dy = frame.sun_center_px[1] - moved[1];
    t
}

/// Isotropic plate scale (arcsec/px) and the roll (degrees) with sign flips folded in.
fn scale_and_roll(meta: &FrameMeta) -> Result<(f64, f64)> {
    let [cx, cy] = meta.plate_scale_arcsec;
    let bad = |reason: String| Err(Error::bad_header(&meta.file, reason));
    if !(cx.is_finite() && cy.is_finite()) || cx == 0.0 || cy == 0.0 {
        return bad(format!("unusable plate scale [{cx}, {cy}] arcsec/px"));
    }
    if (cx < 0.0) != (cy < 0.0) {
        return bad(format!(
            "plate scale [{cx}, {cy}] mirrors the image; a similarity cannot map it"
        ));
    }
    if !meta.rotation_deg.is_finite() {
        return bad(format!("unusable roll angle {}", meta.rotation_deg));
    }
    // diag(−a, −b) = R(180°)·diag(a, b).
    let roll = meta.rotation_deg + if cx < 0.0 { 180.0 } else { 0.0 };
    Ok(((cx * cy).abs().sqrt(), roll))
}

fn usable_radius(meta: &FrameMeta) -> Option<f64> {
    meta.rsun_arcsec.filter(|r| r.is_finite() && *r > 0.0)
}

/// The header-based coarse transform mapping reference pixels to frame pixels
/// (contract convention, centre = reference array centre).
///
/// Scale comes from the plate-scale ratio, corrected by the apparent solar radius ratio
/// when both headers give the radius; rotation from the roll difference; translation
/// from the sun centres. Fails with `BadHeader` on unusable or mirrored plate scales.
pub fn coarse_transform(reference: &FrameMeta, frame: &FrameMeta) -> Result<Similarity> {
    let (scale_r, roll_r) = scale_and_roll(reference)?;
    let (scale_f, roll_f) = scale_and_roll(frame)?;
    for m in [reference, frame] {
        let [x, y] = m.sun_center_px;
        if !(x.is_finite() && y.is_finite()) {
            return Err(Error::bad_header(
                &m.file,
                format!("unusable sun centre [{x}, {y}] px"),
            ));
        }
    }
    let (unit_r, unit_f) = match (usable_radius(reference), usable_radius(frame)) {
        (Some(rr), Some(rf)) => (rr, rf),
        _ => (1.0, 1.0),
    };
    let geometry = |m: &FrameMeta, arcsec_per_px: f64, unit_arcsec: f64, roll: f64| GridGeometry {
        sun_center_px: m.sun_center_px,
        px_per_unit: unit_arcsec / arcsec_per_px,
        roll_deg: roll,
    };
    Ok(similarity_between(
        &geometry(reference, scale_r, unit_r, roll_r),
        &geometry(frame, scale_f, unit_f, roll_f),
        Similarity::array_center(reference.width, reference.height),
    ))
}

/// The solar radius in pixels the header implies (`RSUN / |CDELT|`), if it gives one.
pub fn header_radius_px(meta: &FrameMeta) -> Option<f64> {
    let scale = (meta.plate_scale_arcsec[0] * meta.plate_scale_arcsec[1])
        .abs()
        .sqrt();
    let r = usable_radius(meta)? / scale;
    r.is_finite().then_some(r)
}

/// How the header's disk compares with the disk measured in the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaderCheck {
    /// Distance between the header's sun centre and the measured one, px.
    pub center_offset_px: f64,
    /// Measured radius / header radius; `None` when the header gives no radius.
    pub radius_ratio: Option<f64>,
}

/// Compare a header with the disk [`crate::preprocess::detect_disk`] found in its image
/// (rebinned EIT files: a ratio of 0.13, a header 8× off).
pub fn check_header(meta: &FrameMeta, disk: &crate::preprocess::DiskFit) -> HeaderCheck {
    let [hx, hy] = meta.sun_center_px;
    HeaderCheck {
        center_offset_px: (hx - disk.center_px[0]).hypot(hy - disk.center_px[1]),
        radius_ratio: header_radius_px(meta).map(|r| disk.radius_px / r),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn meta(
        width: usize,
        height: usize,
        scale: [f64; 2],
        roll_deg: f64,
        sun: [f64; 2],
        rsun: Option<f64>,
    ) -> FrameMeta {
        FrameMeta {
            file: PathBuf::from("hand-made.fits"),
            hdu: 0,
            frame: None,
            width,
            height,
            bitpix: -32,
            channel: "TEST".into(),
            instrument: None,
            wavelength: None,
            obs_time_ns: None,
            exptime_s: None,
            plate_scale_arcsec: scale,
            rotation_deg: roll_deg,
            sun_center_px: sun,
            observer: Default::default(),
            rsun_arcsec: rsun,
        }
    }

    fn assert_px(got: [f64; 2], want: [f64; 2], tol: f64) {
        assert!(
            (got[0] - want[0]).abs() < tol && (got[1] - want[1]).abs() < tol,
            "got {got:?}, want {want:?}"
        );
    }

    #[test]
    fn hand_made_pair_maps_sun_centre_north_and_west() {
        // Reference: 2″/px, no roll, sun at (50, 60): 100″ north = +y by 50 px,
        // 100″ west = +x by 50 px.
        let r = meta(101, 121, [2.0, 2.0], 0.0, [50.0, 60.0], None);
        // Frame: 1″/px, CROTA2 = 90°, sun at (200, 100). With PC = [[0, −1], [1, 0]],
        // the offset (a, b) px is seen at (−b, a) arcsec: north (0, 100″) ⇒ (a, b) = (100, 0),
        // west (100″, 0) ⇒ (a, b) = (0, −100).
        let f = meta(400, 300, [1.0, 1.0], 90.0, [200.0, 100.0], None);
        let t = coarse_transform(&r, &f).unwrap();
        assert_px(t.apply([50.0, 60.0]), [200.0, 100.0], 1e-9);
        assert_px(t.apply([50.0, 110.0]), [300.0, 100.0], 1e-9);
        assert_px(t.apply([100.0, 60.0]), [200.0, 0.0], 1e-9);
        assert!((t.scale - 2.0).abs() < 1e-12);
        assert!((t.rotation_rad.to_degrees() + 90.0).abs() < 1e-12);
        assert_eq!(t.center, [50.0, 60.0]);
    }

    #[test]
    fn apparent_radius_ratio_maps_the_limb_onto_the_limb() {
        // Same plate scale, but the frame's observer sees a Sun 1 % larger: the
        // reference limb point 1000″ north must land on the frame's limb, 1010″ north.
        let r = meta(64, 64, [10.0, 10.0], 0.0, [31.5, 31.5], Some(1000.0));
        let f = meta(64, 64, [10.0, 10.0], 0.0, [30.0, 33.0], Some(1010.0));
        let t = coarse_transform(&r, &f).unwrap();
        assert_px(t.apply([31.5, 131.5]), [30.0, 134.0], 1e-9);
        // Without a radius for one of them, angles map to angles.
        let f_no_r = FrameMeta {
            rsun_arcsec: None,
            ..f.clone()
        };
        let t = coarse_transform(&r, &f_no_r).unwrap();
        assert_px(t.apply([31.5, 131.5]), [30.0, 133.0], 1e-9);
    }

    #[test]
    fn two_negative_cdelts_are_a_half_turn_and_one_is_refused() {
        let r = meta(11, 11, [1.0, 1.0], 0.0, [5.0, 5.0], None);
        let f = meta(11, 11, [-1.0, -1.0], 0.0, [5.0, 5.0], None);
        let t = coarse_transform(&r, &f).unwrap();
        // 3″ west in the reference (+x) is at −x in a frame with both axes flipped.
        assert_px(t.apply([8.0, 5.0]), [2.0, 5.0], 1e-9);
        let mirrored = meta(11, 11, [-1.0, 1.0], 0.0, [5.0, 5.0], None);
        let err = coarse_transform(&r, &mirrored).unwrap_err();
        assert_eq!(err.exit_code(), crate::error::ExitCode::BadInput);
        assert!(err.to_string().contains("hand-made.fits"));
        let zero = meta(11, 11, [0.0, 1.0], 0.0, [5.0, 5.0], None);
        assert!(coarse_transform(&r, &zero).is_err());
    }

    #[test]
    fn aia_to_hmi_headers_agree_with_astropy_wcs() {
        // Angles only (no radius), so the mapping is the WCS one astropy computes:
        //   aia = WCS(fits.getheader('data/real/aia_171_20110215T000000_128.fits'))
        //   hmi = WCS(fits.getheader('data/real/hmi_6173_20140301T000027_100.fits'))
        //   hmi.world_to_pixel_values(*aia.pixel_to_world_values(x, y))
        // Sun centres: WCS(h).world_to_pixel_values(0, 0) (AIA 63.736201, 63.350544;
        // HMI 49.619993, 49.582518). Scales and CROTA2 are the header cards.
        let aia = meta(
            128,
            128,
            [19.183648, 19.183648],
            0.019413,
            [63.736201218592186, 63.350544055287],
            None,
        );
        let hmi = meta(
            100,
            100,
            [20.65575936, 20.65575936],
            179.929779,
            [49.6199933665928, 49.5825177542124],
            None,
        );
        let t = coarse_transform(&aia, &hmi).unwrap();
        let truth = [
            ([10.0, 20.0], [99.46344117962678, 89.92155093406824]),
            ([100.0, 90.0], [15.979436297013464, 24.77968138215985]),
            ([63.5, 63.5], [49.839577684030445, 49.444056706520115]),
            ([0.0, 127.0], [108.90621011599353, -9.438055576601592]),
        ];
        // TAN projection vs the linear model: below 1e-4 px over this 0.7° field.
        for (p, q) in truth {
            assert_px(t.apply(p), q, 1e-4);
        }
    }

    #[test]
    fn header_check_exposes_the_rebinned_eit_header() {
        // EIT header: CDELT 2.63″, SOLAR_R 372.27 px (so RSUN = 979.07″), CRPIX 64.5;
        // the image shows a 47.4 px disk at (62.96, 64.77).
        let eit = meta(
            128,
            128,
            [2.63, 2.63],
            180.0,
            [63.5, 63.5],
            Some(372.27 * 2.63),
        );
        assert!((header_radius_px(&eit).unwrap() - 372.27).abs() < 1e-9);
        let disk = crate::preprocess::DiskFit {
            center_px: [62.96, 64.77],
            radius_px: 47.4,
            rms_px: 0.5,
            coverage: 0.6,
            limb: crate::preprocess::LimbFeature::Brightening,
        };
        let check = check_header(&eit, &disk);
        assert!((check.radius_ratio.unwrap() - 47.4 / 372.27).abs() < 1e-12);
        assert!((check.center_offset_px - 0.54_f64.hypot(1.27)).abs() < 1e-9);
        let no_radius = FrameMeta {
            rsun_arcsec: None,
            ..eit
        };
        assert_eq!(header_radius_px(&no_radius), None);
    }

    #[test]
    fn disk_geometry_from_images_gives_radius_ratio_scale() {
        let r = GridGeometry::from_disk([63.0, 64.0], 46.0, 180.0);
        let f = GridGeometry::from_disk([60.0, 62.0], 23.0, 180.0);
        let t = similarity_between(&r, &f, [63.5, 63.5]);
        assert!((t.scale - 0.5).abs() < 1e-12 && t.rotation_rad.abs() < 1e-12);
        assert_px(t.apply([63.0, 64.0]), [60.0, 62.0], 1e-12);
        assert_px(t.apply([63.0, 110.0]), [60.0, 85.0], 1e-12);
    }
}
