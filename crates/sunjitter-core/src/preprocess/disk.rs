//! The solar disk measured from the image itself: limb points, a robust circle, checks.

use ndarray::{Array2, ArrayView2, Axis};
use rayon::prelude::*;

use super::filters::{bilinear, bin_mean};
use super::quantile;

// ---------------------------------------------------------------------------------------
// Solar disk from the image

/// Which feature of the limb a [`DiskFit`] measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LimbFeature {
    /// Steepest outward intensity drop (continuum, chromosphere: the limb's inflection).
    Edge,
    /// Peak of the limb-brightening ring (optically thin EUV / X-ray emission), which
    /// sits just above the photospheric limb; the steepest drop there is in the corona.
    Brightening,
}

/// A solar disk measured in an image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiskFit {
    /// 0-based pixel (x, y) of the disk centre.
    pub center_px: [f64; 2],
    pub radius_px: f64,
    /// RMS distance of the inlying limb points from the circle, px.
    pub rms_px: f64,
    /// Fraction of limb sectors whose strongest limb feature lies on the circle.
    pub coverage: f64,
    pub limb: LimbFeature,
}

/// Smallest disk worth reporting, px: below this a "limb" is a blob.
const MIN_DISK_RADIUS_PX: f64 = 8.0;
/// Fraction of limb sectors that must agree on the circle for it to count as a disk: below
/// what whole disks reach with active regions on the limb, above what a circle forced through
/// a field inside the disk reaches (docs/validation.md#disk-limb-coverage-and-largest-gap).
const MIN_LIMB_COVERAGE: f64 = 0.4;
/// Iterations need at least this fraction of sectors with a limb point.
const MIN_LIMB_POINTS: f64 = 0.5;
/// Largest run of disagreeing sectors tolerated (active regions on the limb), radians: more
/// than active regions leave on a whole disk, less than a circle forced through a field inside
/// the disk leaves (docs/validation.md#disk-limb-coverage-and-largest-gap).
const MAX_LIMB_GAP_RAD: f64 = std::f64::consts::FRAC_PI_2;
/// Step along limb rays, px (finest; coarser when a window would need more samples).
const RAY_STEP_PX: f64 = 0.25;
/// Samples per ray at most: wide windows on 4096² images need no 0.25 px steps.
const MAX_RAY_SAMPLES: f64 = 800.0;
/// Initial estimates are made on an image binned to at most this size.
const COARSE_SIZE_PX: usize = 512;

/// Measure the solar disk from the image: `None` when no whole-enough disk is visible
/// (partial fields, limb-only frames, no disk at all) rather than a wrong circle.
///
/// Method: a first guess from a clipped-intensity centroid and the azimuthal median
/// profile (on an image binned to ≤ 512 px), which also decides whether the limb shows
/// EUV limb brightening; then limb points from the averaged radial profile of each
/// angular sector (steepest drop, or the brightening peak), a seeded RANSAC circle and a
/// geometric least-squares refit, iterated with narrowing search windows; finally a
/// check in a wide window that at least 40 % of all sectors agree, with no gap wider
/// than 90°, and a minimum radius of 8 px. Non-finite pixels read as the darkest sky.
///
/// Images of 2048 px and more are measured on a copy binned to at least 1024 px (2× at 2048²,
/// 4× at 4096²): centre within a few hundredths of a pixel, radius slightly small (the binned
/// limb is blurred), at a fraction of the full-resolution cost; every frame's disk is checked
/// (docs/validation.md#disk-measured-on-a-binned-copy).
pub fn detect_disk(img: ArrayView2<f32>) -> Option<DiskFit> {
    detect_disk_keeping_copy(img).0
}

/// [`detect_disk`], and the binned copy it measured on (`None` when it measured on `img`):
/// a caller that bins the image by the same factor later has it already.
pub fn detect_disk_keeping_copy(img: ArrayView2<f32>) -> (Option<DiskFit>, Option<BlockMeans>) {
    let bin = disk_detection_bin(img.dim());
    if bin == 1 {
        return (detect_disk_at(img), None);
    }
    let binned = bin_mean(img, bin);
    let fit = detect_disk_at(binned.view()).map(|fit| {
        // Binned pixel q covers full pixels b·q … b·q + b − 1: its centre is b·(q + 0.5) − 0.5.
        let b = bin as f64;
        DiskFit {
            center_px: fit.center_px.map(|c| b * (c + 0.5) - 0.5),
            radius_px: b * fit.radius_px,
            rms_px: b * fit.rms_px,
            ..fit
        }
    });
    let copy = BlockMeans { bin, means: binned };
    (fit, Some(copy))
}

