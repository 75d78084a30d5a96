//! gzip-compressed input (`.fits.gz`, as archives ship it): the decompressed copy is private
//! (created exclusively under an unpredictable name, never through a planted link), checked
//! against the header's announced size before any data is decompressed, and removed, also
//! after a killed run. One test in this binary: it points the temporary directory (`TMPDIR`)
//! at its own folder.

use std::io::Write;
use std::path::Path;
use sunjitter_io::fits::{read_frame, remove_stale_gunzipped_copies, FrameSpec};

const TRACE: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/data/real/trace_171_19980519T222143_1024.fits"
);

fn gzip(path: &Path, bytes: &[u8]) {
    let mut gz = flate2::write::GzEncoder::new(
        std::fs::File::create(path).unwrap(),
        flate2::Compression::fast(),
    );
    gz.write_all(bytes).unwrap();
    gz.finish().unwrap();
}

fn names(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn gzip_input_is_decompressed_privately_checked_first_and_cleaned_up() {
    let tmp = tempfile::tempdir().unwrap();
    let inputs = tempfile::tempdir().unwrap();
    std::env::set_var("TMPDIR", tmp.path());
    assert_eq!(std::env::temp_dir(), tmp.path());

    // Links planted at the names a predictable scheme would use (process id, counter,
    // the file's name), all pointing at a file that must not change.
    let victim = inputs.path().join("victim.txt");
    std::fs::write(&victim, b"precious").unwrap();
    let pid = std::process::id();
    for n in 0..8 {
        for name in ["trace.fits", "bomb.fits"] {
            let link = tmp.path().join(format!("sunjitter-{pid}-{n}-{name}"));
            std::os::unix::fs::symlink(&victim, link).unwrap();
        }
    }
    let planted = names(tmp.path());

    // A real frame: the same pixels as the plain file, and no copy left behind.
    let gz = inputs.path().join("trace.fits.gz");
    gzip(&gz, &std::fs::read(TRACE).unwrap());
    let plain = read_frame(&FrameSpec::file(TRACE)).unwrap();
    let unzipped = read_frame(&FrameSpec::file(&gz)).unwrap();
    assert_eq!(unzipped.data, plain.data);
    assert_eq!(unzipped.meta.file, gz);
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    assert_eq!(names(tmp.path()), planted);

    // A header announcing 16384² float pixels (1 GiB) behind 4 KB of gzip: refused on the
    // header, naming the file and the limit, before anything is decompressed.
    let mut header: Vec<u8> = [
        "SIMPLE  =                    T",
        "BITPIX  =                  -32",
        "NAXIS   =                    2",
        "NAXIS1  =                16384",
        "NAXIS2  =                16384",
        "END",
    ]
    .iter()
    .flat_map(|c| format!("{c:<80}").into_bytes())
    .collect();
    header.resize(2880, b' ');
    let bomb = inputs.path().join("bomb.fits.gz");
    gzip(&bomb, &header);
    let err = read_frame(&FrameSpec::file(&bomb)).unwrap_err().to_string();
    assert!(
        err.contains("bomb.fits.gz") && err.contains("268435456 pixels per image"),
        "{err}"
    );
    assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
    assert_eq!(names(tmp.path()), planted);

    // Copies left by a killed process are removed on start; a live process's are kept.
    let mut gone = std::process::Command::new("true").spawn().unwrap();
    let dead = gone.id();
    gone.wait().unwrap();
    let stale = tmp
        .path()
        .join(format!("sunjitter-gunzipped-{dead}-x1y2z3.fits"));
    let live = tmp
        .path()
        .join(format!("sunjitter-gunzipped-{pid}-a1b2c3.fits"));
    std::fs::write(&stale, b"left by a killed run").unwrap();
    std::fs::write(&live, b"in use").unwrap();
    remove_stale_gunzipped_copies();
    assert!(!stale.exists(), "a dead process's copy must be removed");
    assert!(live.exists(), "a live process's copy must be kept");
}
