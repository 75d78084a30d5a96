//! Live monitoring for operators (`watch`): the Foxglove live view ([`live`], [`gate`]), alerts
//! ([`alerts`], [`hook`]) and the health status file ([`status`]).
//!
//! ```text
//! pipeline ──> writer thread: MonitoredSink ── MCAP (the record; alerts go to /alert too)
//!                   │ after each logged message, never waiting:
//!                   ├─ alert rules (pure, in place) ── tracing warning
//!                   ├──bounded, drop when full──> live thread ──> Foxglove WebSocket server
//!                   │        clients ──> gate (origin, client cap) ──┘  (refusals ──> /log)
//!                   ├──bounded──> alert command thread (stdin JSON, time limit) ─failures─> /log
//!                   └─ counters (mutex) <── status thread: status.json every few seconds
//! ```
//!
//! Everything that can be slow (clients, the command, the file system of the status) is off
//! the writer thread; a slow or vanished live client loses live messages, never logged ones.

pub mod alerts;
pub mod gate;
pub mod hook;
pub mod live;
pub mod server;
pub mod status;

use crate::config::{HealthConfig, LiveConfig};
use crate::pipeline::Progress;
use alerts::{AlertEngine, AlertEvent};
use status::{ActiveAlert, Status};
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use sunjitter_core::record::Status as FrameStatus;
use sunjitter_core::Result;
use sunjitter_io::records::{mcap_ns, now_ns, McapRecordSink, Record, RecordSink};
use sunjitter_io::sink::McapSink;

impl HealthConfig {
    /// The status file for output directory `out`.
    pub fn status_path(&self, out: &Path) -> PathBuf {
        if self.status_file.is_empty() {
            out.join(status::STATUS_FILE)
        } else {
            PathBuf::from(&self.status_file)
        }
    }
}

/// Counters kept by the writer thread for the status file.
#[derive(Debug, Default)]
pub struct Health {
    pub status: Status,
    pub started: Option<Instant>,
}

type SharedHealth = Arc<Mutex<Health>>;

/// The MCAP sink with the monitors on its output. Lives on the writer thread.
pub struct MonitoredSink {
    mcap: McapSink,
    alerts: AlertEngine,
    /// Ingest lags announced for frames whose message is still to come.
    lags: HashMap<String, f64>,
    live: Option<live::LiveTap>,
    /// Connections the live view refused, to name on `/log`.
    live_notices: Option<gate::Notices>,
    hook: Option<hook::Hook>,
    health: SharedHealth,
    /// Alert events, command failures and live view notices not yet accepted by the MCAP sink.
    unwritten: VecDeque<Extra>,
}

enum Extra {
    Alert(AlertEvent),
    Failure(String),
    Live(String),
}

impl MonitoredSink {
    /// Alert command failures, alert events and live view notices waiting to be logged; on an
    /// error they wait. `all`: also the live view's refusals not yet named (at the end).
    fn write_extras(&mut self, all: bool) -> Result<()> {
        if let Some(hook) = &self.hook {
            self.unwritten
                .extend(hook.failures().into_iter().map(Extra::Failure));
        }
        if let Some(notices) = &self.live_notices {
            self.unwritten
                .extend(notices.take(all).into_iter().map(Extra::Live));
        }
        while let Some(extra) = self.unwritten.front() {
            let publish = mcap_ns(now_ns());
            match extra {
                Extra::Alert(event) => {
                    self.mcap
                        .write_alert(&event.alert, mcap_ns(event.log_time_ns), publish)?;
                }
                Extra::Failure(reason) => {
                    self.mcap.write_log(
                        sunjitter_io::sink::LogLevel::Warning,
                        "alerts.command",
                        &format!("alert command: {reason}"),
                        publish,
                        publish,
                    )?;
                    if let Ok(mut h) = self.health.lock() {
                        h.status.alert_command_failures += 1;
                    }
                }
                Extra::Live(text) => {
                    self.mcap.write_log(
                        sunjitter_io::sink::LogLevel::Warning,
                        "live",
                        text,
                        publish,
                        publish,
                    )?;
                }
            }
            self.unwritten.pop_front();
        }
        Ok(())
    }

