// The topic relay through RobotSession (§17.5), as the Python client's robot.relay():
// start (repeated over seeded loss until answered), relay/data reassembled per stream and
// delivered whole, stop with the robot's counters, the robot's `ended`, the end with the
// call, refusals, stray data answered with a stop at most once a second, and fuzz of the
// new decoders.
import { test } from "node:test";
import assert from "node:assert/strict";
import { RelayRefused, RobotSession } from "../src/session.js";
import { DecodeError } from "../src/services/util.js";
import { decodeRelayMessage, streamOf } from "../src/services/relay.js";
import { fragmentFrame } from "../src/services/video.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

const SCAN = { name: "/scan", type: "sensor_msgs/msg/LaserScan", schema: "std_msgs/Header header\nfloat32 angle_min\n", encoding: "cdr" };

/** A robot answering relay requests like the Python RelayService: first answer repeated. */
function relayRobot(call, { topics = [SCAN] } = {}) {
  const answers = new Map();
  const robot = { starts: [], stops: [], nextStream: 1, sent: new Map(), seq: 0, msgId: new Map() };
  call.onUser("relay", (p) => {
    const r = JSON.parse(p);
    if (r.type === "start") robot.starts.push(r);
    if (r.type === "stop") robot.stops.push(r);
    if (!answers.has(r.id)) {
      let answer;
      if (r.type === "start") {
        const topic = topics.find((t) => t.name === r.topic);
        if (!topic) answer = { type: "refused", id: r.id, code: "unknown_topic", text: `no topic ${r.topic}`, near: topics.map((t) => t.name) };
        else answer = { type: "started", id: r.id, stream: robot.nextStream++, topic };
      } else if (r.type === "stop") {
        answer = { type: "stopped", id: r.id, stream: r.stream, sent: robot.sent.get(r.stream) ?? 0, dropped: 1 };
      } else if (r.type === "list") {
        answer = { type: "topics", id: r.id, part: 0, parts: 1, topics };
      }
      answers.set(r.id, JSON.stringify(answer));
    }
    call.toUser("relay", answers.get(r.id));
  });
  /** Send one message of `stream` on relay/data (lossy unless told). */
  robot.publish = (stream, data, stamp, opts = {}) => {
    const id = (robot.msgId.get(stream) ?? 0) + 1;
    robot.msgId.set(stream, id);
    robot.sent.set(stream, (robot.sent.get(stream) ?? 0) + 1);
    const frags = fragmentFrame({ frameId: id, camera: String(stream), captureTime: stamp, data, seq: robot.seq, codec: 0x02, interval: 0.5 });
    robot.seq += frags.length;
    for (const f of frags) call.toUser("relay/data", f, opts);
  };
  return robot;
}

async function started({ seed = 1, upLoss = 0, downLoss = 0 } = {}) {
  const clock = new ManualClock();
  const out = [];
  const made = [];
  const robots = [];
  const session = new RobotSession({
    connect: async () => {
      const call = new FakeCall({ seed, upLoss, downLoss });
      call.onUser("map", () => {});
      robots.push(relayRobot(call));
      made.push(call);
      return call;
    },
    emit: (m) => out.push(m),
    user: "alice",
    clock,
    random: seeded(seed),
    mapUrl: () => "blob:map",
    reconnect: { enabled: false },
  });
  await session.start();
  return { clock, out, session, call: () => made.at(-1), robot: () => robots.at(-1) };
}

/** Resolve a session promise while the clock runs. */
async function run(clock, promise, limit = 10) {
  let result;
  let error;
  let done = false;
  promise.then((r) => { result = r; done = true; }, (e) => { error = e; done = true; });
  assert.ok(await clock.until(() => done, limit), "settled in time");
  if (error) throw error;
  return result;
}

