//! Split a 3-D FITS cube (e.g. an IRIS slit-jaw sequence) into one 2-D FITS file per frame,
//! each with the cube's header cards, the frame's own `DATE-OBS` (from the per-frame table or
//! time axis) and `EXPTIME`, so a directory watcher can be fed a real observing sequence.
//!
//! ```text
//! cargo run --example split_cube -- CUBE.fits OUTDIR
//! ```
//! Files are named `<cube stem>_f<NNNN>.fits`; each is written under a temporary name and
//! renamed, so a watcher never sees a partial file.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use sunjitter_io::fits::{self, FrameSpec};

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [cube, out_dir] = args.as_slice() else {
        eprintln!("usage: split_cube CUBE.fits OUTDIR");
        return ExitCode::from(2);
    };
    match split(Path::new(cube), Path::new(out_dir)) {
        Ok(n) => {
            println!("wrote {n} frames to {out_dir}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("split_cube: {e}");
            ExitCode::from(e.exit_code() as u8)
        }
    }
}

/// Write every frame of `cube` into `out_dir`; returns the number of frames written.
fn split(cube: &Path, out_dir: &Path) -> sunjitter_core::error::Result<usize> {
    let metas = fits::read_meta(cube)?;
    if metas.first().and_then(|m| m.frame).is_none() {
        return Err(sunjitter_core::error::Error::bad_input(
            cube,
            "is a 2-D image, not a cube",
        ));
    }
    let (_, header) = fits::read_image_header(cube)?;
    std::fs::create_dir_all(out_dir).map_err(|e| sunjitter_core::error::Error::io(out_dir, e))?;
    let stem = cube.file_stem().and_then(|s| s.to_str()).unwrap_or("frame");
    for meta in &metas {
        let index = meta.frame.unwrap_or(0);
        let image = fits::read_frame(&FrameSpec::cube_frame(cube, index))?;
        let cards = fits::frame_header_cards(&header, &image.meta);
        let out: PathBuf = out_dir.join(format!("{stem}_f{index:04}.fits"));
        fits::write_image(&out, image.data.view(), &cards)?;
    }
    Ok(metas.len())
}
