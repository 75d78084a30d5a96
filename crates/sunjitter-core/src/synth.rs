//! Synthetic full-disk EUV frames with a known, injected pointing jitter (no I/O here).
//!
//! The scene is a continuous function of reference-grid coordinates; frame `k` samples it at
//! `T_k⁻¹(q)` for every pixel centre `q`, where `T_k` is the frame's [`Similarity`]. So content at
//! reference position `p` appears at `T_k(p)` exactly (sub-pixel motion is not resampled):
//! `p_frame = s·R(θ)·(p − c) + c + (dx, dy)`, `c` the array centre, as in the contract.
//!
//! What the scene contains (choices, AIA 171 Å-like):
//! - Plate scale `0.6″ × 4096 / size` per pixel and `RSUN_OBS` = 960″, so the disk fills the
//!   frame as on AIA (radius 1600 px at 4096²) whatever the size.
//! - Radial profile: a uniform disk plus an optically thin shell, `ε/(μ + ε)` inside the limb
//!   (EUV limb brightening, limb ≈ 2.5× centre as in AIA 171 Å), and off the limb an
//!   exponential (scale height 0.03 R☉) plus a `r⁻⁶` extended corona, modulated by streamers
//!   (harmonics 2–5 in position angle).
//! - Texture: a periodic field of cubic-B-spline lattice noise summed over octaves
//!   (lattice spacing 4, 8, … px up to size/8, equal variance per octave, i.e. a `k⁻²` power
//!   spectrum), applied as a log-normal brightness factor (network-like). It is evaluated as
//!   the cubic B-spline surface through the field's samples, so it is smooth and continuous
//!   and can be sampled at any transformed coordinate.
//! - Four active regions: clusters of eight anisotropic Gaussians (loop-like) each; a region's
//!   brightness changes by ±8 % over 2–6 h, all its blobs together, so it does not move (over
//!   10 min it shifts a whole-disk least-squares fit by < 0.002 px at 256²).
//! - PSF: Gaussian σ = 1 px (FWHM 2.4 px, about AIA's), applied analytically to the radial
//!   profile and the active regions, and to the texture samples (a σ = 0.82 px blur, which with
//!   the cubic B-spline's own σ = 0.58 px makes 1 px). It keeps aliasing small, so a sub-pixel
//!   motion of the scene is a sub-pixel motion of the sampled image: a quintic-spline
//!   least-squares fit (scipy) between two noiseless 256² frames recovers a (0.31, 0.16) px
//!   shift to 5e-5 px.
//! - Noise: Poisson (1.1 DN per photon; Gaussian approximation above 20 photons) plus 1.15 DN
//!   read noise; values are rounded to integer DN (int16 in the file).
//!
//! Cost: a 4096² frame takes about 0.9 s of CPU (plus 0.6 s once per run for the texture).
//!
//! The header keeps the nominal pointing (Sun centre at the array centre, `CROTA2` = 0): like a
//! real instrument, it does not know the jitter.

use crate::geometry::{Similarity, ARCSEC_PER_RAD};
use crate::time::format_iso_utc;
use crate::{Error, Result};
use ndarray::Array2;
use rayon::prelude::*;
use std::f64::consts::PI;
use std::str::FromStr;

/// AIA's plate scale at 4096², arcsec per pixel.
pub const AIA_PLATE_SCALE_ARCSEC: f64 = 0.6;
/// Apparent solar radius written as `RSUN_OBS`, arcsec.
pub const RSUN_ARCSEC: f64 = 960.0;
pub const TELESCOPE: &str = "SYNTH";
pub const INSTRUMENT: &str = "SYNTH";
pub const WAVELENGTH_A: i64 = 171;
/// The channel name the headers imply (instrument + wavelength).
pub const CHANNEL: &str = "SYNTH_171";

const PSF_SIGMA_PX: f64 = 1.0;
/// Extra Gaussian blur of the texture samples; with the cubic B-spline (σ² = 1/3 px²) the
/// texture's total blur is the PSF's.
const TEXTURE_BLUR_PX: f64 = 0.816;
const GAIN_DN_PER_PHOTON: f64 = 1.1;
const READ_NOISE_DN: f64 = 1.15;
/// Quiet-Sun disk level, DN (AIA 171 Å, 2 s exposure, order of magnitude).
const DISK_DN: f64 = 400.0;
const TEXTURE_CONTRAST: f64 = 0.4;

// ---------------------------------------------------------------------------------------------
// Jitter specification

/// Which axes a term moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    X,
    Y,
    /// Both; for a sinusoid, y lags x by a quarter period (a circular motion).
    Both,
}

/// One term of `--jitter SPEC`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JitterTerm {
    Sine {
        amp_px: f64,
        period_s: f64,
        axis: Axis,
    },
    Walk {
        step_px: f64,
    },
    Step {
        px: f64,
        at_s: f64,
        axis: Axis,
    },
    Rotation {
        arcsec_per_hour: f64,
    },
    Scale {
        per_hour: f64,
    },
}

/// A comma-separated sum of jitter terms, e.g. `sine:0.3:120,walk:0.02`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct JitterSpec {
    pub terms: Vec<JitterTerm>,
}

pub const DEFAULT_JITTER: &str = "sine:0.3:120,walk:0.02";

impl FromStr for JitterSpec {
    type Err = Error;

