//! The live view: the logged topics served over the Foxglove WebSocket protocol.
//!
//! The writer thread hands each message it has logged to [`LiveTap::offer`], which never
//! waits: a bounded queue feeds one `sunjitter-live` thread, and when the queue is full the
//! message is dropped for the live view only (counted in the status file). That thread encodes
//! the message exactly as the MCAP sink does (same schema, same JSON, same `log_time`) and
//! hands it to the [`Hub`], which queues it for each subscribed client in a bounded queue of
//! its own: a slow client loses live messages, nothing else waits for it.
//!
//! The server is read-only and small: it advertises no capability, so clients can subscribe
//! and nothing else (no publishing, services or parameters). One listening socket, the one
//! the operator named: connections are admitted there by [`super::gate`] (origin, number of
//! clients), the WebSocket handshake is answered there (subprotocols [`SUBPROTOCOLS`]), and
//! every client message is bounded ([`MAX_CLIENT_MESSAGE`]), fragments included.
//!
//! Each channel keeps its latest message, and a client subscribing to a channel gets it at once
//! (then every later one). Messages go only to the subscribers known when they are logged,
//! under the hub's lock, so a subscriber gets each message once: none is lost to the time
//! between a channel's advertisement (with its first message) and the client's subscription.

use futures_util::{SinkExt, StreamExt};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex, MutexGuard};
use sunjitter_io::records::{mcap_ns, Record};
use sunjitter_io::sink::{self, Alert, LogEntry};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, Role, WebSocketConfig};
use tokio_tungstenite::tungstenite::Message;

/// WebSocket subprotocols served, in order of preference: the Foxglove SDK's name of the
/// protocol and the classic one (the same protocol on the wire for what this server does:
/// `serverInfo`, `advertise`, `subscribe`, `unsubscribe`, message data).
pub const SUBPROTOCOLS: [&str; 2] = ["foxglove.sdk.v1", "foxglove.websocket.v1"];

/// Longest message (and frame) a client may send; its messages are small JSON requests. A
/// longer one, however fragmented, closes the connection (1009) before it is held whole.
pub const MAX_CLIENT_MESSAGE: usize = 64 * 1024;

/// Messages queued for one client at most; past that, its live messages are dropped.
const CLIENT_QUEUE: usize = 1024;

/// Subscriptions one client may hold at once.
const MAX_SUBSCRIPTIONS: usize = 4096;

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

// ---------------------------------------------------------------------------------------------
// The hub: channels, clients, subscriptions

/// What goes to one client.
#[derive(Debug, Clone)]
enum Outgoing {
    Text(String),
    Data {
        subscription: u32,
        log_time_ns: u64,
        payload: Arc<Vec<u8>>,
    },
}

impl Outgoing {
    /// The WebSocket message: JSON text, or the binary message-data frame (opcode 1,
    /// subscription id u32 LE, log time u64 LE ns, payload).
    fn message(self) -> Message {
        match self {
            Outgoing::Text(text) => Message::text(text),
            Outgoing::Data {
                subscription,
                log_time_ns,
                payload,
            } => {
                let mut bytes = Vec::with_capacity(13 + payload.len());
                bytes.push(1u8);
                bytes.extend_from_slice(&subscription.to_le_bytes());
                bytes.extend_from_slice(&log_time_ns.to_le_bytes());
                bytes.extend_from_slice(&payload);
                Message::binary(bytes)
            }
        }
    }
}

struct Channel {
    id: u32,
    topic: String,
    schema_name: &'static str,
    schema: String,
    /// Payload and log time.
    latest: Option<(Arc<Vec<u8>>, u64)>,
}

impl Channel {
    fn advertisement(&self) -> serde_json::Value {
        serde_json::json!({
            "id": self.id,
            "topic": self.topic,
            "encoding": sink::MESSAGE_ENCODING,
            "schemaName": self.schema_name,
            "schema": self.schema,
            "schemaEncoding": sink::SCHEMA_ENCODING,
        })
    }
}

struct ClientEntry {
    tx: tokio::sync::mpsc::Sender<Outgoing>,
    /// Subscription id → channel id.
    subscriptions: HashMap<u32, u32>,
}

#[derive(Default)]
struct HubState {
    channels: Vec<Channel>,
    by_topic: HashMap<String, u32>,
    clients: HashMap<u64, ClientEntry>,
    next_client: u64,
}

/// Channels and clients, under one lock.
pub struct Hub {
    state: Mutex<HubState>,
    server_info: String,
}

fn advertise(channels: &[&Channel]) -> Outgoing {
    let list: Vec<serde_json::Value> = channels.iter().map(|c| c.advertisement()).collect();
    Outgoing::Text(serde_json::json!({"op": "advertise", "channels": list}).to_string())
}