/// An image's [`bin_mean`] by `bin`.
#[derive(Debug, Clone)]
pub struct BlockMeans {
    pub bin: usize,
    pub means: Array2<f32>,
}

/// The power of two that bins an image to no less than 1024 px on its shorter side.
pub(super) fn disk_detection_bin((h, w): (usize, usize)) -> usize {
    let mut bin = 1;
    while h.min(w) / (2 * bin) >= DISK_DETECTION_MIN_PX {
        bin *= 2;
    }
    bin
}

/// Least size (shorter side) of the copy a disk is measured on.
const DISK_DETECTION_MIN_PX: usize = 1024;

fn detect_disk_at(img: ArrayView2<f32>) -> Option<DiskFit> {
    let (h, w) = img.dim();
    if h < 16 || w < 16 {
        return None;
    }
    let (n_finite, sky) = img
        .axis_iter(Axis(0))
        .into_par_iter()
        .map(|row| {
            row.iter()
                .filter(|v| v.is_finite())
                .fold((0usize, f32::INFINITY), |(n, lo), &v| (n + 1, lo.min(v)))
        })
        .reduce(|| (0, f32::INFINITY), |a, b| (a.0 + b.0, a.1.min(b.1)));
    if n_finite < h * w / 4 {
        return None;
    }
    // The background level from at most about a million pixels (every k-th row and column:
    // plenty for a quantile; a 4096² frame's full sort costs more than the rest of the fit).
    let k = ((h * w) as f64 / (1 << 20) as f64).sqrt().ceil().max(1.0) as usize;
    let sampled = crate::pages::concat(
        &(0..h.div_ceil(k))
            .into_par_iter()
            .map(|i| {
                let row = img.row(i * k);
                let taken = |v: &f32| v.is_finite().then_some(*v);
                match row.as_slice() {
                    Some(r) => r.iter().step_by(k).filter_map(taken).collect(),
                    None => row.iter().step_by(k).filter_map(taken).collect(),
                }
            })
            .collect::<Vec<Vec<f32>>>(),
    );
    if sampled.is_empty() {
        return None;
    }
    let background = quantile(&sampled, 0.02);
    drop(sampled);
    // NaN (often off-limb in pipeline products) reads as sky: the darkest finite level,
    // since a masked or resampled image may keep almost no sky of its own.
    let filled_copy;
    let filled = if n_finite == h * w {
        img
    } else {
        filled_copy = img.mapv(|v| if v.is_finite() { v } else { sky });
        filled_copy.view()
    };

    let first = first_guess(&img, background, sky)?;
    let mut center = first.center;
    let mut radius = first.radius;
    let ring = first.ring;

    for window in [(0.75, 1.25), (0.9, 1.1), (0.95, 1.05), (0.95, 1.05)] {
        let limb = limb_points(filled, center, radius, ring, window);
        if (limb.points.len() as f64) < MIN_LIMB_POINTS * limb.sectors as f64 {
            return None;
        }
        let tol = (0.02 * radius).max(1.0);
        let (c, r, _) = robust_circle(&limb.points, tol)?;
        center = c;
        radius = r;
        if !(radius.is_finite() && radius > 0.0) {
            return None;
        }
    }

    // Validation in a wide window: the strongest limb feature of most sectors must lie
    // on the circle all the way round.
    let limb = limb_points(filled, center, radius, ring, (0.75, 1.25));
    let tol = (0.02 * radius).max(1.5);
    let mut inlier_angles = Vec::new();
    let (mut sum2, mut n) = (0.0, 0usize);
    for p in &limb.points {
        let res = ((p.xy[0] - center[0]).hypot(p.xy[1] - center[1])) - radius;
        if res.abs() < tol {
            inlier_angles.push(p.angle);
            sum2 += res * res;
            n += 1;
        }
    }
    let coverage = n as f64 / limb.sectors as f64;
    if radius < MIN_DISK_RADIUS_PX
        || coverage < MIN_LIMB_COVERAGE
        || largest_gap(&mut inlier_angles) > MAX_LIMB_GAP_RAD
    {
        return None;
    }
    Some(DiskFit {
        center_px: center,
        radius_px: radius,
        rms_px: (sum2 / n as f64).sqrt(),
        coverage,
        limb: if ring {
            LimbFeature::Brightening
        } else {
            LimbFeature::Edge
        },
    })
}

