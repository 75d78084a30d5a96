//! `sunjitter info` on every real file, against truth values computed independently with
//! sunpy 7.0 / astropy 8.0 by `tools/sunpy_truth.py` (that script documents how each number was
//! obtained; run `python3 tools/sunpy_truth.py` to reproduce them).
//! Tolerances: sun centre 0.01 px, roll 0.001°, plate scale exact, time 1 s.

use serde_json::Value;
use std::path::PathBuf;
use std::process::{Command, Output};
use sunjitter_core::error::ExitCode;

const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/real/");
const MALFORMED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/malformed/");

/// One expected `info` record.
struct Truth {
    file: &'static str,
    frame: Option<u64>,
    size: (u64, u64),
    bitpix: i64,
    channel: &'static str,
    instrument: &'static str,
    wavelength: f64,
    sun_center_px: (f64, f64),
    plate_scale: f64,
    rotation_deg: f64,
    obs_time: &'static str,
    exptime_s: Option<f64>,
    rsun_arcsec: Option<f64>,
}

const AIA: &str = "aia_171_20110215T000000_128.fits";
const EIT_171: &str = "eit_171_20040301T010016_128.fits";
const EIT_195: &str = "eit_195_20040301T000010_128.fits";
const HMI: &str = "hmi_6173_20140301T000027_100.fits";
const TRACE: &str = "trace_171_19980519T222143_1024.fits";
const SJI_1400: &str = "iris_l2_20140329_140938_3860258481_SJI_1400_t000.fits";
const SJI_2796: &str = "iris_l2_20140329_140938_3860258481_SJI_2796_t000_deconvolved.fits";
const SJI_2832: &str = "iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits";

/// Output of `python3 tools/sunpy_truth.py` (sunpy 7.0.5, astropy 8.0.2).
const TRUTH: &[Truth] = &[
    Truth {
        file: AIA,
        frame: None,
        size: (128, 128),
        bitpix: -64,
        channel: "AIA_171",
        instrument: "AIA",
        wavelength: 171.0,
        sun_center_px: (63.736201218592186, 63.350544055287),
        plate_scale: 19.183648,
        rotation_deg: 0.019413,
        // sunpy reference_date = T_OBS (mid-exposure); DATE-OBS is 00:00:00.34.
        obs_time: "2011-02-15T00:00:01.340Z",
        exptime_s: Some(2.000191),
        rsun_arcsec: Some(971.812597),
    },
    Truth {
        file: EIT_171,
        frame: None,
        size: (128, 128),
        bitpix: -64,
        channel: "EIT_171",
        instrument: "EIT",
        wavelength: 171.0,
        sun_center_px: (63.5, 63.4999999999952),
        plate_scale: 2.63,
        // sunpy ignores SC_ROLL; truth is SC_ROLL = 180 from the header.
        rotation_deg: 180.0,
        obs_time: "2004-03-01T01:00:16.178Z",
        exptime_s: Some(7.597),
        rsun_arcsec: Some(979.0701),
    },
    Truth {
        file: EIT_195,
        frame: None,
        size: (128, 128),
        bitpix: -64,
        channel: "EIT_195",
        instrument: "EIT",
        wavelength: 195.0,
        sun_center_px: (63.5, 63.4999999999952),
        plate_scale: 2.63,
        rotation_deg: 180.0,
        obs_time: "2004-03-01T00:00:10.515Z",
        exptime_s: Some(13.0),
        rsun_arcsec: Some(979.0701),
    },
    Truth {
        file: HMI,
        frame: None,
        size: (100, 100),
        bitpix: -64,
        channel: "HMI_6173",
        instrument: "HMI",
        wavelength: 6173.0,
        sun_center_px: (49.6199933665928, 49.5825177542124),
        plate_scale: 20.65575936,
        rotation_deg: 179.929779,
        // T_OBS '2014.03.01_00:01:25_TAI' in UTC (sunpy reference_date); DATE-OBS is 22 s earlier.
        obs_time: "2014-03-01T00:00:50.000Z",
        exptime_s: None,
        rsun_arcsec: Some(968.660583),
    },
    Truth {
        file: TRACE,
        frame: None,
        size: (1024, 1024),
        bitpix: 16,
        channel: "TRACE_171",
        instrument: "TRACE",
        wavelength: 171.0,
        sun_center_px: (-332.555, -290.79300000002524),
        plate_scale: 0.5,
        rotation_deg: 0.0,
        obs_time: "1998-05-19T22:21:43.000Z",
        // No EXPTIME; SHT_MDUR (measured shutter duration) from the header.
        exptime_s: Some(23.1719),
        rsun_arcsec: None,
    },
];

