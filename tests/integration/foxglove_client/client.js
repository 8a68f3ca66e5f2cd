// A Foxglove WebSocket client for tether's tests, built on Foxglove's own @foxglove/ws-protocol.
// Prints one JSON object per line on stdout:
//   watch URL SECONDS TOPIC...: serverInfo, every advertised channel, then up to 3 decoded messages of
//     each channel, until each TOPIC has one or SECONDS pass; the official JSON Schemas of
//     @foxglove/schemas first, for the test to check messages against.
//   schemas: only the official JSON Schemas of @foxglove/schemas.
//   hostile URL SECONDS: garbage and protocol abuse on a raw socket, then subscribes to every channel
//     and stops reading (a viewer that does not keep up); prints what the server answered.
//   subscribe-all URL SECONDS [GARBAGE_HZ]: a viewer that subscribes to every channel advertised and reads
//     all of it; with GARBAGE_HZ > 0 it also sends, that many times a second on the same socket, a round of
//     garbage frames and bogus client messages (GARBAGE below; a round is skipped while more than 1 MiB is
//     still unsent). {subscribed: n} after each advertisement, {stats: {...}} every second, and the same
//     counts with {done: why} when stdin ends (how bench.gate --viewer stops it), SECONDS pass or the
//     server closes: messages (received), bytes, channels (subscribed), garbage (frames sent), skipped
//     (rounds), statuses (the server's status messages).
//   teleop URL SECONDS: client publish as Foxglove's Teleop panel does it, step by step as the test
//     asks on stdin, one JSON object a line: {op: "advertise", topic, encoding, schemaName} -> {advertised: id},
//     {op: "publish", channel, message, hz, seconds} (the panel holding a button) -> {published: n, last: s},
//     {op: "burst", channel, message, count} (a flood) -> {burst: n}, {op: "raw", channel, text} -> {raw: n},
//     {op: "unadvertise", channel} -> {unadvertised: id, at: s}, {op: "close"}; times are Unix seconds.
"use strict";
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const schemas = require("@foxglove/schemas/jsonschema");
const WebSocket = require("ws");

const [mode, url, seconds, ...wanted] = process.argv.slice(2);
// foxglove-sdk's server speaks the protocol of ws-protocol's spec under the name foxglove.sdk.v1
// (foxglove.websocket.v1 before); FoxgloveClient takes whatever subprotocol its socket negotiated.
const SUBPROTOCOL = "foxglove.sdk.v1";
const out = (obj, then) => process.stdout.write(JSON.stringify(obj) + "\n", then);
const deadline = setTimeout(() => finish("timeout"), Number(seconds) * 1000);
let finishing = false;

// Writes to a pipe are asynchronous on POSIX: process.exit() right after one drops whatever the
// reader has not taken yet (a full pipe, a test on a loaded machine). Exit once the last line is out.
function exitAfter(obj, code) {
  out(obj, () => process.exit(code));
}

function finish(why, counts = {}) {
  if (finishing) return;
  finishing = true;
  clearTimeout(deadline);
  exitAfter({ done: why, ...counts }, 0);
}

function official() {
  return { official: { "foxglove.SceneUpdate": schemas.SceneUpdate, "foxglove.FrameTransforms": schemas.FrameTransforms,
    "foxglove.CompressedImage": schemas.CompressedImage, "foxglove.Log": schemas.Log } };
}

function watch() {
  out(official());
  const ws = new WebSocket(url, [SUBPROTOCOL]);
  const client = new FoxgloveClient({ ws });
  const bySubscription = new Map();
  const counts = new Map();
  const pending = new Set(wanted);
  const decoder = new TextDecoder();
  client.on("error", (e) => out({ error: String(e && e.message ? e.message : e) }));
  client.on("close", () => finish("closed"));
  client.on("serverInfo", (info) => out({ serverInfo: info }));
  client.on("status", (status) => out({ status }));
  client.on("advertise", (channels) => {
    for (const channel of channels) {
      out({ channel });
      bySubscription.set(client.subscribe(channel.id), channel);
    }
  });
  client.on("message", ({ subscriptionId, data }) => {
    const channel = bySubscription.get(subscriptionId);
    if (!channel) return;
    const n = counts.get(channel.topic) || 0;
    counts.set(channel.topic, n + 1);
    if (n >= 3) return;
    let message;
    try {
      message = JSON.parse(decoder.decode(data));
    } catch (e) {
      out({ topic: channel.topic, undecodable: String(e) });
      return;
    }
    out({ topic: channel.topic, schemaName: channel.schemaName, message });
    pending.delete(channel.topic);
    if (wanted.length > 0 && pending.size === 0) finish("all");
  });
}

