//! The live view's front door, on the one address it listens on: each connection's WebSocket
//! handshake is read here (at most 16 KiB, within 10 s), checked (its `Origin`, the number of
//! clients, a WebSocket upgrade offering one of [`super::live::SUBPROTOCOLS`]) and answered,
//! and the connection is handed to [`super::live::serve_client`]. A refused handshake gets an
//! HTTP error status and one line saying why.
//!
//! Browsers send `Origin` with every WebSocket handshake and let any page open one to any
//! address, so without the check any web page in the operator's browser could read the live
//! data. Clients outside browsers (the Foxglove desktop app, scripts) send no `Origin`.

use super::live::{serve_client, Hub, SUBPROTOCOLS};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

/// Longest handshake read; a longer one is refused.
const MAX_HEAD: usize = 16 * 1024;
/// A connection must have sent its handshake by then (it holds a client slot meanwhile).
const HEAD_TIMEOUT: Duration = Duration::from_secs(10);
/// Connections over the limit answered at once at most; beyond that they are just closed.
const REFUSING_AT_ONCE: usize = 16;
/// Each kind of refusal is named on `/log` at most once in this period; the rest are counted.
const NOTICE_PERIOD: Duration = Duration::from_secs(60);

/// Who may connect.
#[derive(Debug, Clone)]
pub struct Admission {
    /// Origins allowed besides none (compared without case and trailing `/`).
    pub allowed_origins: Vec<String>,
    /// Connections (clients, and handshakes being read) at once at most.
    pub max_clients: usize,
}

/// Refusals to name on `/log`, at most one per kind and period.
#[derive(Clone, Default)]
pub struct Notices(Arc<Mutex<NoticeState>>);

#[derive(Default)]
struct NoticeState {
    full: Limiter,
    origin: Limiter,
    pending: Vec<String>,
}

#[derive(Default)]
struct Limiter {
    last: Option<Instant>,
    suppressed: u64,
    reason: String,
}

impl Limiter {
    fn event(&mut self, now: Instant, text: String, reason: String, out: &mut Vec<String>) {
        self.summary(now, false, out);
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < NOTICE_PERIOD)
        {
            self.suppressed += 1;
            return;
        }
        tracing::warn!("{text}");
        out.push(text);
        self.last = Some(now);
        self.reason = reason;
    }

    fn summary(&mut self, now: Instant, all: bool, out: &mut Vec<String>) {
        let Some(last) = self.last else { return };
        if self.suppressed == 0 || !(all || now.duration_since(last) >= NOTICE_PERIOD) {
            return;
        }
        let text = format!(
            "live view: {} more connections refused in {:.0} s: {}",
            self.suppressed,
            now.duration_since(last).as_secs_f64(),
            self.reason
        );
        tracing::warn!("{text}");
        out.push(text);
        self.suppressed = 0;
        self.last = Some(now);
    }
}

impl Notices {
    /// Texts not yet taken; with `all`, also the count of refusals not yet named.
    pub fn take(&self, all: bool) -> Vec<String> {
        let mut s = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        let mut out = std::mem::take(&mut s.pending);
        s.full.summary(now, all, &mut out);
        s.origin.summary(now, all, &mut out);
        out
    }

    fn refused_full(&self, peer: SocketAddr, max: usize) {
        let reason = format!("live.max_clients = {max} clients connected");
        let text = format!("live view: connection from {peer} refused: {reason}");
        let mut s = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let s = &mut *s;
        s.full.event(Instant::now(), text, reason, &mut s.pending);
    }

    fn refused_origin(&self, peer: SocketAddr, origin: &str) {
        let reason = "origin not in live.allowed_origins".to_string();
        let text =
            format!("live view: connection from {peer} with origin {origin:?} refused: {reason}");
        let mut s = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let s = &mut *s;
        s.origin.event(Instant::now(), text, reason, &mut s.pending);
    }
}

/// A place in a bounded count, given back when dropped.
struct Slot(Arc<AtomicUsize>);

impl Slot {
    fn take(count: &Arc<AtomicUsize>, max: usize) -> Option<Slot> {
        count
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| Slot(count.clone()))
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The accepting end.
pub struct Gate {
    admission: Admission,
    open: Arc<AtomicUsize>,
    refusing: Arc<AtomicUsize>,
    notices: Notices,
    hub: Arc<Hub>,
}

impl Gate {
    pub fn new(admission: Admission, hub: Arc<Hub>, notices: Notices) -> Arc<Gate> {
        Arc::new(Gate {
            admission,
            open: Arc::default(),
            refusing: Arc::default(),
            notices,
            hub,
        })
    }

