// RobotSession: the §19 client → page messages in the exact shapes app.js and its
// helpers (conference.js, people.js) read, page → client messages, the fail-safe, a
// reconnection after a drop, and seeded fuzz of every decoder (never a throw).
import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { RobotSession } from "../src/session.js";
import { STOP_HOWS } from "../src/services/messages.js";
import { fragmentFrame } from "../src/services/video.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

const POSE = { t: 12.5, x: 1, y: 2, yaw: 0.5, cov: [0.1, 0.1, 0.01], v: 0.3, w: 0, state: "moving", detail: "goto lab", goal: 7 };
const TELEMETRY = { t: 1, battery: 97.8, battery_low: false, state: "idle", detail: "", goal: null, progress: null, camera: "navcam", speed_limit: 0.5, rtt: 0.002, loss: 0, role: "driver", diagnostics: { map: "ok" }, armed: true, stop_reason: "", holder: "alice", video_fps: 15, video_width: 640, video_height: 480, video_quality: 70, map_version: 0, rx_dropped: 0 };

/** A robot on a fake call answering safety, chat, goals and conference like the real one. */
function robot(call) {
  call.onUser("safety", (p) => {
    const r = JSON.parse(p);
    call.toUser("safety", JSON.stringify({ type: "ack", id: r.id, ok: true, reason: "", code: "ok" }));
  });
  call.onUser("chat", (p) => {
    const r = JSON.parse(p);
    call.toUser("chat", JSON.stringify({ id: r.id, seq: 0, text: `ran ${r.text}`, final: true, ok: true, code: "ok" }));
  });
  call.onUser("goals", (p) => {
    const r = JSON.parse(p);
    if (r.type === "goal") call.toUser("goals", JSON.stringify({ type: "status", id: r.id, status: "active", progress: 0.5, reason: "", code: "accepted" }));
  });
  call.onUser("conference", (p) => {
    const r = JSON.parse(p);
    if (r.type === "say") call.toUser("conference", JSON.stringify({ type: "said", id: r.id, ok: true, reason: "", code: "ok" }));
  });
  call.onUser("map", () => {});
}

async function started({ seed = 1, calls = null } = {}) {
  const clock = new ManualClock();
  const out = [];
  const made = [];
  let attempts = 0;
  const session = new RobotSession({
    connect: async () => {
      const call = calls ? calls(attempts++) : new FakeCall({ seed });
      if (call instanceof Error) throw call;
      robot(call);
      made.push(call);
      return call;
    },
    emit: (m) => out.push(m),
    user: "alice",
    clock,
    random: seeded(seed),
    mapUrl: () => "blob:map",
  });
  await session.start();
  return { clock, out, session, made, call: () => made.at(-1) };
}

const ofType = (out, type) => out.filter((m) => m.type === type);

