//! Jobs: one frame through its channel's reference policy and the engine, on a blocking thread.

use super::frames::FrameItem;
use crate::ports::{Aligner, FrameReader};
use crate::reference::{ChannelState, LoadedFrame, PartnerFrame, StepContext};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};
use sunjitter_core::engine::{AlignOutcome, Image};
use sunjitter_core::meta::FrameMeta;
use sunjitter_core::record::{FrameAlignment, Status};
use sunjitter_core::Result;
use sunjitter_io::fits::FrameSpec;
use sunjitter_io::records::Record;
use sunjitter_io::sink::LogLevel;

/// Reads pixels again, with the `[daemon]` back-off, after a fault of the moment (too many open
/// files, no memory): the front ends retry whole files, but the pixels are read later, by the
/// job, and a frame must not fail for good over such a fault. `retry_attempts` reads at most.
pub(super) struct RetryingReader {
    inner: Arc<dyn FrameReader>,
    attempts: u32,
    first: Duration,
    longest: Duration,
}

impl RetryingReader {
    pub(super) fn new(
        inner: Arc<dyn FrameReader>,
        d: &crate::config::DaemonConfig,
    ) -> RetryingReader {
        RetryingReader {
            inner,
            attempts: d.retry_attempts.max(1),
            first: Duration::from_secs_f64(d.retry_initial_s),
            longest: Duration::from_secs_f64(d.retry_max_s.max(d.retry_initial_s)),
        }
    }
}

impl FrameReader for RetryingReader {
    fn read_meta(&self, path: &Path) -> Result<Vec<FrameMeta>> {
        self.inner.read_meta(path)
    }

    fn read_frame(&self, spec: &FrameSpec) -> Result<Image> {
        let mut delay = self.first;
        for _ in 1..self.attempts {
            match self.inner.read_frame(spec) {
                Err(e) if e.is_transient() => {
                    tracing::warn!("{e}: reading again in {delay:?}");
                    std::thread::sleep(delay);
                    delay = (delay * 2).min(self.longest);
                }
                done => return done,
            }
        }
        self.inner.read_frame(spec)
    }
}

/// The reader, aligner and product writer the jobs use.
#[derive(Clone)]
pub struct JobContext {
    pub reader: Arc<dyn FrameReader>,
    pub aligner: Arc<dyn Aligner>,
    pub products: Option<Arc<crate::products::Products>>,
}

impl StepContext for JobContext {
    fn align(&self, reference: &Image, frame: &Image) -> AlignOutcome {
        self.aligner.align(reference, frame)
    }
    fn align_at(&self, reference: &Image, position: u64, frame: &Image) -> AlignOutcome {
        self.aligner.align_at(reference, position, frame)
    }
    fn usable_as_reference(&self, image: &Image) -> std::result::Result<(), String> {
        self.aligner.usable_as_reference(image)
    }
    fn plate_scale_used(&self, image: &Image) -> Option<[f64; 2]> {
        self.aligner.plate_scale_used(image)
    }
    fn geometry_used(&self, image: &Image) -> Option<sunjitter_core::engine::UsedGeometry> {
        self.aligner.geometry_used(image)
    }
    fn load(&self, spec: &FrameSpec) -> Result<Image> {
        self.reader.read_frame(spec)
    }
}

/// One frame of one channel to process, with the channel's state moved in.
#[derive(Debug)]
pub struct Job {
    pub channel: String,
    pub state: ChannelState,
    pub item: FrameItem,
    pub partner: Option<PartnerFrame>,
    /// Emitted after a later frame of its channel (it arrived too late to reorder).
    pub late: bool,
}

#[derive(Debug)]
pub struct JobDone {
    pub channel: String,
    pub state: ChannelState,
    pub records: Vec<Record>,
    pub partner: Option<PartnerFrame>,
    /// When the frame entered the pipeline (for the ingest lag).
    pub arrived: Instant,
}

/// Run one job (blocking: reads the image, runs the engine).
pub fn run_job(job: Job, ctx: &JobContext) -> JobDone {
    let Job {
        channel,
        mut state,
        item,
        partner,
        late,
    } = job;
    let mut records = Vec::new();
    let mut partner_out = None;
    match ctx.reader.read_frame(&item.spec) {
        Err(e) => records.push(Record::log(
            LogLevel::Error,
            &item.key,
            e.reason(),
            item.obs_time_ns,
        )),
        Ok(image) => {
            let frame = LoadedFrame {
                key: item.key.clone(),
                spec: item.spec.clone(),
                obs_time_ns: item.obs_time_ns,
                image: Arc::new(image),
            };
            // The checksum is one serial pass over the pixels: on a thread of its own while
            // the engine runs, not before it (here, should no thread be had).
            let checksum_of = || sunjitter_core::record::pixel_checksum(frame.image.data.view());
            let (checksum, step) = std::thread::scope(|scope| {
                let checksum = std::thread::Builder::new()
                    .name("checksum".into())
                    .spawn_scoped(scope, checksum_of)
                    .ok();
                let step = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    state.process(&frame, partner.as_ref(), ctx)
                }));
                (checksum.and_then(|c| c.join().ok()), step)
            });
            let checksum = checksum.unwrap_or_else(checksum_of);
            match step {
                Ok(mut out) => {
                    // This frame's own message carries what was read (proves no torn reads).
                    for r in &mut out.records {
                        if let Record::Frame { message, .. } = r {
                            if message.align.frame == item.key {
                                message.pixel_checksum = Some(checksum.clone());
                            }
                        }
                    }
                    let notes: Vec<Record> = out
                        .records
                        .iter()
                        .filter_map(|r| match r {
                            Record::Frame {
                                message,
                                log_time_ns,
                            } => frame_note(message, *log_time_ns),
                            _ => None,
                        })
                        .collect();
                    // Written before the frame's records are logged: a frame logged is a frame
                    // whose product is in place (or whose note says why not).
                    let product_note = ctx
                        .products
                        .as_ref()
                        .and_then(|p| p.write(&item.key, &frame.image, &out, ctx));
                    partner_out = out.partner;
                    records.extend(out.records);
                    records.extend(notes);
                    records.extend(product_note);
                }
                Err(panic) => {
                    let what = sunjitter_core::text::panic_message(panic.as_ref());
                    tracing::error!(frame = %item.key, "internal error while aligning: {what}");
                    records.push(Record::log(
                        LogLevel::Error,
                        &item.key,
                        format!("internal error while aligning: {what}"),
                        item.obs_time_ns,
                    ));
                }
            }
        }
    }
    if late {
        records.push(Record::note(
            &item.key,
            "arrived after later frames of its channel: processed out of time order",
            item.obs_time_ns,
        ));
    }
    JobDone {
        channel,
        state,
        records,
        partner: partner_out,
        arrived: item.arrived,
    }
}

/// The `/log` note for a degraded or failed frame (after its message, never instead of it).
fn frame_note(message: &FrameAlignment, log_time_ns: i64) -> Option<Record> {
    let what = match message.align.status {
        Status::Ok => return None,
        status => status.as_str(),
    };
    Some(Record::note(
        &message.align.frame,
        format!("{what}: {}", message.align.message),
        log_time_ns,
    ))
}
