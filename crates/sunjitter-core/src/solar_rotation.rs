//! The Sun's differential rotation between two images' times: where a point of the solar
//! surface seen at a reference pixel appears at the frame's time, in the frame's pixels.
//! Numerics only; the metadata comes in as [`FrameMeta`].
//!
//! The chain is sunpy's (`RotatedSunFrame`): pixel → helioprojective (gnomonic about the disk
//! centre) → the near intersection of the ray with the solar sphere (heliocentric, then
//! heliographic Stonyhurst for the reference's observer) → longitude advanced by the sidereal
//! rate of the profile over Δt → Stonyhurst of the frame's time (whose zero meridian follows
//! the Earth: this makes the rate synodic) → helioprojective for the frame's observer → frame
//! pixel. The Earth's motion comes from Meeus' solar coordinates (*Astronomical Algorithms*,
//! ch. 25 and 29); over a day its rate is exact to about 1e-4.

use crate::meta::{FrameMeta, Observer};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

const RAD_PER_ARCSEC: f64 = PI / (180.0 * 3600.0);
/// Nominal photospheric radius (IAU 2015, sunpy's `RSUN_REF`), m.
pub const RSUN_REF_M: f64 = 695_700_000.0;
/// Astronomical unit, m.
const AU_M: f64 = 149_597_870_700.0;

/// A differential-rotation law: sidereal angular rate `A + B sin²φ + C sin⁴φ` at latitude φ.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// Howard, Harvey & Forgach (1990), magnetic features; sunpy's default.
    #[default]
    Howard,
    /// Snodgrass & Ulrich (1990), magnetic features.
    Snodgrass,
    /// Allen, *Astrophysical Quantities*: 14.44 − 3.0 sin²φ °/day.
    Allen,
    /// No rotation removed.
    None,
}

impl Profile {
    pub fn name(self) -> &'static str {
        match self {
            Profile::Howard => "howard",
            Profile::Snodgrass => "snodgrass",
            Profile::Allen => "allen",
            Profile::None => "none",
        }
    }

    /// Sidereal rate at latitude `lat` (radians), rad/s.
    pub fn sidereal_rad_per_s(self, lat: f64) -> f64 {
        const PER_DAY: f64 = PI / 180.0 / 86_400.0;
        let [a, b, c] = match self {
            Profile::Howard => [2.894e-6, -0.428e-6, -0.370e-6],
            Profile::Snodgrass => [2.851e-6, -0.343e-6, -0.474e-6],
            Profile::Allen => [14.44 * PER_DAY, -3.0 * PER_DAY, 0.0],
            Profile::None => [0.0; 3],
        };
        let s2 = lat.sin().powi(2);
        a + b * s2 + c * s2 * s2
    }
}

impl std::str::FromStr for Profile {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "howard" => Ok(Profile::Howard),
            "snodgrass" => Ok(Profile::Snodgrass),
            "allen" => Ok(Profile::Allen),
            "none" | "off" => Ok(Profile::None),
            other => Err(format!(
                "unknown solar rotation profile '{other}' (howard, snodgrass, allen or none)"
            )),
        }
    }
}

impl std::fmt::Display for Profile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Observer {
    /// Whether the header locates the observer at all.
    pub fn is_known(&self) -> bool {
        self.hglt_deg.is_some() || self.dsun_m.is_some()
    }
}

/// The Earth as seen from the Sun at one instant (Meeus ch. 25 and 29).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Earth {
    /// Heliographic latitude of the Earth (B0), rad.
    pub b0: f64,
    /// Distance to the Sun, m.
    pub distance_m: f64,
    /// Longitude of the Earth in the Sun's (non-rotating) equatorial frame, rad: Stonyhurst
    /// longitude 0 points here.
    pub eta: f64,
    /// Carrington longitude of the sub-Earth point, rad.
    pub l0: f64,
}

/// Julian date (TT) of a UTC instant given in ns since the Unix epoch.
pub fn julian_date_tt(utc_ns: i64) -> f64 {
    let tt_minus_utc = crate::time::tai_minus_utc_s(utc_ns) as f64 + 32.184;
    2_440_587.5 + (utc_ns as f64 * 1e-9 + tt_minus_utc) / 86_400.0
}

