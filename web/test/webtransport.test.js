// The WebTransport link's own parts (docs/protocol.md §26.5): its text framing, the offer
// it takes from the gateway, and how WebTransportSocket maps a WebSocket's sends onto a
// session (a stand-in WebTransport here: node has none). Against a real gateway in
// Chromium: tests/test_browser_e2e.py; the gateway's side: tests/test_gateway_webtransport.py.
import { test } from "node:test";
import assert from "node:assert/strict";
import { GatewayError } from "../src/gateway-link.js";
import { PREAMBLE, TextFrames, WebTransportSocket, connectBest, textFrame, webTransportOffer } from "../src/webtransport.js";

test("text frames round-trip across any split, and an oversize one is a GatewayError", () => {
  const bytes = new Uint8Array([...textFrame('{"op":"challenge"}'), ...textFrame("é"), ...textFrame("")]);
  for (let cut = 0; cut <= bytes.length; cut++) {
    const frames = new TextFrames();
    const got = [...frames.push(bytes.subarray(0, cut)), ...frames.push(bytes.subarray(cut))];
    assert.deepEqual(got, ['{"op":"challenge"}', "é", ""]);
  }
  assert.deepEqual([...textFrame("ab")], [0, 0, 0, 2, 97, 98]);
  const huge = new Uint8Array([0x7f, 0, 0, 0]);
  assert.throws(() => new TextFrames().push(huge), (e) => e instanceof GatewayError && e.message.length < 200);
});

const goodOffer = { port: 8443, path: "/gateway", hashes: ["AAAA"] };

test("the offer is read beside the page and checked; none without WebTransport", async () => {
  const asked = [];
  const fetchImpl = async (url) => {
    asked.push(url);
    return { ok: true, json: async () => goodOffer };
  };
  assert.equal(await webTransportOffer("wss://robot:8443/gateway", fetchImpl), null); // no WebTransport here
  globalThis.WebTransport = class {};
  try {
    assert.deepEqual(await webTransportOffer("wss://robot:8443/gateway", fetchImpl), goodOffer);
    assert.deepEqual(asked, ["https://robot:8443/webtransport"]);
    for (const bad of [{ port: "1" }, { ...goodOffer, hashes: [1] }, { ...goodOffer, path: null }, null]) {
      assert.equal(await webTransportOffer("wss://robot/", async () => ({ ok: true, json: async () => bad })), null);
    }
    assert.equal(await webTransportOffer("wss://robot/", async () => ({ ok: false })), null);
    assert.equal(await webTransportOffer("wss://robot/", async () => { throw new Error("offline"); }), null);
  } finally {
    delete globalThis.WebTransport;
  }
});

/** A stand-in WebTransport recording what is written where. */
function fakeTransport() {
  const written = { text: [], datagrams: [], streams: [] };
  let closeWith;
  class Fake {
    constructor(url, options) {
      this.url = url;
      this.options = options;
      this.ready = Promise.resolve();
      this.closed = new Promise((resolve) => { closeWith = resolve; });
      const writer = (into) => ({ write: async (chunk) => { into.push(chunk); }, close: async () => {} });
      const empty = () => ({ getReader: () => ({ read: () => new Promise(() => {}), cancel: async () => {} }) });
      this.datagrams = { maxDatagramSize: 1000, writable: { getWriter: () => writer(written.datagrams) }, readable: empty() };
      this.incomingUnidirectionalStreams = empty();
    }
    async createBidirectionalStream() {
      return { writable: { getWriter: () => ({ write: async (c) => { written.text.push(c); } }) }, readable: (() => ({ getReader: () => ({ read: () => new Promise(() => {}) }) }))() };
    }
    async createUnidirectionalStream() {
      const chunks = [];
      written.streams.push(chunks);
      return { getWriter: () => ({ write: async (c) => { chunks.push(c); }, close: async () => {} }) };
    }
    close(info) { closeWith({ closeCode: info.closeCode, reason: "" }); }
  }
  return { Fake, written, end: (closeCode, reason) => closeWith({ closeCode, reason }) };
}

