// A Foxglove WebSocket client built on @foxglove/ws-protocol (the protocol's reference client) with
// @foxglove/rosmsg2-serialization decoding every CDR payload from its advertised ros2msg schema.
// Usage: node foxglove_client.cjs URL SUBPROTOCOL SECONDS
// Subscribes to every channel the moment it is advertised, publishes a 2D pose estimate on
// /alice/initialpose until /alice/pf/pose answers near it, calls /alice/tll_pf/global_localization,
// reads /alice/tll_pf.n_particles, then prints one JSON summary line and exits.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader, MessageWriter } = require("@foxglove/rosmsg2-serialization");
const WebSocket = require("ws");

const [url, subprotocol, seconds] = process.argv.slice(2);
const ws = new WebSocket(url, [subprotocol]);
const client = new FoxgloveClient({ ws });
const out = {
  subprotocol: null, capabilities: [], channels: {}, received: {}, decodeErrors: [], statuses: [],
  poseSeen: null, serviceResponse: null, serviceFailure: null, parameters: null, published: 0,
};
const readers = new Map();     // channel id -> [topic, MessageReader]
const bySub = new Map();       // subscription id -> channel id
let poseWriter = null;
let pubChannel = null;
let service = null;
let calls = 0;

function finish(code) {
  process.stdout.write(JSON.stringify(out) + "\n");
  client.close();
  process.exit(code);
}

ws.on("open", () => { out.subprotocol = ws.protocol; });
ws.on("unexpected-response", (_req, res) => { out.statuses.push({ handshake: res.statusCode }); finish(3); });
client.on("error", (err) => { out.statuses.push({ error: String(err) }); });
client.on("serverInfo", (info) => { out.capabilities = info.capabilities; });
client.on("status", (s) => { out.statuses.push({ level: s.level, message: s.message }); });
client.on("advertise", (channels) => {
  for (const ch of channels) {
    out.channels[ch.topic] = ch.schemaName;
    try {
      readers.set(ch.id, [ch.topic, new MessageReader(parse(ch.schema, { ros2: true }))]);
    } catch (err) {
      out.decodeErrors.push(`${ch.topic}: schema: ${err}`);
    }
    bySub.set(client.subscribe(ch.id), ch.id);
    if (ch.topic === "/alice/pf/pose" && pubChannel === null) {
      poseWriter = new MessageWriter(parse(ch.schema, { ros2: true }));
      pubChannel = client.advertise({ topic: "/alice/initialpose", encoding: "cdr",
                                      schemaName: "geometry_msgs/msg/PoseWithCovarianceStamped" });
    }
  }
});
client.on("advertiseServices", (services) => {
  for (const s of services) {
    if (s.name === "/alice/tll_pf/global_localization") service = s;
  }
});
client.on("message", (ev) => {
  const chId = bySub.get(ev.subscriptionId);
  const entry = readers.get(chId);
  if (!entry) return;
  const [topic, reader] = entry;
  try {
    const msg = reader.readMessage(new Uint8Array(ev.data.buffer, ev.data.byteOffset, ev.data.byteLength));
    out.received[topic] = (out.received[topic] || 0) + 1;
    if (topic === "/alice/pf/pose") {
      const p = msg.pose.pose.position;
      if (Math.abs(p.x - 15) < 2 && Math.abs(p.y) < 2) out.poseSeen = [p.x, p.y];
    }
  } catch (err) {
    out.decodeErrors.push(`${topic}: ${err}`);
  }
});
client.on("serviceCallResponse", (r) => { out.serviceResponse = { callId: r.callId, encoding: r.encoding, bytes: r.data.byteLength }; });
client.on("serviceCallFailure", (f) => { out.serviceFailure = f.message; });
client.on("parameterValues", (p) => { if (p.id === "p1") out.parameters = p.parameters; });

const cov = new Array(36).fill(0);
cov[0] = cov[7] = 0.25;
const pose = { header: { stamp: { sec: 0, nanosec: 0 }, frame_id: "map" },
               pose: { pose: { position: { x: 15, y: 0, z: 0 }, orientation: { x: 0, y: 0, z: 0, w: 1 } }, covariance: cov } };
const tick = setInterval(() => {
  if (pubChannel !== null && out.poseSeen === null) {
    client.sendMessage(pubChannel, poseWriter.writeMessage(pose));   // until tll_pf's subscription has matched
    out.published += 1;
  }
  if (out.poseSeen !== null && service !== null && calls === 0) {
    calls += 1;
    // std_srvs/Empty request: CDR little-endian header + the one uint8 placeholder member of an empty struct
    client.sendServiceCallRequest({ serviceId: service.id, callId: 7, encoding: "cdr",
                                    data: new Uint8Array([0, 1, 0, 0, 0]) });
    client.getParameters(["/alice/tll_pf.n_particles"], "p1");
  }
  if (out.poseSeen !== null && (out.serviceResponse || out.serviceFailure) && out.parameters) {
    clearInterval(tick);
    setTimeout(() => finish(0), 1000);     // a last second of messages, all decoded
  }
}, 500);
setTimeout(() => finish(4), Number(seconds) * 1000);