test("start, whole messages over seeded loss, stop with the robot's counters", async () => {
  const { clock, session, call, robot } = await started({ seed: 11, upLoss: 0.3, downLoss: 0.1 });
  const got = [];
  const stream = await run(clock, session.relay("/scan", { rate: 5, onMessage: (m) => got.push(m) }));
  assert.deepEqual(stream.info, SCAN);
  assert.equal(stream.stream, 1);
  const [first] = call().sent("relay");
  assert.deepEqual(Object.keys(first), ["type", "id", "topic", "rate", "latest_only"]);
  assert.deepEqual({ ...first, id: 0 }, { type: "start", id: 0, topic: "/scan", rate: 5, latest_only: false });
  assert.ok(robot().starts.every((s) => s.id === first.id), "a repeat keeps its id: nothing starts twice");
  // 40 messages of 3 fragments each (70,000 bytes) and 40 of one; 10 % lost on the way.
  const sent = [];
  for (let i = 0; i < 80; i++) {
    const data = new Uint8Array(i % 2 ? 70000 : 500).fill(i);
    data[0] = 0; data[1] = 1; // CDR little-endian encapsulation header
    sent.push(data);
    robot().publish(1, data, 1700000000 + i);
    await clock.advance(0.05);
  }
  assert.ok(got.length > 40 && got.length < 80, `most arrived, some lost whole: ${got.length}`);
  for (const m of got) {
    const i = m.stamp - 1700000000;
    assert.equal(m.topic, "/scan");
    assert.equal(m.type, "sensor_msgs/msg/LaserScan");
    assert.deepEqual(m.data, sent[i], "each message whole, exactly the robot's bytes");
  }
  assert.ok(stream.incomplete > 0, "messages with a lost fragment were counted");
  const counters = await run(clock, stream.close());
  assert.deepEqual(counters, { sent: 80, dropped: 1 });
  assert.equal(stream.ended, true);
  const stop = call().sent("relay").find((r) => r.type === "stop");
  assert.deepEqual({ ...stop, id: 0 }, { type: "stop", id: 0, stream: 1 });
  const before = got.length;
  robot().publish(1, Uint8Array.of(0, 1, 0, 0), 1700000100, { lossless: true });
  await clock.advance(0.05);
  assert.equal(got.length, before, "nothing delivered after the stop");
});

test("a refused start: RelayRefused with the robot's code and near names", async () => {
  const { clock, session } = await started();
  await assert.rejects(run(clock, session.relay("/scna")), (err) => {
    assert.ok(err instanceof RelayRefused);
    assert.equal(err.code, "unknown_topic");
    assert.deepEqual(err.near, ["/scan"]);
    assert.equal(err.message, "no topic /scna");
    return true;
  });
  await assert.rejects(run(clock, session.relay("/scan", { rate: 0 })), RangeError);
  await assert.rejects(run(clock, session.relay("")), RangeError);
});

test("the robot's `ended` ends the stream; a for-await loop finishes with it", async () => {
  const { clock, session, call, robot } = await started();
  const stream = await run(clock, session.relay("/scan", { latestOnly: true }));
  const reasons = [];
  stream.onend = (why) => reasons.push(why);
  const got = [];
  const loop = (async () => {
    for await (const m of stream) got.push(m.data[4]);
  })();
  robot().publish(1, Uint8Array.of(0, 1, 0, 0, 7), 1, { lossless: true });
  await clock.advance(0.05);
  call().toUser("relay", JSON.stringify({ type: "ended", stream: 1, text: "the topic went away" }), { lossless: true });
  await clock.advance(0.05);
  await run(clock, loop);
  assert.deepEqual(got, [7]);
  assert.deepEqual(reasons, ["the topic went away"]);
  assert.equal(stream.endReason, "the topic went away");
});

test("a stream ends with its call; requests in flight fail", async () => {
  const { clock, session, call, robot } = await started();
  const stream = await run(clock, session.relay("/scan"));
  call().onUser("relay", () => {}); // the robot stops answering
  const pending = session.topics();
  call().endWith("hung_up", "bye");
  await clock.advance(0.05);
  assert.equal(stream.ended, true);
  assert.equal(stream.endReason, "the call ended");
  await assert.rejects(run(clock, pending), /the call ended/);
  assert.equal(robot().starts.length >= 1, true);
});

