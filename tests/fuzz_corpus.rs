//! The fuzz target's checks (`fuzz/fuzz_targets/fits_header.rs`) on its committed corpus, on
//! stable Rust in every `cargo test`: seeds from the real and malformed files, and the
//! fuzzer's crash inputs (`crash-*`, kept as regression seeds). Nothing may panic,
//! and the reader may only refuse with `BadInput`/`BadHeader`.

use std::path::PathBuf;
use sunjitter_core::error::Error;
use sunjitter_core::header::{self, Header};
use sunjitter_core::meta::{self, ImagePlace};
use sunjitter_io::fits::{self, FrameSpec};

fn input_error<T>(name: &str, result: Result<T, Error>) -> Option<T> {
    match result {
        Ok(v) => Some(v),
        Err(Error::BadInput { .. } | Error::BadHeader { .. }) => None,
        Err(other) => panic!("{name}: unexpected error kind: {other:?}"),
    }
}

#[test]
fn fuzz_corpus_replays_without_panics() {
    let dir = PathBuf::from("fuzz/corpus/fits_header");
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        // The committed files only (a local fuzzing run adds its own there).
        .filter(|p| {
            let name = p.file_name().unwrap().to_string_lossy();
            name.starts_with("seed-") || name.starts_with("crash-")
        })
        .collect();
    inputs.sort();
    assert!(inputs.len() >= 19, "the committed seeds are there");
    let scratch = tempfile::tempdir().unwrap();
    let (mut read, mut refused) = (0, 0);
    for input in &inputs {
        let name = input.file_name().unwrap().to_string_lossy().to_string();
        let data = std::fs::read(input).unwrap();
        // Pure functions on the bytes as one header.
        let h = Header::parse(&data);
        let _ = header::mandatory_order_problem(&h);
        for is_primary in [true, false] {
            if let Ok(kind) = header::hdu_kind(&h, is_primary) {
                let _ = header::data_size_bytes(&h);
                if let Ok(Some(g)) = header::image_geometry(&h, &kind) {
                    let _ = (g.frames(), g.pixels_per_frame());
                    let place = ImagePlace {
                        file: PathBuf::from(&name),
                        hdu: 0,
                        frame: None,
                        width: g.width(),
                        height: g.height(),
                        bitpix: g.bitpix,
                    };
                    let _ = meta::from_header(&h, place).map(|m| m.obs_time_iso());
                }
            }
        }
        let _ = meta::time_reference_ns(&h);
        let _ = meta::time_axis_seconds(&h, 7);
        // The whole reader on the bytes as a file.
        let path = scratch.path().join(format!("{name}.fits"));
        std::fs::write(&path, &data).unwrap();
        let Some(metas) = input_error(&name, fits::read_meta(&path)) else {
            refused += 1;
            continue;
        };
        read += 1;
        if data.windows(6).any(|w| w == b"ZIMAGE") {
            continue;
        }
        let spec = match metas.last().and_then(|m| m.frame) {
            Some(n) => FrameSpec::cube_frame(&path, n),
            None => FrameSpec::file(&path),
        };
        if let Some(image) = input_error(&name, fits::read_frame(&spec)) {
            assert_eq!(image.data.dim(), (image.meta.height, image.meta.width));
        }
    }
    // The small real-derived seeds read; the header-only and garbage ones are refused.
    assert!(read >= 8 && refused >= 9, "read {read}, refused {refused}");
}
