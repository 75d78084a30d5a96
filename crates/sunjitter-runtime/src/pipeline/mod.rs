//! The one pipeline both front ends feed: frame → channel → reference policy → engine → sink.
//!
//! ```text
//! front end (watch: watcher + readers; replay: file list)
//!   └─ bounded queue of Input ──> scheduler task: per-channel reorder buffers, partner choice
//!        └─ blocking jobs (≤ workers, ≤ 1 per channel): read image, policy step, engine
//!             └─ bounded queue of records ──> ONE writer thread: RecordSink (MCAP)
//! ```
//!
//! Determinism: per channel, frames are processed one at a time in (observation time, key)
//! order; a frame's messages depend only on its channel's earlier frames (and for
//! `channel:NAME` on the partner frame, chosen once the partner has been processed past the
//! frame's time). So `replay` of a set of frames writes what the daemon wrote for them,
//! apart from `publish_time` and the engine's own `elapsed_ms`.
//!
//! Submodules follow the diagram: `frames` enter, `scheduler` orders them, `job` runs
//! one, `writer` logs, `run` drives the lot; `replay` and the daemon are front ends.

mod aligner;
mod frames;
mod job;
mod output;
mod progress;
mod replay;
mod run;
mod scheduler;
mod time;
mod writer;

pub use aligner::{EngineAligner, FitsReader};
pub use frames::{
    file_stamp, inspect_file, unreadable_record, waiting_record, FileOutcome, FileStamp, FrameItem,
    Input, Unready,
};
pub use job::{run_job, Job, JobContext, JobDone};
pub use output::{open_output, read_history};
pub use progress::Progress;
pub use replay::{replay_inputs, run_replay};
pub use run::{run_pipeline, RunParts};
pub use scheduler::{Action, Scheduler, SchedulerSettings};
pub use time::{iso8601_utc, parse_iso8601_utc};
pub use writer::{spawn_writer, WriterMsg};
