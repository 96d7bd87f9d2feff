// The call driver (call.js) over an in-memory link, with a JS robot built from the same
// sans-IO parts (ResponderHandshake, CallSession): keys, lanes, order of declarations,
// early frames, heartbeats, hang-up copies, drops, refusals, KEY MISMATCH, close.
// Conditions are polled, never timed.
import { test } from "node:test";
import assert from "node:assert/strict";
import { CallEnded, CallError, CallRejected, CallTimeout, KeyMismatch } from "../src/errors.js";
import { toHex, utf8 } from "../src/bytes.js";
import { encodeKey, generateKeyPair } from "../src/identity.js";
import { decodeFrame, encodeRetry, encodeWelcome } from "../src/proto/frames.js";
import { ResponderHandshake } from "../src/proto/noise.js";
import { CallSession } from "../src/proto/session.js";
import { Endpoint } from "../src/call.js";

/** zenoh-style matching: `*` one chunk, `**` any number. */
function matches(/** @type {string} */ pattern, /** @type {string} */ key) {
  const p = pattern.split("/");
  const k = key.split("/");
  const go = (/** @type {number} */ i, /** @type {number} */ j) => {
    if (i === p.length) return j === k.length;
    if (p[i] === "**") return go(i + 1, j) || (j < k.length && go(i, j + 1));
    return j < k.length && (p[i] === "*" || p[i] === k[j]) && go(i + 1, j + 1);
  };
  return go(0, 0);
}

/** An in-memory link; every publish is logged, delivery is asynchronous as on a network. */
class MemoryLink {
  constructor() {
    /** @type {Set<{pattern: string, cb: Function}>} */
    this.subs = new Set();
    /** @type {Set<{pattern: string, cb: Function}>} */
    this.watches = new Set();
    /** @type {Set<string>} */
    this.tokens = new Set();
    /** @type {{op: string, key: string, payload?: Uint8Array, lane?: string}[]} */
    this.log = [];
  }
  subscribe(/** @type {string} */ pattern, /** @type {Function} */ cb) {
    const entry = { pattern, cb };
    this.subs.add(entry);
    this.log.push({ op: "sub", key: pattern });
    return { close: () => this.subs.delete(entry) };
  }
  publish(/** @type {string} */ key, /** @type {Uint8Array} */ payload, /** @type {string} */ lane) {
    this.log.push({ op: "pub", key, payload, lane });
    for (const s of [...this.subs]) if (matches(s.pattern, key)) setImmediate(() => this.subs.has(s) && s.cb(key, payload.slice()));
  }
  declareToken(/** @type {string} */ key) {
    this.log.push({ op: "token", key });
    this.setToken(key, true);
    return { close: () => (this.log.push({ op: "untoken", key }), this.setToken(key, false)) };
  }
  setToken(/** @type {string} */ key, /** @type {boolean} */ alive) {
    if (alive) this.tokens.add(key);
    else this.tokens.delete(key);
    for (const w of [...this.watches]) if (matches(w.pattern, key)) setImmediate(() => w.cb(key, alive));
  }
  watch(/** @type {string} */ pattern, /** @type {Function} */ cb) {
    const entry = { pattern, cb };
    this.watches.add(entry);
    for (const key of this.tokens) if (matches(pattern, key)) setImmediate(() => this.watches.has(entry) && cb(key, true));
    return { close: () => this.watches.delete(entry) };
  }
}

/** A JS robot "guiabot" on the link: answers HELLOs per `answer`, echoes datagrams. */
function robotOn(/** @type {MemoryLink} */ link, { answer = { accepted: true, robot: "guiabot", role: "driver" }, pick = 0, early = false, heartbeats = true } = {}) {
  const keys = generateKeyPair();
  const robot = { keys, /** @type {CallSession|null} */ session: null, received: /** @type {any[]} */ ([]), hellos: 0, userBase: "", timer: /** @type {any} */ (null) };
  link.subscribe("telebot/robot/guiabot/in/*", (/** @type {string} */ key, /** @type {Uint8Array} */ data) => {
    const hello = /** @type {any} */ (decodeFrame(data));
    robot.hellos += 1;
    const inbox = `telebot/user/${hello.caller}/${toHex(hello.instance)}/in/guiabot`;
    if (pick && hello.suite !== pick) return link.publish(inbox, encodeRetry(hello.callId, pick), "control");
    if (robot.session) return;
    const responder = new ResponderHandshake({ staticPrivate: keys.privateKey, prologue: hello.prologue, suite: hello.suite });
    try {
      responder.readMessage(hello.noiseMessage);
    } catch {
      return; // not for this robot's key: no answer (§5.8 step 4)
    }
    const { message, keys: callKeys } = responder.writeMessage(utf8(JSON.stringify(answer)));
    if (!answer.accepted) return link.publish(inbox, encodeWelcome(hello.callId, message), "control");
    const session = new CallSession({ callId: hello.callId, keys: callKeys, peer: "alice", now: performance.now() / 1000, timeout: 30 });
    robot.session = session;
    robot.userBase = `telebot/user/${hello.caller}/${toHex(hello.instance)}/call/guiabot/${toHex(hello.callId)}`;
    const own = `telebot/robot/guiabot/call/${key.split("/").at(-1)}/${toHex(hello.callId)}`;
    for (const lane of ["ctl", "data"]) {
      link.subscribe(`${own}/${lane}`, (/** @type {string} */ k, /** @type {Uint8Array} */ frame) => {
        const { datagrams, ended } = session.receive(frame, performance.now() / 1000);
        for (const d of datagrams) {
          robot.received.push({ lane: k.split("/").at(-1), ...d });
          link.publish(`${robot.userBase}/data`, session.sealDatagram(d.channel, d.payload), "data");
        }
        if (ended) robot.received.push({ ended });
      });
    }
    if (early) link.publish(`${robot.userBase}/data`, session.sealDatagram("early", "first"), "data");
    link.publish(inbox, encodeWelcome(hello.callId, message), "control");
    if (heartbeats) {
      robot.timer = setInterval(() => {
        const { heartbeat } = session.tick(performance.now() / 1000);
        if (heartbeat) link.publish(`${robot.userBase}/ctl`, heartbeat, "control");
      }, 20);
    }
  });
  link.declareToken(`telebot/presence/robot/guiabot/${encodeKey(keys.publicKey)}`);
  return robot;
}

