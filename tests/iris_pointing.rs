//! Per-frame pointing of IRIS slit-jaw cubes: each frame's sun centre follows the frame's own
//! `XCENIX`/`YCENIX` (HDU 1) rather than the one primary header's nominal `XCEN`/`YCEN`.
//!
//! Truth: `python3 tools/iris_pointing_truth.py` (astropy 8.0.2): a copy of the primary header
//! with `CRVAL1 += XCENIX(p) − XCEN`, `CRVAL2 += YCENIX(p) − YCEN`, then
//! `WCS(copy).celestial.wcs_world2pix([[0, 0]], 0)` (full TAN projection, 0-based pixels), at
//! table row p = i·(rows−1)/(frames−1) interpolated (1400: 540 rows for 54 frames) or p = i
//! (2832: 18 rows for 18 frames). sunjitter moves the centre by the linear −M⁻¹·d, within
//! 0.0007 px of that. Tolerance 0.01 px, as for every sun centre in tests/info.rs.

use std::path::{Path, PathBuf};
use sunjitter_core::header::HeaderValue;
use sunjitter_io::fits::{
    frame_header_cards, read_frame, read_image_header, read_meta, write_image, FrameSpec,
};

const SJI_1400: &str = "iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2832: &str = "iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits";

/// One frame's truth, as printed by tools/iris_pointing_truth.py.
struct Pointed {
    file: &'static str,
    frame: usize,
    xcenix: f64,
    ycenix: f64,
    sun_center_px: [f64; 2],
}

const TRUTH: &[Pointed] = &[
    // SJI 1400: XCEN 505.392, YCEN 279.88; header centre (−2964.8161731086875, −1662.8686007811825).
    Pointed {
        file: SJI_1400,
        frame: 0,
        xcenix: 490.48617670931196,
        ycenix: 280.10361310799647,
        sun_center_px: [-2875.2011058005073, -1663.2025526899365],
    },
    Pointed {
        file: SJI_1400,
        frame: 27, // table row 274.58490566037733
        xcenix: 505.7463920111625,
        ycenix: 279.8533252516306,
        sun_center_px: [-2966.9482552152026, -1662.7322756408903],
    },
    Pointed {
        file: SJI_1400,
        frame: 53,
        xcenix: 520.3503302398066,
        ycenix: 279.9880976044362,
        sun_center_px: [-3054.7244211829798, -1664.5321336563816],
    },
    // SJI 2832: XCEN 505.278, YCEN 279.838; header centre (−2964.137551869601, −1662.6064252184203).
    Pointed {
        file: SJI_2832,
        frame: 0,
        xcenix: 490.48722896316036,
        ycenix: 280.1454150732973,
        sun_center_px: [-2875.2083353901508, -1663.4520041161381],
    },
    Pointed {
        file: SJI_2832,
        frame: 9,
        xcenix: 506.40070528013695,
        ycenix: 279.9263459622921,
        sun_center_px: [-2970.8802304392902, -1663.2135574484873],
    },
    Pointed {
        file: SJI_2832,
        frame: 17,
        xcenix: 520.290311313802,
        ycenix: 279.90390409854433,
        sun_center_px: [-3054.373204088077, -1664.019897016962],
    },
];

/// The 1400 cube's header centre (astropy, nominal pointing).
const HEADER_CENTRE_1400: [f64; 2] = [-2964.8161731086875, -1662.8686007811825];
/// The header's plate scale, arcsec per pixel.
const CDELT: f64 = 0.16635;

fn real(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data/real")
        .join(name)
}

fn centre(file: &str, frame: usize) -> [f64; 2] {
    read_frame(&FrameSpec::cube_frame(real(file), frame))
        .unwrap_or_else(|e| panic!("{file}[{frame}]: {e}"))
        .meta
        .sun_center_px
}

fn assert_near(got: [f64; 2], want: [f64; 2], tol: f64, what: &str) {
    for k in 0..2 {
        assert!(
            (got[k] - want[k]).abs() <= tol,
            "{what}: sun_center_px {got:?} vs truth {want:?}"
        );
    }
}

