//! sunjitter: pointing-jitter monitor for solar telescopes.
//!
//! The modules follow the pipeline a frame goes through:
//!
//! FITS ingestion ([`fits`], [`header`]) → header metadata ([`meta`], [`time`]) →
//! coarse alignment ([`coarse`], [`resample`], [`preprocess`]) → dense flow ([`flow`]) →
//! sampling ([`sampling`]) → fit and covariance ([`fit`]) → one alignment ([`engine`]) →
//! reference policy ([`reference`]) → sinks ([`sink`]) → daemon and replay ([`pipeline`],
//! [`daemon`]) → inspection ([`inspect`]). [`synth`] and [`simulate`] make ground truth.
//!
//! Numerics (flow, sampling, fit, resample, preprocess) do no I/O.

pub mod error;
pub mod geometry;
pub mod record;

pub mod fits;
pub mod header;
pub mod meta;
pub mod time;

pub mod coarse;
pub mod preprocess;
pub mod resample;

pub mod crosscorr;
pub mod fit;
pub mod flow;
pub mod sampling;
pub mod stats;

pub mod engine;
pub mod simulate;

pub mod config;
pub mod daemon;
pub mod monitor;
pub mod pipeline;
pub mod reference;
pub mod sink;

pub mod inspect;
pub mod synth;

pub mod commands;

// Frames are tens of MB and every alignment allocates a few dozen such arrays. glibc maps and
// unmaps each one, and on a virtual machine faulting fresh pages in cost as much CPU as the
// numerics (measured: 1.4 s of system time per GB at 4096²). mimalloc keeps them for reuse.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

pub use error::{Error, Result};
pub use geometry::Similarity;
pub use meta::FrameMeta;
pub use record::{AlignResult, FrameAlignment, Status};