test("hello, then the robot's streams in the page's shapes", async () => {
  const { clock, out, call } = await started();
  assert.deepEqual(out[0], { type: "hello", robot: "guiabot", user: "alice", role: "driver", may_drive: true, map: null });
  assert.deepEqual(out[1], { type: "connection", state: "connected", detail: "", seconds: 0 });
  call().toUser("pose", JSON.stringify(POSE), { lossless: true });
  call().toUser("telemetry", JSON.stringify(TELEMETRY), { lossless: true });
  call().toUser("safety", JSON.stringify({ type: "state", armed: false, reason: "stop requested by bob (key)", code: "stopped", holder: "bob", cap: 0, blocked: false }), { lossless: true });
  call().toUser("plan", JSON.stringify({ type: "plan", seq: 3, goal: 7, points: [[1, 2], [3, 4]] }), { lossless: true });
  call().toUser("plan", JSON.stringify({ type: "plan", seq: 2, goal: 7, points: [] }), { lossless: true });
  call().toUser("plan", JSON.stringify({ type: "places", places: [{ name: "lab", x: 1, y: 2, yaw: null }] }), { lossless: true });
  call().toUser("plan", JSON.stringify({ type: "places", places: [{ name: "lab", x: 1, y: 2, yaw: null }] }), { lossless: true });
  const people = { type: "people", seq: 4, t: 1.5, cams: { navcam: 70 }, tracks: [{ id: 3, x: 4, y: 1.5, vx: -0.9, vy: 0, c: 0.93, src: ["laser", "camera"], r: 2.1, b: 0.52 }] };
  call().toUser("people", JSON.stringify(people), { lossless: true });
  const alert = { type: "alert", seq: 7, kind: "approaching", id: 3, text: "person approaching ahead, 2.1 m", distance: 2.1, bearing: 0.1 };
  for (let i = 0; i < 3; i++) call().toUser("people", JSON.stringify(alert), { lossless: true });
  call().toUser("conference", JSON.stringify({ type: "msg", seq: 1, from: "guiabot", kind: "robot", text: "alice joined (driver)" }), { lossless: true });
  call().toUser("conference", JSON.stringify({ type: "roster", seq: 1, users: [{ name: "alice", role: "driver", driving: true, you: true }] }), { lossless: true });
  call().toUser("conference", JSON.stringify({ type: "roster", seq: 1, users: [{ name: "alice", role: "driver", driving: true, you: true }] }), { lossless: true });
  await clock.advance(0.6);
  const pose = ofType(out, "pose")[0];
  assert.equal(typeof pose.recv, "number");
  delete pose.recv;
  assert.deepEqual(pose, { type: "pose", x: 1, y: 2, yaw: 0.5, v: 0.3, w: 0, state: "moving", detail: "goto lab", goal: 7, t: 12.5, cov: [0.1, 0.1, 0.01] });
  assert.deepEqual(ofType(out, "telemetry"), [{ type: "telemetry", ...TELEMETRY }]);
  assert.deepEqual(ofType(out, "safety"), [{ type: "safety", armed: false, text: "stop requested by bob (key)", code: "stopped", holder: "bob", cap: 0, blocked: false }], "the state's code (§18) goes to the page");
  assert.deepEqual(ofType(out, "plan"), [{ type: "plan", seq: 3, goal: 7, points: [[1, 2], [3, 4]] }], "an older plan is dropped");
  assert.deepEqual(ofType(out, "places"), [{ type: "places", places: [{ name: "lab", x: 1, y: 2, yaw: null }] }], "once while unchanged");
  assert.deepEqual(ofType(out, "people"), [{ ...people, tracks: [{ ...people.tracks[0], src: ["camera", "laser"] }] }]);
  assert.deepEqual(ofType(out, "people_alert"), [{ ...alert, type: "people_alert" }], "an alert once");
  assert.deepEqual(ofType(out, "roster"), [{ type: "roster", users: [{ name: "alice", role: "driver", driving: true, you: true }] }]);
  assert.deepEqual(ofType(out, "msg"), [{ type: "msg", seq: 1, from: "guiabot", kind: "robot", text: "alice joined (driver)" }]);
  const link = ofType(out, "link")[0];
  assert.deepEqual(link, { type: "link", rtt: 0.01, loss: 0 });
});

test("every stop `how` of §18's table reaches the robot as the page said it", async () => {
  // The table in docs/protocol.md, between its header row and the blank line after it.
  const doc = readFileSync(new URL("../../docs/protocol.md", import.meta.url), "utf8");
  const table = doc.split("| `how` | the user… |")[1].split("\n\n")[0];
  const documented = [...table.matchAll(/^\| `([a-z_]+)` \|/gm)].map((m) => m[1]);
  assert.ok(documented.includes("page_hidden") && documented.includes("touch"), documented.join());
  assert.deepEqual([...STOP_HOWS].sort(), [...documented].sort());
  const { clock, session, call } = await started();
  for (const how of documented) session.send({ type: "stop", how });
  await clock.advance(0.2);
  const hows = new Set(call().sent("safety").filter((m) => m.type === "stop").map((s) => s.how));
  assert.deepEqual([...hows].sort(), [...documented].sort());
});