impl Earth {
    pub fn at(utc_ns: i64) -> Earth {
        let jd = julian_date_tt(utc_ns);
        let t = (jd - 2_451_545.0) / 36_525.0;
        let l0 = 280.466_46 + 36_000.769_83 * t + 0.000_303_2 * t * t;
        let m = (357.529_11 + 35_999.050_29 * t - 0.000_153_7 * t * t).to_radians();
        let e = 0.016_708_634 - 0.000_042_037 * t - 0.000_000_126_7 * t * t;
        let c = (1.914_602 - 0.004_817 * t - 0.000_014 * t * t) * m.sin()
            + (0.019_993 - 0.000_101 * t) * (2.0 * m).sin()
            + 0.000_289 * (3.0 * m).sin();
        let lambda = (l0 + c).to_radians();
        let nu = m + c.to_radians();
        let r_au = 1.000_001_018 * (1.0 - e * e) / (1.0 + e * nu.cos());
        // Node and inclination of the solar equator on the ecliptic of date.
        let k = (73.6667 + 1.395_833_3 * (jd - 2_396_758.0) / 36_525.0).to_radians();
        let i = 7.25f64.to_radians();
        let u = lambda - k;
        let b0 = (u.sin() * i.sin()).asin();
        let eta = (-u.sin() * i.cos()).atan2(-u.cos());
        let theta = ((jd - 2_398_220.0) * 360.0 / 25.38).to_radians();
        Earth {
            b0,
            distance_m: r_au * AU_M,
            eta,
            l0: (eta - theta).rem_euclid(2.0 * PI),
        }
    }
}

/// One image's view of the Sun: its pixel geometry, time and observer.
#[derive(Debug, Clone, PartialEq)]
pub struct View {
    time_ns: i64,
    sun_center_px: [f64; 2],
    /// Pixel offset → helioprojective arcsec, `R(ρ)·diag(CDELT)`, and its inverse.
    to_arcsec: [[f64; 2]; 2],
    to_px: [[f64; 2]; 2],
    /// Observer's Stonyhurst longitude and latitude, rad, and distance, m.
    lon: f64,
    lat: f64,
    distance_m: f64,
    /// The Earth's longitude in the Sun's equatorial frame at this time.
    earth_eta: f64,
    /// Sphere radius, m: the radius the image shows (its apparent radius at its distance).
    radius_m: f64,
    /// Whether the observer was assumed (the Earth's) for want of header keywords.
    pub observer_assumed: bool,
}

impl View {
    /// `None` without an observation time or with a singular pixel scale.
    pub fn new(meta: &FrameMeta) -> Option<View> {
        let time_ns = meta.obs_time_ns?;
        let [cx, cy] = meta.plate_scale_arcsec;
        let (s, c) = meta.rotation_deg.to_radians().sin_cos();
        let to_arcsec = [[c * cx, -s * cy], [s * cx, c * cy]];
        let det = to_arcsec[0][0] * to_arcsec[1][1] - to_arcsec[0][1] * to_arcsec[1][0];
        if !(det.is_finite() && det.abs() > 0.0) {
            return None;
        }
        let to_px = [
            [to_arcsec[1][1] / det, -to_arcsec[0][1] / det],
            [-to_arcsec[1][0] / det, to_arcsec[0][0] / det],
        ];
        let earth = Earth::at(time_ns);
        let o = &meta.observer;
        let distance_m = o
            .dsun_m
            .filter(|d| d.is_finite() && *d > RSUN_REF_M)
            .unwrap_or(earth.distance_m);
        let lat = o
            .hglt_deg
            .filter(|b| b.is_finite() && b.abs() <= 90.0)
            .map_or(earth.b0, f64::to_radians);
        let lon = match (o.hgln_deg, o.crln_deg) {
            (Some(l), _) if l.is_finite() => l.to_radians(),
            (_, Some(cr)) if cr.is_finite() => cr.to_radians() - earth.l0,
            _ => 0.0,
        };
        // The sphere the image shows: its apparent radius at the observer's distance.
        let radius_m = match meta.rsun_arcsec.filter(|r| r.is_finite() && *r > 0.0) {
            Some(r) => distance_m * (r * RAD_PER_ARCSEC).sin(),
            None => o.rsun_ref_m.filter(|r| *r > 0.0).unwrap_or(RSUN_REF_M),
        };
        if !(radius_m > 0.0 && radius_m < distance_m) {
            return None;
        }
        Some(View {
            time_ns,
            sun_center_px: meta.sun_center_px,
            to_arcsec,
            to_px,
            lon,
            lat,
            distance_m,
            earth_eta: earth.eta,
            radius_m,
            observer_assumed: !o.is_known(),
        })
    }