    fn raise(&mut self, events: Vec<AlertEvent>) {
        if events.is_empty() {
            return;
        }
        for event in events {
            let a = &event.alert;
            if a.state == "raised" {
                tracing::warn!(channel = a.channel, kind = a.kind, "ALERT {}", a.message);
            } else {
                tracing::warn!(
                    channel = a.channel,
                    kind = a.kind,
                    "alert resolved: {}",
                    a.message
                );
            }
            if let Some(live) = &self.live {
                live.offer(live::LiveMessage::Alert(
                    Box::new(a.clone()),
                    event.log_time_ns,
                ));
            }
            if let Some(hook) = &self.hook {
                match serde_json::to_string(a) {
                    Ok(json) => hook.offer(json + "\n"),
                    Err(e) => tracing::error!("alert command: cannot encode the alert: {e}"),
                }
            }
            if let Ok(mut h) = self.health.lock() {
                if a.state == "raised" {
                    h.status.alerts_raised += 1;
                }
            }
            self.unwritten.push_back(Extra::Alert(event));
        }
        let active = self.alerts.active();
        if let Ok(mut h) = self.health.lock() {
            h.status.active_alerts = active
                .into_iter()
                .map(|(channel, kind)| ActiveAlert { channel, kind })
                .collect();
        }
    }

    fn count(&mut self, record: &Record, lag_s: Option<f64>, wall_ns: i64) {
        let Ok(mut h) = self.health.lock() else {
            return;
        };
        let s = &mut h.status;
        match record {
            Record::Frame {
                message,
                log_time_ns,
            } => {
                let a = &message.align;
                let c = s.channels.entry(message.channel.clone()).or_default();
                c.frames += 1;
                s.frames += 1;
                match a.status {
                    FrameStatus::Ok => {
                        c.ok += 1;
                        s.ok += 1;
                    }
                    FrameStatus::Degraded => {
                        c.degraded += 1;
                        s.degraded += 1;
                    }
                    FrameStatus::Failed => {
                        c.failed += 1;
                        s.failed += 1;
                    }
                }
                if a.status != FrameStatus::Ok {
                    let e = format!("{}: {}", a.frame, a.message);
                    c.last_error = Some(e.clone());
                    s.last_error = Some(e);
                }
                c.last_frame = Some(a.frame.clone());
                c.last_obs_time = Some(sunjitter_core::time::format_iso_utc(*log_time_ns));
                c.last_logged = Some(sunjitter_core::time::format_iso_utc(wall_ns));
                if lag_s.is_some() {
                    c.lag_s = lag_s;
                }
            }
            Record::Log {
                finishes: true,
                file,
                message,
                ..
            } => {
                s.skipped += 1;
                s.last_error = Some(format!("{file}: {message}"));
            }
            _ => {}
        }
    }
}

