// Chat (§14) and safety (§18) over a fake call with seeded loss: requests repeat until
// answered, replies are taken once each, a stop is repeated until acked.
import { test } from "node:test";
import assert from "node:assert/strict";
import { ChatService, SafetyService } from "../src/services/services.js";
import { decodeSafetyReply } from "../src/services/messages.js";
import { DecodeError } from "../src/services/util.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

/** A robot's chat: "fwd 1" gets an ack and, 0.5 s later, its final reply; repeats get every reply sent so far. */
function chatRobot(call, clock) {
  const replies = new Map();
  const requests = [];
  call.onUser("chat", (payload) => {
    const req = JSON.parse(payload);
    requests.push(req);
    if (!replies.has(req.id)) {
      replies.set(req.id, []);
      const say = (text, final, ok, code) => {
        const list = replies.get(req.id);
        const reply = JSON.stringify({ id: req.id, seq: list.length, text, final, ok, code });
        list.push(reply);
        call.toUser("chat", reply);
      };
      if (req.text === "fwd 1") {
        say("Forward command received", false, true, "accepted");
        clock.sleep(0.5).then(() => say("finished moving", true, true, "finished"));
      } else {
        say("x 1.00 m, y 2.00 m, heading 90°", true, true, "ok");
      }
    } else {
      for (const reply of replies.get(req.id)) call.toUser("chat", reply);
    }
  });
  return requests;
}

test("a chat request gets each reply once, and its final, over 30 % loss", async () => {
  const clock = new ManualClock();
  const call = new FakeCall({ seed: 7, upLoss: 0.3, downLoss: 0.3 });
  const requests = chatRobot(call, clock);
  const chat = new ChatService(call, { random: seeded(3) });
  clock.every(0.02, () => chat.tick(clock.now()));
  chat.tick(clock.now());
  const got = [];
  let final = null;
  chat.request("fwd 1", (r) => got.push(r), { now: clock.now() }).then((r) => { final = r; });
  assert.ok(await clock.until(() => final !== null, 30));
  assert.deepEqual(got.map((r) => r.seq), [0, 1]);
  assert.equal(final.text, "finished moving");
  assert.equal(final.code, "finished");
  assert.equal(final.ok, true);
  assert.ok(requests.every((r) => r.id === requests[0].id && r.text === "fwd 1"));
});

test("a query with no answer times out; ids are fresh per request", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const chat = new ChatService(call);
  clock.every(0.02, () => chat.tick(clock.now()));
  let error = null;
  chat.request("where?", null, { timeout: 2, now: clock.now() }).catch((e) => { error = e; });
  chat.request("where?", null, { timeout: 2, now: clock.now() }).catch(() => {});
  await clock.advance(2.5);
  assert.equal(error?.code, "timeout");
  const ids = new Set(call.sent("chat").map((m) => m.id));
  assert.equal(ids.size, 2);
  assert.ok(call.sent("chat").length >= 6, "each request was repeated every 0.3 s");
});

test("a stop is repeated after 20, 20, then every 50 ms until acked, and no stop is lost when acks are", async () => {
  const clock = new ManualClock();
  // Every ack of the first 5 is lost: the user must keep sending.
  const call = new FakeCall({ seed: 11 });
  const stops = [];
  const at = [];
  let acksSent = 0;
  const t0 = clock.now();
  call.onUser("safety", (payload) => {
    const req = JSON.parse(payload);
    stops.push(req);
    acksSent += 1;
    if (acksSent <= 5) return; // lost on the way back
    call.toUser("safety", JSON.stringify({ type: "ack", id: req.id, ok: true, reason: "", code: "ok" }));
  });
  const safety = new SafetyService(call, { random: seeded(5) });
  const send = safety.send.bind(safety);
  safety.send = (type, payload) => { at.push(Math.round((clock.now() - t0) * 1000)); send(type, payload); };
  clock.every(0.02, () => safety.tick(clock.now()));
  let ack = null;
  safety.request("stop", { how: "key", now: clock.now() }).then((a) => { ack = a; });
  assert.ok(await clock.until(() => ack !== null, 5));
  assert.equal(ack.ok, true);
  assert.equal(stops.length, 6, "sent until the 6th copy's ack came back");
  // When each copy left: the quick first repeats, then every 50 ms (on the 20 ms tick: 60).
  assert.deepEqual(at, [0, 20, 40, 100, 160, 220]);
  assert.ok(stops.every((s) => s.type === "stop" && s.how === "key" && s.id === stops[0].id));
  const sentAt = safety.sent.stop;
  await clock.advance(1);
  assert.equal(safety.sent.stop, sentAt, "no more copies after the ack");
});

