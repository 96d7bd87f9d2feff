// docs/protocol.md §11: the test vectors of both cipher suites, reproduced byte for byte
// from the §11.1 inputs (ephemeral keys and ts injected).
import { test } from "node:test";
import assert from "node:assert/strict";
import { fromHex, toHex } from "../src/bytes.js";
import { encodeKey, publicKeyOf } from "../src/identity.js";
import { InitiatorHandshake, ResponderHandshake, AESGCM, CHACHAPOLY } from "../src/proto/noise.js";
import { CallSession, CallSetup, buildHello, readWelcome } from "../src/proto/session.js";
import { decodeFrame, encodeWelcome, encodeRetry } from "../src/proto/frames.js";
import { concat, utf8 } from "../src/bytes.js";
import { blake2s } from "@noble/hashes/blake2";

const h = (/** @type {string} */ s) => fromHex(s.replace(/\s+/g, ""));
const USER_STATIC = h("000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f");
const USER_EPHEMERAL = h("202122232425262728292a2b2c2d2e2f303132333435363738393a3b3c3d3e3f");
const ROBOT_STATIC = h("404142434445464748494a4b4c4d4e4f505152535455565758595a5b5c5d5e5f");
const ROBOT_EPHEMERAL = h("606162636465666768696a6b6c6d6e6f707172737475767778797a7b7c7d7e7f");
const RETRY_EPHEMERAL = h("808182838485868788898a8b8c8d8e8f909192939495969798999a9b9c9d9e9f");
const CALL_ID = h("0123456789abcdef");
const INSTANCE = h("a1a2a3a4a5a6a7a8");
const TS = 1700000000000000000n;
const ACCEPT = utf8('{"accepted": true, "robot": "guiabot", "role": "driver"}');
const REFUSE = utf8('{"accepted": false, "robot": "guiabot", "reason": "not in the contact list of guiabot"}');

const SUITES = {
  chachapoly: {
    offers: [CHACHAPOLY, AESGCM],
    hello: `02040123456789abcdef05616c696365a1a2a3a4a5a6a7a801020102358072d6365880d1aeea329adf912138
3851ed21a28e3b75e965d0d2cd166254ad5b8febedeb97415be53612205e6bfab385e34cb127dd8854c4f9af
b10f9b0ec0dac86a3e21bb4660768fd35324b3f3f05e9528e0cb591051056197c382dccfc7ace9811f40c60e
f59e2c07a56bd42becbc42634210cbe0313c878e639b04cd42d896b55b0c1b4dfb388e29`,
    accepted: `02020123456789abcdef675dd574ed7789310b3d2e7681f3790b466c773b1521fecf36577958371ea52f5063
7ed421e34c13332ae8012bf9d561453dc323f5ae980223602cf74fbe8df5f22f151a39f68a11f83e4efb0076
c9f51ca9fec1ece47ae67fe2ac213e017578a449b9bd901b3cf3`,
    refused: `02020123456789abcdef675dd574ed7789310b3d2e7681f3790b466c773b1521fecf36577958371ea52f5063
7ed421e34c13332ae8012bebc6785374cf21a5b3950f383634ed4dfb9fe9fa2c18016ff88613a82347ff5123
87f542fbb5d9e6e278f254130668a16a8404288a68faa4cddc7019f469ffd195a81921799ae616a7280b04c6
662ca79d8654ac6cad9f9d9323`,
    k1: "1ffa520b7b784b83355f4ca5754d333f51f53ff31d9d98f697c22e8f79b66e22",
    k2: "1657d025486888648386e46e37e6722a42c605d3f1b0ec24454190a645355089",
    hash: "04644eefb6d1583e18af2ba854272f4e2ad7a3c0f3d973fb1b7507e5cdad2244",
    dataHello: "02030123456789abcdef0000000000000000b57d4c9b157c2d4fe97f33bb20aa17eef2af988482413903015b63f4",
    dataEcho: "02030123456789abcdef000000000000000069f4ef4025b7c333812a61ad960f5ca00348d122db53108374779c7a",
    dataBye: "02030123456789abcdef000000000000000180cf74d8a4b0f280b4ba516d2eb8d09f371d1788",
  },
  aesgcm: {
    offers: [AESGCM, CHACHAPOLY],
    hello: `02040123456789abcdef05616c696365a1a2a3a4a5a6a7a802020201358072d6365880d1aeea329adf912138
3851ed21a28e3b75e965d0d2cd16625467e89736a020bfbd9f31f737e3881df8d35dd0308d94db3d9759851b
5eef0ab12ba6bac8530f70035fe02ff7865d7aa843b761a18a67eb5f29afe5b10937b002f712eedec6f5c504
f8a9ac38ae509b8e9fb786ecf7b1a9be70d85d3cc5609497867854d65d0d16e587a6f79f`,
    accepted: `02020123456789abcdef675dd574ed7789310b3d2e7681f3790b466c773b1521fecf36577958371ea52ff113
859cb1098ec1e723ce53ebb40aa154b048ef48b7b8f09bf7011f1212d6c719975e78a7bcd185730dbe684afc
d2798f0f9ca4d1166c31af444a59de0b7086708405ba3371249b`,
    refused: `02020123456789abcdef675dd574ed7789310b3d2e7681f3790b466c773b1521fecf36577958371ea52ff113
859cb1098ec1e723ce53eba619b842f944ed18aab5fd80a119051057c4db11945363f1b2dd872310b76c1ba9
9c79d15dd7bcdb106e2517d6636e075788d09300b91851f391e36084518f665c967b8617a5b133aa6025723c
6483963900c37ad8b88bb8db78`,
    k1: "505abdde14530362a66e6697354f4a3dc5b183714178db09ccea5ea5728ba7a6",
    k2: "c0b99ec9a74cc71ea5d2bd2b2c465061ddd0b4657a1b55788261a1caffe28e44",
    hash: "97d3b0a43985a29329eced70bf7fd9c349c5df8ec41c21a9c5482053b555590e",
    dataHello: "02030123456789abcdef000000000000000051e0a5c594b06247d7444f0babde44310408a1f5dd5d4e35cf189fad",
    dataEcho: "02030123456789abcdef0000000000000000acefaa7e6ed8593c48033ce69a52580ce5c2d097399b2cee87a037c7",
    dataBye: "02030123456789abcdef0000000000000001d3aed71b06e5b383cbe6a019fc9f42f238a383c8",
  },
};