    /// Helioprojective (Tx, Ty), rad, of a pixel.
    fn helioprojective(&self, p: [f64; 2]) -> (f64, f64) {
        let (u, v) = (p[0] - self.sun_center_px[0], p[1] - self.sun_center_px[1]);
        let m = &self.to_arcsec;
        let xi = (m[0][0] * u + m[0][1] * v) * RAD_PER_ARCSEC;
        let eta = (m[1][0] * u + m[1][1] * v) * RAD_PER_ARCSEC;
        (xi.atan(), (eta / (1.0 + xi * xi).sqrt()).atan())
    }

    /// Pixel of helioprojective (Tx, Ty), rad.
    fn pixel(&self, tx: f64, ty: f64) -> [f64; 2] {
        let xi = tx.tan() / RAD_PER_ARCSEC;
        let eta = ty.tan() / tx.cos() / RAD_PER_ARCSEC;
        let m = &self.to_px;
        [
            self.sun_center_px[0] + m[0][0] * xi + m[0][1] * eta,
            self.sun_center_px[1] + m[1][0] * xi + m[1][1] * eta,
        ]
    }

    /// Unit vectors of the heliocentric axes (x west, y north, z to the observer) in
    /// Stonyhurst Cartesian coordinates.
    fn axes(&self) -> [[f64; 3]; 3] {
        let (sl, cl) = self.lon.sin_cos();
        let (sb, cb) = self.lat.sin_cos();
        [
            [-sl, cl, 0.0],
            [-sb * cl, -sb * sl, cb],
            [cb * cl, cb * sl, sb],
        ]
    }

    pub fn time_ns(&self) -> i64 {
        self.time_ns
    }
}

/// Where a reference pixel's surface point is at the frame's time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Moved {
    /// On the disk then and now: the frame pixel.
    To([f64; 2]),
    /// On the disk then, behind the limb now.
    Hidden,
    /// Not on the disk: sky, which does not rotate.
    OffDisk,
}

/// The surface motion between a reference view and a frame view.
#[derive(Debug, Clone)]
pub struct SurfaceMotion {
    from: View,
    to: View,
    profile: Profile,
    dt_s: f64,
    /// Stonyhurst longitude lost by the Earth's motion between the times, rad.
    frame_drift: f64,
    radius_m: f64,
    from_axes: [[f64; 3]; 3],
    to_axes: [[f64; 3]; 3],
}

impl SurfaceMotion {
    pub fn new(from: View, to: View, profile: Profile) -> SurfaceMotion {
        let dt_s = (to.time_ns - from.time_ns) as f64 * 1e-9;
        let mut frame_drift = to.earth_eta - from.earth_eta;
        frame_drift -= (frame_drift / (2.0 * PI)).round() * 2.0 * PI;
        let radius_m = from.radius_m;
        SurfaceMotion {
            from_axes: from.axes(),
            to_axes: to.axes(),
            from,
            to,
            profile,
            dt_s,
            frame_drift,
            radius_m,
        }
    }

    pub fn dt_s(&self) -> f64 {
        self.dt_s
    }

    pub fn profile(&self) -> Profile {
        self.profile
    }

    /// Angle between the two observers as seen from the Sun (Stonyhurst), degrees.
    pub fn viewpoint_separation_deg(&self) -> f64 {
        let dir = |v: &View| {
            let (sl, cl) = v.lon.sin_cos();
            let (sb, cb) = v.lat.sin_cos();
            [cb * cl, cb * sl, sb]
        };
        let (a, b) = (dir(&self.from), dir(&self.to));
        let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        dot.clamp(-1.0, 1.0).acos().to_degrees()
    }