    fn from_str(spec: &str) -> Result<Self> {
        let spec = spec.trim();
        if spec.is_empty() || spec.eq_ignore_ascii_case("none") {
            return Ok(JitterSpec::default());
        }
        let terms = spec
            .split(',')
            .map(|t| parse_term(t.trim()))
            .collect::<Result<Vec<_>>>()?;
        Ok(JitterSpec { terms })
    }
}

fn parse_term(term: &str) -> Result<JitterTerm> {
    let bad = |why: &str| Error::Usage(format!("--jitter: bad term '{term}': {why}"));
    let parts: Vec<&str> = term.split(':').collect();
    let num = |i: usize, what: &str| -> Result<f64> {
        let s = parts
            .get(i)
            .ok_or_else(|| bad(&format!("missing {what}")))?;
        match s.trim().parse::<f64>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(bad(&format!("{what} '{s}' is not a number"))),
        }
    };
    let axis = |i: usize| -> Result<Axis> {
        match parts.get(i).map(|s| s.trim()) {
            None => Ok(Axis::Both),
            Some("x") | Some("X") => Ok(Axis::X),
            Some("y") | Some("Y") => Ok(Axis::Y),
            Some(other) => Err(bad(&format!("axis '{other}' is not x or y"))),
        }
    };
    let arity = |min: usize, max: usize| -> Result<()> {
        if parts.len() < min || parts.len() > max {
            Err(bad(&format!("expected {} to {} fields", min - 1, max - 1)))
        } else {
            Ok(())
        }
    };
    match parts[0].trim() {
        "sine" => {
            arity(3, 4)?;
            let period_s = num(2, "period")?;
            if period_s <= 0.0 {
                return Err(bad("period must be positive"));
            }
            Ok(JitterTerm::Sine {
                amp_px: num(1, "amplitude")?,
                period_s,
                axis: axis(3)?,
            })
        }
        "walk" => {
            arity(2, 2)?;
            let step_px = num(1, "step")?;
            if step_px < 0.0 {
                return Err(bad("step must not be negative"));
            }
            Ok(JitterTerm::Walk { step_px })
        }
        "step" => {
            arity(3, 4)?;
            Ok(JitterTerm::Step {
                px: num(1, "size")?,
                at_s: num(2, "time")?,
                axis: axis(3)?,
            })
        }
        "rot" => {
            arity(2, 2)?;
            Ok(JitterTerm::Rotation {
                arcsec_per_hour: num(1, "rate")?,
            })
        }
        "scale" => {
            arity(2, 2)?;
            Ok(JitterTerm::Scale {
                per_hour: num(1, "rate")?,
            })
        }
        other => Err(bad(&format!(
            "unknown kind '{other}' (sine, walk, step, rot, scale)"
        ))),
    }
}

