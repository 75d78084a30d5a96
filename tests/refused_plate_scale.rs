//! The plate scale used where a header's is refused, against truths the files' provenance gives
//! (data/README.md):
//! - the EIT 195 and 171 images were binned 8× from 1024² without their CDELT (2.63″/px) being
//!   updated: the true plate scale is 8 × 2.63 = 21.04″/px, where a plate scale from the EUV
//!   limb's radius, which stands above the photosphere, is 4 % small;
//! - a `CDi_j` matrix left stale by a resampling (it wins over `CDELTi`, as the WCS standard
//!   says) is caught by the full disk the image shows, even though it predicts a disk larger
//!   than the frame: made here from the AIA 171 128² image (CDELT 19.18″/px, right) with a CD
//!   matrix of its 1024² original (÷ 8), and of a 7.5× resampling (no whole number).

mod support;

use std::path::{Path, PathBuf};
use sunjitter_core::error::ExitCode;
use sunjitter_core::header::HeaderValue;
use sunjitter_io::fits::{
    frame_header_cards, read_frame, read_image_header, write_image, FrameSpec,
};

const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/real/");

/// `align REF FRAME --json`: the plate scale the alignment used (arcsec over px of a σ).
fn plate_scale_used(reference: &Path, frame: &Path) -> (f64, String) {
    let (code, stdout, stderr) = support::sunjitter(&[
        "align".as_ref(),
        reference.as_os_str(),
        frame.as_os_str(),
        "--json".as_ref(),
    ]);
    assert_eq!(code, ExitCode::Ok.code(), "{stderr}");
    let doc: serde_json::Value = serde_json::from_str(&stdout).expect("one JSON document");
    let num = |k: &str| doc[k].as_f64().unwrap_or_else(|| panic!("{k} in {doc}"));
    let plate = num("sigma_dx_arcsec") / num("sigma_dx_px");
    (plate.abs(), doc["message"].as_str().unwrap().to_string())
}

#[test]
fn an_euv_pair_binned_without_its_header_gets_the_binned_plate_scale() {
    let (plate, message) = plate_scale_used(
        &PathBuf::from(REAL).join("eit_195_20040301T000010_128.fits"),
        &PathBuf::from(REAL).join("eit_171_20040301T010016_128.fits"),
    );
    assert!(
        (plate / 21.04 - 1.0).abs() <= 0.015,
        "{plate}″/px: {message}"
    );
    assert!(message.contains("binned 8×"), "{message}");
}

/// The AIA 171 128² image with a `CD` matrix of the header's plate scale over `factor`.
fn with_stale_cd(dir: &Path, factor: f64) -> PathBuf {
    let source = PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits");
    let image = read_frame(&FrameSpec {
        path: source.clone(),
        frame: None,
    })
    .unwrap();
    let (_, header) = read_image_header(&source).unwrap();
    let mut cards = frame_header_cards(&header, &image.meta);
    let cdelt = |k: &str| {
        cards
            .iter()
            .find(|(key, _)| key == k)
            .and_then(|(_, v)| v.as_f64())
            .expect("CDELT")
    };
    let (c1, c2) = (cdelt("CDELT1"), cdelt("CDELT2"));
    cards.retain(|(k, _)| !k.starts_with("PC") && !k.starts_with("CROTA"));
    for (k, v) in [
        ("CD1_1", c1 / factor),
        ("CD1_2", 0.0),
        ("CD2_1", 0.0),
        ("CD2_2", c2 / factor),
    ] {
        cards.push((k.to_string(), HeaderValue::Float(v)));
    }
    let path = dir.join(format!("aia_stale_cd_{factor}.fits"));
    write_image(&path, image.data.view(), &cards).unwrap();
    path
}

#[test]
fn a_stale_cd_matrix_is_caught_by_the_disk_the_image_shows() {
    let dir = tempfile::tempdir().unwrap();
    let truth = 19.183648;
    // The matrix of the 1024² original: a whole-number binning, exact.
    let stale = with_stale_cd(dir.path(), 8.0);
    let (plate, message) = plate_scale_used(&stale, &stale);
    assert!(
        (plate / truth - 1.0).abs() <= 1e-9,
        "{plate}″/px: {message}"
    );
    assert!(message.contains("disagrees with the image"), "{message}");
    // A 7.5× resampling is no whole number: the plate scale from the disk's radius, which the
    // EUV limb at 171 Å makes a little small.
    let stale = with_stale_cd(dir.path(), 7.5);
    let (plate, message) = plate_scale_used(&stale, &stale);
    assert!(
        (plate / truth - 1.0).abs() <= 0.015,
        "{plate}″/px: {message}"
    );
}