const ROBOT_PUBLIC = publicKeyOf(ROBOT_STATIC);

test("the §11.1 public keys", () => {
  assert.equal(encodeKey(publicKeyOf(USER_STATIC)), "j0DFrbaPJWJK5bIU6nZ6bslNgp09e14a0bpvPiE4KF8");
  assert.equal(encodeKey(ROBOT_PUBLIC), "eaYx7t4b-cmPEgMs3q3Q56B5OY_HhriMyEbsia-FpRo");
  assert.equal(toHex(publicKeyOf(USER_EPHEMERAL)), "358072d6365880d1aeea329adf9121383851ed21a28e3b75e965d0d2cd166254");
  assert.equal(toHex(publicKeyOf(ROBOT_EPHEMERAL)), "675dd574ed7789310b3d2e7681f3790b466c773b1521fecf36577958371ea52f");
});

function hello(/** @type {number[]} */ offers, suite = offers[0], eph = USER_EPHEMERAL, ts = TS) {
  return buildHello({
    staticPrivate: USER_STATIC,
    robotPublic: ROBOT_PUBLIC,
    caller: "alice",
    instance: INSTANCE,
    callId: CALL_ID,
    wallTimeNs: ts,
    offers,
    suite,
    ephemeralPrivate: eph,
  });
}

/** The robot's side of the vectors, from the JS responder (used only by tests). */
function answer(/** @type {Uint8Array} */ helloBytes, /** @type {Uint8Array} */ payload) {
  const frame = /** @type {any} */ (decodeFrame(helloBytes));
  const responder = new ResponderHandshake({
    staticPrivate: ROBOT_STATIC,
    prologue: frame.prologue,
    suite: frame.suite,
    ephemeralPrivate: ROBOT_EPHEMERAL,
  });
  const p1 = responder.readMessage(frame.noiseMessage);
  const { message, keys } = responder.writeMessage(payload);
  return { welcome: encodeWelcome(CALL_ID, message), keys, p1: new TextDecoder().decode(p1) };
}