test("an arm waits for the client's own stop, so the stop's repeats cannot undo it", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  // The robot: a stop disarms it (every copy), an arm arms it; the first 3 stop acks are lost.
  let armed = true;
  let stopAcks = 0;
  const order = [];
  call.onUser("safety", (payload) => {
    const req = JSON.parse(payload);
    order.push(req.type);
    armed = req.type === "arm" ? true : req.type === "stop" ? false : armed;
    if (req.type === "stop" && ++stopAcks <= 3) return;
    call.toUser("safety", JSON.stringify({ type: "ack", id: req.id, ok: true, reason: "", code: "ok" }));
  });
  const safety = new SafetyService(call, { random: seeded(9) });
  clock.every(0.02, () => safety.tick(clock.now()));
  let stopAck = null;
  let armAck = null;
  safety.request("stop", { how: "key", now: clock.now() }).then((a) => { stopAck = a; });
  safety.request("arm", { now: clock.now() }).then((a) => { armAck = a; });
  assert.ok(await clock.until(() => armAck !== null, 5));
  assert.equal(stopAck?.ok, true);
  assert.equal(armAck.ok, true);
  await clock.advance(0.5);
  assert.deepEqual(order, ["stop", "stop", "stop", "stop", "arm"]);
  assert.equal(armed, true, "a copy of the stop undid the arm");
  assert.equal(safety.stopsInFlight.size, 0);
});

test("a stop asked for while an arm waits wins: the arm is not sent", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  let armed = true;
  let firstStopAcks = 0;
  let firstId = null;
  const order = [];
  call.onUser("safety", (payload) => {
    const req = JSON.parse(payload);
    order.push(req.type);
    armed = req.type === "arm" ? true : req.type === "stop" ? false : armed;
    firstId ??= req.id;
    if (req.id === firstId && ++firstStopAcks <= 3) return; // the first stop's acks are lost
    call.toUser("safety", JSON.stringify({ type: "ack", id: req.id, ok: true, reason: "", code: "ok" }));
  });
  const safety = new SafetyService(call, { random: seeded(4) });
  clock.every(0.02, () => safety.tick(clock.now()));
  let arm = null;
  safety.request("stop", { how: "key", now: clock.now() });
  safety.request("arm", { now: clock.now() }).then((a) => { arm = a; });
  await clock.advance(0.03);
  safety.request("stop", { how: "button", now: clock.now() });
  assert.ok(await clock.until(() => arm !== null, 5));
  assert.equal(arm.ok, false);
  assert.equal(arm.code, "stopped");
  await clock.advance(0.5);
  assert.equal(safety.sent.arm, 0);
  assert.ok(!order.includes("arm"));
  assert.equal(armed, false, "the arm undid a later stop");
});

/** A safety service on its 20 ms tick, towards a robot that answers nothing. */
function towardsASilentRobot() {
  const clock = new ManualClock();
  const safety = new SafetyService(new FakeCall());
  clock.every(0.02, () => safety.tick(clock.now()));
  return { clock, safety };
}

