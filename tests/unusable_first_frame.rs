//! A frame that cannot serve as a reference (blank, constant) arriving first in time is
//! `failed` with its reason, and the next usable frame starts the reference: the frames after
//! it are measured (replay through the binary, read back with `inspect --csv`).

mod support;

use std::path::Path;
use support::faults::*;
use support::{read_csv, sunjitter_ok};

#[test]
fn an_unusable_first_frame_never_becomes_the_reference() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in");
    std::fs::create_dir(&input).unwrap();
    let src = source();
    let good = crops(&src, "good_", 4, 96, 3);
    for (name, fill) in [("blank.fits", f32::NAN), ("constant.fits", 100.0)] {
        let unusable = Source {
            cards: src.cards.clone(),
            pixels: src.pixels.mapv(|_| fill),
        };
        // Earlier than every good frame.
        let t = good[0].obs_time_ns - if fill.is_nan() { 24 * S } else { 12 * S };
        let f = crop(&unusable, name, (0, 0), 96, t);
        std::fs::write(input.join(name), &f.bytes).unwrap();
    }
    for f in &good {
        std::fs::write(input.join(&f.name), &f.bytes).unwrap();
    }
    let (out, csv) = (dir.path().join("log"), dir.path().join("series.csv"));
    sunjitter_ok(&[
        "replay",
        input.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    sunjitter_ok(&[
        "inspect",
        out.to_str().unwrap(),
        "--csv",
        csv.to_str().unwrap(),
    ]);
    let rows = read_csv(&csv);
    let by_name = |name: &str| {
        rows.iter()
            .find(|r| Path::new(&r["frame"]).file_name().unwrap() == name)
            .unwrap_or_else(|| panic!("{name} logged"))
    };
    assert_eq!(rows.len(), 6, "every frame logged once");
    for name in ["blank.fits", "constant.fits"] {
        let r = by_name(name);
        assert_eq!(r["status"], "failed", "{name}");
        let text = std::fs::read_to_string(&csv).unwrap();
        let line = text.lines().find(|l| l.contains(name)).unwrap();
        assert!(line.contains("cannot start a reference"), "{line}");
    }
    // The first good frame starts the reference; the others are measured against it.
    assert_eq!(by_name(&good[0].name)["reference_kind"], "self");
    for f in &good[1..] {
        let r = by_name(&f.name);
        assert_eq!(r["status"], "ok", "{}: {r:?}", f.name);
        assert_ne!(r["reference_kind"], "self", "{}", f.name);
    }
}
