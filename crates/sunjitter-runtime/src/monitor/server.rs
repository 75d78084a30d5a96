//! The live view's server: the listening socket's gate, the hub of clients and the thread
//! that publishes what the writer logs.

use super::gate::{self, Notices};
use super::live::{publish_all, Hub, LiveTap};
use std::net::SocketAddr;
use std::sync::Arc;
use sunjitter_core::{Error, Result};

/// The running server, its front door and its publishing thread.
pub struct LiveServer {
    tap: LiveTap,
    gate_stop: Option<tokio::sync::oneshot::Sender<()>>,
    notices: Notices,
    thread: Option<std::thread::JoinHandle<()>>,
    hub: Arc<Hub>,
    pub addr: SocketAddr,
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
        let hub = Arc::new(Hub::new());
        hub.open_channels(topics);
        let notices = Notices::default();
        let admission = gate::Admission {
            allowed_origins: config.allowed_origins.clone(),
            max_clients: config.max_clients,
        };
        let (gate_stop, stop) = tokio::sync::oneshot::channel();
        tokio::spawn(gate::Gate::new(admission, hub.clone(), notices.clone()).run(listener, stop));
        let (tap, rx) = LiveTap::new(config.queue);
        let publisher = hub.clone();
        let thread = std::thread::Builder::new()
            .name("sunjitter-live".into())
            .spawn(move || publish_all(&publisher, rx))
            .map_err(|e| Error::output("live view", e.to_string()))?;
        tracing::info!(%addr, "live view: Foxglove WebSocket server listening (ws://{addr})");
        Ok(LiveServer {
            tap,
            gate_stop: Some(gate_stop),
            notices,
            thread: Some(thread),
            hub,
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
        self.hub.disconnect_all();
        // The thread ends when every tap is gone (the sink drops its copy when it finishes).
        drop(self.tap);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}
