//! FITS ingestion: images and cube frames as `f32` arrays with their metadata, and f32 output.
//!
//! How a file is read:
//! 1. `scan` walks the HDU headers with sunjitter's own parser ([`sunjitter_core::header`]): this
//!    refuses non-FITS, truncated and absurdly sized files with a clear reason *before*
//!    anything large is allocated, and tolerates header quirks cfitsio rejects (NAXISn cards
//!    out of order, as in old IDL-written TRACE files).
//! 2. The image is the first HDU holding image data (primary, IMAGE extension, or a
//!    tile-compressed `ZIMAGE` table).
//! 3. Uncompressed pixels are decoded here (big-endian, `BSCALE`/`BZERO`, `BLANK` → NaN), reading
//!    only the requested frame. Tile-compressed pixels are decompressed by cfitsio, read with a
//!    NaN null value so blank pixels become NaN; files are opened as plain disk files so
//!    cfitsio's extended file-name syntax never applies to `[`, `]` or spaces in paths.
//! 4. Per-frame times of cubes come from the per-frame table (IRIS: HDU 1, column index in
//!    header key `TIME`, seconds after `STARTOBS`), else from the time axis, else the header.
//!    Per-frame pointing comes from the same table (`XCENIX`/`YCENIX`): one primary header
//!    describes the whole cube at its nominal pointing, while IRIS re-points between frames
//!    (it follows the Sun's rotation), so each frame's sun centre is moved by its own offset.

mod cube;
mod gzip;
mod layout;
mod options;
mod pixels;
mod read;
mod spec;
mod write;

pub use gzip::remove_stale_gunzipped_copies;
pub use layout::is_incomplete;
pub use options::{PlateScales, ReadLimits, ReadOptions, DEFAULT_MAX_FRAME_PIXELS};
pub use read::{
    read_frame, read_frame_with, read_image_header, read_image_header_as_read, read_meta,
    read_meta_with,
};
pub use spec::{frame_key, parse_frame_key, FrameSpec};
pub use write::{frame_header_cards, write_image};
