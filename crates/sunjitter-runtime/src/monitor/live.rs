//! The live view: the logged topics served over the Foxglove WebSocket protocol.
//!
//! The writer thread hands each message it has logged to [`LiveTap::offer`], which never
//! waits: a bounded queue feeds one `sunjitter-live` thread, and when the queue is full the
//! message is dropped for the live view only (counted in the status file). That thread encodes
//! the message exactly as the MCAP sink does (same schema, same JSON, same `log_time`) and logs
//! it to the SDK's server, which keeps its own bounded queue per client and drops the oldest
//! messages of a slow client. The server advertises no capability: clients can subscribe,
//! nothing else (no publishing, services or parameters). Clients reach it through the
//! [`super::gate`], which admits them by origin and number.
//!
//! Each channel keeps its latest message, and a client subscribing to a channel gets it at once
//! (then every later one). Messages go only to the subscribers known when they are logged, under
//! the same lock, so a subscriber gets each message once: none is lost to the time between a
//! channel's advertisement (with its first message) and the client's subscription.

use super::gate::{self, Notices};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{
    ChannelId, Context, PartialMetadata, RawChannel, Schema, SinkId, WebSocketServerHandle,
};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard};
use sunjitter_core::{Error, Result};
use sunjitter_io::records::{mcap_ns, Record};
use sunjitter_io::sink::{self, Alert, LogEntry};

/// What the live thread publishes.
#[derive(Debug)]
pub enum LiveMessage {
    Record(Record),
    Alert(Box<Alert>, i64),
}

/// The writer thread's end: non-blocking.
#[derive(Clone)]
pub struct LiveTap {
    tx: SyncSender<LiveMessage>,
    dropped: Arc<AtomicU64>,
}

impl LiveTap {
    /// A tap on a queue of `capacity` messages, and the queue's receiving end.
    pub fn new(capacity: usize) -> (LiveTap, Receiver<LiveMessage>) {
        let (tx, rx) = sync_channel(capacity.max(1));
        let tap = LiveTap {
            tx,
            dropped: Arc::new(AtomicU64::new(0)),
        };
        (tap, rx)
    }

    /// Queue a message for the live view; drops it when the queue is full.
    pub fn offer(&self, message: LiveMessage) {
        match self.tx.try_send(message) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Messages the live view did not get (queue full or live thread gone).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}

/// The running server, its front door and its publishing thread.
pub struct LiveServer {
    tap: LiveTap,
    handle: Option<WebSocketServerHandle>,
    gate_stop: Option<tokio::sync::oneshot::Sender<()>>,
    notices: Notices,
    thread: Option<std::thread::JoinHandle<()>>,
    pub addr: SocketAddr,
}

/// The live channels: who subscribed to each, and its latest message.
#[derive(Default)]
struct Channels {
    /// Topic → channel (`None`: it could not be created; not retried).
    by_topic: HashMap<String, Option<ChannelId>>,
    by_id: HashMap<ChannelId, Latched>,
}

struct Latched {
    channel: Arc<RawChannel>,
    subscribers: Vec<SinkId>,
    /// Payload and log time.
    latest: Option<(Vec<u8>, u64)>,
}

type SharedChannels = Arc<Mutex<Channels>>;

fn lock(channels: &SharedChannels) -> MutexGuard<'_, Channels> {
    // The data stays consistent whatever panicked while holding it.
    channels.lock().unwrap_or_else(|e| e.into_inner())
}

/// Keeps the subscribers of each channel and hands a new one the latest message; logs
/// subscriptions (read-only server: that is all a client can do).
struct Listener {
    channels: SharedChannels,
}

impl ServerListener for Listener {
    fn on_subscribe(&self, client: Client, channel: ChannelView) {
        tracing::info!(
            client = client.id().to_string(),
            topic = channel.topic(),
            "live: subscribed"
        );
        let Some(sink) = client.sink_id() else {
            return;
        };
        let mut channels = lock(&self.channels);
        if let Some(latched) = channels.by_id.get_mut(&channel.id()) {
            if !latched.subscribers.contains(&sink) {
                latched.subscribers.push(sink);
            }
            if let Some((data, log_time)) = &latched.latest {
                latched.channel.log_with_meta_to_sink(
                    data,
                    PartialMetadata::with_log_time(*log_time),
                    Some(sink),
                );
            }
        }
    }
    fn on_unsubscribe(&self, client: Client, channel: ChannelView) {
        tracing::info!(
            client = client.id().to_string(),
            topic = channel.topic(),
            "live: unsubscribed"
        );
        if let Some(sink) = client.sink_id() {
            if let Some(latched) = lock(&self.channels).by_id.get_mut(&channel.id()) {
                latched.subscribers.retain(|s| *s != sink);
            }
        }
    }
    fn on_client_connect(&self) {
        tracing::info!("live: client connected");
    }
    fn on_client_disconnect(&self) {
        tracing::info!("live: client disconnected");
    }
}