struct FirstGuess {
    center: [f64; 2],
    radius: f64,
    ring: bool,
}

/// Centre, radius and limb type from a binned copy of the image.
fn first_guess(img: &ArrayView2<f32>, background: f32, sky: f32) -> Option<FirstGuess> {
    let (h, w) = img.dim();
    let bin = h.max(w).div_ceil(COARSE_SIZE_PX).max(1);
    let small = bin_mean(img.view(), bin);
    let (sh, sw) = small.dim();
    let vals: Vec<f32> = small.iter().copied().filter(|v| v.is_finite()).collect();
    if vals.is_empty() {
        return None;
    }
    let top = quantile(&vals, 0.75);
    if top.partial_cmp(&background) != Some(std::cmp::Ordering::Greater) {
        return None;
    }
    // Centroid of the clipped intensity: bright active regions weigh no more than the disk.
    let (mut total, mut sx, mut sy) = (0.0f64, 0.0f64, 0.0f64);
    for ((y, x), &v) in small.indexed_iter() {
        if v.is_finite() {
            let wgt = (v.min(top) - background).max(0.0) as f64;
            total += wgt;
            sx += wgt * x as f64;
            sy += wgt * y as f64;
        }
    }
    if total <= 0.0 {
        return None;
    }
    let (cx, cy) = (sx / total, sy / total);
    // Azimuthal median profile over 1-px annuli that are at least half inside the image.
    let rmax = (cx.max(sw as f64 - 1.0 - cx)).hypot(cy.max(sh as f64 - 1.0 - cy));
    let nr = rmax as usize + 1;
    let mut annuli: Vec<Vec<f32>> = vec![Vec::new(); nr];
    for ((y, x), &v) in small.indexed_iter() {
        let k = (x as f64 - cx).hypot(y as f64 - cy) as usize;
        if k < nr {
            annuli[k].push(if v.is_finite() { v } else { sky });
        }
    }
    let profile: Vec<f64> = annuli
        .iter()
        .enumerate()
        .map(|(k, a)| {
            let expected = 2.0 * std::f64::consts::PI * (k as f64 + 0.5);
            if !a.is_empty() && a.len() as f64 >= 0.5 * expected {
                quantile(a, 0.5) as f64
            } else {
                f64::NAN
            }
        })
        .collect();
    // The most significant drop of the profile, away from the centre: a median over an
    // annulus of radius k is uncertain by ∝ 1/√k, so the drop is weighed by √k (with noise,
    // the plain steepest drop of a small disk's profile can fall on a feature inside it, not
    // on the limb; docs/validation.md#limb-search-the-most-significant-drop).
    let mut kd = None;
    let mut best = 0.0;
    for k in 3..nr.saturating_sub(1) {
        let g = (profile[k + 1] - profile[k - 1]) * (k as f64 + 0.5).sqrt();
        if g < best {
            best = g;
            kd = Some(k);
        }
    }
    let kd = kd?;
    let r0 = kd as f64 + 0.5;
    // Limb brightening: a peak inside the drop, above the level 15 % further in.
    let lo = (kd as f64 - 0.15 * r0).max(1.0) as usize;
    let (kp, peak) = (lo..=kd)
        .filter(|&k| profile[k].is_finite())
        .map(|k| (k, profile[k]))
        .fold(
            (lo, f64::NEG_INFINITY),
            |a, b| if b.1 > a.1 { b } else { a },
        );
    let ring = kp > lo
        && profile[lo].is_finite()
        && peak - profile[lo] > 0.05 * (peak - background as f64);
    let b = bin as f64;
    Some(FirstGuess {
        center: [(cx + 0.5) * b - 0.5, (cy + 0.5) * b - 0.5],
        radius: r0 * b,
        ring,
    })
}

struct LimbPoint {
    xy: [f64; 2],
    angle: f64,
}

struct Limb {
    points: Vec<LimbPoint>,
    sectors: usize,
}