test("data of a stream this side does not know is answered with a stop, at most once a second", async () => {
  const { clock, call, robot } = await started();
  for (let i = 0; i < 20; i++) {
    robot().publish(9, Uint8Array.of(0, 1, 0, 0, i), i, { lossless: true });
    await clock.advance(0.1);
  }
  const stops = call().sent("relay").filter((r) => r.type === "stop" && r.stream === 9);
  assert.ok(stops.length >= 2 && stops.length <= 3, `stops: ${stops.length} in 2 s`);
});

test("topics: every part of one answer", async () => {
  const { clock, session } = await started({ seed: 4, upLoss: 0.3 });
  assert.deepEqual(await run(clock, session.topics()), [SCAN]);
});

test("seeded fuzz: relay answers and relay/data garbage are dropped and counted, never thrown", async () => {
  const random = seeded(99);
  const valid = [
    JSON.stringify({ type: "started", id: 1, stream: 1, topic: SCAN }),
    JSON.stringify({ type: "refused", id: 1, code: "unknown_topic", text: "", near: ["/a"] }),
    JSON.stringify({ type: "stopped", id: 1, stream: 1, sent: 1, dropped: 0 }),
    JSON.stringify({ type: "ended", stream: 1, text: "" }),
    JSON.stringify({ type: "topics", id: 1, part: 0, parts: 1, topics: [SCAN] }),
  ];
  for (const v of valid) assert.equal(decodeRelayMessage(v).type, JSON.parse(v).type);
  let ok = 0;
  for (let i = 0; i < 5000; i++) {
    let text = valid[Math.floor(random() * valid.length)];
    const at = Math.floor(random() * text.length);
    text = text.slice(0, at) + String.fromCharCode(Math.floor(random() * 128)) + text.slice(at + 1);
    try {
      decodeRelayMessage(random() < 0.05 ? new Uint8Array(3) : text);
      ok += 1;
    } catch (err) {
      assert.ok(err instanceof DecodeError, `${err}`);
      assert.ok(!err.message.includes("\n"));
    }
  }
  assert.ok(ok > 0 && ok < 5000);
  for (const bad of [{ type: "started", id: 1, stream: 0, topic: SCAN }, { type: "started", id: 1, stream: 2 ** 31, topic: SCAN },
    { type: "started", id: 1, stream: 1, topic: { ...SCAN, encoding: "" } }, { type: "refused", id: 1, code: "", text: "" },
    { type: "refused", id: 1, code: "x", text: "", near: new Array(11).fill("/a") }, { type: "stopped", id: 1, stream: 1, sent: -1, dropped: 0 },
    { type: "start", id: 1, topic: "/scan" }, { type: "ended", stream: 1 }]) {
    assert.throws(() => decodeRelayMessage(JSON.stringify(bad)), DecodeError, JSON.stringify(bad));
  }
  for (const [camera, n] of [["1", 1], ["2147483647", 2147483647], ["0", null], ["2147483648", null], ["1a", null], ["", null], ["١", null]]) assert.equal(streamOf(camera), n, camera);
  const { clock, out, session, call } = await started({ seed: 6 });
  const stream = await run(clock, session.relay("/scan", { onMessage: () => {} }));
  const frag = fragmentFrame({ frameId: 5, camera: "1", captureTime: 1, data: new Uint8Array(100), codec: 0x02 })[0];
  for (let i = 0; i < 3000; i++) {
    const bytes = random() < 0.5 ? frag.slice() : new Uint8Array(Math.floor(random() * 60));
    for (let f = 0; f < 2 && bytes.length; f++) bytes[Math.floor(random() * bytes.length)] = Math.floor(random() * 256);
    const name = random() < 0.5 ? "relay/data" : "relay";
    assert.doesNotThrow(() => call().channels.get(name).onmessage(name === "relay" && random() < 0.5 ? String.fromCharCode(...bytes) : bytes));
  }
  await clock.advance(0.1);
  assert.ok(session.drops.relay > 1000, `counted: ${JSON.stringify(session.drops)}`);
  assert.equal(stream.ended, false, "the stream goes on");
  session.send({ type: "ping", t: 3 });
  assert.deepEqual(out.at(-1), { type: "pong", t: 3 });
});
