//! `sunjitter synth` against truth: the motion measured in the written images (by an independent
//! Lucas–Kanade fit written here) matches `truth.csv`, and the headers read back as astropy and
//! sunpy read them.

use fitsio::FitsFile;
use std::path::Path;
use std::process::Command;

/// A Sun that does not turn: the fit below measures one similarity per frame, and the Sun's
/// rotation is no similarity.
fn synth(out: &Path, extra: &[&str]) {
    let status = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("synth")
        .arg("--out")
        .arg(out)
        .args(["--solar-rotation", "none"])
        .args(extra)
        .output()
        .expect("run sunjitter synth");
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
}

struct Frame {
    w: usize,
    h: usize,
    data: Vec<f64>,
}

impl Frame {
    fn at(&self, x: i64, y: i64) -> f64 {
        let x = x.clamp(0, self.w as i64 - 1) as usize;
        let y = y.clamp(0, self.h as i64 - 1) as usize;
        self.data[y * self.w + x]
    }

    /// Keys cubic convolution (a = −0.5) at a real position.
    fn cubic(&self, x: f64, y: f64) -> f64 {
        fn k(t: f64) -> f64 {
            let t = t.abs();
            if t < 1.0 {
                1.5 * t * t * t - 2.5 * t * t + 1.0
            } else if t < 2.0 {
                -0.5 * t * t * t + 2.5 * t * t - 4.0 * t + 2.0
            } else {
                0.0
            }
        }
        let (x0, y0) = (x.floor() as i64, y.floor() as i64);
        let mut s = 0.0;
        for j in -1..=2 {
            let wy = k(y - (y0 + j) as f64);
            for i in -1..=2 {
                s += wy * k(x - (x0 + i) as f64) * self.at(x0 + i, y0 + j);
            }
        }
        s
    }
}

/// Binomial [1 4 6 4 1]/16 smoothing along both axes (σ = 1 px): it damps the photon noise
/// and, being shift-invariant and nearly isotropic, leaves the motion between frames unchanged.
fn smooth(f: &Frame) -> Frame {
    const K: [f64; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    let pass = |src: &Frame, dx: i64, dy: i64| -> Frame {
        let data = (0..src.h * src.w)
            .map(|i| {
                let (x, y) = ((i % src.w) as i64, (i / src.w) as i64);
                K.iter()
                    .enumerate()
                    .map(|(k, w)| w * src.at(x + dx * (k as i64 - 2), y + dy * (k as i64 - 2)))
                    .sum()
            })
            .collect();
        Frame {
            w: src.w,
            h: src.h,
            data,
        }
    };
    pass(&pass(f, 1, 0), 0, 1)
}

fn read_frame(path: &Path) -> Frame {
    let mut f = FitsFile::open(path).unwrap();
    let hdu = f.primary_hdu().unwrap();
    let w: i64 = hdu.read_key(&mut f, "NAXIS1").unwrap();
    let h: i64 = hdu.read_key(&mut f, "NAXIS2").unwrap();
    let data: Vec<f32> = hdu.read_image(&mut f).unwrap();
    Frame {
        w: w as usize,
        h: h as usize,
        data: data.into_iter().map(f64::from).collect(),
    }
}

/// Truth rows: (dx, dy, rotation_arcsec, scale).
fn read_truth(dir: &Path) -> Vec<(String, [f64; 4])> {
    let text = std::fs::read_to_string(dir.join("truth.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next(),
        Some("frame,file,obs_time,dx_px,dy_px,rotation_arcsec,scale")
    );
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let n = |i: usize| f[i].parse::<f64>().unwrap();
            (f[1].to_string(), [n(3), n(4), n(5), n(6)])
        })
        .collect()
}

