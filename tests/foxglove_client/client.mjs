// A Foxglove WebSocket client built from Foxglove's own packages (@foxglove/ws-protocol,
// @foxglove/rosmsg, @foxglove/rosmsg2-serialization): what the Foxglove app does with a live
// connection, minus the drawing. It subscribes the topics it is asked for, decodes each message
// from its CDR bytes with the channel's ros2msg schema, and prints one JSON line per message
// with what the tests compare (stamps, sizes, sums of the pixel values, poses, fields).
//
//   node client.mjs --url ws://localhost:8765 --topics /a,/b [--count N] [--timeout S] [--stay 1]
//
// It exits 0 once every topic has given N messages (with --stay 1: at SIGTERM or when the server
// stops, if they have by then), 1 otherwise, printing the topics still missing.
import { parse } from "@foxglove/rosmsg";
import { MessageReader } from "@foxglove/rosmsg2-serialization";
import wsProtocol from "@foxglove/ws-protocol";
import WebSocket from "ws";

const SUBPROTOCOL = "foxglove.sdk.v1"; // what foxglove-sdk servers accept
const { FoxgloveClient } = wsProtocol; // a CommonJS package: no named exports for ESM

function options(argv) {
  const out = { url: "ws://localhost:8765", topics: [], count: 1, timeout: 120, stay: 0 };
  for (let i = 0; i < argv.length; i += 2) {
    const [key, value] = [argv[i].replace(/^--/, ""), argv[i + 1]];
    if (key === "topics") out.topics = value.split(",").filter(Boolean);
    else if (key === "url") out.url = value;
    else if (key === "count" || key === "timeout" || key === "stay") out[key] = Number(value);
    else throw new Error(`unknown option --${key}`);
  }
  return out;
}

const stampNs = (stamp) => (BigInt(stamp.sec) * 1000000000n + BigInt(stamp.nanosec)).toString();

function imageSummary(msg) {
  const out = {
    stamp_ns: stampNs(msg.header.stamp),
    frame_id: msg.header.frame_id,
    encoding: msg.encoding,
    width: msg.width,
    height: msg.height,
    step: msg.step,
    bytes: msg.data.byteLength,
  };
  if (msg.encoding === "32FC1") {
    // the pixels need not start 4-byte aligned in the received buffer: read them one by one
    const view = new DataView(msg.data.buffer, msg.data.byteOffset, msg.data.byteLength);
    let finite = 0, sum = 0, min = Infinity, max = -Infinity;
    for (let i = 0; i + 4 <= msg.data.byteLength; i += 4) {
      const v = view.getFloat32(i, !msg.is_bigendian);
      if (!Number.isFinite(v)) continue;
      finite += 1; sum += v;
      if (v < min) min = v;
      if (v > max) max = v;
    }
    Object.assign(out, { finite, sum, min, max });
  } else {
    let sum = 0;
    for (const v of msg.data) sum += v;
    out.sum = sum;
  }
  return out;
}

function cloudSummary(msg) {
  const view = new DataView(msg.data.buffer, msg.data.byteOffset, msg.data.byteLength);
  const points = msg.width * msg.height;
  const fields = {};
  for (const field of msg.fields) {
    if (field.datatype !== 7) continue; // FLOAT32
    let sum = 0, min = Infinity, max = -Infinity;
    for (let i = 0; i < points; i++) {
      const v = view.getFloat32(i * msg.point_step + field.offset, !msg.is_bigendian);
      sum += v;
      if (v < min) min = v;
      if (v > max) max = v;
    }
    fields[field.name] = { sum, min, max };
  }
  return {
    stamp_ns: stampNs(msg.header.stamp),
    frame_id: msg.header.frame_id,
    names: msg.fields.map((f) => f.name),
    points,
    point_step: msg.point_step,
    fields,
  };
}

const pose = (p) => [p.position.x, p.position.y, p.position.z,
  p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w];