function hostile() {
  const ws = new WebSocket(url, [SUBPROTOCOL]);
  const answers = { text: 0, binary: 0, statuses: [] };
  let channels = [];
  ws.on("message", (data, isBinary) => {
    if (isBinary) { answers.binary += 1; return; }
    answers.text += 1;
    let msg;
    try { msg = JSON.parse(data.toString()); } catch (e) { return; }
    if (msg.op === "status" && answers.statuses.length < 20) answers.statuses.push(msg.message);
    if (msg.op === "advertise") channels = channels.concat(msg.channels);
  });
  ws.on("close", (code) => { out({ closed: code, answers }); });
  ws.on("error", (e) => out({ error: String(e.message) }));
  ws.on("open", () => {
    const junk = [
      "not json at all",
      "{\"op\":",
      JSON.stringify({ op: "subscribe" }),
      JSON.stringify({ op: "subscribe", subscriptions: [{ id: "x", channelId: "y" }] }),
      JSON.stringify({ op: "subscribe", subscriptions: [{ id: 1, channelId: 999999 }] }),
      JSON.stringify({ op: "unsubscribe", subscriptionIds: [424242] }),
      JSON.stringify({ op: "advertise", channels: [{ id: 1, topic: "tether/x/cmd/teleop/cmd_vel", encoding: "json", schemaName: "x" }] }),
      JSON.stringify({ op: "setParameters", parameters: [{ name: "a", value: 1 }] }),
      JSON.stringify({ op: "no-such-op" }),
      "[".repeat(10000),
    ];
    for (const text of junk) ws.send(text);
    ws.send(Buffer.from([0x01, 0xff, 0xff, 0xff, 0xff, 0x00]));  // client MESSAGE_DATA on a channel never advertised
    ws.send(Buffer.from([0x7f]));  // an opcode that does not exist
    ws.send(Buffer.alloc(2 * 1024 * 1024, 0x61), { binary: true });  // 2 MiB of nothing
    // Then subscribe to every channel, many times over, and stop reading: the server must not wait for us.
    setTimeout(() => {
      const subscriptions = [];
      let id = 1;
      for (let round = 0; round < 50; round++) {
        for (const channel of channels) subscriptions.push({ id: id++, channelId: channel.id });
      }
      ws.send(JSON.stringify({ op: "subscribe", subscriptions }));
      out({ subscribed: subscriptions.length, channels: channels.length, answers });
      ws._socket.pause();
    }, 500);
  });
  // Held open, not read, until the deadline.
  deadline.refresh();
}

// One round of garbage for subscribe-all: frames the protocol cannot parse and well-formed requests
// that make no sense (ids that exist nowhere, ops this server does not offer), all answered by a status
// at most. No subscription to a real channel: the viewer's own subscriptions stay as they are.
const NOWHERE = 1000000;  // subscription and channel ids above this are never the viewer's own
const GARBAGE = [
  "not json at all",
  "{\"op\":",
  JSON.stringify({ op: "subscribe" }),
  JSON.stringify({ op: "subscribe", subscriptions: [{ id: "x", channelId: "y" }] }),
  JSON.stringify({ op: "subscribe", subscriptions: [{ id: NOWHERE + 1, channelId: NOWHERE + 1 }] }),
  JSON.stringify({ op: "unsubscribe", subscriptionIds: [NOWHERE + 2] }),
  JSON.stringify({ op: "advertise", channels: [{ id: 1, topic: "/cmd_vel", encoding: "json", schemaName: "x" }] }),
  JSON.stringify({ op: "unadvertise", channelIds: [NOWHERE + 3] }),
  JSON.stringify({ op: "setParameters", parameters: [{ name: "a", value: 1 }] }),
  JSON.stringify({ op: "getParameters", parameterNames: ["a"] }),
  JSON.stringify({ op: "subscribeConnectionGraph" }),
  JSON.stringify({ op: "fetchAsset", uri: "file:///etc/passwd", requestId: 7 }),
  JSON.stringify({ op: "no-such-op" }),
  "[".repeat(10000),
  Buffer.from([0x01, 0xff, 0xff, 0xff, 0xff, 0x00]),  // client MESSAGE_DATA on a channel never advertised
  Buffer.from([0x02, 0x01, 0x00, 0x00, 0x00]),  // a service call request, cut short
  Buffer.from([0x7f]),  // an opcode that does not exist
  Buffer.alloc(64 * 1024, 0x61),  // 64 KiB of nothing
];

