// The user side of a call as a sans-IO state machine (§5.7, §7, §8): driven with bytes
// and clock values, no I/O and no timers. A JS responder plays the robot.
import { test } from "node:test";
import assert from "node:assert/strict";
import { CallEnded, CallError, CallRejected, CallTimeout, KeyMismatch } from "../src/errors.js";
import { concat, fromHex, utf8 } from "../src/bytes.js";
import { encodeKey, generateKeyPair } from "../src/identity.js";
import { decodeFrame, encodeBundle, encodeDatagram, encodeRetry, encodeWelcome, dataHeader } from "../src/proto/frames.js";
import { AESGCM, CHACHAPOLY, ResponderHandshake } from "../src/proto/noise.js";
import { CallSession, CallSetup, HELLO_REPEAT, checkRobotKey, suiteNumbers } from "../src/proto/session.js";

const user = generateKeyPair();
const robot = generateKeyPair();
const CALL_ID = fromHex("0011223344556677");

function setup(offers = [AESGCM, CHACHAPOLY], connectTimeout = 5) {
  let ts = 1000n;
  return new CallSetup({
    staticPrivate: user.privateKey,
    robotPublic: robot.publicKey,
    caller: "alice",
    robot: "guiabot",
    instance: new Uint8Array(8).fill(1),
    callId: CALL_ID,
    offers,
    now: 100,
    connectTimeout,
    wallTimeNs: () => (ts += 1n),
  });
}

/** The robot: reads the HELLO and answers with `body` (JSON text). */
function welcome(/** @type {Uint8Array} */ hello, /** @type {object} */ body, key = robot.privateKey) {
  const frame = /** @type {any} */ (decodeFrame(hello));
  const responder = new ResponderHandshake({ staticPrivate: key, prologue: frame.prologue, suite: frame.suite });
  const p1 = JSON.parse(new TextDecoder().decode(responder.readMessage(frame.noiseMessage)));
  const { message, keys } = responder.writeMessage(utf8(JSON.stringify(body)));
  return { frame: encodeWelcome(CALL_ID, message), keys, p1 };
}

test("HELLO schedule: at once, every 0.25 s, then the connect timeout", () => {
  const s = setup();
  assert.deepEqual(s.poll(100).send, s.hello);
  assert.equal(s.poll(100.1).send, null);
  assert.deepEqual(s.poll(100 + HELLO_REPEAT).send, s.hello);
  assert.equal(s.nextDeadline(), 100 + 2 * HELLO_REPEAT);
  const { expired } = s.poll(105);
  assert.ok(expired instanceof CallTimeout);
  assert.equal(expired.message, "robot guiabot did not answer within 5 s (is it online?)");
  assert.equal(s.poll(105.5).send, null); // over
});

test("a robot's token appearing makes the next HELLO due at once, after the first 0.25 s", () => {
  const s = setup();
  s.robotAppeared(99); // before any HELLO: nothing changes
  assert.deepEqual(s.poll(100).send, s.hello);
  s.robotAppeared(100.1); // the watch's history, during the first 0.25 s: no news
  assert.equal(s.nextDeadline(), 100 + HELLO_REPEAT);
  assert.deepEqual(s.poll(100 + HELLO_REPEAT).send, s.hello);
  s.robotAppeared(100.3); // the link is back: now, not at 100.5
  assert.equal(s.nextDeadline(), 100.3);
  assert.deepEqual(s.poll(100.3).send, s.hello);
  assert.equal(s.nextDeadline(), 100.3 + HELLO_REPEAT);
  s.fail(new CallError("closing"));
  s.robotAppeared(101); // over: nothing more is due
  assert.equal(s.poll(101).send, null);
});

test("accepted WELCOME: keys match the robot's, p1 carries user and an increasing ts", () => {
  const s = setup();
  const w = welcome(s.hello, { accepted: true, robot: "guiabot", role: "driver" });
  assert.equal(w.p1.user, "alice");
  const r = /** @type {any} */ (s.receive(w.frame, "guiabot"));
  assert.equal(r.kind, "accepted");
  assert.equal(r.answer.role, "driver");
  assert.deepEqual(r.keys.sendKey, w.keys.receiveKey);
  assert.deepEqual(r.keys.receiveKey, w.keys.sendKey);
  assert.equal(s.receive(w.frame, "guiabot").kind, "ignored"); // an answer to a repeat
});

test("a forged WELCOME is dropped and does not spoil the genuine one (§5.7, §12)", () => {
  const s = setup();
  // Anyone can read the call id in the HELLO and inject an answer: a valid point and junk.
  const forged = encodeWelcome(CALL_ID, concat(generateKeyPair().publicKey, new Uint8Array(72).fill(3)));
  assert.deepEqual(s.receive(forged, "guiabot"), { kind: "ignored", reason: "forged" });
  const short = encodeWelcome(CALL_ID, new Uint8Array(40));
  assert.deepEqual(s.receive(short, "guiabot"), { kind: "ignored", reason: "malformed" });
  const genuine = welcome(s.hello, { accepted: true, robot: "guiabot", role: "observer" });
  assert.deepEqual(s.receive(genuine.frame, "mallory"), { kind: "ignored", reason: "sender_mismatch" });
  assert.equal(s.receive(genuine.frame, "guiabot").kind, "accepted");
});