impl RecordSink for MonitoredSink {
    fn write(&mut self, record: &Record, publish_time_ns: i64) -> Result<()> {
        McapRecordSink::write_to(&mut self.mcap, record, publish_time_ns)?;
        // Logged: from here on nothing may fail the write (it would be retried).
        if let Record::Frame { message, .. } = record {
            tracing::info!("{}", frame_line(message));
        }
        let lag_s = match record {
            Record::Frame { message, .. } => self.lags.remove(&message.align.frame),
            _ => None,
        };
        self.count(record, lag_s, publish_time_ns);
        if let Some(live) = &self.live {
            live.offer(live::LiveMessage::Record(record.clone()));
        }
        if let Record::Frame {
            message,
            log_time_ns,
        } = record
        {
            let events = self
                .alerts
                .frame(message, *log_time_ns, publish_time_ns, lag_s);
            self.raise(events);
        }
        if let Record::Reference {
            change,
            log_time_ns,
        } = record
        {
            let events = self.alerts.reference(change, *log_time_ns);
            self.raise(events);
        }
        if let Err(e) = self.write_extras(false) {
            tracing::warn!("alerts wait to be logged: {e}");
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        let events = self.alerts.tick(now_ns());
        self.raise(events);
        self.write_extras(false)?;
        self.mcap.tick(mcap_ns(now_ns()))
    }

    fn finish(mut self: Box<Self>) -> Result<()> {
        if let Some(hook) = self.hook.take() {
            // The queued alerts run (each within its time limit) so their failures are logged.
            let failures = hook.finish();
            self.unwritten
                .extend(failures.into_iter().map(Extra::Failure));
        }
        self.write_extras(true)?;
        self.mcap.finish()
    }

    fn note_lag(&mut self, frame: &str, lag_s: f64) {
        if self.lags.len() > 10_000 {
            self.lags.clear(); // never grows without bound, whatever happens upstream
        }
        self.lags.insert(frame.to_string(), lag_s);
    }
}

/// The operator's line for one logged frame: channel, file name, status, the shift with its
/// σ against the frame's reference and chained to the channel's first reference, and for a
/// frame that is not `ok` the first of its reasons, e.g.
/// `SJI_1400 f0123.fits ok dx 0.077 ± 0.096 px dy 0.054 ± 0.096 px; chained dx 1.23 ± 0.14 px
/// dy -0.54 ± 0.14 px`. A frame that starts a reference (its own transform the identity)
/// says so instead of its zero shift: `starts a chain` (the channel's first reference, or
/// the first after failures) or `starts a reference` (a new keyframe) with where it sits.
pub fn frame_line(message: &sunjitter_core::record::FrameAlignment) -> String {
    use sunjitter_core::text::value_pm;
    let a = &message.align;
    let spec = sunjitter_io::fits::parse_frame_key(&a.frame);
    let mut file = match spec.path.file_name() {
        Some(name) => sunjitter_core::text::name(name).into_owned(),
        None => sunjitter_core::text::escape(&a.frame).into_owned(),
    };
    if let Some(n) = spec.frame {
        file.push_str(&format!("[{n}]"));
    }
    let status = a.status.as_str();
    let mut line = format!(
        "{} {file} {status}",
        sunjitter_core::text::escape(&message.channel)
    );
    let shift = |dx: f64, sx: Option<f64>, dy: f64, sy: Option<f64>| {
        format!(
            "dx {} dy {}",
            value_pm(dx, sx, " px"),
            value_pm(dy, sy, " px")
        )
    };
    let chained = match (message.chained_dx_px, message.chained_dy_px) {
        (Some(dx), Some(dy)) => Some((
            dx,
            dy,
            shift(
                dx,
                message.sigma_chained_dx_px,
                dy,
                message.sigma_chained_dy_px,
            ),
        )),
        _ => None,
    };
    let starts = message.reference_kind == sunjitter_core::record::ReferenceKind::Itself;
    if a.status != FrameStatus::Failed && starts {
        match &chained {
            Some((dx, dy, _)) if *dx == 0.0 && *dy == 0.0 => line.push_str(" starts a chain"),
            Some((_, _, text)) => line.push_str(&format!(" starts a reference; chained {text}")),
            None => line.push_str(" starts a reference"),
        }
    } else if let (Some(dx), Some(dy)) = (a.dx_px, a.dy_px) {
        line.push(' ');
        line.push_str(&shift(dx, a.sigma_dx_px, dy, a.sigma_dy_px));
        if let Some((_, _, text)) = &chained {
            line.push_str(&format!("; chained {text}"));
        }
    }
    let reason = a.message.split("; ").next().unwrap_or_default().trim();
    if a.status != FrameStatus::Ok && !reason.is_empty() {
        line.push_str(&format!(" ({})", sunjitter_core::text::escape(reason)));
    }
    line
}

/// The monitors of one `watch` run: build with [`Monitor::start`], hand the
/// [`MonitoredSink`] it returns to the pipeline, call [`Monitor::stop`] after it ended.
pub struct Monitor {
    health: SharedHealth,
    live: Option<server::LiveServer>,
    status_path: PathBuf,
    status_stop: Option<std::sync::mpsc::Sender<()>>,
    status_thread: Option<std::thread::JoinHandle<()>>,
    progress: tokio::sync::watch::Receiver<Progress>,
    interval: Duration,
}

/// What [`Monitor::start`] needs.
pub struct MonitorSetup<'a> {
    pub config: &'a crate::config::Config,
    pub watching: &'a Path,
    pub out: &'a Path,
    pub live: Option<std::net::SocketAddr>,
    pub progress: tokio::sync::watch::Receiver<Progress>,
}