test("a WebTransportSocket sends text in order, small bytes as datagrams, large ones on a stream", async () => {
  const { Fake, written, end } = fakeTransport();
  const socket = new WebTransportSocket("wss://robot.local:8443/gateway", { port: 9443, path: "/gateway", hashes: ["AAEC"] }, Fake);
  assert.equal(socket.wt.url, "https://robot.local:9443/gateway");
  assert.deepEqual([...socket.wt.options.serverCertificateHashes[0].value], [0, 1, 2]);
  await socket.opened;
  // A busy page keeps the datagrams that arrive meanwhile (the browser's default: a few).
  assert.equal(socket.wt.datagrams.incomingMaxBufferedDatagrams, 1024);
  socket.send('{"op":"sub"}');
  socket.send(new Uint8Array(1000));
  socket.send(new Uint8Array(1001));
  assert.equal(socket.bufferedAmount, 1001); // until QUIC took the stream
  await new Promise((r) => setTimeout(r, 10));
  assert.equal(socket.bufferedAmount, 0);
  assert.deepEqual(written.text.map((c) => [...c]), [[...PREAMBLE], [...textFrame('{"op":"sub"}')]]);
  assert.equal(written.datagrams.length, 1);
  assert.equal(written.streams.length, 1);
  assert.equal(written.streams[0][0].length, 1001);
  const closes = [];
  socket.onclose = (e) => closes.push(e);
  end(4008, "flood");
  await new Promise((r) => setTimeout(r, 0));
  assert.deepEqual(closes, [{ code: 4008, reason: "flood" }]);
  socket.send("after"); // closed: dropped, no throw
  assert.equal(written.text.length, 2);
});

/** A stand-in WebTransport whose session never opens (UDP blocked); counts its tries. */
function blockedTransport(tries) {
  return class {
    constructor() {
      tries.push(1);
      this.ready = Promise.reject(new Error("QUIC blocked"));
      this.ready.catch(() => {});
      this.closed = new Promise(() => {});
    }
    close() {}
  };
}

class NoWebSocket {
  static opened = [];
  constructor(url) {
    NoWebSocket.opened.push(url);
    throw new Error("no network in this test");
  }
}

const alice = { name: "alice", privateKey: new Uint8Array(32), publicKey: new Uint8Array(32), WebSocket: NoWebSocket };

/** Run `body` in a browser with `Transport` as its WebTransport and the gateway's offer
 * at /webtransport; nothing of it is left behind. */
async function inBrowser(Transport, body) {
  globalThis.WebTransport = Transport;
  const realFetch = globalThis.fetch;
  globalThis.fetch = async () => ({ ok: true, json: async () => goodOffer });
  NoWebSocket.opened = [];
  try {
    await body();
  } finally {
    delete globalThis.WebTransport;
    globalThis.fetch = realFetch;
  }
}

test("connectBest redeems an invite on a websocket, never trying WebTransport", async () => {
  const tries = [];
  await inBrowser(blockedTransport(tries), async () => {
    await assert.rejects(connectBest("wss://robot:8443/gateway", { ...alice, invite: "T" }), (e) => e instanceof GatewayError);
    assert.deepEqual(tries, []);
    assert.deepEqual(NoWebSocket.opened, ["wss://robot:8443/gateway"]); // one, for the invite
  });
});

test("connectBest falls back to websockets when the WebTransport session never opens", async () => {
  const tries = [];
  await inBrowser(blockedTransport(tries), async () => {
    await assert.rejects(connectBest("wss://robot:8443/gateway", alice), (e) => e instanceof GatewayError);
    assert.equal(tries.length, 2); // WebTransport was tried (two sessions, at once), and failed
    // Then both of the split link's websockets.
    assert.deepEqual(NoWebSocket.opened, ["wss://robot:8443/gateway", "wss://robot:8443/gateway"]);
    // Within the next minute the page goes straight to websockets.
    await assert.rejects(connectBest("wss://robot:8443/gateway", alice));
    assert.equal(tries.length, 2);
  });
});

/**
 * A stand-in WebTransport whose gateway challenges after the preamble and answers the
 * page's admission with `answer` (counts its sessions in `tries`).
 * @param {object} answer @param {number[]} [tries]
 */
