//! The engine's and pipeline's log lines (`tracing`, info and above) handed on to Python's
//! `logging` under the logger `sunjitter`, where users configure them like any library's.
//!
//! Events can come from any thread, attached to the interpreter or not; they are queued here
//! and passed on by the thread that waits for the work ([`crate::wait`]) or by the next call.

use pyo3::prelude::*;
use std::collections::VecDeque;
use std::sync::Mutex;
use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::{Context, Layer};

/// At most this many lines wait to be handed on; older ones are dropped (counted).
const QUEUED: usize = 10_000;

struct Queue {
    lines: VecDeque<(Level, String)>,
    dropped: usize,
}

static QUEUE: Mutex<Queue> = Mutex::new(Queue {
    lines: VecDeque::new(),
    dropped: 0,
});

/// The message and fields of one event, as the command line's log writes them.
struct Line(String);

impl Visit for Line {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        let text = format!("{value:?}");
        let text = sunjitter_core::text::escape(&text);
        if !self.0.is_empty() {
            self.0.push(' ');
        }
        match field.name() {
            "message" => self.0.push_str(&text),
            name => self.0.push_str(&format!("{name}={text}")),
        }
    }
}

struct Queued;

impl<S: Subscriber> Layer<S> for Queued {
    fn on_event(&self, event: &Event<'_>, _ctx: Context<'_, S>) {
        let mut line = Line(String::new());
        event.record(&mut line);
        let mut queue = QUEUE.lock().unwrap_or_else(|p| p.into_inner());
        if queue.lines.len() >= QUEUED {
            queue.lines.pop_front();
            queue.dropped += 1;
        }
        queue.lines.push_back((*event.metadata().level(), line.0));
    }
}

/// Collect events from now on (info and above; `SUNJITTER_LOG` chooses otherwise, as for
/// the command line). Does nothing if another subscriber was installed first.
pub fn install() {
    use tracing_subscriber::layer::SubscriberExt;
    let filter = tracing_subscriber::EnvFilter::try_from_env("SUNJITTER_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let subscriber = tracing_subscriber::registry().with(Queued.with_filter(filter));
    let _ = tracing::subscriber::set_global_default(subscriber);
}

/// Hand the queued lines on to `logging.getLogger("sunjitter")`.
pub fn forward(py: Python<'_>) {
    let (lines, dropped) = {
        let mut queue = QUEUE.lock().unwrap_or_else(|p| p.into_inner());
        let dropped = std::mem::take(&mut queue.dropped);
        (std::mem::take(&mut queue.lines), dropped)
    };
    if lines.is_empty() && dropped == 0 {
        return;
    }
    let Ok(logger) = py
        .import("logging")
        .and_then(|m| m.call_method1("getLogger", ("sunjitter",)))
    else {
        return;
    };
    if dropped > 0 {
        let _ = logger.call_method1("warning", (format!("{dropped} log lines dropped"),));
    }
    for (level, line) in lines {
        let number = match level {
            Level::ERROR => 40,
            Level::WARN => 30,
            Level::INFO => 20,
            _ => 10,
        };
        let _ = logger.call_method1("log", (number, line));
    }
}