test("refusals: the robot's reason, a default, another robot name, a bad payload", () => {
  let s = setup();
  let r = /** @type {any} */ (s.receive(welcome(s.hello, { accepted: false, robot: "guiabot", reason: "not in the contact list of guiabot" }).frame, "guiabot"));
  assert.ok(r.error instanceof CallRejected);
  assert.equal(r.error.message, "not in the contact list of guiabot");
  s = setup();
  r = s.receive(welcome(s.hello, { accepted: false, robot: "guiabot" }).frame, "guiabot");
  assert.equal(r.error.message, "guiabot refused the call");
  s = setup();
  r = s.receive(welcome(s.hello, { accepted: true, robot: "x" }).frame, "guiabot");
  assert.ok(r.error instanceof CallError);
  assert.equal(r.error.message, `the robot with guiabot's key answered as "x"`);
  s = setup();
  r = s.receive(welcome(s.hello, { accepted: "yes", robot: "guiabot" }).frame, "guiabot");
  assert.deepEqual(r, { kind: "ignored", reason: "malformed" });
  assert.equal(s.outcome, null); // still waiting for a good one
});

test("RETRY: once to a suite offered; a second pick fails; others ignored (§5.2)", () => {
  const s = setup([AESGCM, CHACHAPOLY]);
  const first = s.hello;
  assert.equal(/** @type {any} */ (s.receive(encodeRetry(CALL_ID, 7), "guiabot")).reason, "unexpected_retry");
  assert.equal(/** @type {any} */ (s.receive(encodeRetry(CALL_ID, AESGCM), "guiabot")).reason, "retry_repeated");
  const r = /** @type {any} */ (s.receive(encodeRetry(CALL_ID, CHACHAPOLY), "guiabot"));
  assert.equal(r.kind, "resend");
  assert.notDeepEqual(r.hello, first);
  const hello = /** @type {any} */ (decodeFrame(r.hello));
  assert.deepEqual([hello.suite, hello.offers], [CHACHAPOLY, [AESGCM, CHACHAPOLY]]);
  assert.deepEqual(s.poll(100).send, r.hello); // the repeats carry the new HELLO
  assert.equal(s.receive(welcome(r.hello, { accepted: true, robot: "guiabot" }).frame, "guiabot").kind, "accepted");
  const t = setup([CHACHAPOLY, AESGCM]);
  t.receive(encodeRetry(CALL_ID, AESGCM), "guiabot");
  const failed = /** @type {any} */ (t.receive(encodeRetry(CALL_ID, CHACHAPOLY), "guiabot"));
  assert.equal(failed.error.message, "cipher suite negotiation with guiabot failed: it asked for aesgcm, then chachapoly");
});

test("KEY MISMATCH only when the robot is online with other keys only (§2.2)", () => {
  const stored = encodeKey(robot.publicKey);
  const other = encodeKey(generateKeyPair().publicKey);
  assert.equal(checkRobotKey("guiabot", stored, new Map()), null);
  assert.equal(checkRobotKey("guiabot", stored, new Map([["not-a-key", true]])), null);
  assert.equal(checkRobotKey("guiabot", stored, new Map([[other, true], [stored, true]])), null);
  assert.equal(checkRobotKey("guiabot", stored, new Map([[other, false]])), null);
  const error = checkRobotKey("guiabot", stored, new Map([[other, true]]));
  assert.ok(error instanceof KeyMismatch);
  assert.equal(error.message, `KEY MISMATCH: robot guiabot is online with key ${other} but known_robots has ${stored}`);
});

test("suite labels", () => {
  assert.deepEqual(suiteNumbers(["aesgcm", "chachapoly"]), [2, 1]);
  assert.throws(() => suiteNumbers(["rot13"]), /unknown cipher suite/);
  assert.throws(() => suiteNumbers([]), /at least one/);
});

/** Both ends of an established call, as CallSessions. */
function pair(now = 0) {
  const s = setup([CHACHAPOLY]);
  const w = welcome(s.hello, { accepted: true, robot: "guiabot" });
  const r = /** @type {any} */ (s.receive(w.frame, "guiabot"));
  return {
    user: new CallSession({ callId: CALL_ID, keys: r.keys, peer: "guiabot", now }),
    robot: new CallSession({ callId: CALL_ID, keys: w.keys, peer: "alice", now }),
  };
}

