//! Bad input through the real binary: exit code 2, exactly one line on stderr that names the
//! file and the problem, no panic. Truth: the FITS standard (a file starts with `SIMPLE = T`,
//! headers end with `END`, data size = |BITPIX|/8 · ΠNAXISn) and the contract's exit codes.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::Command;
use sunjitter_core::error::ExitCode;

const REAL: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/real/");
const MALFORMED: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/data/malformed/");

/// Run `sunjitter info FILE` and check the bad-input contract; returns the stderr line.
fn expect_bad(file: &Path, problem: &str) -> String {
    expect_bad_arg(file.as_os_str(), &file.display().to_string(), problem)
}

fn expect_bad_arg(arg: &OsStr, shown_name: &str, problem: &str) -> String {
    for json in [false, true] {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_sunjitter"));
        cmd.arg("info");
        if json {
            cmd.arg("--json");
        }
        let out = cmd.arg(arg).output().expect("run sunjitter");
        let stderr = String::from_utf8_lossy(&out.stderr).to_string();
        assert_eq!(
            out.status.code(),
            Some(ExitCode::BadInput.code()),
            "exit code for {shown_name}: {stderr}"
        );
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert_eq!(stderr.lines().count(), 1, "one line expected: {stderr:?}");
        let line = stderr.trim_end();
        assert!(
            line.starts_with(&format!("sunjitter: {shown_name}: ")),
            "file not named: {line}"
        );
        assert!(line.contains(problem), "problem {problem:?} not in: {line}");
        if json {
            assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "[]");
        }
    }
    String::new()
}

/// A primary header from `cards` (80 columns each, then END, padded to 2880) plus `data` bytes.
fn fits_bytes(cards: &[&str], data: &[u8]) -> Vec<u8> {
    let mut bytes: Vec<u8> = cards
        .iter()
        .chain(["END"].iter())
        .flat_map(|c| format!("{c:<80}").into_bytes())
        .collect();
    bytes.resize(bytes.len().div_ceil(2880) * 2880, b' ');
    bytes.extend_from_slice(data);
    bytes
}

fn temp_file(dir: &tempfile::TempDir, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.path().join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn not_actually_fits() {
    expect_bad(
        &PathBuf::from(MALFORMED).join("not_actually_fits.fits"),
        "not a FITS file",
    );
}

#[test]
fn zero_length_file() {
    let dir = tempfile::tempdir().unwrap();
    expect_bad(&temp_file(&dir, "empty.fits", b""), "empty file");
}

#[test]
fn truncated_in_the_data() {
    let dir = tempfile::tempdir().unwrap();
    let whole =
        std::fs::read(PathBuf::from(REAL).join("trace_171_19980519T222143_1024.fits")).unwrap();
    // Header is 2 blocks; 1024² int16 needs 2 MiB of data, keep 100 kB of it.
    let cut = temp_file(&dir, "trace_cut.fits", &whole[..5760 + 100_000]);
    expect_bad(
        &cut,
        "truncated: the header announces 2097152 bytes of data, the file holds 100000",
    );
    // The out-of-order IDL file, truncated too: still a clear error.
    let idl =
        std::fs::read(PathBuf::from(MALFORMED).join("trace_171_naxis_cards_out_of_order.fits"))
            .unwrap();
    expect_bad(
        &temp_file(&dir, "idl_cut.fits", &idl[..idl.len() / 2]),
        "truncated",
    );
}

#[test]
fn truncated_in_the_header() {
    let dir = tempfile::tempdir().unwrap();
    let whole =
        std::fs::read(PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits")).unwrap();
    expect_bad(
        &temp_file(&dir, "aia_cut.fits", &whole[..4000]),
        "ends without an END card",
    );
}

#[test]
fn cube_truncated_in_an_extension() {
    let dir = tempfile::tempdir().unwrap();
    let whole = std::fs::read(
        PathBuf::from(REAL).join("iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits"),
    )
    .unwrap();
    // Cut inside the last HDU (the ASCII table), as a file still being written would be.
    expect_bad(
        &temp_file(&dir, "iris_cut.fits", &whole[..whole.len() - 3000]),
        "HDU 2: truncated",
    );
}

#[test]
fn absurd_naxis1_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                   16",
        "NAXIS   =                    2",
        "NAXIS1  =           2000000000",
        "NAXIS2  =                    1",
    ];
    let path = temp_file(&dir, "huge.fits", &fits_bytes(&cards, &[0u8; 2880]));
    expect_bad(&path, "absurd image size: NAXIS1 = 2000000000");
}