/// One limb point per angular sector: the steepest drop (or the brightening peak) of
/// the sector's mean radial profile within `window` × radius.
fn limb_points(
    img: ArrayView2<f32>,
    center: [f64; 2],
    radius: f64,
    ring: bool,
    window: (f64, f64),
) -> Limb {
    use std::f64::consts::TAU;
    let sectors = ((TAU * radius / 4.0).round() as usize).clamp(16, 180);
    let per = ((TAU * radius / sectors as f64).round() as usize).clamp(1, 8);
    let n_rays = sectors * per;
    let r_lo = window.0 * radius;
    let step = RAY_STEP_PX.max((window.1 - window.0) * radius / MAX_RAY_SAMPLES);
    let n_samples = (((window.1 - window.0) * radius) / step) as usize;
    let smooth_sigma = 1.0 / step; // 1 px
    let kernel: Vec<f64> = {
        let r = (4.0 * smooth_sigma) as isize;
        (-r..=r)
            .map(|d| (-0.5 * (d as f64 / smooth_sigma).powi(2)).exp())
            .collect()
    };
    let margin = ((1.0 / step) as usize).max(1);
    let points = (0..sectors)
        .into_par_iter()
        .filter_map(|k| {
            let mut profile = vec![0.0f64; n_samples];
            let mut len = n_samples;
            for j in 0..per {
                let a = (k * per + j) as f64 * TAU / n_rays as f64;
                let ray = Ray {
                    center,
                    direction: [a.cos(), a.sin()],
                    r_lo,
                    step,
                };
                len = add_ray(img, &ray, &mut profile[..len]);
            }
            if (len as f64) < 0.6 * n_samples as f64 || len < 2 * margin + 3 {
                return None;
            }
            let smooth = smooth_nearest(&profile[..len], &kernel);
            let grad: Vec<f64> = (0..len)
                .map(|i| {
                    let (a, b) = (i.saturating_sub(1), (i + 1).min(len - 1));
                    (smooth[b] - smooth[a]) / (b - a) as f64
                })
                .collect();
            let mut i = (margin..len - margin).min_by(|&a, &b| grad[a].total_cmp(&grad[b]))?;
            if grad[i] >= 0.0 {
                return None;
            }
            let neg_smooth: Vec<f64>;
            let feature: &[f64] = if ring {
                let j0 = i.saturating_sub((0.15 * radius / step) as usize);
                let j = (j0..=i).max_by(|&a, &b| smooth[a].total_cmp(&smooth[b]))?;
                if j == j0 {
                    return None;
                }
                i = j;
                neg_smooth = smooth.iter().map(|v| -v).collect();
                &neg_smooth
            } else {
                &grad
            };
            if i == 0 || i + 1 >= len {
                return None;
            }
            // Parabola through the extremum and its neighbours.
            let (fm, f0, fp) = (feature[i - 1], feature[i], feature[i + 1]);
            let den = fm - 2.0 * f0 + fp;
            let offset = if den > 0.0 {
                (0.5 * (fm - fp) / den).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            let r = r_lo + (i as f64 + offset) * step;
            let angle = (k as f64 * per as f64 + (per as f64 - 1.0) / 2.0) * TAU / n_rays as f64;
            Some(LimbPoint {
                xy: [center[0] + r * angle.cos(), center[1] + r * angle.sin()],
                angle,
            })
        })
        .collect();
    Limb { points, sectors }
}

/// Samples `r_lo + i·step` from `center` along `direction`.
struct Ray {
    center: [f64; 2],
    direction: [f64; 2],
    r_lo: f64,
    step: f64,
}

/// Adds the image along `ray` (bilinear) to `profile`, up to where the ray leaves the image:
/// the length it reached. Four samples at a time with AVX2 where the CPU has it, each lane
/// taking [`bilinear`]'s operations in its order (no FMA): the same sums bit for bit.
fn add_ray(img: ArrayView2<f32>, ray: &Ray, profile: &mut [f64]) -> usize {
    #[cfg(target_arch = "x86_64")]
    if crate::flow::simd::has_avx2_fma() {
        if let Some(data) = img.as_slice() {
            // SAFETY: the CPU has AVX2; `data` is `img` in row-major order.
            return unsafe { ray_x86::add_ray(data, img.dim(), ray, profile) };
        }
    }
    add_ray_from(img, ray, profile, 0)
}

/// [`add_ray`] one sample at a time, from sample `start` on.
fn add_ray_from(img: ArrayView2<f32>, ray: &Ray, profile: &mut [f64], start: usize) -> usize {
    let ([cx, cy], [ca, sa]) = (ray.center, ray.direction);
    for (i, p) in profile.iter_mut().enumerate().skip(start) {
        let r = ray.r_lo + i as f64 * ray.step;
        match bilinear(img, cx + r * ca, cy + r * sa) {
            Some(v) => *p += v,
            None => return i,
        }
    }
    profile.len()
}

#[cfg(target_arch = "x86_64")]
mod ray_x86 {
    use super::Ray;
    use std::arch::x86_64::*;

    /// [`super::add_ray`] on a row-major `(h, w)` image, four samples at a time; a block
    /// with a sample outside the image, and the last samples, go one at a time.
    ///
    /// # Safety
    /// The CPU must have AVX2, and `data` must hold `h × w` values.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn add_ray(
        data: &[f32],
        (h, w): (usize, usize),
        ray: &Ray,
        profile: &mut [f64],
    ) -> usize {
        let img = ndarray::ArrayView2::from_shape((h, w), data).expect("h × w values");
        // Gathers index with 32 bits.
        if data.len() >= i32::MAX as usize || h < 2 || w < 2 {
            return super::add_ray_from(img, ray, profile, 0);
        }
        let set = _mm256_set1_pd;
        let (cx, cy, ca, sa) = (
            set(ray.center[0]),
            set(ray.center[1]),
            set(ray.direction[0]),
            set(ray.direction[1]),
        );
        let (r_lo, step, one, zero) = (set(ray.r_lo), set(ray.step), set(1.0), set(0.0));
        let (x_max, y_max) = (set((w - 1) as f64), set((h - 1) as f64));
        let width = set(w as f64);
        let base = data.as_ptr();
        let n = profile.len();
        let mut i = 0;
        while i + 4 <= n {
            let k = _mm256_setr_pd(i as f64, (i + 1) as f64, (i + 2) as f64, (i + 3) as f64);
            let r = _mm256_add_pd(r_lo, _mm256_mul_pd(k, step));
            let x = _mm256_add_pd(cx, _mm256_mul_pd(r, ca));
            let y = _mm256_add_pd(cy, _mm256_mul_pd(r, sa));
            // `x >= 0 && y >= 0 && x <= w − 1 && y <= h − 1` (false for NaN).
            let inside = _mm256_and_pd(
                _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_GE_OQ>(x, zero),
                    _mm256_cmp_pd::<_CMP_GE_OQ>(y, zero),
                ),
                _mm256_and_pd(
                    _mm256_cmp_pd::<_CMP_LE_OQ>(x, x_max),
                    _mm256_cmp_pd::<_CMP_LE_OQ>(y, y_max),
                ),
            );
            if _mm256_movemask_pd(inside) != 0b1111 {
                return super::add_ray_from(img, ray, profile, i);
            }
            let (x0, y0) = (_mm256_floor_pd(x), _mm256_floor_pd(y));
            let x1 = _mm256_min_pd(_mm256_add_pd(x0, one), x_max);
            let y1 = _mm256_min_pd(_mm256_add_pd(y0, one), y_max);
            let (tx, ty) = (_mm256_sub_pd(x, x0), _mm256_sub_pd(y, y0));
            // Row-major offsets, exact in f64 (below 2³¹).
            let at = |yy: __m256d, xx: __m256d| {
                let offset = _mm256_cvtpd_epi32(_mm256_add_pd(_mm256_mul_pd(yy, width), xx));
                _mm256_cvtps_pd(_mm_i32gather_ps::<4>(base, offset))
            };
            let (ux, uy) = (_mm256_sub_pd(one, tx), _mm256_sub_pd(one, ty));
            let top = _mm256_add_pd(_mm256_mul_pd(at(y0, x0), ux), _mm256_mul_pd(at(y0, x1), tx));
            let bottom =
                _mm256_add_pd(_mm256_mul_pd(at(y1, x0), ux), _mm256_mul_pd(at(y1, x1), tx));
            let v = _mm256_add_pd(_mm256_mul_pd(top, uy), _mm256_mul_pd(bottom, ty));
            let p = profile.as_mut_ptr().add(i);
            _mm256_storeu_pd(p, _mm256_add_pd(_mm256_loadu_pd(p), v));
            i += 4;
        }
        super::add_ray_from(img, ray, profile, i)
    }
}