/// Gauss–Newton fit of `frame(T(p)) ≈ reference(p)` over the disk, with
/// `T(p) = c + [[a, −b], [b, a]](p − c) + t`. Returns (a, b, tx, ty).
fn fit_similarity(reference: &Frame, frame: &Frame, radius: f64) -> [f64; 4] {
    let (w, h) = (reference.w, reference.h);
    let c = [(w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0];
    let mut p = [1.0, 0.0, 0.0, 0.0];
    for _ in 0..12 {
        let (a, b, tx, ty) = (p[0], p[1], p[2], p[3]);
        // Warp the frame onto the reference grid.
        let warped: Vec<f64> = (0..h * w)
            .map(|i| {
                let (u, v) = ((i % w) as f64 - c[0], (i / w) as f64 - c[1]);
                frame.cubic(c[0] + a * u - b * v + tx, c[1] + b * u + a * v + ty)
            })
            .collect();
        let warped = Frame { w, h, data: warped };
        let mut jtj = [[0.0f64; 4]; 4];
        let mut jtr = [0.0f64; 4];
        for y in 2..h - 2 {
            for x in 2..w - 2 {
                let (u, v) = (x as f64 - c[0], y as f64 - c[1]);
                if u.hypot(v) > radius {
                    continue;
                }
                let (xi, yi) = (x as i64, y as i64);
                let gx = 0.25
                    * (reference.at(xi + 1, yi) - reference.at(xi - 1, yi) + warped.at(xi + 1, yi)
                        - warped.at(xi - 1, yi));
                let gy = 0.25
                    * (reference.at(xi, yi + 1) - reference.at(xi, yi - 1) + warped.at(xi, yi + 1)
                        - warped.at(xi, yi - 1));
                let r = warped.at(xi, yi) - reference.at(xi, yi);
                // ∂T/∂a = (u, v), ∂T/∂b = (−v, u), ∂T/∂t = identity.
                let j = [gx * u + gy * v, -gx * v + gy * u, gx, gy];
                for m in 0..4 {
                    jtr[m] += j[m] * r;
                    for n in 0..4 {
                        jtj[m][n] += j[m] * j[n];
                    }
                }
            }
        }
        let step = solve4(jtj, jtr);
        for m in 0..4 {
            p[m] -= step[m];
        }
    }
    p
}

fn solve4(mut a: [[f64; 4]; 4], mut b: [f64; 4]) -> [f64; 4] {
    for col in 0..4 {
        let piv = (col..4)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap();
        a.swap(col, piv);
        b.swap(col, piv);
        for row in col + 1..4 {
            let f = a[row][col] / a[col][col];
            let pivot = a[col];
            for (v, p) in a[row].iter_mut().zip(pivot).skip(col) {
                *v -= f * p;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; 4];
    for row in (0..4).rev() {
        let s: f64 = (row + 1..4).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x
}

/// The transform from frame i's grid to frame j's grid implied by the truth rows,
/// `T_j ∘ T_i⁻¹`, as (a, b, tx, ty) about the array centre.
fn relative_truth(ti: [f64; 4], tj: [f64; 4]) -> [f64; 4] {
    let rad = |arcsec: f64| arcsec / 206_264.806_247_096_36;
    let (si, ri) = (ti[3], rad(ti[2]));
    let (sj, rj) = (tj[3], rad(tj[2]));
    let (s, r) = (sj / si, rj - ri);
    let (a, b) = (s * r.cos(), s * r.sin());
    // T_j(T_i⁻¹(c + u)) = c + A u + (d_j − A d_i).
    let tx = tj[0] - (a * ti[0] - b * ti[1]);
    let ty = tj[1] - (b * ti[0] + a * ti[1]);
    [a, b, tx, ty]
}

#[test]
fn measured_shift_between_frames_matches_truth_csv() {
    let dir = tempfile::tempdir().unwrap();
    // Default jitter (sine:0.3:120, walk:0.02).
    synth(
        dir.path(),
        &["--frames", "6", "--size", "256", "--seed", "5"],
    );
    let truth = read_truth(dir.path());
    assert_eq!(truth.len(), 6);
    let f0 = smooth(&read_frame(&dir.path().join(&truth[0].0)));
    let radius = 0.95 * 960.0 / (0.6 * 4096.0 / 256.0);
    for k in [2usize, 5] {
        let fk = smooth(&read_frame(&dir.path().join(&truth[k].0)));
        let got = fit_similarity(&f0, &fk, radius);
        let want = relative_truth(truth[0].1, truth[k].1);
        eprintln!("frame {k}: measured {got:?}, truth {want:?}");
        // Photon noise alone moves a whole-disk least-squares shift by ~0.01 px at 256²
        // (scipy's quintic-spline least squares on the same smoothed files agrees within 0.003).
        assert!(
            (got[2] - want[2]).abs() < 0.03,
            "frame {k}: dx {} vs {}",
            got[2],
            want[2]
        );
        assert!(
            (got[3] - want[3]).abs() < 0.03,
            "frame {k}: dy {} vs {}",
            got[3],
            want[3]
        );
        // The motion is a real sub-pixel one, not zero.
        assert!(want[2].hypot(want[3]) > 0.1);
    }
}

#[test]
fn rotation_and_scale_follow_the_contract_convention() {
    let dir = tempfile::tempdir().unwrap();
    // 12 s of rot:360000″/h = 1200″ (0.0058 rad) counter-clockwise, scale +0.0012, dx 0.28 px.
    synth(
        dir.path(),
        &[
            "--frames",
            "2",
            "--size",
            "256",
            "--seed",
            "9",
            "--jitter",
            "rot:360000,scale:0.36,sine:0.3:48:x",
        ],
    );
    let truth = read_truth(dir.path());
    let f0 = smooth(&read_frame(&dir.path().join(&truth[0].0)));
    let f1 = smooth(&read_frame(&dir.path().join(&truth[1].0)));
    assert!((truth[1].1[2] - 1200.0).abs() < 1e-6 && (truth[1].1[3] - 1.0012).abs() < 1e-9);
    let got = fit_similarity(&f0, &f1, 0.95 * 100.0);
    eprintln!("measured {got:?}");
    let want = relative_truth(truth[0].1, truth[1].1);
    let rot = |p: [f64; 4]| p[1].atan2(p[0]) * 206_264.806;
    let scale = |p: [f64; 4]| p[0].hypot(p[1]);
    assert!((rot(got) - 1200.0).abs() < 30.0, "rotation {}″", rot(got));
    assert!(
        (scale(got) - scale(want)).abs() < 1.5e-4,
        "scale {}",
        scale(got)
    );
    assert!(
        (got[2] - want[2]).abs() < 0.03 && (got[3] - want[3]).abs() < 0.03,
        "{got:?} vs {want:?}"
    );
}

#[test]
fn headers_and_disk_read_as_astropy_reads_them() {
    let dir = tempfile::tempdir().unwrap();
    // step:10:0:x puts every frame 10 px to +x of the nominal pointing (headers do not know).
    synth(
        dir.path(),
        &[
            "--frames",
            "2",
            "--size",
            "256",
            "--seed",
            "2",
            "--jitter",
            "step:10:0:x",
        ],
    );
    let path = dir.path().join("synth_0001.fits");
    let mut f = FitsFile::open(&path).unwrap();
    let hdu = f.primary_hdu().unwrap();
    let s = |f: &mut FitsFile, k: &str| hdu.read_key::<String>(f, k).unwrap();
    let x = |f: &mut FitsFile, k: &str| hdu.read_key::<f64>(f, k).unwrap();
    // python3 -c "from astropy.io import fits; h=fits.getheader('synth_0001.fits');
    //   print([h[k] for k in ['BITPIX','DATE-OBS','EXPTIME','TELESCOP','INSTRUME','WAVELNTH',
    //   'CTYPE1','CTYPE2','CUNIT1','CDELT1','CDELT2','CRPIX1','CRPIX2','CRVAL1','CROTA2','RSUN_OBS']])"
    // → [16, '2024-05-01T12:00:12.000', 2.0, 'SYNTH', 'SYNTH', 171, 'HPLN-TAN', 'HPLT-TAN',
    //    'arcsec', 9.6, 9.6, 128.5, 128.5, 0.0, 0.0, 960.0]
    assert_eq!(hdu.read_key::<i64>(&mut f, "BITPIX").unwrap(), 16);
    assert_eq!(s(&mut f, "DATE-OBS"), "2024-05-01T12:00:12.000");
    assert_eq!(x(&mut f, "EXPTIME"), 2.0);
    assert_eq!(s(&mut f, "TELESCOP"), "SYNTH");
    assert_eq!(s(&mut f, "INSTRUME"), "SYNTH");
    assert_eq!(hdu.read_key::<i64>(&mut f, "WAVELNTH").unwrap(), 171);
    assert_eq!(s(&mut f, "CTYPE1"), "HPLN-TAN");
    assert_eq!(s(&mut f, "CTYPE2"), "HPLT-TAN");
    assert_eq!(s(&mut f, "CUNIT1"), "arcsec");
    assert_eq!((x(&mut f, "CDELT1"), x(&mut f, "CDELT2")), (9.6, 9.6));
    assert_eq!((x(&mut f, "CRPIX1"), x(&mut f, "CRPIX2")), (128.5, 128.5));
    assert_eq!((x(&mut f, "CRVAL1"), x(&mut f, "CROTA2")), (0.0, 0.0));
    assert_eq!(x(&mut f, "RSUN_OBS"), 960.0);
    // sunpy: m = sunpy.map.Map('synth_0001.fits') gives m.reference_pixel (127.5, 127.5) pix,
    // m.rsun_obs 960″, m.scale 9.6″/pix, m.date.isot '2024-05-01T12:00:12.000', m.wavelength
    // 171 Å, m.rotation_matrix identity, and m.wcs.world_to_pixel(SkyCoord(0*u.arcsec,
    // 0*u.arcsec, frame=m.coordinate_frame)) → (127.5, 127.5): the nominal Sun centre, 0-based.
    assert_eq!(x(&mut f, "CRPIX1") - 1.0, 127.5);

    // The disk in the data sits at the injected centre (137.5, 127.5) with radius
    // RSUN_OBS / CDELT = 100 px. Azimuthal mean profile in 0.5 px bins about a centre; the
    // limb is the steepest drop between neighbouring bins (an EUV limb's steepest descent lies
    // just above the photospheric radius, ≈ 1.01 R, where the shell emission starts to fall).
    // numpy on the same file:
    //   d=fits.getdata('synth_0001.fits').astype(float); yy,xx=np.indices(d.shape)
    //   r=np.hypot(xx-cx,yy-cy); b=np.floor(r*2).astype(int)
    //   prof=np.bincount(b.ravel(),d.ravel())/np.maximum(np.bincount(b.ravel()),1)
    //   g=np.diff(prof[160:240]); i=np.argmin(g)
    // → about (137.5, 127.5): edge at r = (161+i)/2 = 101.5, drop −60.5 DN;
    //   about the nominal (127.5, 127.5): edge at 93.5, drop −48.5 DN (limb smeared by 10 px).
    let frame = read_frame(&path);
    let (edge, drop) = steepest_limb_drop(&frame, [137.5, 127.5], 80.0, 120.0);
    let (edge_nominal, drop_nominal) = steepest_limb_drop(&frame, [127.5, 127.5], 80.0, 120.0);
    assert!((edge - 101.5).abs() <= 0.5, "limb at r = {edge}");
    assert!((edge - 1.01 * 100.0).abs() <= 1.5, "limb at r = {edge}");
    assert!((drop + 60.5).abs() < 0.5, "drop {drop}");
    assert!((edge_nominal - 93.5).abs() <= 0.5 && (drop_nominal + 48.5).abs() < 0.5);
    assert!(drop_nominal.abs() < drop.abs(), "{drop_nominal} vs {drop}");
}

/// (radius, drop) of the steepest fall of the azimuthal mean profile (0.5 px bins) in `[r0, r1)`.
fn steepest_limb_drop(frame: &Frame, c: [f64; 2], r0: f64, r1: f64) -> (f64, f64) {
    let bins = (r1 * 2.0) as usize + 2;
    let (mut sum, mut count) = (vec![0.0; bins], vec![0.0; bins]);
    for y in 0..frame.h {
        for x in 0..frame.w {
            let b = ((x as f64 - c[0]).hypot(y as f64 - c[1]) * 2.0).floor() as usize;
            if b < bins {
                sum[b] += frame.data[y * frame.w + x];
                count[b] += 1.0;
            }
        }
    }
    let prof: Vec<f64> = sum
        .iter()
        .zip(&count)
        .map(|(s, n)| s / f64::max(*n, 1.0))
        .collect();
    let lo = (r0 * 2.0) as usize;
    let hi = (r1 * 2.0) as usize;
    (lo..hi - 1)
        .map(|i| ((i + 1) as f64 / 2.0, prof[i + 1] - prof[i]))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap()
}