fn status(level: u8, message: &str) -> Outgoing {
    Outgoing::Text(
        serde_json::json!({"op": "status", "level": level, "message": message}).to_string(),
    )
}

impl Hub {
    pub(super) fn new() -> Hub {
        let session = sunjitter_io::records::now_ns().to_string();
        let server_info = serde_json::json!({
            "op": "serverInfo",
            "name": format!("sunjitter {}", env!("CARGO_PKG_VERSION")),
            "capabilities": [],
            "supportedEncodings": [],
            "metadata": {},
            "sessionId": session,
        })
        .to_string();
        Hub {
            state: Mutex::new(HubState::default()),
            server_info,
        }
    }

    fn lock(&self) -> MutexGuard<'_, HubState> {
        // The data stays consistent whatever panicked while holding it.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queue a control message for a client; a client too far behind to take one is dropped
    /// (its connection closes).
    fn send_control(state: &mut HubState, client: u64, message: Outgoing) {
        let full = state
            .clients
            .get(&client)
            .is_some_and(|c| c.tx.try_send(message).is_err());
        if full {
            state.clients.remove(&client);
        }
    }

    /// The channel of `topic`, created (and advertised to every client) on first use.
    /// Channels for `topics`, advertised before their first message.
    pub(super) fn open_channels(&self, topics: &[String]) {
        let mut state = self.lock();
        for topic in topics {
            self.channel(&mut state, topic);
        }
    }

    fn channel(&self, state: &mut HubState, topic: &str) -> u32 {
        if let Some(id) = state.by_topic.get(topic) {
            return *id;
        }
        let id = state.channels.len() as u32 + 1;
        let (schema_name, schema) = schema_of(topic);
        let channel = Channel {
            id,
            topic: topic.to_string(),
            schema_name,
            schema: schema().to_string(),
            latest: None,
        };
        let ad = advertise(&[&channel]);
        state.channels.push(channel);
        state.by_topic.insert(topic.to_string(), id);
        let clients: Vec<u64> = state.clients.keys().copied().collect();
        for c in clients {
            Hub::send_control(state, c, ad.clone());
        }
        id
    }

    /// Log a message on `topic`: kept as the channel's latest, queued for its subscribers.
    fn publish(&self, topic: &str, payload: Vec<u8>, log_time_ns: u64) {
        let mut state = self.lock();
        let id = self.channel(&mut state, topic);
        let payload = Arc::new(payload);
        for client in state.clients.values() {
            for (&subscription, _) in client.subscriptions.iter().filter(|(_, c)| **c == id) {
                // A full queue: this client loses the message (live only).
                let _ = client.tx.try_send(Outgoing::Data {
                    subscription,
                    log_time_ns,
                    payload: payload.clone(),
                });
            }
        }
        if let Some(channel) = state.channels.get_mut(id as usize - 1) {
            channel.latest = Some((payload, log_time_ns));
        }
    }

    /// A new client: its id and queue, already holding `serverInfo` and the advertisement of
    /// every channel there is.
    fn connect(&self) -> (u64, tokio::sync::mpsc::Receiver<Outgoing>) {
        let (tx, rx) = tokio::sync::mpsc::channel(CLIENT_QUEUE);
        let mut state = self.lock();
        state.next_client += 1;
        let id = state.next_client;
        let _ = tx.try_send(Outgoing::Text(self.server_info.clone()));
        if !state.channels.is_empty() {
            let all: Vec<&Channel> = state.channels.iter().collect();
            let _ = tx.try_send(advertise(&all));
        }
        state.clients.insert(
            id,
            ClientEntry {
                tx,
                subscriptions: HashMap::new(),
            },
        );
        (id, rx)
    }

    fn disconnect(&self, client: u64) {
        self.lock().clients.remove(&client);
    }

    /// Every client's queue closed: their connections end.
    pub(super) fn disconnect_all(&self) {
        self.lock().clients.clear();
    }