/// Convolution with edge samples repeated (kernel normalised).
fn smooth_nearest(v: &[f64], kernel: &[f64]) -> Vec<f64> {
    let (r, n) = ((kernel.len() / 2) as isize, v.len());
    let norm: f64 = kernel.iter().sum();
    let padded: Vec<f64> = (-r..n as isize + r)
        .map(|j| v[j.clamp(0, n as isize - 1) as usize])
        .collect();
    // Tap by tap over all the outputs (which vectorises): each output still sums its taps in
    // order, from −0.0 as `Iterator::sum` does.
    let mut out = vec![-0.0; n];
    for (k, &w) in kernel.iter().enumerate() {
        for (o, &x) in out.iter_mut().zip(&padded[k..k + n]) {
            *o += w * x;
        }
    }
    out.iter_mut().for_each(|o| *o /= norm);
    out
}

/// Largest angular gap (radians) between consecutive angles around the circle.
fn largest_gap(angles: &mut [f64]) -> f64 {
    use std::f64::consts::TAU;
    if angles.is_empty() {
        return TAU;
    }
    angles.sort_by(f64::total_cmp);
    let wrap = angles[0] + TAU - angles[angles.len() - 1];
    angles.windows(2).map(|p| p[1] - p[0]).fold(wrap, f64::max)
}

