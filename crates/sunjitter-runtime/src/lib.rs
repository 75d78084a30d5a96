//! sunjitter's runtime: what turns files into logged measurements and logs into answers.
//!
//! Files found ([`ingest`]) → reference policy and restart ([`reference`](mod@reference)) → the pipeline:
//! frames read and measured through [`ports`], scheduler,
//! jobs on the engine, one writer ([`pipeline`]) → the daemon ([`daemon`]), replays
//! ([`replay`]) and sharded ones ([`shard`], [`merge`]) → health, alerts and the live view ([`monitor`]) →
//! corrected frames ([`products`]) → inspection of a log ([`inspect`]). [`config`] is the
//! configuration file, read once.

pub mod config;
pub use config::limits;
pub mod daemon;
/// Fakes with known truths for the pipeline's tests; not part of the product.
#[cfg(any(test, feature = "test-fakes"))]
pub mod fake;
pub mod ingest;
pub mod inspect;
pub mod merge;
pub mod monitor;
pub mod pipeline;
pub mod ports;
pub mod products;
pub mod reference;
pub mod replay;
pub mod runs;
pub mod shard;