    /// A text message from `client`: `subscribe` and `unsubscribe` are served; anything else
    /// is answered with a status message (this server offers nothing more).
    fn request(&self, client: u64, text: &str) {
        let request: serde_json::Value = match serde_json::from_str(text) {
            Ok(v) => v,
            Err(_) => {
                let mut state = self.lock();
                Hub::send_control(&mut state, client, status(2, "not a JSON request"));
                return;
            }
        };
        let mut state = self.lock();
        match request["op"].as_str() {
            Some("subscribe") => {
                let wanted = request["subscriptions"]
                    .as_array()
                    .cloned()
                    .unwrap_or_default();
                for s in wanted {
                    let (Some(sub), Some(chan)) = (s["id"].as_u64(), s["channelId"].as_u64())
                    else {
                        continue;
                    };
                    let (Ok(sub), Ok(chan)) = (u32::try_from(sub), u32::try_from(chan)) else {
                        continue;
                    };
                    let Some(channel) = state.channels.get(chan.wrapping_sub(1) as usize) else {
                        Hub::send_control(&mut state, client, status(1, "no such channel"));
                        continue;
                    };
                    let topic = channel.topic.clone();
                    let latest = channel.latest.clone();
                    let Some(entry) = state.clients.get_mut(&client) else {
                        return;
                    };
                    if entry.subscriptions.len() >= MAX_SUBSCRIPTIONS
                        || entry.subscriptions.contains_key(&sub)
                    {
                        Hub::send_control(
                            &mut state,
                            client,
                            status(1, "subscription id in use, or too many subscriptions"),
                        );
                        continue;
                    }
                    entry.subscriptions.insert(sub, chan);
                    tracing::info!(client = client.to_string(), topic, "live: subscribed");
                    if let Some((payload, log_time_ns)) = latest {
                        let _ = entry.tx.try_send(Outgoing::Data {
                            subscription: sub,
                            log_time_ns,
                            payload,
                        });
                    }
                }
            }
            Some("unsubscribe") => {
                let ids = request["subscriptionIds"]
                    .as_array()
                    .cloned()
                    .unwrap_or_default();
                let mut topics = Vec::new();
                if let Some(entry) = state.clients.get_mut(&client) {
                    for id in ids.iter().filter_map(|v| v.as_u64()) {
                        if let Some(chan) = u32::try_from(id)
                            .ok()
                            .and_then(|id| entry.subscriptions.remove(&id))
                        {
                            topics.push(chan);
                        }
                    }
                }
                for chan in topics {
                    if let Some(c) = state.channels.get(chan as usize - 1) {
                        tracing::info!(
                            client = client.to_string(),
                            topic = c.topic.as_str(),
                            "live: unsubscribed"
                        );
                    }
                }
            }
            _ => Hub::send_control(
                &mut state,
                client,
                status(
                    1,
                    "read-only server: only subscribe and unsubscribe are served",
                ),
            ),
        }
    }
}

/// Serve one admitted client whose handshake (with `subprotocol`) has been answered: the
/// hub's messages out, its requests in, until it leaves, is dropped or the server stops.
/// `read_ahead` is whatever the client sent after its handshake.
pub async fn serve_client(
    hub: Arc<Hub>,
    stream: tokio::net::TcpStream,
    read_ahead: Vec<u8>,
    peer: SocketAddr,
) {
    let config = WebSocketConfig::default()
        .read_buffer_size(16 * 1024)
        .write_buffer_size(64 * 1024)
        .max_write_buffer_size(1024 * 1024)
        .max_message_size(Some(MAX_CLIENT_MESSAGE))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE));
    let ws = tokio_tungstenite::WebSocketStream::from_partially_read(
        stream,
        read_ahead,
        Role::Server,
        Some(config),
    )
    .await;
    let (mut write, mut read) = ws.split();
    let (id, mut queue) = hub.connect();
    tracing::info!(client = id.to_string(), "live: client connected");
    tracing::debug!(client = id.to_string(), %peer, "live: client's address");
    loop {
        tokio::select! {
            out = queue.recv() => match out {
                Some(message) => {
                    if write.send(message.message()).await.is_err() {
                        break;
                    }
                }
                None => break,
            },
            incoming = read.next() => match incoming {
                Some(Ok(Message::Text(text))) => hub.request(id, text.as_str()),
                Some(Ok(Message::Close(_))) | None => break,
                Some(Err(e)) => {
                    tracing::info!(client = id.to_string(), "live: connection closed: {e}");
                    if let tokio_tungstenite::tungstenite::Error::Capacity(_) = e {
                        // RFC 6455 §7.4.1: 1009, a message too big to process.
                        let frame = CloseFrame {
                            code: CloseCode::Size,
                            reason: "message too big".into(),
                        };
                        let _ = tokio::time::timeout(
                            std::time::Duration::from_secs(1),
                            write.send(Message::Close(Some(frame))),
                        )
                        .await;
                    }
                    break;
                }
                // Pings are answered by the WebSocket layer; binary frames are not requests.
                Some(Ok(_)) => {}
            },
        }
    }
    hub.disconnect(id);
    let _ = tokio::time::timeout(std::time::Duration::from_secs(1), write.close()).await;
    tracing::info!(client = id.to_string(), "live: client disconnected");
}

pub(super) fn publish_all(hub: &Hub, rx: Receiver<LiveMessage>) {
    while let Ok(message) = rx.recv() {
        if let Some((topic, data, log_time_ns)) = encode(&message) {
            hub.publish(&topic, data, log_time_ns);
        }
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