test("datagrams and bundles; replays, forgeries and strangers are counted and dropped", () => {
  const { user: u, robot: r } = pair();
  const frame = r.sealDatagram("chat", "hi");
  assert.deepEqual(u.receive(frame, 0.01).datagrams.map((d) => d.payload), ["hi"]);
  assert.deepEqual(u.receive(frame, 0.02).datagrams, []);
  const bundle = r.seal(encodeBundle([encodeDatagram("a", "1"), encodeDatagram("b", new Uint8Array([2]))]));
  assert.deepEqual(u.receive(bundle, 0.03).datagrams.map((d) => d.channel), ["a", "b"]);
  const forged = r.sealDatagram("chat", "x");
  forged[forged.length - 1] ^= 1;
  u.receive(forged, 0.04);
  u.receive(concat(dataHeader(fromHex("ffffffffffffffff"), 9n), new Uint8Array(20)), 0.04);
  u.receive(r.seal(fromHex("09")), 0.05); // authentic, malformed: a sign of life
  assert.deepEqual(u.stats.rejected, { replayed: 1, forged: 1, not_this_call: 1, malformed: 1 });
  assert.equal(u.lastHeard, 0.05);
  assert.equal(u.stats.framesReceived, 3);
});

test("heartbeats: due at once then every interval, no burst after a stall; rtt and loss", () => {
  const { user: u, robot: r } = pair(10);
  const first = u.tick(10).heartbeat;
  assert.ok(first);
  assert.equal(u.tick(10.01).heartbeat, null);
  assert.ok(u.tick(10.05).heartbeat);
  r.receive(/** @type {Uint8Array} */ (first), 10.02);
  // The robot echoes the user's beat 30 ms after it received it; it arrives at 10.2.
  const echo = r.tick(10.05).heartbeat;
  u.receive(/** @type {Uint8Array} */ (echo), 10.2);
  assert.ok(Math.abs(/** @type {number} */ (u.stats.rtt) - 0.17) < 1e-6, `rtt ${u.stats.rtt}`);
  // Loss over the peer's seq numbers: beats 2 and 3 lost, 4 arrives.
  assert.ok(r.tick(10.11).heartbeat);
  assert.ok(r.tick(10.17).heartbeat);
  u.receive(/** @type {Uint8Array} */ (r.tick(10.23).heartbeat), 10.24);
  assert.equal(u.stats.loss, 0.5);
  // After a stall: one beat, then the cadence starts afresh.
  assert.ok(u.tick(10.3).heartbeat);
  assert.equal(u.tick(10.31).heartbeat, null);
  assert.ok(u.tick(10.36).heartbeat);
});

test("drop after the timeout without an authentic frame (§8)", () => {
  const { user: u, robot: r } = pair(0);
  assert.equal(u.tick(0.4).ended, null);
  u.receive(r.sealDatagram("x", ""), 0.45);
  assert.equal(u.tick(0.9).ended, null);
  const { ended } = u.tick(0.96);
  assert.deepEqual(ended, { kind: "dropped", byPeer: true, detail: "nothing from guiabot for 0.51 s" });
  assert.throws(() => u.sealDatagram("x", "late"), CallEnded);
});

test("hang-up both ways, and the robot going offline", () => {
  let { user: u, robot: r } = pair();
  const frame = /** @type {Uint8Array} */ (u.hangup("bye"));
  assert.deepEqual(u.ended, { kind: "hung_up", byPeer: false, detail: "bye" });
  assert.equal(u.hangup("again"), null);
  assert.deepEqual(r.receive(frame, 0.1).ended, { kind: "hung_up", byPeer: true, detail: "bye" });
  assert.deepEqual(r.receive(frame, 0.1).ended, null); // the other copies
  ({ user: u, robot: r } = pair());
  assert.deepEqual(u.receive(/** @type {Uint8Array} */ (r.hangup("")), 0.1).ended, { kind: "hung_up", byPeer: true, detail: "hung up" });
  ({ user: u } = pair());
  assert.deepEqual(u.peerGone(), { kind: "dropped", byPeer: true, detail: "guiabot went offline" });
});

test("garbage on the inbox and on the call's keys never throws: it is counted", () => {
  let seed = 5;
  const random = () => ((seed = (seed * 1103515245 + 12345) % 2 ** 31) / 2 ** 31);
  const s = setup();
  const { user: u } = pair();
  for (let i = 0; i < 3000; i++) {
    const bytes = new Uint8Array(Math.floor(random() * 120));
    for (let j = 0; j < bytes.length; j++) bytes[j] = Math.floor(random() * 256);
    if (bytes.length > 10 && i % 2) bytes.set(CALL_ID, 2); // this call's id, to reach deeper
    // Version 2 and a WELCOME, DATA or RETRY type on a third of them.
    if (bytes.length > 1 && i % 3 === 0) bytes.set([2, [2, 3, 5][Math.floor(i / 3) % 3]], 0);
    assert.equal(s.receive(bytes, "guiabot").kind, "ignored");
    assert.deepEqual(u.receive(bytes, 1), { datagrams: [], ended: null });
  }
  assert.equal(s.outcome, null);
  assert.ok(Object.values(u.stats.rejected).reduce((a, b) => a + b, 0) === 3000);
});