test("an arm whose time ran out waiting for a stop is not sent", async () => {
  const { clock, safety } = towardsASilentRobot();
  let armError = null;
  safety.request("stop", { now: clock.now() }).catch(() => {});
  safety.request("arm", { now: clock.now() }).catch((e) => { armError = e; });
  assert.ok(await clock.until(() => armError !== null, 7));
  assert.equal(armError.code, "timeout");
  assert.equal(safety.sent.arm, 0, "the arm never went");
});

test("an arm waiting for a stop ends with the call, not never", async () => {
  const { clock, safety } = towardsASilentRobot();
  let stopError = null;
  let armError = null;
  safety.request("stop", { now: clock.now() }).catch((e) => { stopError = e; });
  safety.request("arm", { now: clock.now() }).catch((e) => { armError = e; });
  await clock.advance(0.1);
  safety.close();
  assert.ok(await clock.until(() => armError !== null, 1));
  assert.equal(stopError?.code, "call_ended");
  assert.equal(armError.code, "call_ended");
  assert.equal(safety.sent.arm, 0, "the arm never went");
});

test("a stop reaches the robot over 50 % loss both ways", async () => {
  const clock = new ManualClock();
  const call = new FakeCall({ seed: 23, upLoss: 0.5, downLoss: 0.5 });
  let robotStops = 0;
  call.onUser("safety", (payload) => {
    const req = JSON.parse(payload);
    robotStops += 1;
    call.toUser("safety", JSON.stringify({ type: "ack", id: req.id, ok: true, reason: "", code: "ok" }));
  });
  const safety = new SafetyService(call);
  clock.every(0.02, () => safety.tick(clock.now()));
  let ack = null;
  safety.request("stop", { how: "button", now: clock.now() }).then((a) => { ack = a; });
  assert.ok(await clock.until(() => ack !== null, 5));
  assert.ok(robotStops >= 1);
});

test("arm repeats every 0.3 s, a refusal comes back with its code, the state is passed on", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  let arms = 0;
  const states = [];
  call.onUser("safety", (payload) => {
    const req = JSON.parse(payload);
    arms += 1;
    if (arms < 3) return;
    call.toUser("safety", JSON.stringify({ type: "ack", id: req.id, ok: false, reason: "refused: not yours", code: "not_holder" }));
    call.toUser("safety", JSON.stringify({ type: "state", armed: false, reason: "stopped", holder: "bob", cap: 0, blocked: false }));
  });
  const safety = new SafetyService(call, { onState: (s) => states.push(s) });
  clock.every(0.02, () => safety.tick(clock.now()));
  let ack = null;
  safety.request("arm", { now: clock.now() }).then((a) => { ack = a; });
  assert.ok(await clock.until(() => ack !== null, 5));
  assert.deepEqual([ack.ok, ack.code], [false, "not_holder"]);
  assert.equal(arms, 3);
  // An older robot sends no code: it reads as "".
  assert.deepEqual(states, [{ type: "state", armed: false, reason: "stopped", code: "", holder: "bob", cap: 0, blocked: false }]);
});

test("the safety state carries the code of the latest stop, so a page tells a deadman from a button", () => {
  const state = (fields) => decodeSafetyReply(JSON.stringify({ type: "state", armed: false, holder: "alice", cap: 0, blocked: false, ...fields }));
  const deadman = state({ reason: "driver alice's link lost: silent 0.45 s (deadman)", code: "link_silent" });
  assert.equal(deadman.code, "link_silent");
  assert.equal(state({ reason: "video frozen for 1.0 s: the robot stopped itself", code: "video_stale" }).code, "video_stale");
  assert.equal(state({ reason: "stop requested by alice (button)", code: "stopped" }).code, "stopped");
  // A code this page does not know is kept as it is; one that is not short text does not decode.
  assert.equal(state({ reason: "", code: "newer_code" }).code, "newer_code");
  assert.throws(() => state({ reason: "", code: 7 }), DecodeError);
  assert.throws(() => state({ reason: "", code: "x".repeat(65) }), DecodeError);
});
