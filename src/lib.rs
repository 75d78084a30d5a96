//! sunjitter: pointing-jitter monitor for solar telescopes.
//!
//! Three library crates hold the pipeline, each depending only on the one before; code names
//! their modules by the crate they live in:
//!
//! - [`sunjitter_core`]: numerics, no I/O and no process-wide state. Header metadata
//!   (`header`, `meta`, `time`) → coarse alignment (`coarse`, `preprocess`, `resample`) → solar
//!   rotation (`solar_rotation`) → dense flow (`flow`) → sampling (`sampling`) → fit and
//!   covariance (`fit`, `geometry`) → one alignment (`engine`). `synth` and `simulate` make
//!   ground truth.
//! - [`sunjitter_io`]: FITS in (`fits`), MCAP out and back (`sink`, `records`), corrected frames
//!   (`aligned`), output paths (`outputs`).
//! - [`sunjitter_runtime`]: files found (`ingest`) → reference policy (`reference`) → pipeline
//!   (`pipeline`) → daemon and replay (`daemon`, `replay`, `shard`, `merge`) → `monitor`,
//!   `products` → `inspect`.
//!
//! This crate is the command line ([`cli`]) and the process (`src/main.rs`: the allocator and
//! exit codes).

pub mod cli;