async function until(/** @type {() => boolean} */ condition, what = "condition") {
  for (let i = 0; i < 2000; i++) {
    if (condition()) return;
    await new Promise((resolve) => setTimeout(resolve, 5));
  }
  assert.fail(`${what} not met`);
}

const alice = generateKeyPair();

test("a call: keys, lanes, early frames, echo, heartbeats with rtt, hang-up copies, close", async () => {
  const link = new MemoryLink();
  const robot = robotOn(link, { early: true });
  const endpoint = new Endpoint({ link, name: "alice", privateKey: alice.privateKey, suites: ["chachapoly"] });
  const base = `telebot/user/alice/${endpoint.instance}`;
  assert.match(endpoint.instance, /^[0-9a-f]{16}$/);
  assert.deepEqual(link.log.slice(-2).map((e) => [e.op, e.key]), [["sub", `${base}/in/*`], ["token", `telebot/presence/user/alice/${endpoint.instance}`]]);
  /** @type {any[]} */
  const unrouted = [];
  const call = await endpoint.call("guiabot", encodeKey(robot.keys.publicKey));
  call.onDatagram = (name, payload, isText) => unrouted.push([name, payload, isText]);
  assert.equal(call.suite, "chachapoly");
  assert.equal(call.role, "driver");
  assert.match(call.id, /^[0-9a-f]{16}$/);
  const hello = link.log.find((e) => e.op === "pub" && e.key === "telebot/robot/guiabot/in/alice");
  assert.equal(hello?.lane, "control");
  // The call's keys were subscribed before the first HELLO went out.
  const firstHello = link.log.indexOf(/** @type {any} */ (hello));
  const ctl = link.log.findIndex((e) => e.op === "sub" && e.key === `${base}/call/guiabot/${call.id}/ctl`);
  assert.ok(ctl >= 0 && ctl < firstHello);
  // DATA: one subscription for every call with guiabot, kept while the endpoint lives.
  const data = link.log.findIndex((e) => e.op === "sub" && e.key === `${base}/call/guiabot/*/data`);
  assert.ok(data >= 0 && data < firstHello);
  await until(() => unrouted.length > 0, "the early datagram");
  assert.deepEqual(unrouted[0], ["early", "first", true]);
  const chat = call.channel("chat");
  assert.equal(call.channel("chat"), chat);
  /** @type {any[]} */
  const got = [];
  chat.onmessage = (payload) => got.push(payload);
  chat.send("where?");
  call.channel("stop", { lane: "control" }).send(new Uint8Array([1]));
  await until(() => got.length === 1 && robot.received.length === 2, "the echo");
  assert.deepEqual(got, ["where?"]);
  assert.deepEqual(robot.received.map((r) => [r.lane, r.channel]), [["data", "chat"], ["ctl", "stop"]]);
  const sent = link.log.filter((e) => e.op === "pub" && e.key.startsWith(`telebot/robot/guiabot/call/alice/${call.id}/`));
  assert.ok(sent.some((e) => e.key.endsWith("/ctl") && e.lane === "control" && e.payload?.length === 59)); // heartbeats
  await until(() => call.stats.rtt !== null, "an rtt");
  assert.ok(/** @type {number} */ (call.stats.rtt) >= 0);
  // The handshake's time (first HELLO -> WELCOME accepted) is on the stats (bench/browser.py).
  assert.equal(typeof call.stats.handshakeMs, "number");
  assert.ok(call.stats.handshakeMs >= 0 && Number.isFinite(call.stats.handshakeMs));
  await call.hangup("bye");
  assert.deepEqual(await call.ended, { kind: "hung_up", detail: "bye", byPeer: false });
  const hangups = link.log.filter((e) => e.op === "pub" && e.key.endsWith("/ctl") && e.payload?.length === 34 + 4);
  assert.equal(hangups.length, 3);
  assert.deepEqual(hangups[0].payload, hangups[2].payload); // one frame, three copies
  await until(() => robot.received.some((r) => r.ended), "the robot sees the hang-up");
  assert.deepEqual(robot.received.at(-1).ended, { kind: "hung_up", byPeer: true, detail: "bye" });
  assert.throws(() => chat.send("late"), CallEnded);
  // A frame on the ended call's DATA key reaches no call: counted, dropped.
  link.publish(`${base}/call/guiabot/${call.id}/data`, new Uint8Array(40), "data");
  await until(() => endpoint.rejected.unknown_call === 1, "the late frame counted");
  // Another robot's key is not listened to at all.
  link.publish(`${base}/call/intruder/${call.id}/data`, new Uint8Array(40), "data");
  await new Promise((resolve) => setTimeout(resolve, 20));
  assert.equal(endpoint.rejected.unknown_call, 1);
  clearInterval(robot.timer);
  await endpoint.close();
  assert.equal(link.log.at(-1)?.op, "untoken");
});