    pub fn observer_assumed(&self) -> bool {
        self.from.observer_assumed || self.to.observer_assumed
    }

    /// Where the surface point at reference pixel `p` appears at the frame's time.
    pub fn map(&self, p: [f64; 2]) -> Moved {
        let (tx, ty) = self.from.helioprojective(p);
        let (d0, r) = (self.from.distance_m, self.radius_m);
        // Ray from the observer (0, 0, D) along u; its near intersection with the sphere.
        let u = [ty.cos() * tx.sin(), ty.sin(), -ty.cos() * tx.cos()];
        let c = -u[2];
        let disc = r * r - d0 * d0 * (1.0 - c * c);
        if disc < 0.0 || c <= 0.0 {
            return Moved::OffDisk;
        }
        let s = d0 * c - disc.sqrt();
        let h = [s * u[0], s * u[1], d0 + s * u[2]];
        let a = &self.from_axes;
        let hgs: [f64; 3] =
            std::array::from_fn(|k| h[0] * a[0][k] + h[1] * a[1][k] + h[2] * a[2][k]);
        let lat = (hgs[2] / r).clamp(-1.0, 1.0).asin();
        let lon = hgs[1].atan2(hgs[0]) + self.profile.sidereal_rad_per_s(lat) * self.dt_s
            - self.frame_drift;
        let (sl, cl) = lon.sin_cos();
        let (sb, cb) = lat.sin_cos();
        let moved = [r * cb * cl, r * cb * sl, r * sb];
        let b = &self.to_axes;
        let hc: [f64; 3] =
            std::array::from_fn(|k| moved[0] * b[k][0] + moved[1] * b[k][1] + moved[2] * b[k][2]);
        let d1 = self.to.distance_m;
        if hc[2] * d1 <= r * r {
            return Moved::Hidden;
        }
        let along = d1 - hc[2];
        let dist = (hc[0] * hc[0] + hc[1] * hc[1] + along * along).sqrt();
        let tx1 = hc[0].atan2(along);
        let ty1 = (hc[1] / dist).asin();
        Moved::To(self.to.pixel(tx1, ty1))
    }
}

/// Where a [`DisplacementGrid`] is read along one axis: its first node and the cubic
/// convolution's four weights.
#[derive(Debug, Clone, Copy)]
pub struct GridTap {
    first: usize,
    weights: [f64; 4],
}

/// A displacement sampled on a regular grid and read by cubic convolution (Catmull–Rom):
/// `map(p) − p` over an image, NaN where a point has no image (hidden behind the limb).
#[derive(Debug, Clone)]
pub struct DisplacementGrid {
    step: f64,
    nx: usize,
    ny: usize,
    /// `(dx, dy)` per node, row-major; node `(i, j)` sits at `((i − 1)·step, (j − 1)·step)`.
    nodes: Vec<[f64; 2]>,
}

impl DisplacementGrid {
    /// Sample `displacement` every `step` px over a `width × height` grid, with one node beyond
    /// every edge.
    pub fn sample<F>(width: usize, height: usize, step: usize, displacement: F) -> DisplacementGrid
    where
        F: Fn([f64; 2]) -> [f64; 2] + Sync,
    {
        use rayon::prelude::*;
        let step = step.max(1);
        let nx = (width.max(1) - 1) / step + 4;
        let ny = (height.max(1) - 1) / step + 4;
        let at = |i: usize| (i as f64 - 1.0) * step as f64;
        let nodes = (0..nx * ny)
            .into_par_iter()
            .map(|k| displacement([at(k % nx), at(k / nx)]))
            .collect();
        DisplacementGrid {
            step: step as f64,
            nx,
            ny,
            nodes,
        }
    }

    /// The displacement at `p` (NaN when a node around is NaN or `p` lies outside the grid).
    #[inline]
    pub fn at(&self, p: [f64; 2]) -> [f64; 2] {
        self.at_taps(
            self.tap(p[0], self.nx).as_ref(),
            self.tap(p[1], self.ny).as_ref(),
        )
    }