function subscribeAll() {
  const [garbageHz = "0"] = wanted;
  const ws = new WebSocket(url, [SUBPROTOCOL]);
  const client = new FoxgloveClient({ ws });
  const counts = { messages: 0, bytes: 0, channels: 0, garbage: 0, skipped: 0, statuses: 0 };
  const stop = (why) => finish(why, counts);
  client.on("error", (e) => out({ error: String(e && e.message ? e.message : e) }));
  client.on("close", (event) => stop(`closed ${event && event.code}`));
  client.on("status", () => { counts.statuses += 1; });
  client.on("advertise", (channels) => {
    for (const channel of channels) client.subscribe(channel.id);
    counts.channels += channels.length;
    out({ subscribed: counts.channels });
  });
  client.on("message", ({ data }) => { counts.messages += 1; counts.bytes += data.byteLength; });
  client.on("open", () => {
    if (Number(garbageHz) > 0) {
      setInterval(() => {
        if (ws.bufferedAmount > 1024 * 1024) { counts.skipped += 1; return; }
        for (const frame of GARBAGE) ws.send(frame);
        counts.garbage += GARBAGE.length;
      }, 1000 / Number(garbageHz));
    }
  });
  setInterval(() => out({ stats: { ...counts } }), 1000);
  process.stdin.on("data", () => {});
  process.stdin.on("end", () => stop("stdin"));
}

function teleop() {
  const ws = new WebSocket(url, [SUBPROTOCOL]);
  const client = new FoxgloveClient({ ws });
  const encoder = new TextEncoder();
  const now = () => Date.now() / 1000;
  client.on("error", (e) => out({ error: String(e && e.message ? e.message : e) }));
  client.on("close", () => finish("closed"));
  client.on("serverInfo", (info) => out({ serverInfo: info }));
  client.on("status", (status) => out({ status }));
  const steps = {
    advertise: (s) => out({ advertised: client.advertise({ topic: s.topic, encoding: s.encoding, schemaName: s.schemaName }) }),
    publish: (s) => {
      // As the panel does: one at once, then one every 1/hz seconds while the button is held.
      const data = encoder.encode(JSON.stringify(s.message));
      let n = 0;
      const send = () => { client.sendMessage(s.channel, data); n += 1; };
      send();
      const timer = setInterval(send, 1000 / s.hz);
      setTimeout(() => { clearInterval(timer); out({ published: n, last: now() }); }, s.seconds * 1000);
    },
    burst: (s) => {
      const data = encoder.encode(JSON.stringify(s.message));
      for (let i = 0; i < s.count; i++) client.sendMessage(s.channel, data);
      out({ burst: s.count, at: now() });
    },
    raw: (s) => { client.sendMessage(s.channel, encoder.encode(s.text)); out({ raw: s.text.length }); },
    unadvertise: (s) => { client.unadvertise(s.channel); out({ unadvertised: s.channel, at: now() }); },
    close: () => ws.close(),
  };
  let pending = "";
  process.stdin.setEncoding("utf8");
  process.stdin.on("data", (chunk) => {
    pending += chunk;
    let newline;
    while ((newline = pending.indexOf("\n")) >= 0) {
      const step = JSON.parse(pending.slice(0, newline));
      pending = pending.slice(newline + 1);
      steps[step.op](step);
    }
  });
  process.stdin.on("end", () => ws.close());
}

if (mode === "schemas") exitAfter(official(), 0);
else if (mode === "watch") watch();
else if (mode === "hostile") hostile();
else if (mode === "teleop") teleop();
else if (mode === "subscribe-all") subscribeAll();
else exitAfter({ error: `unknown mode ${mode}` }, 2);