/// The injected image motion of every frame (frame `k` at `k · cadence_s` after the start),
/// relative to the nominal pointing, about the centre of a `size × size` array.
pub fn jitter_truth(
    spec: &JitterSpec,
    frames: usize,
    cadence_s: f64,
    seed: u64,
    size: usize,
) -> Vec<Similarity> {
    let center = Similarity::array_center(size, size);
    let mut walk_rng = Rng::new(mix(seed, 0x5741_4c4b));
    let mut walks = vec![[0.0f64; 2]; spec.terms.len()];
    (0..frames)
        .map(|k| {
            let t = k as f64 * cadence_s;
            let mut m = Similarity::identity(center);
            for (term, walk) in spec.terms.iter().zip(walks.iter_mut()) {
                match *term {
                    JitterTerm::Sine {
                        amp_px,
                        period_s,
                        axis,
                    } => {
                        let phase = 2.0 * PI * t / period_s;
                        match axis {
                            Axis::X => m.dx += amp_px * phase.sin(),
                            Axis::Y => m.dy += amp_px * phase.sin(),
                            Axis::Both => {
                                m.dx += amp_px * phase.sin();
                                m.dy += amp_px * (phase - PI / 2.0).sin();
                            }
                        }
                    }
                    JitterTerm::Walk { step_px } => {
                        if k > 0 {
                            walk[0] += step_px * walk_rng.normal();
                            walk[1] += step_px * walk_rng.normal();
                        }
                        m.dx += walk[0];
                        m.dy += walk[1];
                    }
                    JitterTerm::Step { px, at_s, axis } => {
                        if t >= at_s {
                            if axis != Axis::Y {
                                m.dx += px;
                            }
                            if axis != Axis::X {
                                m.dy += px;
                            }
                        }
                    }
                    JitterTerm::Rotation { arcsec_per_hour } => {
                        m.rotation_rad += arcsec_per_hour * t / 3600.0 / ARCSEC_PER_RAD;
                    }
                    JitterTerm::Scale { per_hour } => m.scale += per_hour * t / 3600.0,
                }
            }
            m
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Scene

/// What to generate (the command line's knobs, minus the file layout).
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    /// Frames are `size × size`.
    pub size: usize,
    pub seed: u64,
    pub cadence_s: f64,
    pub exptime_s: f64,
    /// Poisson and read noise on (off gives the noiseless expectation).
    pub noise: bool,
    /// The Sun's differential rotation between frames (`none`: a Sun that does not turn).
    pub solar_rotation: crate::solar_rotation::Profile,
    /// Observation time of frame 0, ns since the Unix epoch (UTC): the Earth's position.
    pub start_ns: i64,
}

impl SynthConfig {
    pub fn new(size: usize, seed: u64, cadence_s: f64) -> Self {
        SynthConfig {
            size,
            seed,
            cadence_s,
            exptime_s: 2.0,
            noise: true,
            solar_rotation: crate::solar_rotation::Profile::default(),
            start_ns: DEFAULT_START_NS,
        }
    }

    /// Arcsec per pixel: AIA's 0.6″ at 4096², scaled so the disk fills any size the same way.
    pub fn plate_scale_arcsec(&self) -> f64 {
        AIA_PLATE_SCALE_ARCSEC * 4096.0 / self.size as f64
    }

    pub fn rsun_px(&self) -> f64 {
        RSUN_ARCSEC / self.plate_scale_arcsec()
    }

    /// What a frame's header says, as the engine reads it (nominal pointing).
    pub fn meta(&self, obs_time_ns: i64) -> crate::meta::FrameMeta {
        let cdelt = self.plate_scale_arcsec();
        let c = (self.size as f64 - 1.0) / 2.0;
        crate::meta::FrameMeta {
            file: std::path::PathBuf::from("synth.fits"),
            hdu: 0,
            frame: None,
            width: self.size,
            height: self.size,
            bitpix: 16,
            channel: CHANNEL.into(),
            instrument: Some(INSTRUMENT.into()),
            wavelength: Some(WAVELENGTH_A as f64),
            obs_time_ns: Some(obs_time_ns),
            exptime_s: Some(self.exptime_s),
            plate_scale_arcsec: [cdelt, cdelt],
            rotation_deg: 0.0,
            sun_center_px: [c, c],
            rsun_arcsec: Some(RSUN_ARCSEC),
            observer: crate::meta::Observer {
                hgln_deg: Some(0.0),
                hglt_deg: Some(0.0),
                crln_deg: None,
                dsun_m: Some(dsun_m()),
                rsun_ref_m: Some(RSUN_REF_M),
            },
        }
    }

    /// The surface motion from the time `time_s` after frame 0 back to frame 0's time, when
    /// the Sun turns.
    fn back_to_start(&self, time_s: f64) -> Option<crate::solar_rotation::SurfaceMotion> {
        use crate::solar_rotation::{Profile, SurfaceMotion, View};
        if self.solar_rotation == Profile::None || time_s == 0.0 {
            return None;
        }
        let now = self.start_ns + (time_s * 1e9).round() as i64;
        Some(SurfaceMotion::new(
            View::new(&self.meta(now))?,
            View::new(&self.meta(self.start_ns))?,
            self.solar_rotation,
        ))
    }
}

/// Frame 0's time when none is given: 2024-05-01T12:00:00Z.
pub const DEFAULT_START_NS: i64 = 1_714_564_800_000_000_000;
/// The sphere the synthetic disk shows, m, and the observer's distance that makes it
/// [`RSUN_ARCSEC`] across.
const RSUN_REF_M: f64 = 6.96e8;
fn dsun_m() -> f64 {
    RSUN_REF_M / (RSUN_ARCSEC / ARCSEC_PER_RAD).sin()
}

/// A bright active-region component: an anisotropic Gaussian, brightness evolving slowly.
#[derive(Debug, Clone)]
struct Blob {
    center: [f64; 2],
    /// Inverse covariance (a, b, c): exponent −½(a·u² + 2b·u·v + c·v²).
    inv: [f64; 3],
    half_extent: f64,
    amplitude: f64,
    period_s: f64,
    phase: f64,
}

/// The continuous scene; build once per seed, then [`SunModel::render`] each frame.
pub struct SunModel {
    cfg: SynthConfig,
    center: [f64; 2],
    rsun_px: f64,
    /// Texture samples, periodic with `tex_n`, padded by 3 wrapped rows/columns.
    tex: Vec<f32>,
    tex_n: usize,
    tex_stride: usize,
    /// PSF-convolved radial profile, DN, sampled every `1/PROFILE_STEPS` px.
    profile: Vec<f32>,
    /// Streamers: (a·cos φ₀, a·sin φ₀) of the harmonics 2, 3, 4, 5 in position angle.
    streamers: Vec<(f64, f64)>,
    blobs: Vec<Blob>,
}

const PROFILE_STEPS: f64 = 16.0;

impl SunModel {
    pub fn new(cfg: &SynthConfig) -> Result<Self> {
        if cfg.size < 32 || cfg.size > 16384 {
            return Err(Error::Usage(format!(
                "--size {} is out of range (32 to 16384)",
                cfg.size
            )));
        }
        let n = cfg.size;
        let center = Similarity::array_center(n, n);
        let rsun_px = cfg.rsun_px();
        let mut rng = Rng::new(mix(cfg.seed, 0x5343_454e));

        let (tex, tex_n) = texture(n, &mut rng);
        let tex_stride = tex_n + 3;

        // Radius of the farthest point any frame may sample, with room for big steps.
        let r_max = (2.0f64).sqrt() * n as f64 * 0.75 + 64.0;
        let profile = radial_profile(rsun_px, r_max);

        let streamers = (2..6)
            .map(|_| {
                let (amp, phase) = (rng.uniform_in(0.1, 0.3), rng.uniform_in(0.0, 2.0 * PI));
                (amp * phase.cos(), amp * phase.sin())
            })
            .collect();

        let px = |arcsec: f64| arcsec / cfg.plate_scale_arcsec();
        let mut blobs = Vec::new();
        for _ in 0..4 {
            // Active-region centres within 0.75 R, a cluster of loop-like Gaussians each.
            let r = 0.75 * rsun_px * rng.uniform().sqrt();
            let phi = rng.uniform_in(0.0, 2.0 * PI);
            let ar = [center[0] + r * phi.cos(), center[1] + r * phi.sin()];
            // One brightening cycle per region: its blobs scale together, so the evolution
            // changes brightness, not the (gradient-weighted) position of the region.
            let period_s = rng.uniform_in(2.0 * 3600.0, 6.0 * 3600.0);
            let phase = rng.uniform_in(0.0, 2.0 * PI);
            for _ in 0..8 {
                let off = [rng.normal() * px(50.0), rng.normal() * px(50.0)];
                let s_major =
                    (px(rng.uniform_in(15.0, 45.0)).powi(2) + PSF_SIGMA_PX.powi(2)).sqrt();
                let s_minor = (px(rng.uniform_in(5.0, 15.0)).powi(2) + PSF_SIGMA_PX.powi(2)).sqrt();
                let angle = rng.uniform_in(0.0, PI);
                let (c, s) = (angle.cos(), angle.sin());
                let (ia, ib) = (1.0 / (s_major * s_major), 1.0 / (s_minor * s_minor));
                blobs.push(Blob {
                    center: [ar[0] + off[0], ar[1] + off[1]],
                    inv: [
                        ia * c * c + ib * s * s,
                        (ia - ib) * c * s,
                        ia * s * s + ib * c * c,
                    ],
                    half_extent: 4.0 * s_major,
                    amplitude: DISK_DN * rng.uniform_in(1.0, 3.0),
                    period_s,
                    phase,
                });
            }
        }

        Ok(SunModel {
            cfg: cfg.clone(),
            center,
            rsun_px,
            tex,
            tex_n,
            tex_stride,
            profile,
            streamers,
            blobs,
        })
    }

    pub fn config(&self) -> &SynthConfig {
        &self.cfg
    }

    /// Frame `index` seen through `motion` at `time_s` after the start: shape `(size, size)`, DN.
    /// The surface has turned with the Sun since frame 0 (unless the profile is `none`);
    /// `motion` is the telescope's, on top.
    pub fn render(&self, motion: &Similarity, time_s: f64, index: u64) -> Array2<f32> {
        let n = self.cfg.size;
        let turned = self.cfg.back_to_start(time_s);
        // Where a point seen at `p` (nominal pointing, now) was at frame 0's time.
        let unturn = |p: [f64; 2]| match turned.as_ref().map(|m| m.map(p)) {
            Some(crate::solar_rotation::Moved::To(q)) => q,
            _ => p,
        };
        // Rotation moves features by at most this much (rows of blobs to look at).
        let reach = if turned.is_some() {
            let c = self.center;
            let q = unturn(c);
            2.0 * (q[0] - c[0]).hypot(q[1] - c[1]) + 1.0
        } else {
            0.0
        };

        // Frame pixel q → reference point p = T⁻¹(q).
        let inv = motion.recentered(self.center).inverse();
        let (a, b) = inv.ab();
        let c = self.center;
        let amps: Vec<f64> = self
            .blobs
            .iter()
            .map(|bl| {
                bl.amplitude * (1.0 + 0.08 * (2.0 * PI * time_s / bl.period_s + bl.phase).sin())
            })
            .collect();
        let noise_seed = mix(self.cfg.seed, 0x4e4f_4953 ^ index.wrapping_mul(0x9E37_79B9));
        let mut data = vec![0f32; n * n];
        data.par_chunks_mut(n).enumerate().for_each(|(y, row)| {
            let qy = y as f64 - c[1];
            // Reference coordinates along this row: p = c + t + A·(q − c).
            let px0 = c[0] + inv.dx - a * c[0] - b * qy;
            let py0 = c[1] + inv.dy + b * (-c[0]) + a * qy;
            let (ya, yb) = (py0, py0 + b * (n as f64 - 1.0));
            let (ylo, yhi) = (ya.min(yb) - reach, ya.max(yb) + reach);
            let row_blobs: Vec<(usize, &Blob)> = self
                .blobs
                .iter()
                .enumerate()
                .filter(|(_, bl)| {
                    bl.center[1] + bl.half_extent >= ylo && bl.center[1] - bl.half_extent <= yhi
                })
                .collect();
            let mut rng = Rng::new(mix(noise_seed, y as u64));
            for (x, out) in row.iter_mut().enumerate() {
                let p = unturn([px0 + a * x as f64, py0 + b * x as f64]);
                let mut v = self.scene(p);
                for (i, bl) in &row_blobs {
                    let (u, w) = (p[0] - bl.center[0], p[1] - bl.center[1]);
                    if u.abs() < bl.half_extent && w.abs() < bl.half_extent {
                        let q = bl.inv[0] * u * u + 2.0 * bl.inv[1] * u * w + bl.inv[2] * w * w;
                        v.0 += amps[*i] * (-0.5 * q).exp();
                    }
                }
                let mut dn = v.0 * v.1;
                if self.cfg.noise {
                    dn = noisy(dn, &mut rng);
                }
                *out = dn as f32;
            }
        });
        // Shape is n × n by construction.
        Array2::from_shape_vec((n, n), data).unwrap_or_else(|_| Array2::zeros((n, n)))
    }

    /// Noise-free (base brightness, texture factor) at reference point `p`, without active regions.
    fn scene(&self, p: [f64; 2]) -> (f64, f64) {
        let (dx, dy) = (p[0] - self.center[0], p[1] - self.center[1]);
        let r = (dx * dx + dy * dy).sqrt();
        let mut base = self.profile_at(r);
        if r > self.rsun_px {
            // Streamers fade in smoothly above the limb (C¹ at the limb).
            let h = 1.0 - (-(r - self.rsun_px) / (0.05 * self.rsun_px)).exp();
            // Σ aₖ·cos(kφ + φₖ) with (cos kφ, sin kφ) from powers of (dx + i·dy)/r.
            let (c1, s1) = (dx / r, dy / r);
            let (mut ck, mut sk) = (c1, s1);
            let mut g = 0.0;
            for &(re, im) in &self.streamers {
                (ck, sk) = (ck * c1 - sk * s1, sk * c1 + ck * s1);
                g += re * ck - im * sk;
            }
            base *= 1.0 + g * h * h;
        }
        let t = self.texture_at(p);
        let a = TEXTURE_CONTRAST;
        (base, (a * t - 0.5 * a * a).exp())
    }

    fn profile_at(&self, r: f64) -> f64 {
        let u = r * PROFILE_STEPS;
        let i = u as usize;
        if i + 1 >= self.profile.len() {
            return *self.profile.last().unwrap_or(&0.0) as f64;
        }
        let f = u - i as f64;
        self.profile[i] as f64 * (1.0 - f) + self.profile[i + 1] as f64 * f
    }

    /// Cubic B-spline surface through the periodic texture samples.
    fn texture_at(&self, p: [f64; 2]) -> f64 {
        let (fx, fy) = (p[0].floor(), p[1].floor());
        let wx = crate::resample::bspline3_weights(p[0] - fx);
        let wy = crate::resample::bspline3_weights(p[1] - fy);
        let n = self.tex_n as i64;
        let ix = (fx as i64 - 1).rem_euclid(n) as usize;
        let iy = (fy as i64 - 1).rem_euclid(n) as usize;
        let mut acc = 0.0f64;
        for (r, wyr) in wy.iter().enumerate() {
            let base = (iy + r) * self.tex_stride + ix;
            let row = &self.tex[base..base + 4];
            let s = wx[0] * row[0] as f64
                + wx[1] * row[1] as f64
                + wx[2] * row[2] as f64
                + wx[3] * row[3] as f64;
            acc += wyr * s;
        }
        acc
    }
}

/// Periodic octave noise on an `m × m` grid (`m ≥ size`, a multiple of the largest lattice),
/// unit variance, padded to `(m + 3)²` with wrapped copies for branch-free spline taps.
fn texture(size: usize, rng: &mut Rng) -> (Vec<f32>, usize) {
    let mut spacings = vec![4usize];
    while spacings.last().is_some_and(|&l| l * 2 <= (size / 8).max(8)) {
        let next = spacings[spacings.len() - 1] * 2;
        spacings.push(next);
    }
    let l_max = *spacings.last().unwrap_or(&4);
    let m = size.div_ceil(l_max) * l_max;
    let mut grid = vec![0f32; m * m];
    for &l in &spacings {
        let cells = m / l;
        let lattice: Vec<f32> = (0..cells * cells).map(|_| rng.normal() as f32).collect();
        // Upsample along x: for each lattice row, values at every pixel column.
        let weights: Vec<(usize, [f32; 4])> = (0..m)
            .map(|x| {
                let u = x as f64 / l as f64;
                let i0 = u.floor();
                let w = crate::resample::bspline3_weights(u - i0);
                (i0 as usize, w.map(|v| v as f32))
            })
            .collect();
        let mut rows = vec![0f32; cells * m];
        for j in 0..cells {
            let lat = &lattice[j * cells..(j + 1) * cells];
            let out = &mut rows[j * m..(j + 1) * m];
            for (x, (i0, w)) in weights.iter().enumerate() {
                let mut s = 0f32;
                for (k, wk) in w.iter().enumerate() {
                    s += wk * lat[(i0 + cells + k - 1) % cells];
                }
                out[x] = s;
            }
        }
        // Then along y, accumulating into the grid.
        grid.par_chunks_mut(m).enumerate().for_each(|(y, out)| {
            let (j0, w) = weights[y];
            for (k, wk) in w.iter().enumerate() {
                let src = &rows[((j0 + cells + k - 1) % cells) * m..][..m];
                for (o, s) in out.iter_mut().zip(src) {
                    *o += wk * s;
                }
            }
        });
    }
    let grid = blur_periodic(&grid, m, TEXTURE_BLUR_PX);
    let count = grid.len() as f64;
    let mean = grid.iter().map(|&v| v as f64).sum::<f64>() / count;
    let var = grid.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / count;
    let inv_sd = if var > 0.0 { 1.0 / var.sqrt() } else { 1.0 };
    let stride = m + 3;
    let mut padded = vec![0f32; stride * stride];
    for y in 0..stride {
        for x in 0..stride {
            padded[y * stride + x] = ((grid[(y % m) * m + (x % m)] as f64 - mean) * inv_sd) as f32;
        }
    }
    (padded, m)
}

/// Separable Gaussian blur of a periodic `m × m` grid.
fn blur_periodic(grid: &[f32], m: usize, sigma: f64) -> Vec<f32> {
    let half = (4.0 * sigma).ceil() as usize;
    let mut kernel: Vec<f32> = (0..=2 * half)
        .map(|k| (-0.5 * ((k as f64 - half as f64) / sigma).powi(2)).exp() as f32)
        .collect();
    let norm: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= norm);
    // Rows, then columns (as rows of the transpose-free column pass).
    let mut rows = vec![0f32; m * m];
    rows.par_chunks_mut(m).enumerate().for_each(|(y, out)| {
        let src = &grid[y * m..(y + 1) * m];
        for (x, o) in out.iter_mut().enumerate() {
            *o = kernel
                .iter()
                .enumerate()
                .map(|(k, w)| w * src[(x + m * 2 + k - half) % m])
                .sum();
        }
    });
    let mut out = vec![0f32; m * m];
    out.par_chunks_mut(m).enumerate().for_each(|(y, o)| {
        for (k, w) in kernel.iter().enumerate() {
            let src = &rows[((y + m * 2 + k - half) % m) * m..][..m];
            for (a, b) in o.iter_mut().zip(src) {
                *a += w * b;
            }
        }
    });
    out
}

/// Disk + limb-brightened shell + corona, DN, convolved with the Gaussian PSF along r.
fn radial_profile(rsun: f64, r_max: f64) -> Vec<f32> {
    let len = (r_max * PROFILE_STEPS) as usize + 2;
    let eps = 0.08;
    let shell = 2.0 * DISK_DN;
    let h = 0.03 * rsun;
    let raw: Vec<f64> = (0..len)
        .map(|i| {
            let r = i as f64 / PROFILE_STEPS;
            if r < rsun {
                let mu = (1.0 - (r / rsun).powi(2)).max(0.0).sqrt();
                DISK_DN + shell * eps / (mu + eps)
            } else {
                shell * (0.85 * (-(r - rsun) / h).exp() + 0.15 * (r / rsun).powi(-6))
            }
        })
        .collect();
    let half = (4.0 * PSF_SIGMA_PX * PROFILE_STEPS).ceil() as i64;
    let kernel: Vec<f64> = (-half..=half)
        .map(|k| {
            let r = k as f64 / PROFILE_STEPS;
            (-0.5 * (r / PSF_SIGMA_PX).powi(2)).exp()
        })
        .collect();
    let norm: f64 = kernel.iter().sum();
    (0..len as i64)
        .map(|i| {
            let mut s = 0.0;
            for (k, w) in kernel.iter().enumerate() {
                // Mirror at r = 0 (the profile is even in r).
                let j = (i + k as i64 - half).unsigned_abs() as usize;
                s += w * raw[j.min(len - 1)];
            }
            (s / norm) as f32
        })
        .collect()
}

/// Poisson photon noise (gain 1.1 DN/photon) plus read noise, rounded to integer DN.
fn noisy(dn: f64, rng: &mut Rng) -> f64 {
    let lambda = dn.max(0.0) / GAIN_DN_PER_PHOTON;
    let v = if lambda >= 20.0 {
        dn + (lambda * GAIN_DN_PER_PHOTON * GAIN_DN_PER_PHOTON + READ_NOISE_DN * READ_NOISE_DN)
            .sqrt()
            * rng.fast_normal()
    } else {
        // Knuth's multiplication method: fine for small means.
        let limit = (-lambda).exp();
        let mut k = 0u32;
        let mut prod = rng.uniform();
        while prod > limit {
            k += 1;
            prod *= rng.uniform();
        }
        k as f64 * GAIN_DN_PER_PHOTON + READ_NOISE_DN * rng.fast_normal()
    };
    v.round().clamp(i16::MIN as f64, i16::MAX as f64)
}

// ---------------------------------------------------------------------------------------------
// Header

/// A header card value, written by the command with `fitsio`.
#[derive(Debug, Clone, PartialEq)]
pub enum CardValue {
    Str(String),
    Float(f64),
    Int(i64),
}

/// One header card: keyword, value, comment.
#[derive(Debug, Clone, PartialEq)]
pub struct Card {
    pub key: &'static str,
    pub value: CardValue,
    pub comment: &'static str,
}

/// A level-1-like header for a frame observed at `obs_time_ns` (nominal pointing only).
pub fn header_cards(cfg: &SynthConfig, frame: usize, obs_time_ns: i64) -> Vec<Card> {
    use CardValue::*;
    let cdelt = cfg.plate_scale_arcsec();
    let crpix = (cfg.size as f64 + 1.0) / 2.0;
    let (rsun_ref, dsun) = (RSUN_REF_M, dsun_m());
    let card = |key, value, comment| Card {
        key,
        value,
        comment,
    };
    vec![
        card(
            "DATE-OBS",
            Str(format_iso_utc(obs_time_ns)
                .trim_end_matches('Z')
                .to_string()),
            "start of exposure, UTC",
        ),
        card("EXPTIME", Float(cfg.exptime_s), "[s] exposure time"),
        card("TELESCOP", Str(TELESCOPE.into()), "synthetic telescope"),
        card("INSTRUME", Str(INSTRUMENT.into()), "synthetic instrument"),
        card("WAVELNTH", Int(WAVELENGTH_A), "[angstrom] wavelength"),
        card("WAVEUNIT", Str("angstrom".into()), "unit of WAVELNTH"),
        card("BUNIT", Str("DN".into()), "data unit"),
        card("LVL_NUM", Float(1.0), "data level"),
        card(
            "CTYPE1",
            Str("HPLN-TAN".into()),
            "helioprojective longitude",
        ),
        card("CTYPE2", Str("HPLT-TAN".into()), "helioprojective latitude"),
        card("CUNIT1", Str("arcsec".into()), ""),
        card("CUNIT2", Str("arcsec".into()), ""),
        card("CDELT1", Float(cdelt), "[arcsec/px] plate scale"),
        card("CDELT2", Float(cdelt), "[arcsec/px] plate scale"),
        card(
            "CRPIX1",
            Float(crpix),
            "Sun centre, 1-based (nominal pointing)",
        ),
        card(
            "CRPIX2",
            Float(crpix),
            "Sun centre, 1-based (nominal pointing)",
        ),
        card("CRVAL1", Float(0.0), "[arcsec]"),
        card("CRVAL2", Float(0.0), "[arcsec]"),
        card("CROTA2", Float(0.0), "[deg] roll (nominal)"),
        card(
            "RSUN_OBS",
            Float(RSUN_ARCSEC),
            "[arcsec] apparent solar radius",
        ),
        card("R_SUN", Float(cfg.rsun_px()), "[px] apparent solar radius"),
        card("RSUN_REF", Float(rsun_ref), "[m] reference solar radius"),
        card("DSUN_OBS", Float(dsun), "[m] observer to Sun centre"),
        card("HGLN_OBS", Float(0.0), "[deg] observer longitude"),
        card("HGLT_OBS", Float(0.0), "[deg] observer latitude"),
        card("ORIGIN", Str("sunjitter synth".into()), "synthetic data"),
        card("SYNSEED", Int(cfg.seed as i64), "synth seed"),
        card("SYNFRAME", Int(frame as i64), "synth frame index"),
    ]
}

// ---------------------------------------------------------------------------------------------
// Random numbers (deterministic from the seed; no external crate needed)

/// SplitMix64 finaliser: decorrelates seeds for independent streams.
fn mix(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// xoshiro256++ with a cached Box–Muller normal and a table-driven fast normal for pixel noise.
struct Rng {
    s: [u64; 4],
    spare: Option<f64>,
    bits: u64,
    nbits: u32,
}

/// Φ⁻¹ at the centres of 65 536 equal-probability bins: a normal deviate per 16 random bits
/// (tails truncated at 4.3σ, which image noise does not miss).
fn normal_table() -> &'static [f32] {
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (0..65_536)
            .map(|i| inverse_normal_cdf((i as f64 + 0.5) / 65_536.0) as f32)
            .collect()
    })
}

