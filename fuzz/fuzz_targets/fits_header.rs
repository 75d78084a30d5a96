//! FITS header parsing and metadata normalisation under arbitrary bytes.
//!
//! Two levels: the pure header functions on the bytes as one header, then the whole file
//! reader (`fits::read_meta`, and `fits::read_frame` for uncompressed images) on the bytes
//! written to a scratch file. The reader may only fail with `BadInput`/`BadHeader`.
//! Tile-compressed pixels are decoded by cfitsio (C, not ours), so `read_frame` is skipped
//! for inputs mentioning `ZIMAGE`.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::PathBuf;
use std::sync::OnceLock;
use sunjitter::fits::{self, FrameSpec};
use sunjitter::header::{self, Header};
use sunjitter::meta::{self, ImagePlace};
use sunjitter::Error;

/// One scratch file per fuzzing process, on tmpfs when there is one.
fn scratch_file() -> &'static PathBuf {
    static FILE: OnceLock<PathBuf> = OnceLock::new();
    FILE.get_or_init(|| {
        let base = if std::path::Path::new("/dev/shm").is_dir() {
            PathBuf::from("/dev/shm")
        } else {
            std::env::temp_dir()
        };
        base.join(format!("sunjitter-fuzz-{}.fits", std::process::id()))
    })
}

fn expect_input_error<T>(result: Result<T, Error>) -> Option<T> {
    match result {
        Ok(v) => Some(v),
        Err(Error::BadInput { .. } | Error::BadHeader { .. }) => None,
        Err(other) => panic!("unexpected error kind: {other:?}"),
    }
}

fuzz_target!(|data: &[u8]| {
    // Pure functions on the bytes as one header.
    let h = Header::parse(data);
    let _ = header::mandatory_order_problem(&h);
    for is_primary in [true, false] {
        if let Ok(kind) = header::hdu_kind(&h, is_primary) {
            let _ = header::data_size_bytes(&h);
            if let Ok(Some(g)) = header::image_geometry(&h, &kind) {
                let place = ImagePlace {
                    file: PathBuf::from("fuzz.fits"),
                    hdu: 0,
                    frame: None,
                    width: g.width(),
                    height: g.height(),
                    bitpix: g.bitpix,
                };
                let _ = (g.frames(), g.pixels_per_frame(), g.bytes_per_pixel());
                if let Ok(m) = meta::from_header(&h, place) {
                    let _ = m.obs_time_iso();
                }
            }
        }
    }
    let _ = meta::time_reference_ns(&h);
    let _ = meta::time_axis_seconds(&h, 7);

    // The whole reader on the bytes as a file.
    let path = scratch_file();
    if std::fs::write(path, data).is_err() {
        return;
    }
    let Some(metas) = expect_input_error(fits::read_meta(path)) else {
        return;
    };
    for m in &metas {
        let _ = m.obs_time_iso();
    }
    if data.windows(6).any(|w| w == b"ZIMAGE") {
        return;
    }
    let spec = match metas.last().and_then(|m| m.frame) {
        Some(n) => FrameSpec::cube_frame(path, n),
        None => FrameSpec::file(path),
    };
    if let Some(image) = expect_input_error(fits::read_frame(&spec)) {
        assert_eq!(image.data.dim(), (image.meta.height, image.meta.width));
    }
});