    /// Where [`DisplacementGrid::at`] reads along one axis of `n` nodes for coordinate `p`:
    /// `None` outside the grid. The same for every point of a row or column, so a row's
    /// points share the row's tap and each column's.
    #[inline]
    fn tap(&self, p: f64, n: usize) -> Option<GridTap> {
        let g = p / self.step + 1.0;
        if g.is_nan() || g < 1.0 {
            return None;
        }
        let i = g.floor() as usize;
        (i + 2 < n).then(|| GridTap {
            first: i - 1,
            weights: catmull_rom(g - i as f64),
        })
    }

    /// Taps along x for [`DisplacementGrid::row`].
    pub fn x_taps(&self, xs: impl Iterator<Item = f64>) -> Vec<Option<GridTap>> {
        xs.map(|x| self.tap(x, self.nx)).collect()
    }

    /// Taps along y for [`DisplacementGrid::at_taps`].
    pub fn y_taps(&self, ys: impl Iterator<Item = f64>) -> Vec<Option<GridTap>> {
        ys.map(|y| self.tap(y, self.ny)).collect()
    }

    /// [`DisplacementGrid::at`] at the point whose column and row taps are `x` and `y`.
    #[inline]
    pub fn at_taps(&self, x: Option<&GridTap>, y: Option<&GridTap>) -> [f64; 2] {
        match (x, y) {
            (Some(x), Some(y)) => self.read(x, y),
            _ => [f64::NAN; 2],
        }
    }

    /// [`DisplacementGrid::at`] at `(x, y)` for every x of `x_taps` (from
    /// [`DisplacementGrid::x_taps`]), the same values, into `out` in order.
    pub fn row(&self, x_taps: &[Option<GridTap>], y: f64, mut out: impl FnMut(usize, [f64; 2])) {
        let ty = self.tap(y, self.ny);
        for (k, tx) in x_taps.iter().enumerate() {
            out(k, self.at_taps(tx.as_ref(), ty.as_ref()));
        }
    }

    #[inline]
    fn read(&self, x: &GridTap, y: &GridTap) -> [f64; 2] {
        let mut sum = [0.0; 2];
        for (j, wyj) in y.weights.iter().enumerate() {
            let row = &self.nodes[(y.first + j) * self.nx + x.first..][..4];
            for (n, wxi) in row.iter().zip(&x.weights) {
                let w = wyj * wxi;
                sum[0] += w * n[0];
                sum[1] += w * n[1];
            }
        }
        sum
    }

    /// Whether every node holds a displacement (none is hidden): then [`Self::at`] is finite
    /// everywhere on the grid.
    pub fn all_finite(&self) -> bool {
        self.nodes.iter().flatten().all(|v| v.is_finite())
    }

    /// Largest finite displacement, px.
    pub fn max_norm(&self) -> f64 {
        self.nodes
            .iter()
            .map(|d| d[0].hypot(d[1]))
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }
}

