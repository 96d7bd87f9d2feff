// The JS client of tests/test_js_gateway_interop.py: the browser's code in node, THROUGH
// THE GATEWAY of a `telebot-robot run` daemon (its [gateway], plain ws:// on 127.0.0.1),
// as a page uses it: connectGateway (web/src/gateway-link.js), Endpoint (call.js) and
// RobotSession (session.js). Not a node:test file (npm test runs *.test.js only).
//
//   node [--experimental-websocket] web/test/interop/gateway-client.mjs '{"url", "name",
//        "privateKey", "robot", "robotKey" (43-char keys), "suites", "timeout",
//        "loss", "control", "seed", "deadline"}'
//
// Between the GatewayLink and the Endpoint sits a lossy link: it drops a seeded share
// `loss` of the frames each way (published frames, and samples delivered); CONTROL frames
// too when `control` is true (published on the control lane; samples on any key but a
// call's `/data`: HELLO/WELCOME, RETRY, heartbeats, HANGUP). Subscriptions, tokens and
// presence are not frames and are never dropped.
//
// The scenario, each step within `deadline` seconds: call (the suite negotiated),
// `where?` answered, the map complete (its PNG's SHA-256 and decoded size), five poses,
// arm acked, stop acked and the robot latched (safety armed false), hang up. Every step's
// outcome goes to stdout as one JSON line {"event": ...}; a failed step prints
// {"event": "fatal", "message"} and exits 1.
import { createHash } from "node:crypto";
import { Endpoint } from "../../src/call.js";
import { connectGateway } from "../../src/gateway-link.js";
import { decodeKey, publicKeyOf } from "../../src/identity.js";
import { decodeMapPng } from "../../src/services/map.js";
import { RobotSession } from "../../src/session.js";

const options = JSON.parse(process.argv[2]);
const out = (/** @type {object} */ line) => process.stdout.write(JSON.stringify(line) + "\n");
const sleep = (/** @type {number} */ ms) => new Promise((resolve) => setTimeout(resolve, ms));

/** A seeded uniform [0, 1) stream (mulberry32): the same seed, the same losses. */
function seeded(/** @type {number} */ seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

/**
 * `link` (a GatewayLink) losing `loss` of the frames each way, CONTROL frames included
 * when `control`; counts what it dropped and passed.
 * @param {any} link @param {{loss: number, control: boolean, seed: number}} how
 */
function lossy(link, { loss, control, seed }) {
  const random = seeded(seed);
  const stats = { dropped: 0, passed: 0, droppedControl: 0 };
  const passes = (/** @type {boolean} */ isControl) => {
    if (random() < loss && (control || !isControl)) {
      stats.dropped++;
      if (isControl) stats.droppedControl++;
      return false;
    }
    stats.passed++;
    return true;
  };
  return {
    stats,
    subscribe: (/** @type {string} */ keyExpr, /** @type {Function} */ cb) =>
      link.subscribe(keyExpr, (/** @type {string} */ key, /** @type {Uint8Array} */ payload) => {
        if (passes(!key.endsWith("/data"))) cb(key, payload);
      }),
    publish: (/** @type {string} */ key, /** @type {Uint8Array} */ payload, /** @type {string} */ lane) => {
      if (passes(lane === "control")) link.publish(key, payload, lane);
    },
    declareToken: (/** @type {string} */ key) => link.declareToken(key),
    watch: (/** @type {string} */ key, /** @type {Function} */ cb) => link.watch(key, cb),
  };
}

/** @type {any[]} every message the session emitted, in order */
const emitted = [];
const ofType = (/** @type {string} */ type) => emitted.filter((m) => m.type === type);

/** Wait until `predicate()` is truthy (its value), or fail naming `what`. */
async function until(/** @type {() => any} */ predicate, /** @type {string} */ what) {
  const end = Date.now() + options.deadline * 1000;
  for (;;) {
    const value = predicate();
    if (value) return value;
    if (Date.now() > end) throw new Error(`no ${what} within ${options.deadline} s`);
    await sleep(20);
  }
}

async function main() {
  const privateKey = decodeKey(options.privateKey);
  const gateway = await connectGateway(options.url, { name: options.name, privateKey, publicKey: publicKeyOf(privateKey), timeout: options.deadline });
  let gatewayClosed = "";
  gateway.onclose = (/** @type {any} */ info) => { gatewayClosed = info.message; };
  out({ event: "admitted", name: gateway.admitted.name });
  const link = lossy(gateway, options);
  const endpoint = new Endpoint({ link, name: options.name, privateKey, suites: options.suites, timeout: options.timeout });
  /** @type {Uint8Array | null} */
  let png = null;
  const session = new RobotSession({
    connect: () => endpoint.call(options.robot, options.robotKey, { timeout: options.deadline }),
    emit: (/** @type {any} */ msg) => {
      if (msg.type === "video" || msg.type === "audio") return; // pictures and voice: not needed here
      if (msg.type === "map") png = msg.png;
      emitted.push(msg);
    },
    user: options.name,
    robot: options.robot,
    mapUrl: () => "map.png",
  });
  await session.start();
  out({ event: "called", suite: session.call.suite, role: session.role, id: session.call.id });

  session.send({ type: "chat", id: 1, text: "where?" });
  const reply = await until(() => ofType("chat").find((m) => m.id === 1 && m.final), "answer to where?");
  out({ event: "where", reply });

  const map = await until(() => ofType("map")[0], "map");
  const error = ofType("error").find((m) => m.text.startsWith("the map did not arrive"));
  if (error) throw new Error(error.text);
  const bytes = /** @type {Uint8Array} */ (/** @type {unknown} */ (png));
  const decoded = await decodeMapPng(bytes);
  out({
    event: "map",
    size: bytes.length,
    sha256: createHash("sha256").update(bytes).digest("hex"),
    width: map.width,
    height: map.height,
    resolution: map.resolution,
    resent: session.services.map.receiver?.resent ?? null,
    decoded: { width: decoded.width, height: decoded.height },
  });

  await until(() => ofType("pose").length >= 5, "five poses");
  const pose = ofType("pose").at(-1);
  out({ event: "poses", count: ofType("pose").length, last: { x: pose.x, y: pose.y, yaw: pose.yaw } });

  session.send({ type: "arm" });
  const armed = await until(() => ofType("ack").find((m) => m.what === "arm"), "arm ack");
  await until(() => ofType("safety").at(-1)?.armed === true, "safety armed");
  session.send({ type: "stop", how: "api" });
  const stopped = await until(() => ofType("ack").find((m) => m.what === "stop"), "stop ack");
  await until(() => ofType("safety").at(-1)?.armed === false, "safety latched");
  out({ event: "stopped", arm: armed, stop: stopped, safety: ofType("safety").at(-1) });

  const stats = { rtt: session.call.stats.rtt, received: session.call.stats.framesReceived };
  const connections = ofType("connection").map((m) => m.state);
  await session.close();
  await endpoint.close();
  gateway.close();
  out({ event: "closed", link: link.stats, gateway: gateway.stats, stats, drops: session.drops, reconnects: session.reconnects, connections, gatewayClosed });
}

try {
  await main();
  process.exit(0);
} catch (error) {
  out({ event: "fatal", message: String(/** @type {any} */ (error)?.message ?? error) });
  process.exit(1);
}
