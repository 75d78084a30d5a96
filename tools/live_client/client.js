#!/usr/bin/env node
// Independent Foxglove WebSocket client for the live-view test (tests/live.rs).
//
//   node client.js ws://127.0.0.1:PORT read TOPIC...   subscribe to TOPICs, print one JSON line
//                                                      per message on stdout
//   node client.js ws://127.0.0.1:PORT stall           subscribe to every channel, then never
//                                                      read the socket again
//
// Lines on stdout: {"event":"open","protocol":...}, {"event":"advertised","topic":...,"schemaName":...,"schemaEncoding":...,
// "encoding":...}, {"event":"subscribed","topic":...}, {"event":"message","topic":...,
// "logTime":"<ns>","payload":{...}}, {"event":"stalled"}. Errors go to stderr, exit code 1.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { WebSocket } = require("ws");

const [url, mode, ...topics] = process.argv.slice(2);
if (!url || !["read", "stall"].includes(mode)) {
  console.error("usage: client.js URL read TOPIC... | client.js URL stall");
  process.exit(2);
}

const out = (obj) => process.stdout.write(JSON.stringify(obj) + "\n");
// SUBPROTOCOLS (comma-separated) is what the client offers; by default the SDK's name of
// the protocol. `foxglove.websocket.v1` is the classic name of the same protocol.
const offered = (process.env.SUBPROTOCOLS || "foxglove.sdk.v1").split(",");
const ws = new WebSocket(url, offered);
const client = new FoxgloveClient({ ws });
const wanted = new Set(topics);
const channels = new Map(); // channel id -> channel
const subscriptions = new Map(); // subscription id -> channel
const decoder = new TextDecoder();

client.on("error", (e) => {
  console.error(`client error: ${e && e.message ? e.message : e}`);
  process.exit(1);
});
client.on("close", () => process.exit(0));
client.on("open", () => out({ event: "open", protocol: ws.protocol }));
client.on("advertise", (list) => {
  for (const ch of list) {
    channels.set(ch.id, ch);
    out({
      event: "advertised",
      topic: ch.topic,
      schemaName: ch.schemaName,
      schemaEncoding: ch.schemaEncoding,
      encoding: ch.encoding,
    });
    if (mode === "stall" || wanted.has(ch.topic)) {
      const sub = client.subscribe(ch.id);
      subscriptions.set(sub, ch);
      out({ event: "subscribed", topic: ch.topic });
    }
  }
  if (mode === "stall" && subscriptions.size > 0) {
    // Stop reading: the server's send buffer for this client fills and stays full.
    ws._socket.pause();
    out({ event: "stalled" });
  }
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const ch = subscriptions.get(subscriptionId);
  if (!ch) return;
  const text = decoder.decode(new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
  out({ event: "message", topic: ch.topic, logTime: timestamp.toString(), payload: JSON.parse(text) });
});
process.on("SIGTERM", () => process.exit(0));