#[test]
fn absurd_gigapixel_square_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                  -64",
        "NAXIS   =                    2",
        "NAXIS1  =           1000000000",
        "NAXIS2  =           1000000000",
    ];
    expect_bad(
        &temp_file(&dir, "square.fits", &fits_bytes(&cards, &[])),
        "absurd image size",
    );
}

#[test]
fn sizes_that_overflow_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    // Each axis is within the per-axis limit, the product overflows a frame.
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                   16",
        "NAXIS   =                    2",
        "NAXIS1  =                65536",
        "NAXIS2  =                65536",
    ];
    expect_bad(
        &temp_file(&dir, "wide.fits", &fits_bytes(&cards, &[])),
        "absurd image size 65536 × 65536",
    );
}

/// A 4×4 8-bit image (16 data bytes) with `wcs` cards after the structural ones.
fn byte_image_4x4(wcs: &[&'static str]) -> Vec<u8> {
    let mut cards = vec![
        "SIMPLE  =                    T",
        "BITPIX  =                    8",
        "NAXIS   =                    2",
        "NAXIS1  =                    4",
        "NAXIS2  =                    4",
    ];
    cards.extend_from_slice(wcs);
    fits_bytes(&cards, &[7u8; 16])
}

#[test]
fn header_without_wcs_is_a_bad_header() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "CRPIX1  =                  2.5",
        "CRPIX2  =                  2.5",
    ];
    expect_bad(
        &temp_file(&dir, "nowcs.fits", &byte_image_4x4(&cards)),
        "header: CDELT1 is missing",
    );
}

#[test]
fn no_image_in_any_hdu() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                    8",
        "NAXIS   =                    0",
    ];
    expect_bad(
        &temp_file(&dir, "empty_primary.fits", &fits_bytes(&cards, &[])),
        "no image data",
    );
}

#[test]
fn invalid_bitpix() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                   12",
        "NAXIS   =                    2",
        "NAXIS1  =                    4",
        "NAXIS2  =                    4",
    ];
    expect_bad(
        &temp_file(&dir, "bitpix.fits", &fits_bytes(&cards, &[0u8; 2880])),
        "BITPIX = 12",
    );
}

#[test]
fn missing_file_and_directory() {
    let dir = tempfile::tempdir().unwrap();
    expect_bad(&dir.path().join("nope.fits"), "cannot open");
    expect_bad(dir.path(), "is a directory");
}

#[test]
fn heliographic_map_is_a_bad_header() {
    // A Carrington synoptic map (CTYPE CRLN-CEA, as HMI and GONG write them): degrees on the
    // Sun, not an image of the sky (WCS Paper IV, Thompson 2006).
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "CTYPE1  = 'CRLN-CEA'",
        "CTYPE2  = 'CRLT-CEA'",
        "CRPIX1  =                  2.5",
        "CRPIX2  =                  2.5",
        "CDELT1  =                  1.0",
        "CDELT2  =                  0.1",
    ];
    expect_bad(
        &temp_file(&dir, "synoptic.fits", &byte_image_4x4(&cards)),
        "CTYPE1 = 'CRLN-CEA' is a heliographic",
    );
}

#[test]
fn compressed_files_are_named_as_such() {
    // Magic numbers: gzip 1f 8b (RFC 1952), bzip2 "BZh", zstd 28 b5 2f fd (RFC 8878).
    let dir = tempfile::tempdir().unwrap();
    for (name, magic, kind) in [
        (
            "a.fits.gz",
            &[0x1f, 0x8b, 0x08, 0x00][..],
            "gzip-compressed",
        ),
        ("a.fits.bz2", &b"BZh91AY&SY"[..], "bzip2-compressed"),
        (
            "a.fits.zst",
            &[0x28, 0xb5, 0x2f, 0xfd, 0x00][..],
            "zstd-compressed",
        ),
    ] {
        let mut bytes = magic.to_vec();
        bytes.resize(4000, 0);
        expect_bad(&temp_file(&dir, name, &bytes), kind);
    }
}

#[test]
fn a_suffix_that_is_not_a_frame_index_is_explained() {
    let file = PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits");
    for suffix in ["[-1]", "[abc]"] {
        let arg = format!("{}{suffix}", file.display());
        expect_bad_arg(OsStr::new(&arg), &arg, "is not a frame index");
    }
}

