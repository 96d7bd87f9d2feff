// The JS client of tests/test_js_interop.py: its link speaks newline-delimited JSON over
// stdin/stdout (payloads in base64) to the pytest process, which relays to a memory hub
// where a real Python robot runs. Not a node:test file (npm test runs *.test.js only).
//
//   node web/test/interop/client.mjs '{"scenario": "chat"|"wrongkey"|"session", "name",
//                                      "privateKey", "robot", "robotKey", "suites", "timeout"}'
// Lines out: {"op": "sub"|"unsub"|"token"|"untoken"|"watch"|"unwatch", "id", "key"},
//            {"op": "pub", "key", "lane", "data"}, {"op": "result", ...}
// Lines in:  {"op": "sample", "id", "key", "data"}, {"op": "alive", "id", "key", "alive"}
//
// "session" runs a RobotSession (web/src/session.js) on Endpoint.call, as a page would:
// every message it emits goes out as {"op": "emit", "msg"} (a map's PNG and the first
// video picture in base64, other pictures as their size; after a map, its decoded size as
// {"type": "map_decoded", "width", "height"}); lines in {"op": "page", "msg"} are §19 page
// messages for session.send, {"op": "close"} ends it ({"op": "result", "event": "closed"}).
import { createInterface } from "node:readline";
import { Endpoint } from "../../src/call.js";
import { generateKeyPair } from "../../src/identity.js";
import { RobotSession } from "../../src/session.js";
import { decodeMapPng } from "../../src/services/map.js";

const options = JSON.parse(process.argv[2]);
const send = (/** @type {object} */ message) => process.stdout.write(JSON.stringify(message) + "\n");
/** @type {Map<number, Function>} */
const handlers = new Map();
let nextId = 1;

/** @param {string} op @param {string} undo @param {string} key @param {Function|null} handler */
function declare(op, undo, key, handler) {
  const id = nextId++;
  if (handler) handlers.set(id, handler);
  send({ op, id, key });
  return {
    close() {
      handlers.delete(id);
      send({ op: undo, id });
    },
  };
}

const link = {
  subscribe: (/** @type {string} */ key, /** @type {Function} */ cb) => declare("sub", "unsub", key, cb),
  publish: (/** @type {string} */ key, /** @type {Uint8Array} */ payload, /** @type {string} */ lane) =>
    send({ op: "pub", key, lane, data: Buffer.from(payload).toString("base64") }),
  declareToken: (/** @type {string} */ key) => declare("token", "untoken", key, null),
  watch: (/** @type {string} */ key, /** @type {Function} */ cb) => declare("watch", "unwatch", key, cb),
};

/** Page-side lines ({"op": "page"|"close"}) for the session scenario. @type {(m: any) => void} */
let onControl = () => {};

createInterface({ input: process.stdin }).on("line", (line) => {
  const m = JSON.parse(line);
  if (m.op === "page" || m.op === "close") return onControl(m);
  const handler = handlers.get(m.id);
  if (!handler) return;
  if (m.op === "sample") handler(m.key, new Uint8Array(Buffer.from(m.data, "base64")));
  else if (m.op === "alive") handler(m.key, m.alive);
});

const sleep = (/** @type {number} */ ms) => new Promise((resolve) => setTimeout(resolve, ms));

async function chat() {
  const endpoint = new Endpoint({ link, name: options.name, privateKey: options.privateKey, suites: options.suites, timeout: options.timeout });
  const call = await endpoint.call(options.robot, options.robotKey, { timeout: 30 });
  send({ op: "result", event: "called", suite: call.suite, role: call.role, id: call.id });
  const chatChannel = call.channel("chat");
  /** @type {any} */
  let reply = null;
  chatChannel.onmessage = (payload) => {
    const message = JSON.parse(/** @type {string} */ (payload));
    if (message.id === 1 && message.final) reply = message;
  };
  // The channel is lossy: the same request again, same id, until the final reply.
  for (let i = 0; i < 60 && !reply; i++) {
    chatChannel.send(JSON.stringify({ id: 1, text: "where?" }));
    for (let j = 0; j < 10 && !reply; j++) await sleep(50);
  }
  for (let i = 0; i < 600 && call.stats.rtt === null; i++) await sleep(50);
  const stats = { rtt: call.stats.rtt, loss: call.stats.loss, received: call.stats.framesReceived, rejected: call.stats.rejected };
  await call.hangup("bye");
  const end = await call.ended;
  await endpoint.close();
  send({ op: "result", event: "done", reply, stats, end });
}

async function wrongKey() {
  const endpoint = new Endpoint({ link, name: options.name, privateKey: options.privateKey, suites: options.suites });
  try {
    await endpoint.call(options.robot, generateKeyPair().publicKey, { timeout: 30 });
    send({ op: "result", event: "called" });
  } catch (error) {
    const e = /** @type {Error} */ (error);
    send({ op: "result", event: "error", name: e.name, message: e.message });
  }
  await endpoint.close();
}

const b64 = (/** @type {Uint8Array} */ bytes) => Buffer.from(bytes).toString("base64");

async function session() {
  const endpoint = new Endpoint({ link, name: options.name, privateKey: options.privateKey, suites: options.suites, timeout: options.timeout });
  let pictures = 0;
  /** @param {any} msg */
  const emit = (msg) => {
    if (msg.type === "map") {
      const { png, url: _url, ...rest } = msg;
      send({ op: "emit", msg: { ...rest, png: b64(png) } });
      decodeMapPng(png).then(
        ({ width, height }) => send({ op: "emit", msg: { type: "map_decoded", width, height } }),
        (error) => send({ op: "emit", msg: { type: "map_decoded", error: String(error) } }),
      );
    } else if (msg.type === "video" || msg.type === "audio") {
      pictures += 1;
      send({ op: "emit", msg: { type: msg.type, header: msg.header, size: msg.data.length, data: pictures === 1 ? b64(msg.data) : null } });
    } else {
      send({ op: "emit", msg });
    }
  };
  const robotSession = new RobotSession({
    connect: () => endpoint.call(options.robot, options.robotKey, { timeout: 30 }),
    emit,
    user: options.name,
    robot: options.robot,
  });
  /** @type {(value?: unknown) => void} */
  let closed = () => {};
  const done = new Promise((resolve) => {
    closed = resolve;
  });
  onControl = (m) => {
    if (m.op === "page") robotSession.send(m.msg);
    else closed();
  };
  await robotSession.start();
  send({ op: "result", event: "started", role: robotSession.role });
  await done;
  await robotSession.close();
  await endpoint.close();
  send({ op: "result", event: "closed", drops: robotSession.drops, reconnects: robotSession.reconnects });
}

try {
  const scenarios = { wrongkey: wrongKey, session, chat };
  await (scenarios[/** @type {keyof typeof scenarios} */ (options.scenario)] ?? chat)();
  process.exit(0);
} catch (error) {
  send({ op: "result", event: "fatal", message: String(error) });
  process.exit(1);
}