test("page → client: stop, arm, chat, camera, say, goal, ping and bad messages", async () => {
  const { clock, out, session, call } = await started();
  session.send({ type: "stop", how: "key" });
  session.send({ type: "stop", how: "sideways" });
  session.send({ type: "arm" });
  session.send({ type: "chat", id: 4, text: "where?" });
  session.send({ type: "chat", id: 5, text: "say hello all" });
  session.send({ type: "camera", id: 6, name: "usercam" });
  session.send({ type: "goal", x: 1, y: 2, yaw: null });
  session.send({ type: "ping", t: 1234.5 });
  session.send({ type: "goal", x: "a", y: 2 });
  session.send({ type: "camera", id: 7, name: "rearcam" });
  session.send({ type: "chat", id: [1], text: "where?" });
  session.send({ type: "ping", t: "now" });
  session.send({ type: "warp" });
  session.send(null);
  await clock.advance(0.2);
  const stops = call().sent("safety").filter((m) => m.type === "stop");
  assert.deepEqual([...new Set(stops.map((s) => s.how))].sort(), ["button", "key"], "an unknown how is a button");
  assert.deepEqual(ofType(out, "ack"), [
    { type: "ack", what: "stop", ok: true, text: "", code: "ok" },
    { type: "ack", what: "stop", ok: true, text: "", code: "ok" },
    { type: "ack", what: "arm", ok: true, text: "", code: "ok" },
  ]);
  assert.deepEqual(ofType(out, "chat"), [
    { type: "chat", id: 4, text: "ran where?", ok: true, final: true, code: "ok" },
    { type: "chat", id: 6, text: "ran usercam", ok: true, final: true, code: "ok" },
  ]);
  assert.deepEqual(ofType(out, "said"), [{ type: "said", id: 5, ok: true, text: "", code: "ok" }]);
  assert.deepEqual(call().sent("conference").filter((m) => m.type === "say").map((m) => m.text), ["hello all"]);
  assert.deepEqual(ofType(out, "goal"), [
    { type: "goal", x: 1, y: 2, yaw: null, status: "sent", progress: 0, text: "", code: "" },
    { type: "goal", x: 1, y: 2, yaw: null, status: "active", progress: 0.5, text: "", code: "accepted" },
  ]);
  assert.deepEqual(ofType(out, "pong"), [{ type: "pong", t: 1234.5 }]);
  assert.deepEqual(ofType(out, "error").map((m) => m.text), [
    "a goal needs numbers x, y (and yaw)", "camera: 'name' must be navcam or usercam",
    "chat: 'id' must be a number, a text of at most 64 characters or null",
    "ping: 't' must be a finite number or null",
    "unknown message type 'warp'", "not a JSON message with a type",
  ]);
});