test("RETRY: the robot picks ChaChaPoly, the call uses it", async () => {
  const link = new MemoryLink();
  const robot = robotOn(link, { pick: 1 });
  const endpoint = new Endpoint({ link, name: "alice", privateKey: alice.privateKey });
  const call = await endpoint.call("guiabot", robot.keys.publicKey);
  assert.equal(call.suite, "chachapoly");
  clearInterval(robot.timer);
  await endpoint.close();
  assert.equal((await call.ended).detail, "shutting down");
});

test("drops: the robot goes silent; the robot's token goes away", async () => {
  let link = new MemoryLink();
  let robot = robotOn(link, { heartbeats: false });
  let endpoint = new Endpoint({ link, name: "alice", privateKey: alice.privateKey, timeout: 0.2 });
  let call = await endpoint.call("guiabot", robot.keys.publicKey);
  const end = await call.ended;
  assert.equal(end.kind, "dropped");
  assert.match(end.detail, /^nothing from guiabot for \d+\.\d\d s$/);
  await endpoint.close();
  link = new MemoryLink();
  robot = robotOn(link);
  endpoint = new Endpoint({ link, name: "alice", privateKey: alice.privateKey, timeout: 30 });
  call = await endpoint.call("guiabot", robot.keys.publicKey);
  await until(() => call.stats.framesReceived > 0, "a heartbeat");
  link.setToken(`telebot/presence/robot/guiabot/${encodeKey(robot.keys.publicKey)}`, false);
  assert.deepEqual(await call.ended, { kind: "dropped", detail: "guiabot went offline", byPeer: true });
  clearInterval(robot.timer);
  await endpoint.close();
});

test("set-up failures: refusal, no answer, KEY MISMATCH, closing while calling", async () => {
  const link = new MemoryLink();
  const robot = robotOn(link, { answer: { accepted: false, robot: "guiabot", reason: "not in the contact list of guiabot" } });
  const endpoint = new Endpoint({ link, name: "alice", privateKey: alice.privateKey });
  await assert.rejects(endpoint.call("guiabot", robot.keys.publicKey), (e) => e instanceof CallRejected && e.message === "not in the contact list of guiabot");
  // Nobody answers for "ghost": CallTimeout, and the HELLO was repeated.
  await assert.rejects(endpoint.call("ghost", generateKeyPair().publicKey, { timeout: 0.6 }), (e) => e instanceof CallTimeout && /ghost did not answer within 0.6 s/.test(e.message));
  assert.ok(link.log.filter((e) => e.key === "telebot/robot/ghost/in/alice").length >= 2);
  // guiabot is online with another key than the one given: at once, without a timeout.
  const wrong = generateKeyPair().publicKey;
  await assert.rejects(endpoint.call("guiabot", wrong, { timeout: 600 }), (e) => e instanceof KeyMismatch && e.message.includes(encodeKey(robot.keys.publicKey)));
  // The link closed under the endpoint: a call being set up fails at once.
  const orphan = endpoint.call("ghost", wrong, { timeout: 600 });
  endpoint.linkClosed();
  await assert.rejects(orphan, (e) => e instanceof CallError && /the link to the gateway closed/.test(e.message));
  const pending = endpoint.call("ghost", wrong, { timeout: 600 });
  await endpoint.close();
  await assert.rejects(pending, /the endpoint closed while calling/);
  assert.equal(link.subs.size, 1); // only the robot's inbox is left
  // Three calls to ghost, one DATA subscription for them all.
  assert.equal(link.log.filter((e) => e.op === "sub" && e.key.endsWith("/call/ghost/*/data")).length, 1);
});