#[test]
fn frame_out_of_range() {
    let file = PathBuf::from(REAL).join("iris_l2_20140329_140938_3860258481_SJI_2832_t000.fits");
    let arg = format!("{}[18]", file.display());
    expect_bad_arg(
        OsStr::new(&arg),
        &file.display().to_string(),
        "frame 18 does not exist",
    );
}

/// `simulate --noise K` on an image with no varying 16×16 block (a constant frame): the noise
/// has no unit, which is the input's fault: exit 2, one line naming the file.
#[test]
fn noise_without_a_measurable_background_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                    8",
        "NAXIS   =                    2",
        "NAXIS1  =                   64",
        "NAXIS2  =                   64",
        "CRPIX1  =                 32.5",
        "CRPIX2  =                 32.5",
        "CDELT1  =                  0.6",
        "CDELT2  =                  0.6",
        "CRVAL1  =                  0.0",
        "CRVAL2  =                  0.0",
        "CUNIT1  = 'arcsec  '",
        "CUNIT2  = 'arcsec  '",
    ];
    let mut data = vec![7u8; 64 * 64];
    data.resize(2 * 2880, 0); // the data unit padded to whole 2880-byte records
    let file = temp_file(&dir, "flat.fits", &fits_bytes(&cards, &data));
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args([
            "simulate",
            "--trials",
            "1",
            "--cc-trials",
            "0",
            "--noise",
            "3",
        ])
        .arg(&file)
        .output()
        .expect("run sunjitter");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(ExitCode::BadInput.code()),
        "{stderr}"
    );
    assert_eq!(stderr.lines().count(), 1, "one line expected: {stderr:?}");
    assert!(
        stderr.starts_with(&format!("sunjitter: {}: no 16×16 block", file.display())),
        "{stderr}"
    );
}

/// A file claiming more pixels per image than `[daemon] max_frame_pixels` (default 8192²) is
/// refused on its header, even when it is sparse (20 KB on disk, 1 GiB by its length).
#[test]
fn a_sparse_file_claiming_a_huge_image_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "SIMPLE  =                    T",
        "BITPIX  =                  -32",
        "NAXIS   =                    2",
        "NAXIS1  =                16384",
        "NAXIS2  =                16384",
    ];
    let path = temp_file(&dir, "sparse.fits", &fits_bytes(&cards, &[0u8; 20_000]));
    std::fs::File::options()
        .write(true)
        .open(&path)
        .unwrap()
        .set_len(2880 + 16384 * 16384 * 4)
        .unwrap();
    let reference = format!("{REAL}trace_171_19980519T222143_1024.fits");
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .args(["align", &reference])
        .arg(&path)
        .output()
        .expect("run sunjitter");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(ExitCode::BadInput.code()),
        "{stderr}"
    );
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.starts_with(&format!("sunjitter: {}: ", path.display()))
            && stderr.contains("16384×16384 = 268435456 pixels per image"),
        "{stderr}"
    );
}

/// A 4×4 image with a WCS and an observation time, plus `extra` cards.
fn byte_image_with(extra: &[&'static str]) -> Vec<u8> {
    let mut cards = vec![
        "CRPIX1  =                  2.5",
        "CRPIX2  =                  2.5",
        "CDELT1  =                  0.6",
        "CDELT2  =                  0.6",
        "DATE-OBS= '2011-02-15T00:00:00'",
    ];
    cards.extend_from_slice(extra);
    byte_image_4x4(&cards)
}

/// FITS standard §5.3: physical = BZERO + BSCALE · stored. A scaling that is not a finite
/// number cannot be applied; ignoring it would report other pixel values than the file's.
#[test]
fn pixel_scaling_that_is_not_a_finite_number_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (name, card, problem) in [
        (
            "bscale.fits",
            "BSCALE  = 'abc'",
            "BSCALE = 'abc' is not a finite number",
        ),
        (
            "bzero.fits",
            "BZERO   = 'NaN'",
            "BZERO = 'NaN' is not a finite number",
        ),
    ] {
        let path = temp_file(&dir, name, &byte_image_with(&[card]));
        expect_bad(&path, problem);
        // `align` refuses it the same way.
        let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
            .arg("align")
            .arg(PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits"))
            .arg(&path)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(
            out.status.code(),
            Some(ExitCode::BadInput.code()),
            "{stderr}"
        );
        assert_eq!(stderr.lines().count(), 1, "{stderr}");
        assert!(
            stderr.starts_with(&format!("sunjitter: {}: ", path.display()))
                && stderr.contains(problem),
            "{stderr}"
        );
    }
}

/// A plate scale of 1e-300″/px (the Sun would span 10^303 pixels) is no solar image's.
#[test]
fn a_plate_scale_that_is_not_physical_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cards = [
        "CRPIX1  =                  2.5",
        "CRPIX2  =                  2.5",
        "CDELT1  =               1E-300",
        "CDELT2  =                  0.6",
    ];
    expect_bad(
        &temp_file(&dir, "tiny.fits", &byte_image_4x4(&cards)),
        "header: a plate scale of 1e-300 arcsec/px along axis 1 is not physical",
    );
}