/// One IRIS cube frame's truth. All are 110×109, BITPIX −32, plate scale 0.16635″ (the
/// header's; the test cubes were rebinned 10× without updating it). The sun centre is the
/// frame's own (per-frame pointing XCENIX/YCENIX of HDU 1), printed by
/// `python3 tools/iris_pointing_truth.py` (astropy: CRVAL moved by the frame's pointing offset);
/// the other values are tools/sunpy_truth.py's.
struct IrisFrame {
    file: &'static str,
    frame: u64,
    sun_center_px: (f64, f64),
    rotation_deg: f64,
    obs_time: &'static str,
    exptime_s: f64,
}

const IRIS: &[IrisFrame] = &[
    IrisFrame {
        file: SJI_1400,
        frame: 0,
        sun_center_px: (-2875.2011058005073, -1663.2025526899365),
        rotation_deg: -0.6459544553476199,
        obs_time: "2014-03-29T14:09:38.930Z",
        exptime_s: 8.000057220458984,
    },
    IrisFrame {
        file: SJI_1400,
        frame: 1,
        sun_center_px: (-2878.9340724332965, -1664.0308702264024),
        rotation_deg: -0.6459544553476199,
        obs_time: "2014-03-29T14:14:04.344Z",
        exptime_s: 8.000052272148853,
    },
    IrisFrame {
        file: SJI_1400,
        frame: 27,
        sun_center_px: (-2966.9482552152026, -1662.7322756408903),
        rotation_deg: -0.6459544553476199,
        obs_time: "2014-03-29T16:04:07.679Z",
        exptime_s: 3.456562582051979,
    },
    IrisFrame {
        file: SJI_1400,
        frame: 53,
        sun_center_px: (-3054.7244211829798, -1664.5321336563816),
        rotation_deg: -0.6459544553476199,
        obs_time: "2014-03-29T17:54:08.106Z",
        exptime_s: 1.8078919649124146,
    },
    IrisFrame {
        file: SJI_2796,
        frame: 0,
        sun_center_px: (-2875.194807987512, -1663.3413826755009),
        rotation_deg: -0.6459244448721853,
        obs_time: "2014-03-29T14:09:48.490Z",
        exptime_s: 8.000052452087402,
    },
    IrisFrame {
        file: SJI_2796,
        frame: 35,
        sun_center_px: (-2963.567602842368, -1662.8234959888541),
        rotation_deg: -0.6459244448721853,
        obs_time: "2014-03-29T16:00:25.047Z",
        exptime_s: 8.000021195747482,
    },
    IrisFrame {
        file: SJI_2796,
        frame: 71,
        sun_center_px: (-3055.048014518154, -1664.6050530249508),
        rotation_deg: -0.6459244448721853,
        obs_time: "2014-03-29T17:54:11.310Z",
        exptime_s: 8.00007438659668,
    },
    IrisFrame {
        file: SJI_2832,
        frame: 0,
        sun_center_px: (-2875.2083353901508, -1663.4520041161381),
        rotation_deg: -0.6458950118711072,
        obs_time: "2014-03-29T14:09:57.930Z",
        exptime_s: 8.000049591064503,
    },
    IrisFrame {
        file: SJI_2832,
        frame: 17,
        sun_center_px: (-3054.373204088077, -1664.019897016962),
        rotation_deg: -0.6458950118711072,
        obs_time: "2014-03-29T17:53:24.770Z",
        exptime_s: 8.000077247619705,
    },
];