impl Monitor {
    /// Start the live server (inside a tokio runtime), the status thread and the alert command.
    pub async fn start(
        setup: MonitorSetup<'_>,
        mcap: McapSink,
    ) -> Result<(Monitor, MonitoredSink)> {
        let config = setup.config;
        let live = match setup.live {
            Some(addr) => {
                let mut topics: Vec<String> = config
                    .channels
                    .keys()
                    .chain(config.alerts.channels.keys())
                    .map(|c| sunjitter_io::sink::jitter_topic(&config.channel_name(c)))
                    .collect();
                topics.sort();
                topics.dedup();
                topics.push(sunjitter_io::sink::LOG_TOPIC.to_string());
                topics.push(sunjitter_io::sink::ALERT_TOPIC.to_string());
                Some(server::LiveServer::start(addr, &topics, &config.live).await?)
            }
            None => None,
        };
        let hook = if config.alerts.command.is_empty() {
            None
        } else {
            let timeout = Duration::from_secs_f64(config.alerts.command_timeout_s);
            Some(
                hook::Hook::start(config.alerts.command.clone(), timeout).map_err(|e| {
                    sunjitter_core::Error::output("alert command", format!("cannot start: {e}"))
                })?,
            )
        };
        let started_ns = now_ns();
        let health = Arc::new(Mutex::new(Health {
            status: Status {
                program: "sunjitter".into(),
                version: env!("CARGO_PKG_VERSION").into(),
                pid: std::process::id(),
                state: "running".into(),
                started: sunjitter_core::time::format_iso_utc(started_ns),
                interval_s: config.health.interval_s,
                watching: setup.watching.display().to_string(),
                out: setup.out.display().to_string(),
                live: live.as_ref().map(|l| format!("ws://{}", l.addr)),
                ..Default::default()
            },
            started: Some(Instant::now()),
        }));
        let sink = MonitoredSink {
            mcap,
            alerts: AlertEngine::new(config.alerts.clone()),
            lags: HashMap::new(),
            live: live.as_ref().map(|l| l.tap()),
            live_notices: live.as_ref().map(|l| l.notices()),
            hook,
            health: health.clone(),
            unwritten: VecDeque::new(),
        };
        let mut monitor = Monitor {
            health,
            live,
            status_path: config.health.status_path(setup.out),
            status_stop: None,
            status_thread: None,
            progress: setup.progress,
            interval: Duration::from_secs_f64(config.health.interval_s),
        };
        monitor.write_status("running")?;
        monitor.spawn_status_thread()?;
        Ok((monitor, sink))
    }

    /// The live view's address (with the port the system chose for port 0).
    pub fn live_addr(&self) -> Option<std::net::SocketAddr> {
        self.live.as_ref().map(|l| l.addr)
    }

    fn spawn_status_thread(&mut self) -> Result<()> {
        let (stop_tx, stop_rx) = std::sync::mpsc::channel::<()>();
        let writer = StatusWriter {
            health: self.health.clone(),
            progress: self.progress.clone(),
            path: self.status_path.clone(),
            dropped: self.live.as_ref().map(|l| l.tap()),
        };
        let interval = self.interval;
        let thread = std::thread::Builder::new()
            .name("sunjitter-status".into())
            .spawn(move || {
                // Rewrite every interval until told to stop (or the monitor is gone).
                while let Err(std::sync::mpsc::RecvTimeoutError::Timeout) =
                    stop_rx.recv_timeout(interval)
                {
                    if let Err(e) = writer.write("running") {
                        tracing::error!("{e}");
                    }
                }
            })
            .map_err(|e| sunjitter_core::Error::output("status thread", e.to_string()))?;
        self.status_stop = Some(stop_tx);
        self.status_thread = Some(thread);
        Ok(())
    }

    fn write_status(&self, state: &str) -> Result<()> {
        StatusWriter {
            health: self.health.clone(),
            progress: self.progress.clone(),
            path: self.status_path.clone(),
            dropped: self.live.as_ref().map(|l| l.tap()),
        }
        .write(state)
    }

    /// After the pipeline has ended: stop the live view and write the final status.
    pub fn stop(mut self) -> Result<()> {
        drop(self.status_stop.take());
        if let Some(t) = self.status_thread.take() {
            let _ = t.join();
        }
        let result = self.write_status("stopped");
        if let Some(live) = self.live.take() {
            live.stop();
        }
        result
    }
}

struct StatusWriter {
    health: SharedHealth,
    progress: tokio::sync::watch::Receiver<Progress>,
    path: PathBuf,
    dropped: Option<live::LiveTap>,
}

