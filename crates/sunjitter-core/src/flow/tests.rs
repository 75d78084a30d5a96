//! Unit tests on the real TRACE crop (fixtures made by tools/make_flow_fixtures.py).

use super::*;
use ndarray::Array2;

pub(crate) fn load_fixture(name: &str) -> Array2<f32> {
    let path = format!(
        "{}/../../tests/data/flow/{name}",
        env!("CARGO_MANIFEST_DIR")
    );
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let v: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let n = (v.len() as f64).sqrt() as usize;
    Array2::from_shape_vec((n, n), v).expect("square fixture")
}

fn median(mut v: Vec<f32>) -> f32 {
    v.retain(|x| x.is_finite());
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn small_params() -> FarnebackParams {
    FarnebackParams {
        levels: 3,
        winsize: 33,
        ..Default::default()
    }
}

/// Injected translation (+0.30, −0.45) px (scipy spline, tools/make_flow_fixtures.py): the
/// median flow equals it to 0.01 px.
#[test]
fn recovers_subpixel_translation_on_trace() {
    let prev = load_fixture("prev.f32");
    let next = load_fixture("shift_next.f32");
    for gaussian_window in [false, true] {
        let p = FarnebackParams {
            gaussian_window,
            ..small_params()
        };
        let f = farneback(prev.view(), next.view(), &p, None).expect("flow");
        let mu = median(f.u.iter().copied().collect());
        let mv = median(f.v.iter().copied().collect());
        assert!(
            (mu - 0.30).abs() < 0.01 && (mv + 0.45).abs() < 0.01,
            "gaussian={gaussian_window}: median flow ({mu}, {mv}) vs (0.30, -0.45)"
        );
    }
}

/// The flow does not depend on intensity units: ×1e-3 and ×1e4 give the same field.
#[test]
fn flow_is_independent_of_intensity_scale() {
    let prev = load_fixture("prev.f32");
    let next = load_fixture("shift_next.f32");
    let p = small_params();
    let base = farneback(prev.view(), next.view(), &p, None).expect("flow");
    for k in [1e-3f32, 1e4] {
        let (a, b) = (prev.mapv(|x| x * k), next.mapv(|x| x * k));
        let f = farneback(a.view(), b.view(), &p, None).expect("flow");
        let worst =
            f.u.iter()
                .zip(base.u.iter())
                .chain(f.v.iter().zip(base.v.iter()))
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
        assert!(worst < 1e-3, "scale {k}: max |Δflow| = {worst} px");
        let mu = median(f.u.iter().copied().collect());
        assert!((mu - 0.30).abs() < 0.01, "scale {k}: median u = {mu}");
    }
}

/// NaN blocks are missing data: flow elsewhere still recovers the shift, NaN pixels stay NaN.
#[test]
fn nan_is_missing_data_not_poison() {
    let mut prev = load_fixture("prev.f32");
    let mut next = load_fixture("shift_next.f32");
    prev.slice_mut(ndarray::s![100..140, 20..90]).fill(f32::NAN);
    next.slice_mut(ndarray::s![180..256, 180..256])
        .fill(f32::NAN);
    let f = farneback(prev.view(), next.view(), &small_params(), None).expect("flow");
    assert!(f.u[[120, 50]].is_nan());
    let finite = f.u.iter().filter(|x| x.is_finite()).count();
    assert!(finite > 256 * 256 * 8 / 10, "only {finite} finite vectors");
    let mu = median(f.u.iter().copied().collect());
    let mv = median(f.v.iter().copied().collect());
    assert!(
        (mu - 0.30).abs() < 0.01 && (mv + 0.45).abs() < 0.01,
        "median flow ({mu}, {mv}) vs (0.30, -0.45)"
    );
}

/// A ROI computes the same flow as the whole image inside it (to a small tolerance from the
/// truncated margin) and NaN outside.
#[test]
fn roi_matches_whole_image_inside() {
    let prev = load_fixture("prev.f32");
    let next = load_fixture("warp_next.f32");
    let p = small_params();
    let full = farneback(prev.view(), next.view(), &p, None).expect("flow");
    let roi = Roi {
        x: 96,
        y: 80,
        width: 64,
        height: 90,
    };
    let part = farneback(prev.view(), next.view(), &p, Some(roi)).expect("flow");
    assert!(part.u[[10, 10]].is_nan() && part.u[[200, 200]].is_nan());
    let mut worst = 0f32;
    for y in roi.y..roi.y + roi.height {
        for x in roi.x..roi.x + roi.width {
            worst = worst.max((part.u[[y, x]] - full.u[[y, x]]).abs());
            worst = worst.max((part.v[[y, x]] - full.v[[y, x]]).abs());
        }
    }
    assert!(worst < 0.01, "max |roi − full| = {worst} px");
}

#[test]
fn winsize_from_arcsec_is_odd_and_bounded() {
    // Paper: 63″ at TRACE's 0.5″/px = 126 px → 127; at AIA's 0.6″/px = 105.
    assert_eq!(winsize_from_arcsec(63.0, 0.5), 127);
    assert_eq!(winsize_from_arcsec(63.0, 0.6), 105);
    assert_eq!(winsize_from_arcsec(63.0, 21.0), MIN_WINSIZE);
    assert_eq!(winsize_from_arcsec(f64::NAN, 0.5), MIN_WINSIZE);
    assert_eq!(winsize_from_arcsec(63.0, 0.0), MIN_WINSIZE);
}

#[test]
fn bad_input_is_an_error() {
    let a = Array2::<f32>::zeros((10, 12));
    let b = Array2::<f32>::zeros((12, 10));
    assert!(farneback(a.view(), b.view(), &FarnebackParams::default(), None).is_err());
    let bad = FarnebackParams {
        pyr_scale: 1.5,
        ..Default::default()
    };
    assert!(farneback(a.view(), a.view(), &bad, None).is_err());
    // Constant images carry no motion information: all NaN, no panic.
    let f = farneback(a.view(), a.view(), &FarnebackParams::default(), None).expect("flow");
    assert!(f.u.iter().all(|x| x.is_nan()));
}

/// Affine-window grid solver on the TRACE warp fixture (rotation 0.4°, scale 1.003, shift
/// (+0.37, −0.61), scipy spline): the least-squares affine fit of the flow over the interior
/// recovers the injected rotation and scale to within 1 % (the constant window, as OpenCV,
/// under-measures them by 3–5 % here: see tests/flow_oracle.rs), and the RMS flow error
/// against the truth is 0.019 px, against the constant window's 0.055 px (asserted < 0.025).
#[test]
fn affine_window_recovers_rotation_and_scale() {
    let prev = load_fixture("prev.f32");
    let next = load_fixture("warp_next.f32");
    let opts = |model| FlowOptions {
        model,
        grid_stride: 4,
        ..Default::default()
    };
    let run = |o: FlowOptions| {
        Farneback::new(small_params())
            .and_then(|f| f.with_options(o))
            .and_then(|mut f| f.compute(prev.view(), next.view(), None, None))
            .expect("flow")
    };
    // Truth (tools/make_flow_fixtures.py): d(p) = A (p − c) + c + t − p.
    let a = [
        [1.0029755575975108, 0.007002204078855437],
        [-0.007002204078855437, 1.0029755575975108],
    ];
    let (c, t) = (127.5, [0.37, -0.61]);
    let truth = |x: f64, y: f64| {
        let (px, py) = (x - c, y - c);
        (
            a[0][0] * px + a[0][1] * py + c + t[0] - x,
            a[1][0] * px + a[1][1] * py + c + t[1] - y,
        )
    };
    let fit = |f: &Flow| {
        // Least squares u, v = k0 + k1 (x − c) + k2 (y − c) over pixels ≥ winsize from the edge.
        let (mut ata, mut atu, mut atv) = ([[0f64; 3]; 3], [0f64; 3], [0f64; 3]);
        let mut se = 0.0;
        let mut n = 0.0;
        for y in 33..256 - 33 {
            for x in 33..256 - 33 {
                let (u, v) = (f.u[[y, x]] as f64, f.v[[y, x]] as f64);
                let r = [1.0, x as f64 - c, y as f64 - c];
                for i in 0..3 {
                    for j in 0..3 {
                        ata[i][j] += r[i] * r[j];
                    }
                    atu[i] += r[i] * u;
                    atv[i] += r[i] * v;
                }
                let (tu, tv) = truth(x as f64, y as f64);
                se += (u - tu).powi(2) + (v - tv).powi(2);
                n += 1.0;
            }
        }
        let m = nalgebra::Matrix3::from_fn(|i, j| ata[i][j]);
        let inv = m.try_inverse().expect("well-posed fit");
        let ku = inv * nalgebra::Vector3::from(atu);
        let kv = inv * nalgebra::Vector3::from(atv);
        let scale_gain = (ku[1] + kv[2]) / 2.0 / ((a[0][0] + a[1][1]) / 2.0 - 1.0);
        let rot_gain = (ku[2] - kv[1]) / 2.0 / ((a[0][1] - a[1][0]) / 2.0);
        (scale_gain, rot_gain, (se / n).sqrt())
    };
    let (sg_c, rg_c, rms_c) = fit(&run(opts(WindowModel::Constant)));
    let (sg_a, rg_a, rms_a) = fit(&run(opts(WindowModel::Affine)));
    eprintln!("constant: gains scale {sg_c:.4} rot {rg_c:.4} rms {rms_c:.4}; affine: {sg_a:.4} {rg_a:.4} {rms_a:.4}");
    assert!(
        (sg_a - 1.0).abs() < 0.01 && (rg_a - 1.0).abs() < 0.01,
        "affine gains {sg_a} {rg_a}"
    );
    assert!(rms_a < 0.025, "affine RMS vs truth {rms_a}");
    assert!(
        rg_c < 0.98,
        "constant window should under-measure rotation here: {rg_c}"
    );
}

/// The unbiased preset (`FlowOptions::affine_grid`) on the real crop: recovers the injected
/// translation with NaN holes present, and a ROI run agrees with the whole-image run inside it.
#[test]
fn affine_grid_preset_handles_nan_and_roi() {
    let mut prev = load_fixture("prev.f32");
    let mut next = load_fixture("shift_next.f32");
    prev.slice_mut(ndarray::s![100..140, 20..90]).fill(f32::NAN);
    next.slice_mut(ndarray::s![180..256, 180..256])
        .fill(f32::NAN);
    let p = small_params();
    let solver = || {
        Farneback::new(p.clone())
            .and_then(|f| f.with_options(FlowOptions::affine_grid(p.winsize)))
            .expect("solver")
    };
    let full = solver()
        .compute(prev.view(), next.view(), None, None)
        .expect("flow");
    assert!(full.u[[120, 50]].is_nan());
    let mu = median(full.u.iter().copied().collect());
    let mv = median(full.v.iter().copied().collect());
    assert!(
        (mu - 0.30).abs() < 0.01 && (mv + 0.45).abs() < 0.01,
        "median flow ({mu}, {mv}) vs (0.30, -0.45)"
    );
    let roi = Roi {
        x: 60,
        y: 70,
        width: 100,
        height: 80,
    };
    let part = solver()
        .compute(prev.view(), next.view(), Some(roi), None)
        .expect("flow");
    let mut worst = 0f32;
    for y in roi.y..roi.y + roi.height {
        for x in roi.x..roi.x + roi.width {
            let (a, b) = (part.u[[y, x]], full.u[[y, x]]);
            if a.is_finite() || b.is_finite() {
                worst = worst.max((a - b).abs());
            }
        }
    }
    assert!(part.u[[5, 5]].is_nan());
    assert!(worst < 0.01, "max |roi − full| = {worst} px");
}

/// Degenerate shapes never panic, in either solver.
#[test]
fn tiny_and_thin_images_do_not_panic() {
    let tex = |h: usize, w: usize, dx: f32| {
        Array2::from_shape_fn((h, w), |(y, x)| {
            ((x as f32 + dx) * 0.9).sin() + (y as f32 * 0.7).cos()
        })
    };
    for (h, w) in [(1, 1), (1, 7), (9, 1), (3, 50), (40, 40), (33, 200)] {
        for opts in [FlowOptions::default(), FlowOptions::affine_grid(101)] {
            let (a, b) = (tex(h, w, 0.0), tex(h, w, 0.3));
            let f = Farneback::new(FarnebackParams::default())
                .and_then(|s| s.with_options(opts.clone()))
                .and_then(|mut s| s.compute(a.view(), b.view(), None, None))
                .expect("flow");
            assert_eq!(f.u.dim(), (h, w));
        }
    }
}

/// An initial flow carries a motion the single level could not find alone: `next` is the
/// shifted fixture moved 12 more pixels to the right (NaN where it left the frame); with no
/// pyramid the solver recovers (12.30, −0.45) only when started near it.
#[test]
fn initial_flow_is_used() {
    let prev = load_fixture("prev.f32");
    let shifted = load_fixture("shift_next.f32");
    let (h, w) = shifted.dim();
    let next = Array2::from_shape_fn((h, w), |(y, x)| {
        if x >= 12 {
            shifted[[y, x - 12]]
        } else {
            f32::NAN
        }
    });
    let init = Flow {
        u: Array2::from_elem((h, w), 12.0),
        v: Array2::from_elem((h, w), 0.0),
    };
    let p = FarnebackParams {
        levels: 0,
        ..small_params()
    };
    let f = farneback_with_init(prev.view(), next.view(), &p, None, &init).expect("flow");
    let mu = median(f.u.iter().copied().collect());
    let mv = median(f.v.iter().copied().collect());
    assert!(
        (mu - 12.30).abs() < 0.01 && (mv + 0.45).abs() < 0.01,
        "median flow ({mu}, {mv}) vs (12.30, -0.45)"
    );
    let cold = farneback(prev.view(), next.view(), &p, None).expect("flow");
    let cu = median(cold.u.iter().copied().collect());
    assert!((cu - 12.30).abs() > 1.0, "without the initial flow: {cu}");
}

/// A solver told that its first image is unchanged keeps that image's expansion: a second
/// pass against the same reference gives, bit for bit, the field a fresh solver gives (and
/// the injected shift); told so before an image of another size, it expands that one afresh.
#[test]
fn a_kept_reference_expansion_gives_the_fresh_solvers_field() {
    let prev = load_fixture("prev.f32");
    let next = load_fixture("shift_next.f32");
    let other = load_fixture("warp_next.f32");
    let p = FarnebackParams {
        levels: 0,
        ..small_params()
    };
    let solver = || {
        Farneback::new(p.clone())
            .and_then(|f| f.with_options(FlowOptions::affine_grid(p.winsize)))
            .expect("solver")
    };
    let same = |a: &Flow, b: &Flow| {
        let bits = |x: &Array2<f32>| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        bits(&a.u) == bits(&b.u) && bits(&a.v) == bits(&b.v)
    };
    let mut kept = solver();
    kept.compute(prev.view(), other.view(), None, None)
        .expect("flow");
    kept.next_prev_unchanged();
    let again = kept
        .compute(prev.view(), next.view(), None, None)
        .expect("flow");
    let fresh = solver()
        .compute(prev.view(), next.view(), None, None)
        .expect("flow");
    assert!(same(&again, &fresh), "kept expansion changed the field");
    let mu = median(again.u.iter().copied().collect());
    let mv = median(again.v.iter().copied().collect());
    assert!(
        (mu - 0.30).abs() < 0.01 && (mv + 0.45).abs() < 0.01,
        "median flow ({mu}, {mv}) vs (0.30, -0.45)"
    );

    let part = ndarray::s![..160, 20..200];
    kept.next_prev_unchanged();
    let cropped = kept
        .compute(prev.slice(part), next.slice(part), None, None)
        .expect("flow");
    let fresh = solver()
        .compute(prev.slice(part), next.slice(part), None, None)
        .expect("flow");
    assert!(same(&cropped, &fresh), "a stale expansion was used");
}