/// Algebraic (Kåsa) circle through points: centre and radius.
fn kasa_circle(points: &[[f64; 2]]) -> Option<([f64; 2], f64)> {
    if points.len() < 3 {
        return None;
    }
    // Solve [2x 2y 1]·(a, b, c) = x² + y², radius² = c + a² + b². Centred for conditioning.
    let n = points.len() as f64;
    let mx = points.iter().map(|p| p[0]).sum::<f64>() / n;
    let my = points.iter().map(|p| p[1]).sum::<f64>() / n;
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for p in points {
        let (x, y) = (p[0] - mx, p[1] - my);
        let row = nalgebra::Vector3::new(2.0 * x, 2.0 * y, 1.0);
        ata += row * row.transpose();
        atb += row * (x * x + y * y);
    }
    let s = ata.lu().solve(&atb)?;
    let r2 = s[2] + s[0] * s[0] + s[1] * s[1];
    (r2 > 0.0 && r2.is_finite()).then(|| ([s[0] + mx, s[1] + my], r2.sqrt()))
}

/// Geometric least-squares circle (Gauss–Newton on point-to-circle distances).
fn geometric_circle(points: &[[f64; 2]], start: ([f64; 2], f64)) -> ([f64; 2], f64) {
    let ([mut cx, mut cy], mut r) = start;
    for _ in 0..10 {
        let mut jtj = nalgebra::Matrix3::<f64>::zeros();
        let mut jtr = nalgebra::Vector3::<f64>::zeros();
        for p in points {
            let (dx, dy) = (p[0] - cx, p[1] - cy);
            let d = dx.hypot(dy);
            if d == 0.0 {
                continue;
            }
            let j = nalgebra::Vector3::new(-dx / d, -dy / d, -1.0);
            jtj += j * j.transpose();
            jtr += j * (d - r);
        }
        let Some(step) = jtj.lu().solve(&(-jtr)) else {
            break;
        };
        cx += step[0];
        cy += step[1];
        r += step[2];
        if step.norm() < 1e-9 {
            break;
        }
    }
    ([cx, cy], r)
}