impl StatusWriter {
    fn write(&self, state: &str) -> Result<()> {
        let progress = self.progress.borrow().clone();
        let mut status = match self.health.lock() {
            Ok(h) => {
                let mut s = h.status.clone();
                s.uptime_s = h.started.map_or(0.0, |t| t.elapsed().as_secs_f64());
                s
            }
            Err(_) => return Ok(()),
        };
        status.state = state.to_string();
        status.updated = sunjitter_core::time::format_iso_utc(now_ns());
        status.queue_depth = progress.queued;
        status.write_errors = progress.write_errors;
        if progress.write_errors > 0 {
            if let Some(e) = &progress.last_error {
                status.last_error = Some(e.clone());
            }
        }
        for (name, queued) in &progress.queued_per_channel {
            status.channels.entry(name.clone()).or_default().queued = *queued;
        }
        status.live_dropped = self.dropped.as_ref().map_or(0, |t| t.dropped());
        status::write_atomic(&self.path, &status)
    }
}

#[cfg(test)]
mod tests {
    use super::frame_line;
    use sunjitter_core::record::{FrameAlignment, ReferenceKind, Status};

    fn message(key: &str, status: Status, message: &str) -> FrameAlignment {
        let mut align =
            sunjitter_core::engine::AlignOutcome::failed("/in/ref.fits", key, message).result;
        align.status = status;
        if status != Status::Failed {
            (align.dx_px, align.sigma_dx_px) = (Some(0.07701), Some(0.09573));
            (align.dy_px, align.sigma_dy_px) = (Some(-0.0537), Some(0.0957));
        }
        let mut m = FrameAlignment::unchained(
            align,
            "SJI_1400".into(),
            String::new(),
            1,
            ReferenceKind::Keyframe,
        );
        if status != Status::Failed {
            (m.chained_dx_px, m.sigma_chained_dx_px) = (Some(1.2341), Some(0.1402));
            (m.chained_dy_px, m.sigma_chained_dy_px) = (Some(-0.5409), Some(0.1411));
        }
        m
    }

    /// A frame that starts a reference: its own transform the identity with σ 0.
    fn starting(chained: (f64, f64), sigma: f64) -> FrameAlignment {
        let mut m = message("/in/f0050.fits", Status::Ok, "");
        m.reference_kind = ReferenceKind::Itself;
        m.align.reference = m.align.frame.clone();
        (m.align.dx_px, m.align.dy_px) = (Some(0.0), Some(0.0));
        (m.align.sigma_dx_px, m.align.sigma_dy_px) = (Some(0.0), Some(0.0));
        (m.chained_dx_px, m.chained_dy_px) = (Some(chained.0), Some(chained.1));
        (m.sigma_chained_dx_px, m.sigma_chained_dy_px) = (Some(sigma), Some(sigma));
        m
    }

    #[test]
    fn a_frame_line_names_channel_file_status_and_shift_with_sigma_raw_and_chained() {
        assert_eq!(
            frame_line(&message("/in/f0123.fits", Status::Ok, "")),
            "SJI_1400 f0123.fits ok dx 0.077 ± 0.096 px dy -0.054 ± 0.096 px; \
             chained dx 1.23 ± 0.14 px dy -0.54 ± 0.14 px"
        );
        assert_eq!(
            frame_line(&message(
                "/in/cube.fits[7]",
                Status::Degraded,
                "weak common structure (correlation 0.210); low histogram similarity 0.400"
            )),
            "SJI_1400 cube.fits[7] degraded dx 0.077 ± 0.096 px dy -0.054 ± 0.096 px; \
             chained dx 1.23 ± 0.14 px dy -0.54 ± 0.14 px \
             (weak common structure (correlation 0.210))"
        );
        assert_eq!(
            frame_line(&message(
                "/in/f0124.fits",
                Status::Failed,
                "no common structure"
            )),
            "SJI_1400 f0124.fits failed (no common structure)"
        );
    }

    #[test]
    fn a_frame_that_starts_a_reference_says_so_and_where_it_sits() {
        assert_eq!(
            frame_line(&starting((0.0, 0.0), 0.0)),
            "SJI_1400 f0050.fits ok starts a chain"
        );
        assert_eq!(
            frame_line(&starting((1.2341, -0.5409), 0.1402)),
            "SJI_1400 f0050.fits ok starts a reference; \
             chained dx 1.23 ± 0.14 px dy -0.54 ± 0.14 px"
        );
    }

    #[test]
    fn a_frame_line_prints_a_hostile_file_name_escaped() {
        // Frame keys are `text::path` renderings: `\xff` is the byte 0xFF, `\n` a newline.
        let line = frame_line(&message(r"/in/b\xffd\n.fits", Status::Ok, ""));
        assert!(line.starts_with(r"SJI_1400 b\xffd\n.fits ok "), "{line}");
        assert!(!line.chars().any(char::is_control), "{line}");
    }
}