test("an observer's goal is refused on the page; the fail-safe stops an armed robot", async () => {
  const { clock, out, session, call } = await started();
  assert.equal(session.failSafe(), false, "nothing may move: no stop");
  call().toUser("safety", JSON.stringify({ type: "state", armed: true, reason: "", holder: "alice", cap: 0.5, blocked: false }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(session.failSafe(), true);
  await clock.advance(0.1);
  assert.equal(call().sent("safety").at(-1).how, "tab_closed");
  session.setRole("observer");
  assert.deepEqual(out.at(-1), { type: "hello", robot: "guiabot", user: "alice", role: "observer", may_drive: false, map: null });
  session.send({ type: "goal", x: 1, y: 2, yaw: 0 });
  assert.equal(out.at(-1).text, "observers may not send goals");
  assert.equal(session.failSafe(), false, "an observer's page does not stop the robot on leaving");
});

test("a dropped call: reconnecting, reconnected with seconds, a request in flight fails, the next one goes", async () => {
  const { clock, out, session, made } = await started({ calls: (n) => (n === 1 ? new Error("no answer") : new FakeCall({ seed: n })) });
  made[0].onUser("chat", () => {}); // this robot never answers the chat
  session.send({ type: "chat", id: 1, text: "fwd 1" });
  await clock.advance(0.1);
  made[0].endWith("dropped", "heartbeats stopped");
  await clock.advance(0.05);
  assert.deepEqual(ofType(out, "connection").at(-1), { type: "connection", state: "reconnecting", detail: "reconnecting… (heartbeats stopped)", seconds: 0 });
  assert.deepEqual(ofType(out, "chat").at(-1), { type: "chat", id: 1, text: "the call ended", ok: false, final: true, code: "" });
  session.send({ type: "stop", how: "button" }); // while no call is up: sent on the next
  assert.ok(await clock.until(() => made.length === 2 && ofType(out, "connection").at(-1).state === "reconnected", 10));
  const reconnected = ofType(out, "connection").at(-1);
  assert.ok(reconnected.seconds > 0);
  await clock.advance(0.1);
  assert.equal(made[1].sent("safety").filter((m) => m.type === "stop").length >= 1, true);
  assert.deepEqual(ofType(out, "ack").at(-1), { type: "ack", what: "stop", ok: true, text: "", code: "ok" });
  assert.equal(made[0].sent("chat").every((m) => m.text === "fwd 1"), true);
  assert.equal(made[1].sent("chat").length, 0, "the old request is never sent on the new call");
  await session.close();
  assert.equal(ofType(out, "connection").at(-1).state, "ended");
});

test("a refusal while reconnecting ends the session", async () => {
  const refused = new Error("not a contact");
  refused.name = "CallRejected";
  const { clock, out, made } = await started({ calls: (n) => (n === 0 ? new FakeCall() : refused) });
  made[0].endWith("dropped", "");
  assert.ok(await clock.until(() => ofType(out, "connection").at(-1).state === "ended", 10));
  assert.equal(ofType(out, "connection").at(-1).detail, "disconnected: guiabot refused the call: not a contact");
});

test("video frames reach the page as {type, header, data}", async () => {
  const { clock, out, call } = await started();
  for (const d of fragmentFrame({ frameId: 9, camera: "navcam", captureTime: 1.5, data: Uint8Array.of(0xff, 0xd8, 0xff, 0xd9) })) call().toUser("video", d, { lossless: true });
  await clock.advance(0.05);
  const [frame] = ofType(out, "video");
  assert.deepEqual(frame.header, { kind: "video", codec: "jpeg", key: true, camera: "navcam", frame_id: 9, capture_time: 1.5 });
  assert.deepEqual([...frame.data], [0xff, 0xd8, 0xff, 0xd9]);
});

test("seeded fuzz: garbage on every channel is dropped and counted, never thrown", async () => {
  const { clock, out, session, call } = await started({ seed: 5 });
  const random = seeded(12345);
  const channels = ["chat", "safety", "goals", "pose", "telemetry", "plan", "people", "conference", "map", "video", "audio", "relay"];
  const valid = [JSON.stringify(POSE), JSON.stringify(TELEMETRY), '{"type":"plan","seq":1,"goal":null,"points":[[0,0]]}', '{"type":"roster","seq":1,"users":[]}', '{"type":"ack","id":1,"ok":true}'];
  const garbage = () => {
    const r = random();
    if (r < 0.3) { // mutate a valid message
      const base = valid[Math.floor(random() * valid.length)];
      const at = Math.floor(random() * base.length);
      return base.slice(0, at) + String.fromCharCode(Math.floor(random() * 128)) + base.slice(at + 1);
    }
    if (r < 0.5) return JSON.stringify({ type: ["ack", "state", "status", "plan", "places", "people", "alert", "roster", "msg", "said", "offer", "topics"][Math.floor(random() * 12)], id: random() < 0.5 ? -1 : 1.5, seq: "x", points: [[NaN]], users: [1], tracks: {}, places: [{}], parts: 0 });
    const bytes = new Uint8Array(Math.floor(random() * 80));
    for (let i = 0; i < bytes.length; i++) bytes[i] = Math.floor(random() * 256);
    if (bytes.length) bytes[0] = [1, 2, 3, random() * 256][Math.floor(random() * 4)];
    return bytes;
  };
  const before = out.length;
  for (let i = 0; i < 3000; i++) {
    const name = channels[Math.floor(random() * channels.length)];
    const payload = garbage();
    assert.doesNotThrow(() => call().channels.get(name)?.onmessage?.(payload));
  }
  await clock.advance(0.5);
  const drops = session.drops;
  const total = Object.values(drops).reduce((a, b) => a + b, 0);
  assert.ok(total > 1000, `dropped and counted: ${JSON.stringify(drops)}`);
  for (const m of out.slice(before)) assert.equal(typeof m.type, "string");
  session.send({ type: "ping", t: 1 });
  assert.deepEqual(out.at(-1), { type: "pong", t: 1 }, "the session still works");
});