fn sunjitter(args: &[&std::ffi::OsStr]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(args)
        .output()
        .expect("run sunjitter")
}

fn info_json(paths: &[PathBuf]) -> (Vec<Value>, Output) {
    let mut args: Vec<&std::ffi::OsStr> = vec!["info".as_ref(), "--json".as_ref()];
    args.extend(paths.iter().map(|p| p.as_os_str()));
    let out = sunjitter(&args);
    let parsed: Value = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    });
    (parsed.as_array().expect("a JSON array").clone(), out)
}

fn real(name: &str) -> PathBuf {
    PathBuf::from(REAL).join(name)
}

/// Seconds of day of `YYYY-MM-DDTHH:MM:SS.sssZ` after checking the date part is `date`.
fn seconds_of_day(iso: &str, date: &str) -> f64 {
    assert_eq!(&iso[..10], date, "{iso}");
    assert!(
        iso.ends_with('Z') && iso.len() == 24,
        "not ISO 8601 UTC with ms: {iso}"
    );
    let t: Vec<f64> = iso[11..23].split(':').map(|v| v.parse().unwrap()).collect();
    t[0] * 3600.0 + t[1] * 60.0 + t[2]
}

fn assert_time(got: &Value, truth: &str) {
    let got = got.as_str().expect("obs_time is a string");
    let dt = seconds_of_day(got, &truth[..10]) - seconds_of_day(truth, &truth[..10]);
    assert!(dt.abs() <= 1.0, "obs_time {got} vs truth {truth}");
}

fn assert_close(got: &Value, truth: f64, tol: f64, what: &str) {
    let g = got
        .as_f64()
        .unwrap_or_else(|| panic!("{what} is not a number: {got}"));
    assert!((g - truth).abs() <= tol, "{what}: {g} vs truth {truth}");
}

fn assert_option(got: &Value, truth: Option<f64>, tol: f64, what: &str) {
    match truth {
        Some(t) => assert_close(got, t, tol, what),
        None => assert!(got.is_null(), "{what} should be null, got {got}"),
    }
}

/// The fields and nothing else (the contract's list).
fn assert_contract_fields(rec: &Value) {
    let mut keys: Vec<&str> = rec
        .as_object()
        .unwrap()
        .keys()
        .map(String::as_str)
        .collect();
    keys.sort_unstable();
    let mut want = vec![
        "file",
        "hdu",
        "frame",
        "width",
        "height",
        "bitpix",
        "channel",
        "instrument",
        "wavelength",
        "obs_time",
        "exptime_s",
        "plate_scale_arcsec",
        "rotation_deg",
        "sun_center_px",
        "rsun_arcsec",
    ];
    want.sort_unstable();
    assert_eq!(keys, want);
}

fn check(rec: &Value, t: &Truth) {
    assert_contract_fields(rec);
    let what = format!("{}[{:?}]", t.file, t.frame);
    assert!(rec["file"].as_str().unwrap().ends_with(t.file), "{what}");
    assert_eq!(rec["frame"].as_u64(), t.frame, "{what}");
    assert_eq!(
        (
            rec["width"].as_u64().unwrap(),
            rec["height"].as_u64().unwrap()
        ),
        t.size,
        "{what}"
    );
    assert_eq!(rec["bitpix"].as_i64(), Some(t.bitpix), "{what}");
    assert_eq!(rec["channel"], t.channel, "{what}");
    assert_eq!(rec["instrument"], t.instrument, "{what}");
    assert_close(
        &rec["wavelength"],
        t.wavelength,
        0.0,
        &format!("{what} wavelength"),
    );
    assert_close(
        &rec["sun_center_px"][0],
        t.sun_center_px.0,
        0.01,
        &format!("{what} sun x"),
    );
    assert_close(
        &rec["sun_center_px"][1],
        t.sun_center_px.1,
        0.01,
        &format!("{what} sun y"),
    );
    assert_close(
        &rec["plate_scale_arcsec"][0],
        t.plate_scale,
        0.0,
        &format!("{what} scale x"),
    );
    assert_close(
        &rec["plate_scale_arcsec"][1],
        t.plate_scale,
        0.0,
        &format!("{what} scale y"),
    );
    assert_close(
        &rec["rotation_deg"],
        t.rotation_deg,
        0.001,
        &format!("{what} roll"),
    );
    assert_time(&rec["obs_time"], t.obs_time);
    assert_option(
        &rec["exptime_s"],
        t.exptime_s,
        1e-6,
        &format!("{what} exptime"),
    );
    assert_option(
        &rec["rsun_arcsec"],
        t.rsun_arcsec,
        1e-6,
        &format!("{what} rsun"),
    );
}