/// RANSAC over 3-point circles (deterministic), then a geometric refit on the inliers.
fn robust_circle(points: &[LimbPoint], tol: f64) -> Option<([f64; 2], f64, usize)> {
    let xy: Vec<[f64; 2]> = points.iter().map(|p| p.xy).collect();
    let n = xy.len();
    if n < 3 {
        return None;
    }
    let count = |c: [f64; 2], r: f64| {
        xy.iter()
            .filter(|p| ((p[0] - c[0]).hypot(p[1] - c[1]) - r).abs() < tol)
            .count()
    };
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = |m: usize| {
        // xorshift64*: fixed seed, same answer every run.
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        (state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % m
    };
    let mut best: Option<([f64; 2], f64)> = None;
    let mut best_count = 0;
    for _ in 0..300 {
        let (i, j, k) = (next(n), next(n), next(n));
        if i == j || j == k || i == k {
            continue;
        }
        if let Some((c, r)) = kasa_circle(&[xy[i], xy[j], xy[k]]) {
            let m = count(c, r);
            if m > best_count {
                best_count = m;
                best = Some((c, r));
            }
        }
    }
    let (mut c, mut r) = best?;
    let mut inliers = Vec::new();
    for _ in 0..3 {
        inliers = xy
            .iter()
            .copied()
            .filter(|p| ((p[0] - c[0]).hypot(p[1] - c[1]) - r).abs() < tol)
            .collect::<Vec<_>>();
        let start = kasa_circle(&inliers)?;
        (c, r) = geometric_circle(&inliers, start);
    }
    Some((c, r, inliers.len()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The profile's smoothing is the convolution with edge samples repeated, each output's
    /// taps summed in order and divided by the kernel's sum, bit for bit; profiles shorter
    /// and longer than the kernel.
    #[test]
    fn profiles_are_smoothed_as_the_convolution_with_edges_repeated() {
        let kernel: Vec<f64> = (-4..=4)
            .map(|d| (-0.5 * (d as f64 / 1.3).powi(2)).exp())
            .collect();
        let norm: f64 = kernel.iter().sum();
        for n in [1, 3, 9, 40] {
            let v: Vec<f64> = (0..n)
                .map(|i| ((i * 37 % 11) as f64 - 4.5) * 1e3f64.powi(i % 5))
                .collect();
            let got = smooth_nearest(&v, &kernel);
            for (i, g) in got.iter().enumerate() {
                let mut sum = -0.0;
                for (k, w) in kernel.iter().enumerate() {
                    let j = (i as isize + k as isize - 4).clamp(0, n as isize - 1) as usize;
                    sum += w * v[j];
                }
                assert_eq!(
                    g.to_bits(),
                    (sum / norm).to_bits(),
                    "length {n}, sample {i}"
                );
            }
        }
    }

    /// Rays sampled four at a time give, bit for bit, the sums of the textbook bilinear
    /// interpolation sample by sample, and stop where it leaves the image: rays inside, rays
    /// that leave through every side after any number of samples, lengths not a multiple of
    /// four, a start outside.
    #[test]
    fn rays_add_the_textbook_bilinear_samples_and_stop_at_the_edge() {
        let (h, w) = (37, 53);
        let mut next = crate::test_data::uniform(11);
        let img = Array2::from_shape_fn((h, w), |_| (next() * 1000.0 - 200.0) as f32);
        let textbook = |x: f64, y: f64| -> Option<f64> {
            if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
                return None;
            }
            let (fx, fy) = (x.floor(), y.floor());
            let (x0, y0) = (fx as usize, fy as usize);
            let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
            let (tx, ty) = (x - fx, y - fy);
            let v = |yy: usize, xx: usize| img[[yy, xx]] as f64;
            let top = v(y0, x0) * (1.0 - tx) + v(y0, x1) * tx;
            let bottom = v(y1, x0) * (1.0 - tx) + v(y1, x1) * tx;
            Some(top * (1.0 - ty) + bottom * ty)
        };
        let mut stops = [0usize; 2];
        for case in 0..400 {
            let angle = next() * std::f64::consts::TAU;
            let ray = Ray {
                center: [next() * (w + 6) as f64 - 3.0, next() * (h + 6) as f64 - 3.0],
                direction: [angle.cos(), angle.sin()],
                r_lo: next() * 10.0 - 2.0,
                step: 0.05 + next() * 0.5,
            };
            let n = 1 + case % 97;
            let start: Vec<f64> = (0..n).map(|_| next() * 10.0).collect();
            let mut expected = start.clone();
            let mut reached = n;
            for (i, p) in expected.iter_mut().enumerate() {
                let r = ray.r_lo + i as f64 * ray.step;
                let xy = (
                    ray.center[0] + r * ray.direction[0],
                    ray.center[1] + r * ray.direction[1],
                );
                match textbook(xy.0, xy.1) {
                    Some(v) => *p += v,
                    None => {
                        reached = i;
                        break;
                    }
                }
            }
            let mut got = start;
            let len = add_ray(img.view(), &ray, &mut got);
            assert_eq!(len, reached, "ray {case}");
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&expected), "ray {case}");
            stops[usize::from(reached < n)] += 1;
        }
        // Both kinds of ray were drawn.
        assert!(stops[0] > 20 && stops[1] > 20, "{stops:?}");
    }
}