impl LiveServer {
    /// Start serving on `addr` (inside a tokio runtime). `topics` are advertised at once (the
    /// channels named in the configuration, `/log`, `/alert`), so a client can subscribe before
    /// their first message; other topics appear with their first message. Connections are
    /// admitted as `config` says (origins, number of clients); `config.queue` is the capacity
    /// of the writer → live queue.
    pub async fn start(
        addr: SocketAddr,
        topics: &[String],
        config: &super::LiveConfig,
    ) -> Result<LiveServer> {
        if !addr.ip().is_loopback() {
            tracing::warn!(
                %addr,
                "live view on a non-loopback address: anyone who can reach it can read the data"
            );
        }
        let unavailable = |e: &dyn std::fmt::Display| {
            Error::Usage(format!("--live {addr}: cannot serve the live view: {e}"))
        };
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|e| unavailable(&e))?;
        let addr = listener.local_addr().map_err(|e| unavailable(&e))?;
        let context = Context::new();
        let channels = SharedChannels::default();
        let private = gate::private_loopback();
        let handle = context
            .websocket_server()
            .name(format!("sunjitter {}", env!("CARGO_PKG_VERSION")))
            .bind(private.to_string(), 0)
            .listener(Arc::new(Listener {
                channels: channels.clone(),
            }))
            .start()
            .await
            .map_err(|e| unavailable(&e))?;
        let notices = Notices::default();
        let admission = gate::Admission {
            allowed_origins: config.allowed_origins.clone(),
            max_clients: config.max_clients,
        };
        let backend = SocketAddr::new(private, handle.port());
        let (gate_stop, stop) = tokio::sync::oneshot::channel();
        tokio::spawn(gate::Gate::new(admission, backend, notices.clone()).run(listener, stop));
        let publisher = Publisher { context, channels };
        for topic in topics {
            publisher.channel(&mut lock(&publisher.channels), topic);
        }
        let (tap, rx) = LiveTap::new(config.queue);
        let thread = std::thread::Builder::new()
            .name("sunjitter-live".into())
            .spawn(move || publisher.run(rx))
            .map_err(|e| Error::output("live view", e.to_string()))?;
        tracing::info!(%addr, "live view: Foxglove WebSocket server listening (ws://{addr})");
        Ok(LiveServer {
            tap,
            handle: Some(handle),
            gate_stop: Some(gate_stop),
            notices,
            thread: Some(thread),
            addr,
        })
    }

    pub fn tap(&self) -> LiveTap {
        self.tap.clone()
    }

    /// Refused connections to name on `/log`.
    pub fn notices(&self) -> Notices {
        self.notices.clone()
    }

    /// Stop serving: close client connections without waiting for slow ones.
    pub fn stop(mut self) {
        if let Some(stop) = self.gate_stop.take() {
            let _ = stop.send(());
        }
        if let Some(handle) = self.handle.take() {
            handle.stop().detach_all();
        }
        // The thread ends when every tap is gone (the sink drops its copy when it finishes).
        drop(self.tap);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

struct Publisher {
    context: Arc<Context>,
    channels: SharedChannels,
}

impl Publisher {
    fn run(self, rx: Receiver<LiveMessage>) {
        while let Ok(message) = rx.recv() {
            let Some((topic, data, log_time_ns)) = encode(&message) else {
                continue;
            };
            let mut channels = lock(&self.channels);
            let Some(id) = self.channel(&mut channels, &topic) else {
                continue;
            };
            if let Some(latched) = channels.by_id.get_mut(&id) {
                for sink in &latched.subscribers {
                    latched.channel.log_with_meta_to_sink(
                        &data,
                        PartialMetadata::with_log_time(log_time_ns),
                        Some(*sink),
                    );
                }
                latched.latest = Some((data, log_time_ns));
            }
        }
    }

    /// The channel of `topic`, created (and advertised) on first use. Created under the lock,
    /// so a subscription to it waits until it is known here.
    fn channel(&self, channels: &mut Channels, topic: &str) -> Option<ChannelId> {
        if let Some(id) = channels.by_topic.get(topic) {
            return *id;
        }
        let (name, schema) = schema_of(topic);
        let bytes = serde_json::to_vec(&schema()).unwrap_or_default();
        let built = self
            .context
            .channel_builder(topic)
            .message_encoding(sink::MESSAGE_ENCODING)
            .schema(Schema::new(name, sink::SCHEMA_ENCODING, bytes))
            .build_raw();
        let id = match built {
            Ok(channel) => {
                let id = channel.id();
                channels.by_id.insert(
                    id,
                    Latched {
                        channel,
                        subscribers: Vec::new(),
                        latest: None,
                    },
                );
                Some(id)
            }
            Err(e) => {
                tracing::error!(topic, "live view: cannot create the channel: {e}");
                None
            }
        };
        channels.by_topic.insert(topic.to_string(), id);
        id
    }
}

/// Schema of a topic, as the MCAP sink writes it.
fn schema_of(topic: &str) -> (&'static str, fn() -> serde_json::Value) {
    if topic.starts_with("/jitter/") {
        (sink::FRAME_ALIGNMENT_SCHEMA, sink::frame_alignment_schema)
    } else if topic.starts_with("/reference/") {
        (sink::REFERENCE_CHANGE_SCHEMA, sink::reference_change_schema)
    } else if topic == sink::ALERT_TOPIC {
        (sink::ALERT_SCHEMA, sink::alert_schema)
    } else {
        (sink::LOG_SCHEMA, sink::log_schema)
    }
}

/// Topic, JSON payload and `log_time` of a message: the bytes the MCAP sink writes.
pub fn encode(message: &LiveMessage) -> Option<(String, Vec<u8>, u64)> {
    let encoded = match message {
        LiveMessage::Alert(alert, log_time_ns) => (
            sink::ALERT_TOPIC.to_string(),
            serde_json::to_vec(alert),
            mcap_ns(*log_time_ns),
        ),
        LiveMessage::Record(record) => {
            let log_time = mcap_ns(record.log_time_ns());
            let data = match record {
                Record::Frame { message, .. } => serde_json::to_vec(message.as_ref()),
                Record::Reference { change, .. } => serde_json::to_vec(change.as_ref()),
                Record::Log {
                    level,
                    file,
                    message,
                    ..
                } => serde_json::to_vec(&LogEntry {
                    timestamp: sink::FoxgloveTime::from_ns(log_time),
                    level: *level,
                    message: message.clone(),
                    name: "sunjitter".to_string(),
                    file: file.clone(),
                    line: 0,
                }),
            };
            (record.topic(), data, log_time)
        }
    };
    match encoded {
        (topic, Ok(data), t) => Some((topic, data, t)),
        (topic, Err(e), _) => {
            tracing::error!(topic, "live view: cannot encode: {e}");
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sunjitter_io::sink::LogLevel;

    #[test]
    fn a_full_live_queue_drops_for_the_live_view_and_never_waits() {
        // Nobody reads the queue (a stalled live thread): offers return at once, extras drop.
        let (tap, rx) = LiveTap::new(2);
        for i in 0..5 {
            let r = Record::log(LogLevel::Warning, &format!("f{i}.fits"), "note", i);
            tap.offer(LiveMessage::Record(r));
        }
        assert_eq!(tap.dropped(), 3);
        let kept: Vec<i64> = rx
            .try_iter()
            .map(|m| match m {
                LiveMessage::Record(r) => r.log_time_ns(),
                LiveMessage::Alert(_, t) => t,
            })
            .collect();
        assert_eq!(kept, vec![0, 1], "the oldest queued messages are kept");
    }

    #[test]
    fn log_entries_are_encoded_as_foxglove_log_at_their_log_time() {
        let r = Record::log(
            LogLevel::Error,
            "/data/a.fits",
            "not a FITS file",
            1_500_000_000,
        );
        let (topic, data, t) = encode(&LiveMessage::Record(r)).unwrap();
        assert_eq!((topic.as_str(), t), ("/log", 1_500_000_000));
        let v: serde_json::Value = serde_json::from_slice(&data).unwrap();
        // foxglove.Log: ERROR is level 4; timestamp split into sec / nsec.
        assert_eq!(v["level"], 4);
        assert_eq!(
            v["timestamp"],
            serde_json::json!({"sec": 1, "nsec": 500_000_000})
        );
        assert_eq!(v["file"], "/data/a.fits");
    }
}