/// Cubic convolution weights (Keys, a = −½) of the four nodes around fraction `t`.
#[inline(always)]
fn catmull_rom(t: f64) -> [f64; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// Node spacing (px) that keeps a cubic reading of a rotation displacement within about
/// 1e-4 px inside `fraction` of the disk. The displacement goes like the sphere's depth
/// `z = √(R² − ρ²)`, whose fourth derivative is about `15·R⁴/z⁷·(1/R³)`; cubic convolution errs
/// by about `h⁴/24` times it, largest at the edge, `z = R·√(1 − fraction²)`.
pub fn grid_step_px(max_shift_px: f64, radius_px: f64, fraction: f64) -> usize {
    let depth = (1.0 - fraction.clamp(0.0, 0.99).powi(2)).sqrt();
    let r = radius_px.max(1.0);
    let fourth = 15.0 * max_shift_px.abs() / (r.powi(4) * depth.powi(7));
    if !(fourth.is_finite() && fourth > 0.0) {
        return 64;
    }
    ((24.0 * 1e-4 / fourth).powf(0.25).floor() as usize).clamp(2, 64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles_match_their_published_rates() {
        // Howard et al. (1990): 2.894 µrad/s at the equator is 14.326 °/day sidereal.
        let per_day =
            |p: Profile, lat: f64| p.sidereal_rad_per_s(lat.to_radians()).to_degrees() * 86_400.0;
        assert!((per_day(Profile::Howard, 0.0) - 14.3258).abs() < 1e-3);
        assert!((per_day(Profile::Allen, 0.0) - 14.44).abs() < 1e-12);
        // Allen at 30°: 14.44 − 3.0 / 4.
        assert!((per_day(Profile::Allen, 30.0) - 13.69).abs() < 1e-12);
        assert_eq!(per_day(Profile::None, 10.0), 0.0);
        assert_eq!("Snodgrass".parse::<Profile>(), Ok(Profile::Snodgrass));
        assert!("rigid".parse::<Profile>().is_err());
    }

    #[test]
    fn earth_b0_and_distance_follow_the_almanac() {
        // Astronomical Almanac: B0 = −7.25° near 6 March and +7.25° near 8 September; the
        // Earth at 0.9833 AU at perihelion (3–4 January) and 1.0167 AU at aphelion (4 July).
        let at = |y, m, d| crate::time::days_from_civil(y, m, d) * 86_400_000_000_000;
        let march = Earth::at(at(2024, 3, 6));
        let september = Earth::at(at(2024, 9, 8));
        assert!(
            (march.b0.to_degrees() + 7.25).abs() < 0.03,
            "{}",
            march.b0.to_degrees()
        );
        assert!((september.b0.to_degrees() - 7.25).abs() < 0.03);
        assert!((Earth::at(at(2024, 1, 3)).distance_m / AU_M - 0.98331).abs() < 2e-4);
        assert!((Earth::at(at(2024, 7, 5)).distance_m / AU_M - 1.01672).abs() < 2e-4);
        // The Stonyhurst zero meridian turns with the Earth's orbit, about 0.95–1.02 °/day.
        let day = 86_400_000_000_000;
        let rate =
            (Earth::at(at(2024, 1, 3) + day).eta - Earth::at(at(2024, 1, 3)).eta).to_degrees();
        assert!((1.0..1.03).contains(&rate), "{rate}");
    }

    #[test]
    fn a_cubic_grid_reads_a_quadratic_field_exactly() {
        let f = |p: [f64; 2]| {
            [
                1e-4 * p[0] * p[0] - 0.3,
                2.0 - 0.02 * p[1] + 1e-4 * p[0] * p[1],
            ]
        };
        let g = DisplacementGrid::sample(100, 60, 7, f);
        for p in [[0.0, 0.0], [13.3, 41.9], [99.0, 59.0]] {
            let (d, want) = (g.at(p), f(p));
            assert!(
                (d[0] - want[0]).abs() < 1e-12 && (d[1] - want[1]).abs() < 1e-12,
                "{p:?}"
            );
        }
        assert!(g.at([-1.0, 3.0])[0].is_nan());
    }

    #[test]
    fn a_cubic_grid_read_row_by_row_gives_the_quadratic_field_and_nothing_outside() {
        let f = |p: [f64; 2]| [1e-4 * p[0] * p[0] - 0.3, 2.0 + 1e-4 * p[0] * p[1]];
        let g = DisplacementGrid::sample(100, 60, 7, f);
        // Columns from outside the grid on the left to beyond it on the right.
        let xs: Vec<f64> = (0..30).map(|k| -2.5 + 4.1 * k as f64).collect();
        let taps = g.x_taps(xs.iter().copied());
        for y in [0.0, 17.25, 59.0, 61.0e3] {
            let mut seen = 0;
            g.row(&taps, y, |k, d| {
                seen += 1;
                let want = f([xs[k], y]);
                let inside = xs[k] >= 0.0 && xs[k] <= 99.0 + 7.0 && y <= 59.0;
                if inside {
                    assert!((d[0] - want[0]).abs() < 1e-12, "{k} {y}");
                    assert!((d[1] - want[1]).abs() < 1e-12, "{k} {y}");
                } else if xs[k] < 0.0 || y > 100.0 {
                    assert!(d[0].is_nan() && d[1].is_nan(), "{k} {y}");
                }
            });
            assert_eq!(seen, xs.len());
        }
    }
}
