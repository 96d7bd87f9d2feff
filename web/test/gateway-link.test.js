// The gateway link's pure parts: the admission proof of docs/protocol.md §26.1 (its test
// vector, computed there from the bare primitives in Python) and the key encoding.
// The link against a live gateway runs in tests/test_gateway.py (node + a real gateway).
import { test } from "node:test";
import assert from "node:assert/strict";
import { x25519 } from "@noble/curves/ed25519";
import { admissionProof, connectGateway, decodeKey, encodeKey, GatewayError, GatewayLink } from "../src/gateway-link.js";

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
