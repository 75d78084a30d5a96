//! The solar-surface motion model against sunpy (`RotatedSunFrame`, followed with the Sun's
//! centre), on a real AIA header at 4096² geometry: `tests/data/solar_rotation/oracle.json`,
//! made by `python3 tools/solar_rotation_oracle.py`.

use serde_json::Value;
use std::path::PathBuf;
use sunjitter_core::header::{Header, HeaderValue};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::meta::{from_header, ImagePlace};
use sunjitter_core::solar_rotation::{
    grid_step_px, DisplacementGrid, Moved, Profile, SurfaceMotion, View,
};

fn oracle() -> Value {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/solar_rotation/oracle.json");
    serde_json::from_str(&std::fs::read_to_string(path).expect("read oracle")).expect("parse")
}

fn meta_of(cards: &Value) -> FrameMeta {
    let mut h = Header::new();
    for (k, v) in cards.as_object().expect("cards") {
        let value = match v {
            Value::String(s) => HeaderValue::Str(s.clone()),
            Value::Bool(b) => HeaderValue::Bool(*b),
            Value::Number(n) if n.is_i64() => HeaderValue::Int(n.as_i64().unwrap()),
            Value::Number(n) => HeaderValue::Float(n.as_f64().unwrap()),
            other => panic!("card {k}: {other}"),
        };
        h.push(k, value);
    }
    let place = ImagePlace {
        file: PathBuf::from("oracle.fits"),
        hdu: 0,
        frame: None,
        width: 4096,
        height: 4096,
        bitpix: -32,
    };
    from_header(&h, place).expect("usable header")
}

/// Worst distance (px) between the model and sunpy over the visible points, and the number
/// of points whose visibility disagrees.
fn compare(profile: &str, case: &Value, reference: &FrameMeta) -> (f64, usize, usize) {
    let frame = meta_of(&case["frame"]["cards"]);
    let motion = SurfaceMotion::new(
        View::new(reference).expect("reference view"),
        View::new(&frame).expect("frame view"),
        profile.parse::<Profile>().expect("profile"),
    );
    let (mut worst, mut disagree, mut n) = (0.0f64, 0, 0);
    for p in case["profiles"][profile].as_array().expect("points") {
        let p = p.as_array().expect("point");
        let from = [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()];
        let visible = p[4].as_bool().unwrap();
        match (motion.map(from), visible) {
            (Moved::To(q), true) => {
                let want = [p[2].as_f64().unwrap(), p[3].as_f64().unwrap()];
                worst = worst.max((q[0] - want[0]).hypot(q[1] - want[1]));
                n += 1;
            }
            (Moved::Hidden, false) => {}
            _ => disagree += 1,
        }
    }
    (worst, disagree, n)
}

#[test]
fn the_surface_motion_agrees_with_sunpy_within_a_hundredth_of_a_pixel_up_to_an_hour() {
    let oracle = oracle();
    let reference = meta_of(&oracle["reference"]["cards"]);
    for case in oracle["cases"].as_array().unwrap() {
        let dt = case["dt_s"].as_f64().unwrap();
        let tolerance = if dt <= 3600.0 { 0.01 } else { 0.1 };
        for profile in ["howard", "snodgrass", "allen"] {
            let (worst, disagree, n) = compare(profile, case, &reference);
            eprintln!("{profile} Δt={dt}: worst {worst:.5} px over {n} points");
            assert!(n > 150, "{profile} Δt={dt}: {n} points");
            assert_eq!(disagree, 0, "{profile} Δt={dt}: visibility differs");
            assert!(
                worst <= tolerance,
                "{profile} Δt={dt} s: {worst:.4} px from sunpy (tolerance {tolerance})"
            );
        }
    }
}

#[test]
fn sunpy_sidereal_rates_are_the_profiles() {
    let oracle = oracle();
    let lats = oracle["diff_rot_latitudes_deg"].as_array().unwrap();
    for profile in ["howard", "snodgrass", "allen"] {
        let rates = oracle["diff_rot_deg_per_day"][profile]["sidereal"]
            .as_array()
            .unwrap();
        let p: Profile = profile.parse().unwrap();
        for (lat, want) in lats.iter().zip(rates) {
            let got = p
                .sidereal_rad_per_s(lat.as_f64().unwrap().to_radians())
                .to_degrees()
                * 86_400.0;
            assert!(
                (got - want.as_f64().unwrap()).abs() < 1e-9,
                "{profile} {lat}"
            );
        }
    }
}

#[test]
fn without_rotation_the_disk_centre_stays_within_the_observer_motion() {
    // Profile `none`: a point fixed in the Stonyhurst frame for twelve seconds moves by the
    // Earth's orbital motion only (about 0.05 px of the 0.05 px the Sun's rotation gives).
    let oracle = oracle();
    let reference = meta_of(&oracle["reference"]["cards"]);
    let frame = meta_of(&oracle["cases"][0]["frame"]["cards"]);
    let motion = SurfaceMotion::new(
        View::new(&reference).unwrap(),
        View::new(&frame).unwrap(),
        Profile::None,
    );
    let centre = reference.sun_center_px;
    let Moved::To(q) = motion.map(centre) else {
        panic!("the disk centre is on the disk")
    };
    // Synodic is sidereal less the Earth's rate: none moves east by about 1/14 of howard's.
    let howard = 0.05202;
    let shift = q[0] - centre[0];
    assert!(shift < 0.0 && shift.abs() < howard / 10.0, "{shift}");
    // Off the disk nothing moves.
    assert_eq!(motion.map([10.0, 10.0]), Moved::OffDisk);
}

#[test]
fn the_sampled_displacement_reads_the_model_within_a_thousandth_of_a_pixel_inside_the_mask() {
    // The engine reads the surface motion from a grid whose spacing follows the motion's size
    // (`grid_step_px`); inside 0.9 R it must agree with the model itself.
    let oracle = oracle();
    let reference = meta_of(&oracle["reference"]["cards"]);
    let radius = reference.rsun_arcsec.unwrap() / reference.plate_scale_arcsec[0];
    let c = reference.sun_center_px;
    for case in oracle["cases"].as_array().unwrap() {
        let frame = meta_of(&case["frame"]["cards"]);
        let motion = SurfaceMotion::new(
            View::new(&reference).unwrap(),
            View::new(&frame).unwrap(),
            Profile::Howard,
        );
        let shift = |p: [f64; 2]| match motion.map(p) {
            Moved::To(q) => [q[0] - p[0], q[1] - p[1]],
            _ => [f64::NAN; 2],
        };
        let centre = shift(c);
        let step = grid_step_px(centre[0].hypot(centre[1]), radius, 0.9);
        let grid = DisplacementGrid::sample(4096, 4096, step, shift);
        let mut worst = 0.0f64;
        // A spiral of points out to 0.9 R.
        for k in 0..4000 {
            let r = 0.9 * radius * ((k as f64 + 0.5) / 4000.0).sqrt();
            let a = k as f64 * 2.399_963;
            let p = [c[0] + r * a.cos(), c[1] + r * a.sin()];
            let (want, got) = (shift(p), grid.at(p));
            if want[0].is_finite() {
                worst = worst.max((want[0] - got[0]).hypot(want[1] - got[1]));
            }
        }
        let dt = case["dt_s"].as_f64().unwrap();
        eprintln!("Δt = {dt} s: grid step {step} px, worst {worst:.2e} px");
        assert!(
            worst < 1e-3,
            "Δt = {dt} s: grid reads {worst} px off the model"
        );
    }
}
