// Frames and messages (§4, §6): round trips, the doc's examples, strict decoders, and a
// seeded fuzz of every decoder (garbage raises ProtocolError and nothing else).
import { test } from "node:test";
import assert from "node:assert/strict";
import { ProtocolError } from "../src/errors.js";
import { fromHex, toHex, concat } from "../src/bytes.js";
import {
  MAX_BUNDLE,
  MAX_DATAGRAM,
  MAX_FRAME,
  dataHeader,
  decodeFrame,
  decodeMessage,
  encodeBundle,
  encodeDatagram,
  encodeHangup,
  encodeHeartbeat,
  encodeRetry,
  encodeWelcome,
  helloPrologue,
} from "../src/proto/frames.js";
import { decodeKey, encodeKey, contactLine, parseContactLine, fingerprint, generateKeyPair, publicKeyOf } from "../src/identity.js";
import { ReplayWindow, WINDOW } from "../src/proto/replay.js";

const CALL_ID = fromHex("0123456789abcdef");

/** A small seeded PRNG (mulberry32): the same garbage on every run. */
function prng(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

test("§6.1 example: text 'hello' on 'chat'", () => {
  assert.equal(toHex(encodeDatagram("chat", "hello")), "0101046368617468656c6c6f");
  assert.deepEqual(decodeMessage(fromHex("0101046368617468656c6c6f")), { kind: "datagram", channel: "chat", payload: "hello", text: true });
});

test("datagrams round-trip: text, bytes, empty, largest, unicode names", () => {
  for (const [name, payload] of [
    ["c", ""],
    ["video", new Uint8Array([0, 1, 255])],
    ["ü/ß", "\ufeffé°—"],
    ["x".repeat(255), new Uint8Array(MAX_DATAGRAM).fill(7)],
    ["empty", new Uint8Array(0)],
  ]) {
    const m = /** @type {any} */ (decodeMessage(encodeDatagram(/** @type {string} */ (name), payload)));
    assert.equal(m.channel, name);
    assert.deepEqual(m.payload, payload);
    assert.equal(m.text, typeof payload === "string");
  }
  assert.throws(() => encodeDatagram("c", new Uint8Array(MAX_DATAGRAM + 1)), ProtocolError);
  assert.throws(() => encodeDatagram("", "x"), ProtocolError);
  assert.throws(() => encodeDatagram("x".repeat(256), "x"), ProtocolError);
});

test("datagram decoder refuses bad flags, names, UTF-8 and oversize", () => {
  for (const hex of ["0102016361", "010100", "01010563", "010101ff", "01010163ff", "0100"]) {
    assert.throws(() => decodeMessage(fromHex(hex)), ProtocolError, hex);
  }
  const big = concat(fromHex("01000163"), new Uint8Array(MAX_DATAGRAM + 1));
  assert.throws(() => decodeMessage(big), ProtocolError);
});

test("§6.2 heartbeat examples", () => {
  assert.equal(
    toHex(encodeHeartbeat({ seq: 1, sentUs: 1000000n, echoUs: 0n, echoDelayUs: 0 })),
    "0200000001" + "00000000000f4240" + "0000000000000000" + "00000000",
  );
  const seven = "0200000007" + "00000000002625a0" + "00000000000f4240" + "00003039";
  assert.equal(toHex(encodeHeartbeat({ seq: 7, sentUs: 2500000n, echoUs: 1000000n, echoDelayUs: 12345 })), seven);
  assert.deepEqual(decodeMessage(fromHex(seven)), { kind: "heartbeat", seq: 7, sentUs: 2500000n, echoUs: 1000000n, echoDelayUs: 12345 });
  assert.throws(() => decodeMessage(fromHex(seven + "00")), ProtocolError);
  // The delay is clamped to u32, never wrapped.
  const clamped = /** @type {any} */ (decodeMessage(encodeHeartbeat({ seq: 1, sentUs: 1n, echoUs: 1n, echoDelayUs: 2 ** 40 })));
  assert.equal(clamped.echoDelayUs, 0xffffffff);
});

test("§6.3 hangup: example, and the reason cut to 200 bytes on a character boundary", () => {
  assert.equal(toHex(encodeHangup("bye")), "03627965");
  const cut = encodeHangup("é".repeat(150)); // 300 bytes of 2-byte characters
  assert.equal(cut.length, 1 + 200);
  const m = /** @type {any} */ (decodeMessage(encodeHangup("a" + "é".repeat(150)))); // odd boundary
  assert.equal(m.reason, "a" + "é".repeat(99));
  assert.throws(() => decodeMessage(fromHex("03ff")), ProtocolError);
});

test("§6.4 BUNDLE: example, round trip, and what is malformed", () => {
  const example = "04" + "0005" + "0101016361" + "0005" + "0101016362";
  assert.equal(toHex(encodeBundle([encodeDatagram("c", "a"), encodeDatagram("c", "b")])), example);
  const m = /** @type {any} */ (decodeMessage(fromHex(example)));
  assert.deepEqual(m.datagrams.map((/** @type {any} */ d) => d.payload), ["a", "b"]);
  for (const bad of [
    "04" + "0005" + "0101016361", // one entry
    "04" + "0005" + "0101016361" + "0006" + "0101016362", // truncated entry
    "04" + "0005" + "0101016361" + "00", // truncated length
    "04" + "0005" + "0101016361" + "0000", // empty entry
    "04" + "0005" + "0101016361" + "0004" + "03627965", // a HANGUP inside
    "04" + "0005" + "0101016361" + "0005" + "0104016362", // bad flags inside
    "04",
  ]) {
    assert.throws(() => decodeMessage(fromHex(bad)), ProtocolError, bad);
  }
  assert.throws(() => encodeBundle([encodeDatagram("c", "a")]), ProtocolError);
  const half = encodeDatagram("c", new Uint8Array(MAX_DATAGRAM / 2));
  assert.throws(() => encodeBundle([half, half, half]), ProtocolError);
  const over = concat(fromHex("04"), new Uint8Array(MAX_BUNDLE));
  assert.throws(() => decodeMessage(over), ProtocolError);
});

test("outer frames: header checks, RETRY, WELCOME, DATA, HELLO", () => {
  assert.throws(() => decodeFrame(fromHex("0203")), ProtocolError);
  assert.throws(() => decodeFrame(fromHex("01050123456789abcdef01")), /version 1/);
  assert.throws(() => decodeFrame(fromHex("02090123456789abcdef01")), /unknown frame type 9/);
  assert.throws(() => decodeFrame(new Uint8Array(MAX_FRAME + 1).fill(2)), /too long/);
  assert.deepEqual(decodeFrame(encodeRetry(CALL_ID, 2)), { type: "retry", callId: CALL_ID, suite: 2 });
  assert.throws(() => decodeFrame(fromHex("02050123456789abcdef0102")), ProtocolError);
  assert.throws(() => decodeFrame(fromHex("02020123456789abcdef")), ProtocolError); // no Noise message
  assert.equal(/** @type {any} */ (decodeFrame(encodeWelcome(CALL_ID, new Uint8Array(48)))).noiseMessage.length, 48);
  const data = /** @type {any} */ (decodeFrame(concat(dataHeader(CALL_ID, 2n ** 64n - 2n), new Uint8Array(16))));
  assert.equal(data.counter, 2n ** 64n - 2n);
  assert.throws(() => decodeFrame(concat(dataHeader(CALL_ID, 0n), new Uint8Array(15))), ProtocolError);
  const prologue = helloPrologue({ callId: CALL_ID, caller: "alice", instance: new Uint8Array(8), suite: 2, offers: [2, 1] });
  const hello = /** @type {any} */ (decodeFrame(concat(prologue, new Uint8Array(96))));
  assert.deepEqual([hello.caller, hello.suite, hello.offers, hello.noiseMessage.length], ["alice", 2, [2, 1], 96]);
  assert.deepEqual(hello.prologue, prologue);
  assert.throws(() => helloPrologue({ callId: CALL_ID, caller: "a b", instance: new Uint8Array(8), suite: 1, offers: [1] }), ProtocolError);
  assert.throws(() => helloPrologue({ callId: CALL_ID, caller: "a", instance: new Uint8Array(8), suite: 2, offers: [1] }), ProtocolError);
  assert.throws(() => helloPrologue({ callId: CALL_ID, caller: "a", instance: new Uint8Array(8), suite: 1, offers: [1, 1] }), ProtocolError);
});

test("seeded fuzz: every decoder raises only ProtocolError on garbage and mutations", () => {
  const random = prng(24);
  const seeds = [
    encodeDatagram("chat", "hello"),
    encodeBundle([encodeDatagram("c", "a"), encodeDatagram("d", new Uint8Array([1, 2]))]),
    encodeHeartbeat({ seq: 3, sentUs: 5n, echoUs: 6n, echoDelayUs: 7 }),
    encodeHangup("bye"),
    encodeRetry(CALL_ID, 1),
    encodeWelcome(CALL_ID, new Uint8Array(60)),
    concat(dataHeader(CALL_ID, 9n), new Uint8Array(30)),
    concat(helloPrologue({ callId: CALL_ID, caller: "alice", instance: new Uint8Array(8), suite: 1, offers: [1, 2] }), new Uint8Array(140)),
  ];
  const keyText = encodeKey(new Uint8Array(32).fill(9));
  let decoded = 0;
  for (let i = 0; i < 20000; i++) {
    let bytes;
    if (i % 3 === 0) {
      bytes = new Uint8Array(Math.floor(random() * 80));
      for (let j = 0; j < bytes.length; j++) bytes[j] = Math.floor(random() * 256);
    } else {
      const seed = seeds[Math.floor(random() * seeds.length)];
      bytes = seed.slice(0, Math.floor(random() * (seed.length + 2)));
      for (let k = Math.floor(random() * 4); k > 0 && bytes.length; k--) {
        bytes[Math.floor(random() * bytes.length)] = Math.floor(random() * 256);
      }
    }
    for (const decode of [decodeFrame, decodeMessage]) {
      try {
        decode(bytes);
        decoded += 1;
      } catch (error) {
        assert.ok(error instanceof ProtocolError, `${decode.name}(${toHex(bytes)}) threw ${error}`);
      }
    }
    const text = [...keyText].map((c) => (random() < 0.05 ? String.fromCharCode(Math.floor(random() * 128)) : c)).join("");
    for (const parse of [decodeKey, parseContactLine]) {
      try {
        const cut = text.slice(0, 40 + Math.floor(random() * 6));
        parse(parse === decodeKey ? cut : `telebot-x25519 ${cut} ${random() < 0.5 ? "alice" : "a/b"}`);
      } catch (error) {
        assert.ok(error instanceof ProtocolError, `${parse.name} threw ${error}`);
      }
    }
  }
  assert.ok(decoded > 100); // the mutations do reach the decoders' insides
});

test("keys: text form, canonical only, the keygen line, fingerprint", () => {
  const priv = fromHex("000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f");
  const pub = publicKeyOf(priv);
  assert.equal(encodeKey(priv), "AAECAwQFBgcICQoLDA0ODxAREhMUFRYXGBkaGxwdHh8"); // §3.2's id_telebot
  assert.deepEqual(decodeKey("  j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8\n"), pub);
  assert.equal(contactLine("alice", pub), "telebot-x25519 j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8 alice");
  assert.deepEqual(parseContactLine("telebot-x25519 j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8 alice\n"), { name: "alice", publicKey: pub });
  assert.throws(() => decodeKey("j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF9"), /canonical/); // non-zero pad bits
  assert.throws(() => decodeKey("j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF"), /43/);
  assert.throws(() => decodeKey("j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4K+8"), ProtocolError);
  assert.throws(() => parseContactLine("ssh-ed25519 AAAA alice"), ProtocolError);
  assert.throws(() => contactLine("bad name", pub), ProtocolError);
  assert.match(fingerprint(pub), /^SHA256:[A-Za-z0-9+/]{43}$/);
  const pair = generateKeyPair();
  assert.deepEqual(publicKeyOf(pair.privateKey), pair.publicKey);
  assert.notDeepEqual(generateKeyPair().privateKey, pair.privateKey);
});

test("replay window (§7): once each, 2048 back, jumps", () => {
  const w = new ReplayWindow();
  const take = (/** @type {bigint} */ c) => {
    if (!w.check(c)) return false;
    w.accept(c);
    return true;
  };
  assert.ok(take(0n));
  assert.ok(!take(0n));
  assert.ok(take(5n));
  assert.ok(take(3n));
  assert.ok(!take(3n));
  assert.ok(take(BigInt(WINDOW) + 4n)); // counter 4 is now 2048 back
  assert.ok(!w.check(4n)); // just out of the window
  assert.ok(w.check(6n)); // inside, never seen
  assert.ok(!w.check(5n)); // still remembered
  assert.ok(take(BigInt(WINDOW) + 40n)); // shift by 36: bits cross word boundaries
  assert.ok(!w.check(BigInt(WINDOW) + 4n));
  assert.ok(w.check(BigInt(WINDOW) + 3n));
  assert.ok(take(2n ** 63n)); // a huge jump forgets everything
  assert.ok(!w.check(2n ** 63n));
  assert.ok(w.check(2n ** 63n - 1n));
  assert.ok(!w.check(2n ** 63n - BigInt(WINDOW)));
  // Against a plain set: random counters near the top.
  const random = prng(7);
  const r = new ReplayWindow();
  const seen = new Set();
  let highest = -1;
  for (let i = 0; i < 5000; i++) {
    const c = Math.max(0, highest + Math.floor(random() * 300) - 2200);
    const expected = c > highest || (highest - c < WINDOW && !seen.has(c));
    assert.equal(r.check(BigInt(c)), expected, `counter ${c}, highest ${highest}`);
    if (expected) {
      r.accept(BigInt(c));
      seen.add(c);
      highest = Math.max(highest, c);
    }
  }
});
