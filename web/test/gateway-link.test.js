// The gateway link's pure parts: the admission proof of docs/protocol.md §26.1 (its test
// vector, computed there from the bare primitives in Python) and the key encoding.
// The link against a live gateway runs in tests/test_gateway.py (node + a real gateway).
import { test } from "node:test";
import assert from "node:assert/strict";
import { x25519 } from "@noble/curves/ed25519";
import { admissionProof, connectGateway, decodeKey, encodeKey, GatewayError, GatewayLink, SplitLink } from "../src/gateway-link.js";

const range = (from) => Uint8Array.from({ length: 32 }, (_, i) => from + i);

test("the admission proof matches the §26.1 test vector", () => {
  const userPrivate = range(0);
  const userPublic = x25519.getPublicKey(userPrivate);
  assert.equal(encodeKey(userPublic), "j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8");
  const gateway = decodeKey("NYBy1jZYgNGu6jKa35EhODhR7SGijjt16WXQ0s0WYlQ");
  assert.deepEqual(gateway, x25519.getPublicKey(range(32)));
  const nonce = decodeKey("QEFCQ0RFRkdISUpLTE1OT1BRUlNUVVZXWFlaW1xdXl8");
  assert.deepEqual(nonce, range(64));
  const proof = admissionProof(userPrivate, userPublic, "alice", gateway, nonce);
  assert.equal(encodeKey(proof), "fgtcjEgNPRuPt8WQX63N6uobseO_X3nZGlf-GzdXTek");
  // Another name, another proof: the name is bound.
  assert.notEqual(encodeKey(admissionProof(userPrivate, userPublic, "alicf", gateway, nonce)), encodeKey(proof));
});

test("keys round-trip and a bad one is a one-line GatewayError", () => {
  const key = range(7);
  assert.deepEqual(decodeKey(encodeKey(key)), key);
  for (const bad of ["", "x".repeat(42), "+".repeat(43), "A".repeat(42) + "B", "x".repeat(10000)]) {
    assert.throws(() => decodeKey(bad), (err) => err instanceof GatewayError && !err.message.includes("\n") && err.message.length < 200);
  }
});

test("an address that is not http(s) or ws(s) is refused before any connection", async () => {
  await assert.rejects(
    connectGateway("ftp://robot/", { name: "alice", privateKey: range(0), publicKey: range(0), WebSocket: class {} }),
    (err) => err instanceof GatewayError && /not a gateway address/.test(err.message),
  );
});

test("a sample for a subscription closed meanwhile is late, a short one malformed", () => {
  const sent = [];
  const ws = { send: (m) => sent.push(m), close() {} };
  const link = new GatewayLink(ws, "alice", { op: "admitted", name: "alice" });
  const got = [];
  const sub = link.subscribe("telebot/user/alice/**", (key, payload) => got.push([key, [...payload]]));
  const { id } = JSON.parse(sent[0]);
  const key = new TextEncoder().encode("telebot/user/alice/x");
  const sample = new Uint8Array([id >> 8, id & 0xff, 0, key.length, ...key, 7, 8]);
  ws.onmessage({ data: sample.buffer });
  assert.deepEqual(got, [["telebot/user/alice/x", [7, 8]]]);
  sub.close();
  ws.onmessage({ data: sample.buffer });
  ws.onmessage({ data: sample.slice(0, 6).buffer });
  assert.equal(got.length, 1);
  assert.deepEqual([link.stats.received, link.stats.late, link.stats.malformed], [1, 1, 1]);
});

/** A websocket whose unsent bytes grow with each send, as a browser's do, until `drain()`. */
function congestibleSocket() {
  const ws = { sent: [], bufferedAmount: 0, close() {} };
  ws.send = (m) => {
    ws.sent.push(m);
    ws.bufferedAmount += typeof m === "string" ? m.length : m.byteLength;
  };
  ws.drain = () => { ws.bufferedAmount = 0; };
  return ws;
}
const lanesSent = (ws) => ws.sent.filter((m) => typeof m !== "string").map((m) => m[0]);
const nextTurn = () => new Promise((resolve) => setTimeout(resolve, 0));

