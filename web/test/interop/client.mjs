// The JS client of tests/test_js_interop.py: its link speaks newline-delimited JSON over
// stdin/stdout (payloads in base64) to the pytest process, which relays to a memory hub
// where a real Python robot runs. Not a node:test file (npm test runs *.test.js only).
//
//   node web/test/interop/client.mjs '{"scenario": "chat"|"wrongkey", "name", "privateKey",
//                                      "robot", "robotKey", "suites", "timeout"}'
// Lines out: {"op": "sub"|"unsub"|"token"|"untoken"|"watch"|"unwatch", "id", "key"},
//            {"op": "pub", "key", "lane", "data"}, {"op": "result", ...}
// Lines in:  {"op": "sample", "id", "key", "data"}, {"op": "alive", "id", "key", "alive"}
import { createInterface } from "node:readline";
import { Endpoint } from "../../src/call.js";
import { generateKeyPair } from "../../src/identity.js";

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

createInterface({ input: process.stdin }).on("line", (line) => {
  const m = JSON.parse(line);
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

try {
  await (options.scenario === "wrongkey" ? wrongKey() : chat());
  process.exit(0);
} catch (error) {
  send({ op: "result", event: "fatal", message: String(error) });
  process.exit(1);
}