for (const [name, v] of Object.entries(SUITES)) {
  test(`${name}: HELLO is byte-exact (§11.2/§11.5)`, () => {
    const { hello: bytes } = hello(v.offers);
    assert.equal(bytes.length, 168);
    assert.equal(toHex(bytes), toHex(h(v.hello)));
  });

  test(`${name}: WELCOME accepted: split keys and hash (§11.3/§11.6)`, () => {
    const { hello: bytes, handshake } = hello(v.offers);
    const robot = answer(bytes, ACCEPT);
    assert.equal(robot.p1, '{"user": "alice", "ts": 1700000000000000000}');
    assert.equal(toHex(robot.welcome), toHex(h(v.accepted)));
    const frame = /** @type {any} */ (decodeFrame(h(v.accepted)));
    const { answer: a, keys } = readWelcome(handshake, frame.noiseMessage);
    assert.deepEqual(a, { accepted: true, robot: "guiabot", role: "driver", reason: "" });
    assert.equal(toHex(keys.sendKey), v.k1);
    assert.equal(toHex(keys.receiveKey), v.k2);
    assert.equal(toHex(keys.handshakeHash), v.hash);
  });

  test(`${name}: WELCOME refused (§11.3/§11.6)`, () => {
    const { hello: bytes, handshake } = hello(v.offers);
    assert.equal(toHex(answer(bytes, REFUSE).welcome), toHex(h(v.refused)));
    const frame = /** @type {any} */ (decodeFrame(h(v.refused)));
    const { answer: a } = readWelcome(handshake, frame.noiseMessage);
    assert.deepEqual(a, { accepted: false, robot: "guiabot", role: "", reason: "not in the contact list of guiabot" });
  });

  test(`${name}: DATA frames (§11.4/§11.7)`, () => {
    const { hello: bytes, handshake } = hello(v.offers);
    const frame = /** @type {any} */ (decodeFrame(h(v.accepted)));
    const { keys } = readWelcome(handshake, frame.noiseMessage);
    const user = new CallSession({ callId: CALL_ID, keys, peer: "guiabot", now: 0 });
    assert.equal(toHex(user.sealDatagram("chat", "hello")), v.dataHello);
    assert.equal(toHex(/** @type {Uint8Array} */ (user.hangup("bye"))), v.dataBye);
    const robotKeys = answer(bytes, ACCEPT).keys;
    const robot = new CallSession({ callId: CALL_ID, keys: robotKeys, peer: "alice", now: 0 });
    assert.equal(toHex(robot.sealDatagram("chat", "hello")), v.dataEcho);
    // And the user opens the echo.
    const user2 = new CallSession({ callId: CALL_ID, keys, peer: "guiabot", now: 0 });
    const got = user2.receive(h(v.dataEcho), 0.01);
    assert.deepEqual(got.datagrams, [{ kind: "datagram", channel: "chat", payload: "hello", text: true }]);
    // The robot opens the user's hang-up.
    const end = robot.receive(h(v.dataBye), 0.01);
    assert.deepEqual(end.ended, { kind: "hung_up", byPeer: true, detail: "bye" });
  });
}

test("RETRY and the HELLO that follows it (§11.8)", () => {
  const retry = encodeRetry(CALL_ID, CHACHAPOLY);
  assert.equal(toHex(retry), "02050123456789abcdef01");
  const ephemerals = [USER_EPHEMERAL, RETRY_EPHEMERAL];
  const times = [TS, TS + 1n];
  const setup = new CallSetup({
    staticPrivate: USER_STATIC,
    robotPublic: ROBOT_PUBLIC,
    caller: "alice",
    robot: "guiabot",
    instance: INSTANCE,
    callId: CALL_ID,
    offers: [AESGCM, CHACHAPOLY],
    now: 0,
    connectTimeout: 5,
    wallTimeNs: () => /** @type {bigint} */ (times.shift()),
    ephemeral: () => ephemerals.shift(),
  });
  assert.equal(toHex(setup.hello), toHex(h(SUITES.aesgcm.hello)));
  const result = /** @type {any} */ (setup.receive(retry, "guiabot"));
  assert.equal(result.kind, "resend");
  const expected = `02040123456789abcdef05616c696365a1a2a3a4a5a6a7a801020201493e82fc74464a59268817623d2053c5
eb8e2cc4a988b4fee179ec6b010d531d32f294c5f359b9bfc9e6b58d230e1fa7681836d92ff585a852293634
494dbcb7adf4ec7d03fbd41a11ecdd20a17374e0aa51fd375a55f4509051a40611e68103a2f267f3cad44879
135ba59ab77ac6aaca7842a8d7008f92f700db121a1d10b85c3821979869efad6394fc91`;
  assert.equal(toHex(result.hello), toHex(h(expected)));
  assert.equal(setup.suite, CHACHAPOLY);
  // From then on the repeats carry that HELLO.
  assert.equal(toHex(/** @type {Uint8Array} */ (setup.poll(0).send)), toHex(h(expected)));
});

test("a handshake's initial h per suite (§5.1, §11.2, §11.5)", () => {
  for (const [suite, hex] of /** @type {[number, string][]} */ ([
    [CHACHAPOLY, "bbea022b948cf3bc5857d70804229179e1116bc40cb8cc074835349c464bca36"],
    [AESGCM, "4e6f6973655f494b5f32353531395f41455347434d5f424c414b453273000000"],
  ])) {
    const prologue = utf8("p");
    const hs = new InitiatorHandshake({ staticPrivate: USER_STATIC, responderStatic: ROBOT_PUBLIC, prologue, suite });
    const expected = blake2s(concat(blake2s(concat(h(hex), prologue)), ROBOT_PUBLIC));
    assert.equal(toHex(hs.state.h), toHex(expected));
    assert.equal(toHex(hs.state.ck), hex);
  }
});
