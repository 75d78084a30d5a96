//! Files `align` can write besides its numbers: the resampled frame and a quick-look composite.

use super::{AlignOutcome, Image};
use crate::{Error, Result};
use std::path::Path;

/// The frame resampled onto the reference grid, with the reference's WCS.
pub fn write_aligned(
    path: &Path,
    _reference: &Image,
    _frame: &Image,
    _outcome: &AlignOutcome,
) -> Result<()> {
    Err(Error::output(path, "--aligned is not implemented yet"))
}

/// Red = reference, green + blue = frame; before and after fine alignment side by side.
pub fn write_quicklook(
    path: &Path,
    _reference: &Image,
    _frame: &Image,
    _outcome: &AlignOutcome,
) -> Result<()> {
    Err(Error::output(path, "--quicklook is not implemented yet"))
}