test("over the bound DATA and BULK frames are dropped and counted, CONTROL frames always sent", async () => {
  const ws = congestibleSocket();
  const link = new GatewayLink(ws, "alice", { op: "admitted", name: "alice" }, { maxBuffered: 1000 });
  const key = "telebot/robot/guiabot/call/alice/0123456789abcdef/data";
  const ctl = "telebot/robot/guiabot/call/alice/0123456789abcdef/ctl";
  const chunk = new Uint8Array(400);
  // One turn: read once (0 bytes waiting), so all of a picture's fragments go, past the bound.
  for (let i = 0; i < 5; i++) assert.equal(link.publish(key, chunk, "bulk"), true);
  assert.ok(ws.bufferedAmount > 2000);
  await nextTurn();
  // Still over the bound next turn: DATA and BULK dropped, CONTROL (a STOP, a HANGUP) sent.
  assert.equal(link.publish(key, chunk, "bulk"), false);
  assert.equal(link.publish(key, chunk, "data"), false);
  assert.equal(link.publish(ctl, chunk, "control"), true);
  assert.equal(link.publish(key, chunk, "data"), false);
  assert.deepEqual(lanesSent(ws), [2, 2, 2, 2, 2, 0]);
  assert.deepEqual([link.stats.sent, link.stats.congested, link.stats.dropped], [6, 3, 0]);
  // Drained: data goes again.
  ws.drain();
  await nextTurn();
  assert.equal(link.publish(key, chunk, "data"), true);
  assert.deepEqual(lanesSent(ws), [2, 2, 2, 2, 2, 0, 1]);
  // Exactly at the bound is not over it; one byte more is.
  ws.bufferedAmount = 1000;
  await nextTurn();
  assert.equal(link.publish(key, chunk, "data"), true);
  ws.bufferedAmount = 1001;
  await nextTurn();
  assert.equal(link.publish(key, chunk, "data"), false);
  assert.deepEqual([link.stats.sent, link.stats.congested], [8, 4]);
});

test("the default bound is 256 KB, and a closed link drops every lane as before", async () => {
  const ws = congestibleSocket();
  const link = new GatewayLink(ws, "alice", { op: "admitted", name: "alice" });
  assert.equal(link.maxBuffered, 256 * 1024);
  ws.bufferedAmount = 256 * 1024 + 1;
  assert.equal(link.publish("telebot/robot/r/in/alice", new Uint8Array(1), "data"), false);
  assert.equal(link.publish("telebot/robot/r/in/alice", new Uint8Array(1), "control"), true);
  link.close();
  assert.equal(link.publish("telebot/robot/r/in/alice", new Uint8Array(1), "control"), false);
  assert.deepEqual([link.stats.sent, link.stats.congested, link.stats.dropped], [1, 1, 1]);
});

