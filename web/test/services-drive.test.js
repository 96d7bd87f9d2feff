// Driving by hand (§27) on the user's side, over the fake call with seeded loss: a command
// is sent at once and repeated at 20 Hz for its hold, then no more (the robot stops
// itself); a release is sent 4 times (0, 20, 40, 90 ms); seq grows by one per datagram; drive_state is
// decoded strictly; the session takes the page's `drive` and ends repeating on a stop.
import { test } from "node:test";
import assert from "node:assert/strict";
import { DriveService, decodeDriveState } from "../src/services/drive.js";
import { RobotSession } from "../src/session.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

const STATE = { type: "drive_state", seq: 41, active: true, code: "ok", reason: "", linear: 0.3, angular: -0.5, cap: 0.42 };

function serviceOn(call, clock, onState = null) {
  const drive = new DriveService(call, { random: seeded(3), onState });
  clock.every(0.02, () => drive.tick(clock.now()));
  drive.tick(clock.now());
  return drive;
}

/** The robot's view: every command that arrived, with the (fake) time it arrived. */
function robotLog(call, clock) {
  const got = [];
  call.onUser("drive", (p) => got.push({ ...JSON.parse(p), at: clock.now() }));
  return got;
}

test("a command is sent at once, repeated at 20 Hz for its hold, then not at all", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const got = robotLog(call, clock);
  const drive = serviceOn(call, clock);
  const t0 = clock.now();
  drive.drive(0.3, -0.5, { now: t0 });
  assert.equal(call.sent("drive").length, 1, "the first copy leaves before any tick");
  await clock.advance(1.0);
  const sent = call.sent("drive");
  // 0.25 s of hold at 20 Hz: the first and 4 or 5 repeats (the last one on the edge).
  assert.ok(sent.length >= 5 && sent.length <= 6, `${sent.length} copies`);
  assert.ok(sent.every((m) => m.type === "drive" && m.linear === 0.3 && m.angular === -0.5));
  for (let i = 1; i < sent.length; i++) assert.equal(sent[i].seq, (sent[0].seq + i) % 2 ** 32);
  const gaps = got.slice(1).map((m, i) => m.at - got[i].at);
  assert.ok(gaps.every((g) => g > 0.035 && g < 0.065), `20 Hz: ${gaps}`);
  assert.ok(got.at(-1).at - t0 <= 0.25 + 1e-9, "nothing after the hold");
  assert.equal(drive.driving, false);
});

test("calling again with the same velocity keeps the 20 Hz cadence; a new one goes at once", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const drive = serviceOn(call, clock);
  // A page holding a key: the same command every 50 ms for 1 s.
  for (let i = 0; i < 20; i++) {
    drive.drive(0.5, 0, { now: clock.now() });
    await clock.advance(0.05);
  }
  const held = call.sent("drive").length;
  assert.ok(held >= 19 && held <= 22, `about 20 datagrams in 1 s, got ${held}`);
  drive.drive(0.5, 1.0, { now: clock.now() });
  assert.equal(call.sent("drive").length, held + 1, "a changed command leaves at once");
  assert.equal(call.sent("drive").at(-1).angular, 1.0);
});

test("a release is sent 4 times, the first repeats 20 ms apart, and ends the repeating", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const got = robotLog(call, clock);
  const drive = serviceOn(call, clock);
  drive.drive(0.5, 0, { now: clock.now(), hold: 10 });
  await clock.advance(0.12);
  const before = call.sent("drive").length;
  const t0 = clock.now();
  const sentAt = []; // when each copy leaves (the fake call's delivery would blur it)
  const send = drive.send.bind(drive);
  drive.send = (linear, angular) => { sentAt.push(Math.round((clock.now() - t0) * 1000)); send(linear, angular); };
  drive.drive(0, -0, { now: t0 });
  await clock.advance(1.0);
  const after = call.sent("drive").slice(before);
  assert.deepEqual(after.map((m) => [m.linear, m.angular]), [[0, 0], [0, 0], [0, 0], [0, 0]]);
  // At once, then the two quick repeats (a lost copy costs 20 ms), then 50 ms later (due
  // at 90 ms, sent on the session's next 20 ms tick).
  assert.deepEqual(sentAt, [0, 20, 40, 100]);
  assert.equal(got.slice(before).length, 4, "all four arrived");
  assert.ok(after.every((m, i) => i === 0 || m.seq === after[i - 1].seq + 1));
  assert.equal(drive.driving, false);
});

test("over 30 % loss the robot keeps getting fresh commands while held, and a release", async () => {
  const clock = new ManualClock();
  const call = new FakeCall({ seed: 9, upLoss: 0.3 });
  const got = robotLog(call, clock);
  const drive = serviceOn(call, clock);
  for (let i = 0; i < 40; i++) {
    drive.drive(0.4, 0, { now: clock.now() }); // a page at 20 Hz for 2 s
    await clock.advance(0.05);
  }
  drive.drive(0, 0, { now: clock.now() });
  await clock.advance(0.5);
  const moving = got.filter((m) => m.linear !== 0);
  const gaps = moving.slice(1).map((m, i) => m.at - moving[i].at);
  // The robot's stale_after is 0.3 s: with repeats, loss never starves it that long.
  assert.ok(Math.max(...gaps) < 0.3, `longest gap ${Math.max(...gaps)}`);
  assert.ok(got.some((m) => m.linear === 0 && m.angular === 0), "a release copy arrived");
  assert.ok(got.every((m, i) => i === 0 || m.seq > got[i - 1].seq), "seq always grows");
});