    /// Accept connections on `listener` until `stop` fires (or its sender is gone).
    pub async fn run(
        self: Arc<Self>,
        listener: TcpListener,
        stop: tokio::sync::oneshot::Receiver<()>,
    ) {
        tokio::pin!(stop);
        // Every connection's task: all ended when the gate stops, slow clients included.
        let mut connections = tokio::task::JoinSet::new();
        loop {
            // Reap the finished ones as they come, so the set stays as small as the clients.
            while connections.try_join_next().is_some() {}
            tokio::select! {
                _ = &mut stop => {
                    connections.abort_all();
                    return;
                }
                accepted = listener.accept() => match accepted {
                    Ok((stream, peer)) => self.clone().admit(stream, peer, &mut connections),
                    Err(e) => {
                        // Out of file descriptors, say: wait rather than spin.
                        tracing::warn!("live view: cannot accept a connection: {e}");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                },
            }
        }
    }

    fn admit(
        self: Arc<Self>,
        stream: TcpStream,
        peer: SocketAddr,
        connections: &mut tokio::task::JoinSet<()>,
    ) {
        match Slot::take(&self.open, self.admission.max_clients) {
            Some(slot) => {
                connections.spawn(self.serve(stream, peer, slot));
            }
            None => {
                self.notices.refused_full(peer, self.admission.max_clients);
                // Answered (the client learns why) while few are; else just closed.
                if let Some(slot) = Slot::take(&self.refusing, REFUSING_AT_ONCE) {
                    connections.spawn(async move {
                        let _slot = slot;
                        let mut stream = stream;
                        if let Ok(_head) = read_head(&mut stream).await {
                            respond(
                                &mut stream,
                                503,
                                "Service Unavailable",
                                "too many live clients",
                            )
                            .await;
                        }
                    });
                }
            }
        }
    }

    async fn serve(self: Arc<Self>, mut stream: TcpStream, peer: SocketAddr, _slot: Slot) {
        let head = match read_head(&mut stream).await {
            Ok(head) => head,
            Err(HeadError::Gone) => return,
            Err(HeadError::Invalid) => {
                respond(&mut stream, 400, "Bad Request", "not an HTTP request").await;
                return;
            }
        };
        if !origin_allowed(&head.origins, &self.admission.allowed_origins) {
            self.notices.refused_origin(peer, &head.origins.join(", "));
            respond(&mut stream, 403, "Forbidden", "origin not allowed").await;
            return;
        }
        let accepted = match accept_upgrade(&head) {
            Ok(accepted) => accepted,
            Err((code, status, why)) => {
                tracing::info!(%peer, "live view: handshake refused: {why}");
                respond(&mut stream, code, status, &why).await;
                return;
            }
        };
        let response = format!(
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Accept: {}\r\nSec-WebSocket-Protocol: {}\r\n\r\n",
            accepted.key, accepted.subprotocol
        );
        if stream.write_all(response.as_bytes()).await.is_err() {
            return;
        }
        // Live messages are small and should go out at once.
        let _ = stream.set_nodelay(true);
        let read_ahead = head.bytes[head.len..].to_vec();
        serve_client(self.hub.clone(), stream, read_ahead, peer).await;
    }
}

/// What an accepted upgrade answers: the `Sec-WebSocket-Accept` value and the subprotocol.
struct Accepted {
    key: String,
    subprotocol: &'static str,
}

/// Check a handshake as RFC 6455 §4.2.1 asks (GET, `Upgrade: websocket`, `Connection:
/// Upgrade`, version 13, a key) and choose the subprotocol; else the HTTP status and why.
fn accept_upgrade(head: &Head) -> Result<Accepted, (u16, &'static str, String)> {
    let has_token = |name: &str, token: &str| {
        head.headers(name)
            .flat_map(|v| v.split(','))
            .any(|t| t.trim().eq_ignore_ascii_case(token))
    };
    if head.method != "GET"
        || !has_token("upgrade", "websocket")
        || !has_token("connection", "upgrade")
    {
        return Err((
            400,
            "Bad Request",
            "this is a Foxglove WebSocket server (ws://): connect with Foxglove".into(),
        ));
    }
    if !head
        .headers("sec-websocket-version")
        .any(|v| v.trim() == "13")
    {
        return Err((426, "Upgrade Required", "WebSocket version 13 only".into()));
    }
    let Some(key) = head.headers("sec-websocket-key").next().map(str::trim) else {
        return Err((400, "Bad Request", "no Sec-WebSocket-Key".into()));
    };
    let offered: Vec<&str> = head
        .headers("sec-websocket-protocol")
        .flat_map(|v| v.split(','))
        .map(str::trim)
        .collect();
    let Some(subprotocol) = SUBPROTOCOLS.into_iter().find(|p| offered.contains(p)) else {
        return Err((
            400,
            "Bad Request",
            format!(
                "no supported subprotocol offered ({}); this server speaks {}",
                if offered.is_empty() {
                    "none".to_string()
                } else {
                    offered.join(", ")
                },
                SUBPROTOCOLS.join(" and ")
            ),
        ));
    };
    Ok(Accepted {
        key: tokio_tungstenite::tungstenite::handshake::derive_accept_key(key.as_bytes()),
        subprotocol,
    })
}

struct Head {
    /// Everything read so far (the handshake, and whatever followed it).
    bytes: Vec<u8>,
    /// Length of the handshake in `bytes`.
    len: usize,
    method: String,
    /// Header names (lower case) and values, in order.
    fields: Vec<(String, String)>,
    origins: Vec<String>,
}

impl Head {
    fn headers<'a>(&'a self, name: &'a str) -> impl Iterator<Item = &'a str> + 'a {
        self.fields
            .iter()
            .filter(move |(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }
}

enum HeadError {
    /// Closed, failed or too slow: nobody to answer.
    Gone,
    Invalid,
}

async fn read_head(stream: &mut TcpStream) -> Result<Head, HeadError> {
    let mut bytes = Vec::with_capacity(1024);
    let read = async {
        let mut chunk = [0u8; 2048];
        loop {
            let n = stream.read(&mut chunk).await.map_err(|_| HeadError::Gone)?;
            if n == 0 {
                return Err(HeadError::Gone);
            }
            bytes.extend_from_slice(&chunk[..n]);
            let mut headers = [httparse::EMPTY_HEADER; 64];
            let mut request = httparse::Request::new(&mut headers);
            match request.parse(&bytes) {
                Ok(httparse::Status::Complete(len)) => {
                    let fields: Vec<(String, String)> = request
                        .headers
                        .iter()
                        .map(|h| {
                            (
                                h.name.to_ascii_lowercase(),
                                String::from_utf8_lossy(h.value).into_owned(),
                            )
                        })
                        .collect();
                    return Ok((len, request.method.unwrap_or("").to_string(), fields));
                }
                Ok(httparse::Status::Partial) if bytes.len() < MAX_HEAD => {}
                _ => return Err(HeadError::Invalid),
            }
        }
    };
    let (len, method, fields) = tokio::time::timeout(HEAD_TIMEOUT, read)
        .await
        .map_err(|_| HeadError::Gone)??;
    let origins = fields
        .iter()
        .filter(|(n, _)| n == "origin")
        .map(|(_, v)| v.clone())
        .collect();
    Ok(Head {
        bytes,
        len,
        method,
        fields,
        origins,
    })
}

/// No `Origin` (not a browser), or exactly one that is configured.
fn origin_allowed(origins: &[String], allowed: &[String]) -> bool {
    match origins {
        [] => true,
        [origin] => allowed.iter().any(|a| same_origin(a, origin)),
        _ => false,
    }
}

fn same_origin(a: &str, b: &str) -> bool {
    let norm = |s: &str| s.trim().trim_end_matches('/').to_ascii_lowercase();
    norm(a) == norm(b)
}

async fn respond(stream: &mut TcpStream, code: u16, status: &str, body: &str) {
    let response = format!(
        "HTTP/1.1 {code} {status}\r\nContent-Type: text/plain\r\nContent-Length: {}\r\n\
         Connection: close\r\n\r\n{body}\n",
        body.len() + 1
    );
    let _ = stream.write_all(response.as_bytes()).await;
    let _ = stream.shutdown().await;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strings(s: &[&str]) -> Vec<String> {
        s.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn only_no_origin_or_a_configured_one_is_allowed() {
        let allowed = strings(&["https://app.foxglove.dev"]);
        assert!(origin_allowed(&[], &allowed));
        assert!(origin_allowed(
            &strings(&["https://app.foxglove.dev"]),
            &allowed
        ));
        assert!(origin_allowed(
            &strings(&["HTTPS://App.Foxglove.dev/"]),
            &allowed
        ));
        assert!(!origin_allowed(
            &strings(&["http://evil.example"]),
            &allowed
        ));
        assert!(!origin_allowed(&strings(&["null"]), &allowed));
        assert!(!origin_allowed(
            &strings(&["http://app.foxglove.dev"]),
            &allowed
        ));
        assert!(!origin_allowed(
            &strings(&["https://app.foxglove.dev.evil.example"]),
            &allowed
        ));
        // Two Origin headers: ambiguous.
        let both = strings(&["https://app.foxglove.dev", "http://evil.example"]);
        assert!(!origin_allowed(&both, &allowed));
        assert!(!origin_allowed(
            &strings(&["https://app.foxglove.dev"]),
            &[]
        ));
    }

    #[test]
    fn a_flood_of_refusals_is_named_once_then_counted() {
        let notices = Notices::default();
        let peer: SocketAddr = "127.0.0.1:5000".parse().unwrap();
        for _ in 0..500 {
            notices.refused_full(peer, 32);
        }
        let first = notices.take(false);
        assert_eq!(first.len(), 1, "{first:?}");
        assert!(first[0].contains("live.max_clients"), "{first:?}");
        assert!(notices.take(false).is_empty());
        let rest = notices.take(true);
        assert_eq!(rest.len(), 1, "{rest:?}");
        assert!(rest[0].contains("499 more"), "{rest:?}");
        assert!(notices.take(true).is_empty());
    }

    #[test]
    fn slots_are_bounded_and_given_back() {
        let count = Arc::new(AtomicUsize::new(0));
        let a = Slot::take(&count, 2).unwrap();
        let _b = Slot::take(&count, 2).unwrap();
        assert!(Slot::take(&count, 2).is_none());
        drop(a);
        assert!(Slot::take(&count, 2).is_some());
    }
}