test("a split link: control, the inbox, tokens and watches on one websocket, a call's data keys on the other", () => {
  const control = { sent: [], close() { this.closed = true; } };
  const bulk = { sent: [], close() { this.closed = true; } };
  for (const ws of [control, bulk]) ws.send = (m) => ws.sent.push(m);
  const links = [new GatewayLink(control, "alice", { op: "admitted" }), new GatewayLink(bulk, "alice", { op: "admitted" })];
  const link = new SplitLink(...links);
  const call = "telebot/user/alice/0011223344556677/call/guiabot/0123456789abcdef";
  link.subscribe(`${call}/ctl`, () => {});
  link.subscribe(`${call}/data`, () => {});
  link.subscribe("telebot/user/alice/0011223344556677/in/*", () => {});
  link.declareToken("telebot/presence/user/alice/0011223344556677");
  link.watch("telebot/presence/robot/guiabot/*", () => {});
  const ops = (ws) => ws.sent.filter((m) => typeof m === "string").map((m) => { const j = JSON.parse(m); return `${j.op} ${j.key}`; });
  assert.deepEqual(ops(control), [
    `sub ${call}/ctl`,
    "sub telebot/user/alice/0011223344556677/in/*",
    "token telebot/presence/user/alice/0011223344556677",
    "watch telebot/presence/robot/guiabot/*",
  ]);
  assert.deepEqual(ops(bulk), [`sub ${call}/data`]);
  const to = "telebot/robot/guiabot/call/alice/0123456789abcdef";
  const payload = new Uint8Array(10);
  assert.equal(link.publish(`${to}/ctl`, payload, "control"), true);
  assert.equal(link.publish(`${to}/data`, payload, "data"), true);
  assert.equal(link.publish(`${to}/data`, payload, "bulk"), true);
  // CONTROL goes on both, flagged with one copy id (§26.2); DATA and BULK on the bulk one.
  assert.deepEqual(lanesSent(control), [0x80]);
  assert.deepEqual(lanesSent(bulk), [0x80, 1, 2]);
  assert.equal(link.stats.sent, 4);
  // Either websocket closing closes the other and the link, and says why once.
  const told = [];
  link.onclose = (info) => told.push(info.code);
  assert.equal(link.closed, false);
  bulk.onclose({ code: 1006, reason: "" });
  assert.equal(control.closed, true);
  control.onclose({ code: 1000, reason: "" });
  assert.deepEqual(told, ["1006"]);
  assert.equal(link.closed, true);
  assert.equal(link.publish(`${to}/ctl`, payload, "control"), false); // dropped, as a closed link does
});

test("a split link sends each CONTROL PUT on both websockets under one copy id, a new id each", () => {
  const sockets = [0, 1].map(() => ({ sent: [], send(m) { this.sent.push(m); }, close() { this.closed = true; } }));
  const link = new SplitLink(...sockets.map((ws) => new GatewayLink(ws, "alice", { op: "admitted" })));
  const key = "telebot/robot/guiabot/call/alice/0123456789abcdef/ctl";
  link.publish(key, Uint8Array.of(7, 8, 9), "control");
  link.publish(key, Uint8Array.of(7, 8, 9), "control"); // the same bytes again: a new PUT
  const keyBytes = new TextEncoder().encode(key);
  const parse = (frame) => ({
    lane: frame[0],
    copy: Buffer.from(frame.subarray(1, 9)).toString("hex"),
    key: new TextDecoder().decode(frame.subarray(11, 11 + ((frame[9] << 8) | frame[10]))),
    payload: [...frame.subarray(11 + keyBytes.length)],
  });
  const [first, second] = sockets.map((ws) => ws.sent.map((m) => parse(new Uint8Array(m))));
  assert.deepEqual(first, second); // the same two PUTs on each websocket
  assert.deepEqual(first.map((p) => [p.lane, p.key, p.payload]), [[0x80, key, [7, 8, 9]], [0x80, key, [7, 8, 9]]]);
  const [a, b] = first.map((p) => BigInt(`0x${p.copy}`));
  assert.equal(b, a + 1n); // one counter, under this link's random prefix
  // Another page's link has another prefix: its copies are never taken for this one's.
  const other = [0, 1].map(() => ({ sent: [], send(m) { this.sent.push(m); }, close() {} }));
  new SplitLink(...other.map((ws) => new GatewayLink(ws, "alice", { op: "admitted" }))).publish(key, Uint8Array.of(1), "control");
  assert.notEqual(parse(new Uint8Array(other[0].sent[0])).copy.slice(0, 8), first[0].copy.slice(0, 8));
  // A copy id must be 8 bytes.
  assert.throws(() => link.control.publish(key, Uint8Array.of(1), "control", new Uint8Array(4)), GatewayError);
});

test("a split link made of a websocket that closed meanwhile closes the other at once", () => {
  const sockets = [0, 1].map(() => ({ sent: [], send(m) { this.sent.push(m); }, close() { this.closed = true; } }));
  const [control, bulk] = sockets.map((ws) => new GatewayLink(ws, "alice", { op: "admitted" }));
  sockets[0].onclose({ code: 1006, reason: "" }); // the first died while the second was admitted
  const link = new SplitLink(control, bulk);
  assert.equal(link.closed, true);
  assert.equal(sockets[1].closed, true);
});