test("drive() refuses numbers that are not finite", () => {
  const drive = new DriveService(new FakeCall());
  assert.throws(() => drive.drive(NaN, 0), RangeError);
  assert.throws(() => drive.drive(0, Infinity), RangeError);
  assert.equal(drive.sent, 0);
});

test("drive_state is decoded strictly; a bad one is dropped and counted", async () => {
  assert.deepEqual(decodeDriveState(JSON.stringify(STATE)), { seq: 41, active: true, code: "ok", reason: "", linear: 0.3, angular: -0.5, cap: 0.42 });
  const bad = [
    "not json",
    "[1]",
    JSON.stringify({ ...STATE, type: "drive" }),
    JSON.stringify({ ...STATE, seq: -1 }),
    JSON.stringify({ ...STATE, seq: 2 ** 32 }),
    JSON.stringify({ ...STATE, active: "yes" }),
    JSON.stringify({ ...STATE, linear: "0.3" }),
    JSON.stringify({ ...STATE, angular: null }),
    JSON.stringify({ ...STATE, cap: -1 }),
    JSON.stringify({ ...STATE, code: 7 }),
    JSON.stringify({ ...STATE, reason: 7 }),
    new Uint8Array([1, 2, 3]),
  ];
  for (const payload of bad) assert.throws(() => decodeDriveState(payload), { name: "DecodeError" }, String(payload));
  const clock = new ManualClock();
  const call = new FakeCall();
  const states = [];
  const drive = serviceOn(call, clock, (s) => states.push(s));
  for (const payload of bad) call.toUser("drive", payload);
  call.toUser("drive", JSON.stringify({ ...STATE, code: "not_armed", active: false, reason: "the robot is stopped: re-arm it" }));
  await clock.advance(0.05);
  assert.equal(drive.drops.total, bad.length);
  assert.deepEqual(states.map((s) => s.code), ["not_armed"]);
});

// ------------------------------------------------------------------ the session

async function session({ role = "driver" } = {}) {
  const clock = new ManualClock();
  const out = [];
  let call = null;
  const s = new RobotSession({
    connect: async () => {
      call = new FakeCall({ role });
      call.onUser("safety", (p) => {
        const r = JSON.parse(p);
        call.toUser("safety", JSON.stringify({ type: "ack", id: r.id, ok: true, reason: "", code: "ok" }));
      });
      return call;
    },
    emit: (m) => out.push(m),
    user: "alice",
    clock,
    random: seeded(2),
    mapUrl: () => "blob:map",
  });
  await s.start();
  return { s, clock, out, call: () => call };
}

test("the page's drive goes on the call, drive_state comes back to the page", async () => {
  const { s, clock, out, call } = await session();
  s.send({ type: "drive", linear: 0.5, angular: 1.0 });
  assert.deepEqual(call().sent("drive").map((m) => [m.linear, m.angular]), [[0.5, 1.0]]);
  call().toUser("drive", JSON.stringify(STATE));
  await clock.advance(0.5);
  assert.ok(call().sent("drive").length >= 5, "repeated for the hold");
  assert.deepEqual(out.filter((m) => m.type === "drive_state"), [{ type: "drive_state", seq: 41, active: true, code: "ok", text: "", linear: 0.3, angular: -0.5, cap: 0.42 }]);
  s.send({ type: "drive", linear: 0, angular: 0 });
  await clock.advance(0.5);
  assert.deepEqual(call().sent("drive").slice(-3).map((m) => m.linear + m.angular), [0, 0, 0]);
  await s.close();
});

test("a bad page drive is a one-line error and releases; observers may not drive", async () => {
  const { s, clock, out, call } = await session();
  s.send({ type: "drive", linear: 0.5, angular: 0 });
  let errors = 0;
  for (const bad of [{ type: "drive", linear: "fast", angular: 0 }, { type: "drive", linear: 0.5 }, { type: "drive", linear: 1e999, angular: 0 }]) {
    const sent = call().sent("drive").length;
    s.send(bad);
    await clock.advance(0.3);
    const after = call().sent("drive").slice(sent);
    assert.deepEqual(after.map((m) => [m.linear, m.angular]), [[0, 0], [0, 0], [0, 0], [0, 0]], "released, no repeat");
    const error = out.filter((m) => m.type === "error").at(-1);
    assert.equal(out.filter((m) => m.type === "error").length, ++errors);
    assert.ok(error && !error.text.includes("\n") && error.text.includes("linear"), error?.text);
    s.send({ type: "drive", linear: 0.5, angular: 0 });
  }
  await s.close();
  const observer = await session({ role: "observer" });
  observer.s.send({ type: "drive", linear: 0.5, angular: 0 });
  assert.equal(observer.call().sent("drive").length, 0);
  assert.deepEqual(observer.out.at(-1), { type: "error", text: "observers may not drive" });
  await observer.s.close();
});

test("a stop or a goal ends the repeating at once: no drive follows it", async () => {
  const { s, clock, call } = await session();
  for (const end of [{ type: "stop", how: "key" }, { type: "goal", x: 1, y: 2, yaw: null }]) {
    s.send({ type: "drive", linear: 0.5, angular: 0 });
    s.drive(0.5, 0, { hold: 10 });
    await clock.advance(0.1);
    s.send(end);
    const sent = call().sent("drive").length;
    await clock.advance(0.5);
    assert.equal(call().sent("drive").length, sent, `no drive after a ${end.type}`);
  }
  await s.close();
});