#[test]
fn each_frame_is_placed_at_its_own_pointing() {
    for t in TRUTH {
        let what = format!("{}[{}]", t.file, t.frame);
        assert_near(centre(t.file, t.frame), t.sun_center_px, 0.01, &what);
    }
}

/// `read_meta` (what `info` and `replay` list) agrees with `read_frame` frame by frame.
#[test]
fn cube_metadata_carries_the_same_pointing() {
    for file in [SJI_1400, SJI_2832] {
        let metas = read_meta(&real(file)).unwrap();
        for t in TRUTH.iter().filter(|t| t.file == file) {
            let what = format!("{file}[{}] via read_meta", t.frame);
            assert_near(metas[t.frame].sun_center_px, t.sun_center_px, 0.01, &what);
        }
    }
}

/// Over the 1400 sequence IRIS re-pointed ~30″ west (following the Sun's rotation): the disk
/// centre moves ~180 header pixels the other way between the first and last frames.
#[test]
fn the_pointing_change_shows_in_the_centre() {
    let (first, last) = (centre(SJI_1400, 0), centre(SJI_1400, 53));
    let moved_arcsec = TRUTH[2].xcenix - TRUTH[0].xcenix;
    assert!((moved_arcsec - 29.864).abs() < 0.001, "{moved_arcsec}");
    let dx = last[0] - first[0];
    // −Δ/CDELT1, up to the 0.65° roll (cos ≈ 0.99994 and Δy·sin ≈ 0.01 px).
    assert!((dx + moved_arcsec / CDELT).abs() < 0.1, "Δx {dx} px");
    assert!(dx < -179.0 && dx > -181.0, "Δx {dx} px");
    let truth_dx = TRUTH[2].sun_center_px[0] - TRUTH[0].sun_center_px[0];
    assert!(
        (dx - truth_dx).abs() < 0.01,
        "Δx {dx} vs astropy {truth_dx}"
    );
}

/// Rows of missing exposures carry XCENIX = YCENIX = 0 (1400 rows 198–221; frames 20 and 21
/// are blank, −200 everywhere): no pointing, so those frames keep the header's centre instead
/// of jumping ~3000 px to a pointing at the disk centre.
#[test]
fn frames_without_a_pointing_keep_the_header_centre() {
    for frame in [20, 21] {
        let what = format!("{SJI_1400}[{frame}]");
        assert_near(centre(SJI_1400, frame), HEADER_CENTRE_1400, 0.01, &what);
    }
    // Neighbours read from valid rows do move.
    assert!((centre(SJI_1400, 22)[0] - HEADER_CENTRE_1400[0]).abs() > 1.0);
}

/// A frame written as its own 2-D file (no table) keeps its pointing in its header.
#[test]
fn a_split_frame_keeps_its_pointing() {
    let t = &TRUTH[2];
    let cube = real(t.file);
    let image = read_frame(&FrameSpec::cube_frame(&cube, t.frame)).unwrap();
    let (_, header) = read_image_header(&cube).unwrap();
    let cards = frame_header_cards(&header, &image.meta);
    let get = |key: &str| {
        cards
            .iter()
            .find(|(k, _)| k == key)
            .and_then(|(_, v)| v.as_f64())
            .unwrap_or_else(|| panic!("{key} missing"))
    };
    assert!(
        (get("XCEN") - t.xcenix).abs() < 1e-6,
        "XCEN {}",
        get("XCEN")
    );
    assert!(
        (get("YCEN") - t.ycenix).abs() < 1e-6,
        "YCEN {}",
        get("YCEN")
    );
    assert!(matches!(
        cards.iter().find(|(k, _)| k == "CRVAL1").map(|(_, v)| v),
        Some(HeaderValue::Float(v)) if *v == 505.392
    ));
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f53.fits");
    write_image(&out, image.data.view(), &cards).unwrap();
    let back = read_frame(&FrameSpec::file(&out)).unwrap();
    assert_near(
        back.meta.sun_center_px,
        image.meta.sun_center_px,
        1e-9,
        "split frame",
    );
    assert_near(
        back.meta.sun_center_px,
        t.sun_center_px,
        0.01,
        "split frame",
    );
}
