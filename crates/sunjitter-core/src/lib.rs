//! sunjitter's numerics: everything between a frame's pixels and header and its measured
//! transform, with no file I/O and no process-wide state.
//!
//! The stages in the order a frame meets them: header metadata ([`header`], [`meta`],
//! [`time`]) → coarse alignment ([`coarse`], [`preprocess`], [`resample`]) → solar rotation
//! ([`solar_rotation`]) → dense flow ([`flow`]) → sampling ([`sampling`]) → fit and
//! covariance ([`fit`], [`geometry`]) → one alignment and its verdict ([`engine`], which
//! returns a [`record::FrameAlignment`]). [`blur`], [`crosscorr`] and [`stats`] serve them;
//! [`synth`] and [`simulate`] make ground truth.

pub mod error;
pub mod geometry;
pub mod record;
pub mod text;

pub mod header;
pub mod meta;
pub mod time;

pub mod blur;
pub mod coarse;
pub mod preprocess;
pub mod resample;
pub mod solar_rotation;

pub mod crosscorr;
pub mod fit;
pub mod flow;
pub mod sampling;
pub mod stats;

pub(crate) mod pages;

pub mod chain;
pub mod engine;
pub mod simulate;
pub mod synth;

#[cfg(test)]
pub(crate) mod test_data;

pub use error::{Error, Result};
pub use geometry::Similarity;
pub use meta::FrameMeta;
pub use record::{AlignResult, FrameAlignment, Status};