/// `replay` (the daemon's pipeline) names a file with a broken scaling on `/log` and goes on
/// with the others.
#[test]
fn replay_logs_a_broken_scaling_and_continues() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().canonicalize().unwrap().join("in");
    std::fs::create_dir(&inputs).unwrap();
    std::fs::copy(
        PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits"),
        inputs.join("aia.fits"),
    )
    .unwrap();
    let bad = inputs.join("bscale.fits");
    std::fs::write(&bad, byte_image_with(&["BSCALE  = 'abc'"])).unwrap();
    let out_dir = dir.path().join("out");
    let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("replay")
        .arg(&inputs)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(ExitCode::Ok.code()),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let files = sunjitter_runtime::inspect::log_files(&[out_dir]).unwrap();
    let contents = sunjitter_io::sink::read_logs(&files).unwrap();
    let frames: Vec<&str> = contents
        .jitter
        .iter()
        .map(|m| m.record.align.frame.as_str())
        .collect();
    assert_eq!(frames, [inputs.join("aia.fits").display().to_string()]);
    let logs: Vec<(String, String)> = contents
        .logs
        .iter()
        .map(|m| (m.entry.file.clone(), m.entry.message.clone()))
        .collect();
    assert_eq!(
        logs,
        [(
            bad.display().to_string(),
            "BSCALE = 'abc' is not a finite number".to_string()
        )]
    );
}

/// An output that cannot be created (here: a regular file stands where a directory must be)
/// is the command line's fault: exit 2, one line naming the path, before any work.
#[test]
fn unwritable_outputs_exit_2_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let aia = PathBuf::from(REAL).join("aia_171_20110215T000000_128.fits");
    let blocker = temp_file(&dir, "blocker", b"a file, not a directory");
    let inputs = dir.path().join("in");
    std::fs::create_dir(&inputs).unwrap();
    let good_log = dir.path().join("log");
    let made = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
        .arg("replay")
        .arg(&aia)
        .arg("--out")
        .arg(&good_log)
        .output()
        .unwrap();
    assert_eq!(made.status.code(), Some(ExitCode::Ok.code()));
    let under = blocker.join("x");
    let cases: Vec<(Vec<&OsStr>, &Path)> = vec![
        (
            vec![
                "replay".as_ref(),
                aia.as_os_str(),
                "--out".as_ref(),
                under.as_os_str(),
            ],
            &under,
        ),
        (
            vec![
                "replay".as_ref(),
                aia.as_os_str(),
                "--out".as_ref(),
                blocker.as_os_str(),
            ],
            &blocker,
        ),
        (
            vec![
                "watch".as_ref(),
                inputs.as_os_str(),
                "--out".as_ref(),
                under.as_os_str(),
            ],
            &under,
        ),
        (
            vec![
                "inspect".as_ref(),
                good_log.as_os_str(),
                "--csv".as_ref(),
                under.as_os_str(),
            ],
            &under,
        ),
        (
            vec![
                "align".as_ref(),
                aia.as_os_str(),
                aia.as_os_str(),
                "--aligned".as_ref(),
                under.as_os_str(),
            ],
            &under,
        ),
    ];
    for (args, path) in cases {
        let out = Command::new(env!("CARGO_BIN_EXE_sunjitter"))
            .args(&args)
            .env("SUNJITTER_LOG", "warn")
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(
            out.status.code(),
            Some(ExitCode::BadInput.code()),
            "{args:?}: {stderr}"
        );
        assert_eq!(stderr.lines().count(), 1, "{args:?}: {stderr}");
        assert!(
            stderr.starts_with(&format!(
                "sunjitter: {}: cannot write here: ",
                path.display()
            )),
            "{args:?}: {stderr}"
        );
    }
}