async function answeringTransport(answer, tries = []) {
  const { x25519 } = await import("@noble/curves/ed25519");
  const { encodeKey } = await import("../src/gateway-link.js");
  return class {
    constructor() {
      tries.push(1);
      this.ready = Promise.resolve();
      this.closed = new Promise(() => {});
      const pending = [];
      let wake = null;
      const push = (text) => { pending.push(textFrame(text)); if (wake) wake(); };
      this.readable = {
        getReader: () => ({
          read: async () => {
            while (!pending.length) await new Promise((r) => { wake = r; });
            return { value: pending.shift(), done: false };
          },
        }),
      };
      const never = () => ({ getReader: () => ({ read: () => new Promise(() => {}) }) });
      this.datagrams = { maxDatagramSize: 1000, writable: { getWriter: () => ({ write: async () => {} }) }, readable: never() };
      this.incomingUnidirectionalStreams = never();
      this.writable = {
        getWriter: () => ({
          write: async (chunk) => {
            if (chunk.length === 4) { // the preamble: the gateway challenges
              push(JSON.stringify({ op: "challenge", v: 1, ns: "telebot", gateway: encodeKey(x25519.getPublicKey(new Uint8Array(32).fill(9))), nonce: encodeKey(new Uint8Array(32)) }));
            } else {
              push(JSON.stringify(answer));
            }
          },
        }),
      };
    }
    async createBidirectionalStream() { return { writable: this.writable, readable: this.readable }; }
    close() {}
  };
}

test("a refusal over WebTransport is the gateway's answer: not retried on websockets", async () => {
  const tries = [];
  const Refusing = await answeringTransport({ op: "refused", code: "wrong_key", text: "alice is admitted with another key" }, tries);
  await inBrowser(Refusing, async () => {
    // A fresh copy of the module: the test before left it going straight to websockets.
    const fresh = await import(`../src/webtransport.js?refusal=${Date.now()}`);
    await assert.rejects(
      fresh.connectBest("wss://robot:8443/gateway", alice),
      (e) => e.code === "wrong_key" && /another key/.test(e.message),
    );
    assert.equal(tries.length, 2); // both sessions, each refused
    assert.deepEqual(NoWebSocket.opened, []); // no websocket tried after a refusal
  });
});

test("once WebTransport worked in the page: its offer is used again, and a later try gets RETRY_FOR s before falling back", async () => {
  const Welcoming = await answeringTransport({ op: "admitted", name: "alice" });
  const fresh = await import(`../src/webtransport.js?retry=${Date.now()}`);
  let fetches = 0;
  const counting = async (body) => {
    const counted = globalThis.fetch;
    globalThis.fetch = async (...args) => { fetches += 1; return counted(...args); };
    try { await body(); } finally { globalThis.fetch = counted; }
  };
  const timers = [];
  const realSetTimeout = globalThis.setTimeout;
  globalThis.setTimeout = (fn, ms, ...rest) => { timers.push(ms); return realSetTimeout(fn, ms, ...rest); };
  try {
    await inBrowser(Welcoming, () => counting(async () => {
      const link = await fresh.connectBest("wss://robot:8443/gateway", alice);
      assert.equal(link.kind, "webtransport");
      link.close();
      // The next link uses the same offer: no fetch (after an outage the page's TCP may
      // still be waiting out its back-off).
      (await fresh.connectBest("wss://robot:8443/gateway", alice)).close();
    }));
    assert.equal(fetches, 1);
    assert.ok(timers.includes(fresh.TRY_FOR * 1000), `the first try waits ${fresh.TRY_FOR} s: ${timers}`);
    timers.length = 0;
    const tries = [];
    await inBrowser(blockedTransport(tries), () => counting(async () => {
      await assert.rejects(fresh.connectBest("wss://robot:8443/gateway", alice));
    }));
    // The cached offer failed: fetched again and tried once more, then websockets.
    assert.equal(fetches, 2);
    assert.equal(tries.length, 4); // two sessions a try
    assert.ok(timers.includes(fresh.RETRY_FOR * 1000), `a later try waits ${fresh.RETRY_FOR} s: ${timers}`);
    assert.ok(!timers.includes(fresh.TRY_FOR * 1000));
  } finally {
    globalThis.setTimeout = realSetTimeout;
  }
});