/// Acklam's rational approximation of Φ⁻¹ (relative error < 1.2e-9).
fn inverse_normal_cdf(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969_683_028_665_376e1,
        2.209_460_984_245_205e2,
        -2.759_285_104_469_687e2,
        1.383_577_518_672_69e2,
        -3.066_479_806_614_716e1,
        2.506_628_277_459_239,
    ];
    const B: [f64; 5] = [
        -5.447_609_879_822_406e1,
        1.615_858_368_580_409e2,
        -1.556_989_798_598_866e2,
        6.680_131_188_771_972e1,
        -1.328_068_155_288_572e1,
    ];
    const C: [f64; 6] = [
        -7.784_894_002_430_293e-3,
        -3.223_964_580_411_365e-1,
        -2.400_758_277_161_838,
        -2.549_732_539_343_734,
        4.374_664_141_464_968,
        2.938_163_982_698_783,
    ];
    const D: [f64; 4] = [
        7.784_695_709_041_462e-3,
        3.224_671_290_700_398e-1,
        2.445_134_137_142_996,
        3.754_408_661_907_416,
    ];
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < 0.024_25 {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - 0.024_25 {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

impl Rng {
    fn new(seed: u64) -> Self {
        let mut s = [0u64; 4];
        for (i, v) in s.iter_mut().enumerate() {
            *v = mix(seed, i as u64 + 1);
        }
        Rng {
            s,
            spare: None,
            bits: 0,
            nbits: 0,
        }
    }

    fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in (0, 1].
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) + 1) as f64 / (1u64 << 53) as f64
    }

    fn uniform_in(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// A normal deviate from 16 random bits (see [`normal_table`]).
    fn fast_normal(&mut self) -> f64 {
        if self.nbits < 16 {
            self.bits = self.next_u64();
            self.nbits = 64;
        }
        let i = (self.bits & 0xFFFF) as usize;
        self.bits >>= 16;
        self.nbits -= 16;
        normal_table()[i] as f64
    }

    fn normal(&mut self) -> f64 {
        if let Some(v) = self.spare.take() {
            return v;
        }
        let r = (-2.0 * self.uniform().ln()).sqrt();
        let a = 2.0 * PI * self.uniform();
        self.spare = Some(r * a.sin());
        r * a.cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parses_every_kind_and_rejects_junk() {
        let s: JitterSpec = "sine:0.3:120,walk:0.02,step:1.5:60:x,rot:10,scale:1e-5"
            .parse()
            .unwrap();
        assert_eq!(s.terms.len(), 5);
        assert_eq!(
            s.terms[2],
            JitterTerm::Step {
                px: 1.5,
                at_s: 60.0,
                axis: Axis::X
            }
        );
        for bad in [
            "sine:0.3",
            "sine:a:120",
            "walk",
            "step:1:2:z",
            "wobble:1",
            "sine:1:0",
            "walk:-1",
        ] {
            let e = bad.parse::<JitterSpec>().unwrap_err();
            assert_eq!(e.exit_code(), crate::error::ExitCode::BadInput, "{bad}");
        }
        assert!("none".parse::<JitterSpec>().unwrap().terms.is_empty());
    }

    #[test]
    fn sine_on_both_axes_has_y_a_quarter_period_behind() {
        let spec: JitterSpec = "sine:0.5:120".parse().unwrap();
        let t = jitter_truth(&spec, 11, 12.0, 1, 64);
        // t = 0: x = 0, y = -A; t = 30 s (quarter period) is not sampled; t = 60 s: x = 0, y = +A.
        assert!(t[0].dx.abs() < 1e-12 && (t[0].dy + 0.5).abs() < 1e-12);
        assert!(t[5].dx.abs() < 1e-12 && (t[5].dy - 0.5).abs() < 1e-12);
        // y(t) = x(t - P/4): y at 36 s equals x at 6 s.
        let x6 = 0.5 * (2.0 * PI * 6.0 / 120.0).sin();
        assert!((t[3].dy - x6).abs() < 1e-12);
    }

    #[test]
    fn drifts_and_steps_follow_their_definitions() {
        let spec: JitterSpec = "rot:3600,scale:0.36,step:2:24:y".parse().unwrap();
        let t = jitter_truth(&spec, 4, 12.0, 1, 64);
        // 3600″/h for 36 s = 36″; scale 0.36/h for 36 s = 0.0036.
        assert!((t[3].rotation_arcsec() - 36.0).abs() < 1e-9);
        assert!((t[3].scale - 1.0036).abs() < 1e-12);
        assert_eq!((t[1].dx, t[1].dy), (0.0, 0.0));
        assert_eq!((t[2].dx, t[2].dy), (0.0, 2.0));
    }

    #[test]
    fn walk_steps_have_the_requested_spread() {
        let spec: JitterSpec = "walk:0.1".parse().unwrap();
        let t = jitter_truth(&spec, 4001, 1.0, 7, 64);
        let steps: Vec<f64> = t.windows(2).map(|w| w[1].dx - w[0].dx).collect();
        let rms = (steps.iter().map(|s| s * s).sum::<f64>() / steps.len() as f64).sqrt();
        // 4000 samples: the sample RMS is within ~3 % (3σ ≈ 3.4 %) of 0.1.
        assert!((rms - 0.1).abs() < 0.0035, "{rms}");
        assert_eq!(t[0].dx, 0.0);
    }

    #[test]
    fn table_normals_are_standard_normal() {
        // scipy.stats.norm.ppf(0.975) = 1.959963984540054, norm.ppf(0.001) = -3.090232306167813,
        // 2*norm.sf(2) = 0.0455.
        assert!((inverse_normal_cdf(0.975) - 1.959_963_984_540_054).abs() < 1e-8);
        assert!((inverse_normal_cdf(0.001) + 3.090_232_306_167_813).abs() < 1e-8);
        let mut rng = Rng::new(5);
        let n = 200_000;
        let v: Vec<f64> = (0..n).map(|_| rng.fast_normal()).collect();
        let mean = v.iter().sum::<f64>() / n as f64;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        let beyond2 = v.iter().filter(|x| x.abs() > 2.0).count() as f64 / n as f64;
        // Standard errors: mean 0.0022, variance 0.0032; P(|z| > 2) = 0.0455 ± 0.0005.
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.015,
            "{mean} {var}"
        );
        assert!((beyond2 - 0.0455).abs() < 0.002, "{beyond2}");
    }

    #[test]
    fn header_has_the_nominal_pointing_and_fits_date() {
        // 2024-05-01T12:00:12.345Z = 1714564812.345 s (date -u -d 2024-05-01T12:00:12Z +%s).
        let cfg = SynthConfig::new(1024, 1, 12.0);
        let cards = header_cards(&cfg, 1, 1_714_564_812_345_000_000);
        let get = |k: &str| cards.iter().find(|c| c.key == k).map(|c| c.value.clone());
        assert_eq!(
            get("DATE-OBS"),
            Some(CardValue::Str("2024-05-01T12:00:12.345".into()))
        );
        // 1024² at 2.4″/px: Sun centre at the array centre, 1-based 512.5; radius 400 px.
        assert_eq!(get("CDELT1"), Some(CardValue::Float(2.4)));
        assert_eq!(get("CRPIX1"), Some(CardValue::Float(512.5)));
        assert_eq!(get("R_SUN"), Some(CardValue::Float(400.0)));
    }

    #[test]
    fn noiseless_frame_moves_by_the_injected_integer_shift() {
        // A whole-pixel shift makes frame pixel (x+3, y-2) sample exactly the reference point (x, y).
        let mut cfg = SynthConfig::new(64, 3, 12.0);
        cfg.noise = false;
        let model = SunModel::new(&cfg).unwrap();
        let c = Similarity::array_center(64, 64);
        let still = model.render(&Similarity::identity(c), 0.0, 0);
        let moved = model.render(
            &Similarity {
                dx: 3.0,
                dy: -2.0,
                ..Similarity::identity(c)
            },
            0.0,
            0,
        );
        for y in 10..50 {
            for x in 10..50 {
                let (a, b) = (still[[y, x]], moved[[y - 2, x + 3]]);
                assert!(
                    (a - b).abs() <= 1e-3 * a.abs().max(1.0),
                    "({x},{y}) {a} {b}"
                );
            }
        }
    }
}
