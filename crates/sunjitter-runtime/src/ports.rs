//! The outside world the pipeline drives, as small traits: frames come from a
//! [`FrameReader`] (FITS files in production) and are measured by an [`Aligner`] (the
//! engine). Tests put fakes with known truths behind them (`fake`, feature `test-fakes`).

use std::path::Path;

use sunjitter_core::engine::{AlignOutcome, Image};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::Result;
use sunjitter_io::fits::FrameSpec;

/// Reads frames: `fits::read_meta` / `fits::read_frame` in production, fakes in tests.
pub trait FrameReader: Send + Sync {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>>;
    fn read_frame(&self, spec: &FrameSpec) -> Result<Image>;
}

/// Aligns one image to another: `engine::align_images` in production.
pub trait Aligner: Send + Sync {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome;
    /// As [`Aligner::align`], to a reference at `position` along its chain (its sequence
    /// number in the log; `engine::PreparedReference::at_position`).
    fn align_at(&self, reference: &Image, _position: u64, frame: &Image) -> AlignOutcome {
        self.align(reference, frame)
    }
    /// Why `image` cannot serve as a reference, if it cannot.
    fn usable_as_reference(&self, _image: &Image) -> std::result::Result<(), String> {
        Ok(())
    }
    /// The plate scale alignments to `image` use (arcsec/px; by default the header's).
    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        Some(image.meta.plate_scale_arcsec)
    }
    /// The geometry alignments to `image` use, where it is not the header's.
    fn geometry_used(&self, _image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        None
    }
}