const SUMMARIES = {
  "sensor_msgs/msg/Image": imageSummary,
  "sensor_msgs/msg/PointCloud2": cloudSummary,
  "nav_msgs/msg/Path": (msg) => ({
    stamp_ns: stampNs(msg.header.stamp),
    frame_id: msg.header.frame_id,
    poses: msg.poses.map((p) => pose(p.pose)),
  }),
  "visualization_msgs/msg/MarkerArray": (msg) => ({
    stamp_ns: msg.markers.length ? stampNs(msg.markers[0].header.stamp) : null,
    markers: msg.markers.map((m) => ({
      ns: m.ns, id: m.id, type: m.type, action: m.action, frame_id: m.header.frame_id,
      position: [m.pose.position.x, m.pose.position.y, m.pose.position.z],
      scale: [m.scale.x, m.scale.y, m.scale.z],
      points: m.points.map((p) => [p.x, p.y, p.z]),
      color: [m.color.r, m.color.g, m.color.b, m.color.a],
    })),
  }),
  // a mesh: its size, bounds and colour range (not its 10^5 points, one JSON line each message)
  "visualization_msgs/msg/Marker": (m) => ({
    stamp_ns: stampNs(m.header.stamp), frame_id: m.header.frame_id, ns: m.ns, type: m.type,
    points: m.points.length, colors: m.colors.length,
    // reduce, not Math.min(...): a spread of 10^5 arguments overflows the call stack
    min: ["x", "y", "z"].map((a) => m.points.reduce((v, p) => Math.min(v, p[a]), Infinity)),
    max: ["x", "y", "z"].map((a) => m.points.reduce((v, p) => Math.max(v, p[a]), -Infinity)),
    color_range: [m.colors.reduce((v, c) => Math.min(v, c.r, c.g, c.b), Infinity),
      m.colors.reduce((v, c) => Math.max(v, c.r, c.g, c.b), -Infinity)],
  }),
  "area3d_interfaces/msg/HardRegionArray": (msg) => ({
    stamp_ns: stampNs(msg.header.stamp),
    frame_id: msg.header.frame_id,
    regions: msg.regions.map((r) => ({
      centroid: [r.centroid.x, r.centroid.y, r.centroid.z],
      extent: [r.extent.x, r.extent.y, r.extent.z],
      voxel_count: r.voxel_count, direction_count: r.direction_count,
      mean_uncertainty: r.mean_uncertainty,
    })),
  }),
  "diagnostic_msgs/msg/DiagnosticArray": (msg) => ({
    status: msg.status.map((s) => ({
      level: s.level, name: s.name, message: s.message,
      values: Object.fromEntries(s.values.map((kv) => [kv.key, kv.value])),
    })),
  }),
  "tf2_msgs/msg/TFMessage": (msg) => ({
    transforms: msg.transforms.map((t) => ({
      parent: t.header.frame_id, child: t.child_frame_id,
      translation: [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z],
      rotation: [t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w],
    })),
  }),
  "std_msgs/msg/String": (msg) => ({ data: msg.data }),
};

function summary(schemaName, msg) {
  const summarise = SUMMARIES[schemaName];
  return summarise ? summarise(msg) : { keys: Object.keys(msg) };
}

function print(line) {
  process.stdout.write(`${JSON.stringify(line)}\n`);
}

function run() {
  const opts = options(process.argv.slice(2));
  const wanted = new Set(opts.topics);
  const counts = new Map(opts.topics.map((t) => [t, 0]));
  const known = new Map(); // channel id -> { topic, schemaName, reader }
  const subscriptions = new Map(); // subscription id -> the channel's entry
  const missing = () => [...counts].filter(([, n]) => n < opts.count).map(([t]) => t);
  let socket = null;
  let finished = false;
  const finish = (code) => {
    if (finished) return;
    finished = true;
    print({ done: true, missing: missing(), counts: Object.fromEntries(counts) });
    // close the connection as a client should, then exit (at once if the server is gone)
    if (socket && socket.readyState === WebSocket.OPEN) {
      socket.once("close", () => process.exit(code));
      socket.close(1000);
      setTimeout(() => process.exit(code), 1000);
    } else {
      process.exit(code);
    }
  };
  setTimeout(() => finish(1), opts.timeout * 1000);
  process.on("SIGTERM", () => finish(missing().length ? 1 : 0));

  const connect = () => {
    const ws = new WebSocket(opts.url, [SUBPROTOCOL]);
    socket = ws;
    ws.on("error", () => {}); // a refused connection is retried below
    ws.on("close", () => {
      if (!connected) setTimeout(connect, 200);
      else finish(missing().length ? 1 : 0); // the server stopped: did it give what was wanted?
    });
    let connected = false;
    ws.on("open", () => { connected = true; print({ connected: opts.url, protocol: ws.protocol }); });
    const client = new FoxgloveClient({ ws });
    client.on("advertise", (channels) => {
      for (const channel of channels) {
        print({ advertised: channel.topic, schemaName: channel.schemaName,
          encoding: channel.encoding, schemaEncoding: channel.schemaEncoding });
        if (!wanted.has(channel.topic)) continue;
        if (channel.encoding !== "cdr" || channel.schemaEncoding !== "ros2msg") {
          print({ error: `unexpected encodings on ${channel.topic}`, channel });
          continue;
        }
        const reader = new MessageReader(parse(channel.schema, { ros2: true }));
        known.set(channel.id, { topic: channel.topic, schemaName: channel.schemaName, reader });
        subscribe(channel.id);
      }
    });
    const subscribe = (channelId) => subscriptions.set(client.subscribe(channelId), known.get(channelId));
    // foxglove-sdk 0.30 sends a channel's advertisement before it records the channel: a
    // subscription that arrives in between is refused with this status. Subscribe again.
    client.on("status", ({ message }) => {
      const refused = /^Unknown channel ID: (\d+)/.exec(message);
      print({ status: message });
      if (refused && known.has(Number(refused[1]))) {
        setTimeout(() => subscribe(Number(refused[1])), 100);
      }
    });
    client.on("message", ({ subscriptionId, timestamp, data }) => {
      const sub = subscriptions.get(subscriptionId);
      if (!sub || finished) return;
      const received_ms = performance.timeOrigin + performance.now();
      const msg = sub.reader.readMessage(data);
      print({
        topic: sub.topic, type: sub.schemaName, log_time_ns: timestamp.toString(), received_ms,
        bytes: data.byteLength, summary: summary(sub.schemaName, msg),
      });
      counts.set(sub.topic, (counts.get(sub.topic) ?? 0) + 1);
      if (!opts.stay && missing().length === 0) finish(0);
    });
  };
  connect();
}

run();
