//! sunjitter: pointing-jitter monitor for solar telescopes.
//!
//! Three library crates hold the pipeline, each depending only on the one before:
//!
//! - `sunjitter-core`: numerics, no I/O and no process-wide state. Header metadata
//!   ([`header`], [`meta`], [`time`]) → coarse alignment ([`coarse`], [`preprocess`],
//!   [`resample`]) → solar rotation ([`solar_rotation`]) → dense flow ([`flow`]) → sampling
//!   ([`sampling`]) → fit and covariance ([`fit`], [`geometry`]) → one alignment
//!   ([`engine`]). [`synth`] and [`simulate`] make ground truth.
//! - `sunjitter-io`: FITS in ([`fits`]), MCAP out and back ([`sink`], [`records`]), corrected
//!   frames ([`aligned`]), output paths ([`outputs`]).
//! - `sunjitter-runtime`: files found ([`ingest`]) → reference policy ([`reference`](mod@reference)) →
//!   pipeline ([`pipeline`]) → daemon and replay ([`daemon`], [`replay`], [`shard`], [`merge`]) →
//!   [`monitor`], [`products`] → [`inspect`].
//!
//! This crate is the command line ([`cli`]) and the process (`src/main.rs`: the allocator and
//! exit codes).
//! It re-exports the three crates' modules under one name for the binary, tests and examples.

pub use sunjitter_core::{
    blur, coarse, crosscorr, engine, error, fit, flow, geometry, header, meta, preprocess, record,
    resample, sampling, simulate, solar_rotation, stats, synth, text, time,
};
pub use sunjitter_io::{aligned, fits, font, input, outputs, records, self_tests, sink};
pub use sunjitter_runtime::{
    config, daemon, ingest, inspect, limits, merge, monitor, pipeline, ports, products, reference,
    replay, runs, shard,
};

pub mod cli;

pub use error::{Error, Result};
pub use geometry::Similarity;
pub use meta::FrameMeta;
pub use record::{AlignResult, FrameAlignment, Status};
