//! FITS ingestion (INTERFACE ONLY for now; implemented with issue 2).

use crate::engine::Image;
use crate::meta::FrameMeta;
use crate::Result;
use std::path::{Path, PathBuf};

/// One image to read: a file, and for a 3-D cube the frame index (`FILE.fits[N]`).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FrameSpec {
    pub path: PathBuf,
    pub frame: Option<usize>,
}

impl FrameSpec {
    /// Parse a command-line argument: `FILE.fits[N]` for frame N of a cube, else a plain path.
    pub fn parse(arg: &str) -> FrameSpec {
        FrameSpec {
            path: PathBuf::from(arg),
            frame: None,
        }
    }
}

/// Read one image (or one frame of a cube) as f32, with its metadata.
pub fn read_frame(spec: &FrameSpec) -> Result<Image> {
    Err(crate::Error::bad_input(
        &spec.path,
        "FITS reading not implemented yet",
    ))
}

/// Metadata of every image (every frame of a cube) in a file.
pub fn read_meta(path: &Path) -> Result<Vec<FrameMeta>> {
    Err(crate::Error::bad_input(
        path,
        "FITS reading not implemented yet",
    ))
}
