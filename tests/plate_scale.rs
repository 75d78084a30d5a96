//! A channel's true plate scale from the configuration (`[channels.X] plate_scale_arcsec`),
//! for data whose headers state another: the bundled IRIS cubes were binned 10× with `CDELTi`
//! left at the native 0.16635″ (their `FOVX`, 183.3″ over 110 px, says about 1.66″/px).
//!
//! Truths: astropy's sun centre of each frame with `CDELTi` set to 1.6635″
//! (`python3 tools/iris_pointing_truth.py --cdelt 1.6635`, which also applies the frame's own
//! pointing from IRIS's table); and IRIS's own pointing records, which predict the image motion
//! between frames (`header_residual` is what they leave unexplained) only at the true scale.

mod support;

use std::path::Path;
use sunjitter_core::error::ExitCode;
use sunjitter_core::record::Status;
use sunjitter_io::fits::{read_frame_with, FrameSpec, PlateScales, ReadOptions};
use support::{sunjitter, sunjitter_ok};

const CUBE: &str = "data/real/iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const TRUE_SCALE: f64 = 1.6635;

/// (frame, sun_center_px) of the 1400 cube as astropy gives them at `--cdelt 1.6635`.
fn astropy_centres() -> Vec<(usize, [f64; 2])> {
    let out = std::process::Command::new("python3")
        .args([
            "tools/iris_pointing_truth.py",
            "--cdelt",
            &TRUE_SCALE.to_string(),
        ])
        .output()
        .expect("python3 runs (needs astropy: see .ci/run)");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let cube = text
        .split("iris_l2_")
        .find(|block| block.contains("SJI_1400"))
        .unwrap();
    cube.lines()
        .filter_map(|line| {
            let frame = line.trim().strip_prefix("frame ")?.split(':').next()?;
            let pair = line.split("sun_center_px (").nth(1)?.split(')').next()?;
            let (x, y) = pair.split_once(", ")?;
            Some((frame.parse().ok()?, [x.parse().ok()?, y.parse().ok()?]))
        })
        .collect()
}

#[test]
fn a_given_plate_scale_places_every_frame_as_astropy_does_at_that_scale() {
    let options = ReadOptions {
        plate_scales: PlateScales([("SJI_1400".to_string(), TRUE_SCALE)].into()),
        ..Default::default()
    };
    let truth = astropy_centres();
    assert!(truth.len() >= 3, "{truth:?}");
    for (frame, want) in truth {
        let image = read_frame_with(&FrameSpec::cube_frame(CUBE, frame), &options).unwrap();
        assert_eq!(image.meta.plate_scale_arcsec, [TRUE_SCALE, TRUE_SCALE]);
        let got = image.meta.sun_center_px;
        for k in 0..2 {
            assert!(
                (got[k] - want[k]).abs() < 0.01,
                "frame {frame}: {got:?} vs astropy {want:?}"
            );
        }
    }
    // Another channel is read as its header says.
    let other = read_frame_with(
        &FrameSpec::cube_frame(
            "data/real/iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits",
            0,
        ),
        &options,
    )
    .unwrap();
    assert_eq!(other.meta.plate_scale_arcsec, [0.16635, 0.16635]);
}

/// Per frame that was measured: (dx_arcsec / dx_px, header_residual dx, dy, message).
fn replay(dir: &Path, name: &str, config: Option<&str>) -> Vec<(f64, f64, f64, String)> {
    let out = dir.join(name);
    let mut args = vec!["replay", CUBE, "--out", out.to_str().unwrap()];
    let config_path = dir.join(format!("{name}.toml"));
    if let Some(text) = config {
        std::fs::write(&config_path, text).unwrap();
        args.extend(["--config", config_path.to_str().unwrap()]);
    }
    sunjitter_ok(&args);
    let logs = sunjitter_io::sink::read_logs(&[out]).unwrap();
    assert_eq!(logs.jitter.len(), 54);
    logs.jitter
        .iter()
        .map(|m| &m.record)
        .filter(|r| r.align.status != Status::Failed && r.align.dx_px.unwrap_or(0.0) != 0.0)
        .map(|r| {
            let a = &r.align;
            let h = a.header_residual.as_ref().unwrap();
            (
                a.dx_arcsec.unwrap() / a.dx_px.unwrap(),
                h.dx_px,
                h.dy_px,
                a.message.clone(),
            )
        })
        .collect()
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let v: Vec<f64> = v.collect();
    (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt()
}

#[test]
fn at_the_true_plate_scale_iris_pointing_records_predict_the_motion() {
    let dir = tempfile::tempdir().unwrap();
    let native = replay(dir.path(), "native", None);
    let given = replay(
        dir.path(),
        "given",
        Some("[channels.SJI_1400]\nplate_scale_arcsec = 1.6635\n"),
    );
    for (ratio, _, _, message) in &native {
        assert!((ratio - 0.16635).abs() < 1e-9, "{ratio}");
        assert!(!message.contains("plate scale from the configuration"));
    }
    for (ratio, _, _, message) in &given {
        assert!((ratio - TRUE_SCALE).abs() < 1e-9, "{ratio}");
        assert!(
            message.contains(
                "plate scale from the configuration, not the header: 1.6635″/px for SJI_1400"
            ),
            "{message}"
        );
    }
    // What the pointing records leave unexplained, in px: at the native scale every 1″ of
    // re-pointing is read as 6 px instead of 0.6 px.
    let unexplained = |s: &[(f64, f64, f64, String)]| rms(s.iter().map(|x| x.1.hypot(x.2)));
    let (at_native, at_true) = (unexplained(&native), unexplained(&given));
    println!("header_residual rms: {at_native:.3} px native, {at_true:.3} px at 1.6635″/px");
    assert!(at_true < 0.5 * at_native, "{at_true} vs {at_native}");
}

#[test]
fn a_plate_scale_that_is_not_one_is_refused_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("bad.toml");
    std::fs::write(
        &config,
        "[channels.SJI_1400]\nplate_scale_arcsec = -1.6635\n",
    )
    .unwrap();
    let out = dir.path().join("log");
    let (code, stdout, stderr) = sunjitter(&[
        "replay",
        CUBE,
        "--out",
        out.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
    ]);
    assert_eq!(code, ExitCode::BadInput.code(), "{stderr}");
    assert!(stdout.is_empty());
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("channels.SJI_1400.plate_scale_arcsec"),
        "{stderr}"
    );
    assert!(!out.exists(), "nothing written");
}