#[test]
fn two_d_images_match_sunpy() {
    let paths: Vec<PathBuf> = TRUTH.iter().map(|t| real(t.file)).collect();
    let (records, out) = info_json(&paths);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(records.len(), TRUTH.len());
    for (rec, t) in records.iter().zip(TRUTH) {
        check(rec, t);
        assert_eq!(rec["hdu"], 0);
    }
}

#[test]
fn iris_cubes_list_every_frame_with_table_times() {
    let (records, out) = info_json(&[real(SJI_1400), real(SJI_2796), real(SJI_2832)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(records.len(), 54 + 72 + 18);
    let offsets = [(SJI_1400, 0usize), (SJI_2796, 54), (SJI_2832, 54 + 72)];
    for iris in IRIS {
        let file = iris.file;
        let base = offsets.iter().find(|(f, _)| *f == file).unwrap().1;
        let rec = &records[base + iris.frame as usize];
        let channel = &file[file.find("SJI_").unwrap()..][..8];
        let truth = Truth {
            file,
            frame: Some(iris.frame),
            size: (110, 109),
            bitpix: -32,
            channel,
            instrument: "SJI",
            wavelength: channel[4..].parse().unwrap(),
            sun_center_px: iris.sun_center_px,
            plate_scale: 0.16635,
            rotation_deg: iris.rotation_deg,
            obs_time: iris.obs_time,
            exptime_s: Some(iris.exptime_s),
            rsun_arcsec: None,
        };
        check(rec, &truth);
    }
}

#[test]
fn one_frame_of_a_cube_by_suffix() {
    let arg = format!("{}[27]", real(SJI_1400).display());
    let (records, out) = info_json(&[PathBuf::from(arg)]);
    assert!(out.status.success());
    assert_eq!(records.len(), 1);
    assert_eq!(records[0]["frame"], 27);
    assert_time(&records[0]["obs_time"], "2014-03-29T16:04:07.679Z");
}

/// astropy reads the IDL file with NAXISn out of order (cfitsio refuses it); so does sunjitter,
/// with the same numbers as the reordered copy, and a warning naming the misplaced cards.
#[test]
fn out_of_order_naxis_file_is_read_tolerantly() {
    let file = PathBuf::from(MALFORMED).join("trace_171_naxis_cards_out_of_order.fits");
    let (records, out) = info_json(&[file]);
    assert!(out.status.success());
    let t = &TRUTH[4];
    let expected = Truth {
        file: "trace_171_naxis_cards_out_of_order.fits",
        ..*t
    };
    check(&records[0], &expected);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("NAXIS1 is card 17") && stderr.contains("NAXIS2 is card 18"),
        "{stderr}"
    );
}

#[test]
fn paths_with_spaces_and_brackets() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("run [2] of 3");
    std::fs::create_dir(&sub).unwrap();
    let aia = sub.join("aia 171 [a].fits");
    std::fs::copy(real(AIA), &aia).unwrap();
    // A cube whose own name ends in [1]: "cube[1].fits" plain, "cube[1].fits[5]" frame 5.
    let cube = sub.join("cube[1].fits");
    std::fs::copy(real(SJI_2832), &cube).unwrap();
    let frame_arg = PathBuf::from(format!("{}[5]", cube.display()));
    let (records, out) = info_json(&[aia.clone(), frame_arg]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(records.len(), 2);
    check(
        &records[0],
        &Truth {
            file: "aia 171 [a].fits",
            ..TRUTH[0]
        },
    );
    assert_eq!(records[1]["frame"], 5);
    assert_eq!(records[1]["channel"], "SJI_2832");
}

#[test]
fn gzip_compressed_files_are_read_as_the_files_they_hold() {
    // `.fits.gz` as archives ship them (RFC 1952; the daemon's default extensions take them):
    // the same sunpy truths as the plain file, under the compressed file's name, and frames of
    // a compressed cube by suffix.
    let dir = tempfile::tempdir().unwrap();
    let gzip = |name: &str| {
        let path = dir.path().join(format!("{name}.gz"));
        let mut encoder = flate2::write::GzEncoder::new(
            std::fs::File::create(&path).unwrap(),
            flate2::Compression::default(),
        );
        std::io::copy(&mut std::fs::File::open(real(name)).unwrap(), &mut encoder).unwrap();
        encoder.finish().unwrap();
        path
    };
    let aia = gzip(AIA);
    let cube = gzip(SJI_2832);
    let frame_arg = PathBuf::from(format!("{}[5]", cube.display()));
    let (records, out) = info_json(&[aia, frame_arg]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    check(
        &records[0],
        &Truth {
            file: "aia_171_20110215T000000_128.fits.gz",
            ..TRUTH[0]
        },
    );
    assert_eq!(records[1]["frame"], 5);
    assert_eq!(records[1]["channel"], "SJI_2832");
    // A truncated stream is bad input naming the file.
    let truncated = dir.path().join("truncated.fits.gz");
    let bytes = std::fs::read(gzip(EIT_195)).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let (_, out) = info_json(std::slice::from_ref(&truncated));
    assert_eq!(out.status.code(), Some(ExitCode::BadInput.code()));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.starts_with(&format!(
            "sunjitter: {}: gzip-compressed",
            truncated.display()
        )),
        "{stderr}"
    );
}

#[test]
fn human_table_lists_each_image() {
    let out = sunjitter(&[
        "info".as_ref(),
        real(AIA).as_os_str(),
        real(HMI).as_os_str(),
    ]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 3, "{text}");
    assert!(lines[0].starts_with("FILE") && lines[0].contains("CHANNEL"));
    assert!(lines[1].contains("AIA_171") && lines[1].contains("2011-02-15T00:00:01.340Z"));
    assert!(lines[2].contains("HMI_6173") && lines[2].contains("179.9298"));
}

/// Several files, one bad: the good ones are printed, the bad one named on stderr, exit 2.
#[test]
fn a_bad_file_among_good_ones() {
    let bad = PathBuf::from(MALFORMED).join("not_actually_fits.fits");
    let (records, out) = info_json(&[real(AIA), bad.clone(), real(EIT_195)]);
    assert_eq!(out.status.code(), Some(ExitCode::BadInput.code()));
    assert_eq!(records.len(), 2);
    check(&records[0], &TRUTH[0]);
    check(&records[1], &TRUTH[2]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with(&format!("sunjitter: {}: not a FITS file", bad.display())),
        "{stderr}"
    );
}

/// Warnings written to a file or a pipe carry no terminal escape codes (ECMA-48 CSI starts
/// with ESC): the bundled 1400 cube's resampled per-frame table is warned about.
#[test]
fn warnings_into_a_pipe_are_plain_text() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("info")
        .arg(format!("{REAL}{SJI_1400}"))
        .env_remove("NO_COLOR")
        .output()
        .expect("run sunjitter info");
    assert!(out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("per-frame table has 540 rows"), "{stderr}");
    assert!(
        !stderr.contains('\u{1b}'),
        "escape codes in a pipe: {stderr:?}"
    );
}
