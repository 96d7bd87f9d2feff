// The user's camera and microphone to the robot through RobotSession (§19.1, §25): the
// page's pictures become video/user FRAGMENTs byte for byte (the Python relay's bytes,
// checked against its `fragment()` output), its Opus packets audio/user AUDIO packets,
// the robot's reports choose the codec and ask the page for keyframes, the 2 s probe,
// a seeded lossy call that recovers by keyframe requests, and fuzz of the new decoders.
import { test } from "node:test";
import assert from "node:assert/strict";
import { RobotSession } from "../src/session.js";
import { DecodeError, toHex } from "../src/services/util.js";
import { KeyframeGate, Reassembler, encodeReport, parseAudio } from "../src/services/video.js";
import { parseMediaMessage, unpackMedia } from "../src/services/uplink.js";
import { packMedia } from "../src/services/video.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

async function started({ seed = 1, upLoss = 0, downLoss = 0, encode = ["vp8", "h264"] } = {}) {
  const clock = new ManualClock();
  const out = [];
  const made = [];
  const session = new RobotSession({
    connect: async () => {
      const call = new FakeCall({ seed, upLoss, downLoss });
      call.onUser("map", () => {});
      made.push(call);
      return call;
    },
    emit: (m) => out.push(m),
    user: "alice",
    clock,
    random: seeded(seed),
    mapUrl: () => "blob:map",
  });
  await session.start();
  if (encode) session.send({ type: "media", decode: ["h264", "vp8", "jpeg"], encode });
  return { clock, out, session, call: () => made.at(-1) };
}

const ofType = (out, type) => out.filter((m) => m.type === type);
const CAPTURE = 1700000000.25;
const report = (over = {}) => encodeReport({ receiverMs: 1, highestSeq: 0, fragments: 0, bytes: 0, frames: 0, dropped: 0, queueDelayMs: 0, ...over });
const picture = (frameId, key, data, codec = "vp8") => ({ type: "video", header: { kind: "video", codec, key, frame_id: frameId, capture_time: CAPTURE }, data });

test("the robot's reports on video/user reach the page as uplink_report (not a BYE, not a reordered one)", async () => {
  const { clock, out, call } = await started();
  const counters = { highestSeq: 120, fragments: 100, bytes: 90000, frames: 40, dropped: 3, queueDelayMs: 17 };
  call().toUser("video/user", report({ receiverMs: 5000, ...counters, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.deepEqual(ofType(out, "uplink_report"), [{
    type: "uplink_report", receiver_ms: 5000, highest_seq: 120, fragments: 100, bytes: 90000, frames: 40, dropped: 3, queue_delay_ms: 17,
  }]);
  call().toUser("video/user", report({ receiverMs: 4000, codecs: [0x04] }), { lossless: true });
  call().toUser("video/user", report({ receiverMs: 5200, bye: true, codecs: [0x04] }), { lossless: true });
  call().toUser("audio/user", report({ receiverMs: 5300, codecs: [0x10] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(ofType(out, "uplink_report").length, 1, "reordered, BYE and audio reports are not the camera's");
});

test("the page's media message is answered send: true in its first codec; the robot's list then chooses", async () => {
  const { clock, out, call } = await started();
  assert.deepEqual(ofType(out, "media"), [{ type: "media", send: true, codec: "vp8", note: "" }]);
  call().toUser("video/user", report({ codecs: [0x03, 0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.deepEqual(ofType(out, "media").at(-1), { type: "media", send: true, codec: "vp8", note: "" }, "the sender's first preference the robot takes (§25.2)");
  call().toUser("video/user", report({ receiverMs: 2, codecs: [0x03] }), { lossless: true });
  await clock.advance(0.05);
  assert.deepEqual(ofType(out, "media").at(-1), { type: "media", send: true, codec: "h264", note: "" });
  call().toUser("video/user", report({ receiverMs: 3, codecs: [0x01] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(ofType(out, "media").at(-1).send, false);
  assert.match(ofType(out, "media").at(-1).note, /decodes none/);
  const count = ofType(out, "media").length;
  call().toUser("video/user", report({ receiverMs: 4, codecs: [0x01] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(ofType(out, "media").length, count, "told again only on a change");
});

test("a page without WebCodecs is told it does not send, and its pictures stay home", async () => {
  const { clock, out, session, call } = await started({ encode: [] });
  assert.equal(ofType(out, "media").at(-1).send, false);
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 0, capture_time: CAPTURE }, data: Uint8Array.of(1) }), false);
  await clock.advance(0.05);
  assert.equal(call().sent("audio/user").length, 0);
});

test("a fragmented keyframe: the exact §17.1/§25.1 bytes of the Python relay", async () => {
  const { session, call } = await started();
  const data = new Uint8Array(70000);
  for (let i = 0; i < data.length; i++) data[i] = (i * 7) % 251;
  // The page's own frame_id (77) is not the wire's: the uplink numbers what it takes.
  assert.equal(session.send(picture(77, true, data)), true);
  const sent = call().sent("video/user");
  assert.deepEqual(sent.map((d) => d.length), [23367, 23366, 23366], "q, r = divmod(70000, 3): 23334, 23333, 23333 bytes");
  // telebot.services.proto.video.fragment(0, "user", 1700000000.25, data, seq=0, codec=4, keyframe=True)
  const headers = [
    "01840000000000000000000000030001117000060a241822109000210475736572",
    "01840000000100000000000100030001117000060a241822109000210475736572",
    "01840000000200000000000200030001117000060a241822109000210475736572",
  ];
  const spans = [[0, 23334], [23334, 46667], [46667, 70000]];
  sent.forEach((d, i) => {
    assert.equal(toHex(d.subarray(0, 33)), headers[i]);
    assert.deepEqual(d.subarray(33), data.subarray(...spans[i]));
  });
  // The next picture, a delta: codec byte 0x04, frame id 1, seq 3.
  assert.equal(session.send(picture(78, false, Uint8Array.of(9, 8, 7))), true);
  assert.equal(toHex(call().sent("video/user")[3]), "01040000000300000001000000010000000300060a241822109000210475736572090807");
});

test("audio packets: the page's Opus as §25.3 AUDIO, numbered by the uplink", async () => {
  const { session, call, out } = await started();
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 7, capture_time: CAPTURE }, data: Uint8Array.of(0xfc, 1, 2) }), true);
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 8, capture_time: CAPTURE + 0.02 }, data: Uint8Array.of(0xfc, 3) }), true);
  const sent = call().sent("audio/user");
  assert.equal(toHex(sent[0]), "03100000000000060a2418221090fc0102"); // encode_audio(0, 1700000000.25, fc0102)
  assert.deepEqual({ ...parseAudio(sent[1]), data: [...parseAudio(sent[1]).data] }, { seq: 1, captureUs: 1700000000270000, data: [0xfc, 3] });
  // Too long an Opus packet (> 1500) is refused with one error naming it, never sent.
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 9, capture_time: CAPTURE }, data: new Uint8Array(1501) }), false);
  assert.match(out.at(-1).text, /^media dropped: an Opus packet must be 1\.\.1500 bytes, got 1501$/);
  assert.equal(call().sent("audio/user").length, 2);
});

test("a congested link: the picture's rest and the audio packet are not sent, counted, and the page told false", async () => {
  const { session, call } = await started();
  const big = new Uint8Array(70000).fill(5); // three fragments
  call().congested = true;
  assert.equal(session.send(picture(0, true, big)), false, "false: the page makes its next picture a keyframe");
  assert.equal(call().refused, 1, "the rest of the picture was not even tried");
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 0, capture_time: CAPTURE }, data: Uint8Array.of(1) }), false);
  const { userMedia } = session.services;
  assert.deepEqual([userMedia.video.dropped, userMedia.video.sent, userMedia.audio.dropped, userMedia.audio.sent], [1, 0, 1, 0]);
  assert.equal(call().sent("video/user").length, 0);
  // Drained: the page's keyframe goes whole, with the next frame id (the robot sees the gap).
  call().congested = false;
  assert.equal(session.send(picture(1, true, big)), true);
  const sent = call().sent("video/user");
  assert.equal(sent.length, 3);
  assert.deepEqual(sent.map((d) => new DataView(d.buffer).getUint32(6)), [1, 1, 1]);
  assert.deepEqual([userMedia.video.dropped, userMedia.video.sent], [1, 1]);
});

test("unasked for 2 s from the first picture; then only while the robot's reports come", async () => {
  const { clock, session, call } = await started();
  const one = Uint8Array.of(1);
  assert.equal(session.send(picture(0, true, one)), true);
  await clock.advance(1.9);
  assert.equal(session.send(picture(1, false, one)), true, "within the probe");
  await clock.advance(0.2);
  assert.equal(session.send(picture(2, false, one)), false, "no report in 2 s: nothing more");
  assert.equal(session.send({ type: "audio", header: { kind: "audio", seq: 0, capture_time: CAPTURE }, data: one }), true, "audio's probe starts with its own first packet");
  call().toUser("video/user", report({ receiverMs: 10, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(session.send(picture(3, true, one)), true, "a report asks again");
  call().toUser("video/user", report({ receiverMs: 11, bye: true, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(session.send(picture(4, false, one)), false, "BYE");
  call().toUser("video/user", report({ receiverMs: 10, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(session.send(picture(5, false, one)), false, "an older report cannot undo the BYE");
  call().toUser("video/user", report({ receiverMs: 12, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.05);
  assert.equal(session.send(picture(6, true, one)), true);
  await clock.advance(2.1);
  assert.equal(session.send(picture(7, false, one)), false, "2 s after the last report");
  // Frame ids count what was taken while asked for: 0, 1, 3, 6 → 0, 1, 2, 3 on the wire.
  assert.deepEqual(call().sent("video/user").map((d) => new DataView(d.buffer).getUint32(6)), [0, 1, 2, 3]);
});

test("the robot's keyframe requests reach the page, at most once per max(RTT, 300 ms)", async () => {
  const { clock, out, call } = await started();
  let ms = 100;
  const ask = () => call().toUser("video/user", report({ receiverMs: ms++, keyframe: true, codecs: [0x04] }), { lossless: true });
  ask();
  await clock.advance(0.02);
  assert.equal(ofType(out, "keyframe_request").length, 1);
  ask();
  await clock.advance(0.1);
  ask();
  await clock.advance(0.02);
  assert.equal(ofType(out, "keyframe_request").length, 1, "a repeat within 300 ms is the same request");
  await clock.advance(0.2);
  ask();
  await clock.advance(0.02);
  assert.equal(ofType(out, "keyframe_request").length, 2);
  call().toUser("video/user", report({ receiverMs: ms++, codecs: [0x04] }), { lossless: true });
  await clock.advance(0.5);
  assert.equal(ofType(out, "keyframe_request").length, 2, "no flag, no request");
});

test("seeded 10 % loss both ways: the robot's requests bring keyframes and its pictures resume", async () => {
  const { clock, out, session, call } = await started({ seed: 7, upLoss: 0.1, downLoss: 0.1 });
  // The robot: §17.3 reassembly, the §25.1 gate, reports every 200 ms with the keyframe flag.
  const reassembler = new Reassembler();
  const gate = new KeyframeGate();
  const decoded = [];
  let ms = 0;
  const robotReport = (keyframe) => call().toUser("video/user", reassembler.report(ms++, { keyframe, codecs: [0x04, 0x03] }));
  call().onUser("video/user", (d) => {
    const frame = reassembler.onDatagram(d, clock.now());
    if (!frame) return;
    if (gate.admit(frame.frameId, frame.codec, frame.keyframe)) decoded.push(frame);
    else robotReport(true);
  });
  let last = clock.now();
  const robotTimer = clock.every(0.2, () => robotReport(gate.needKeyframe));
  // The page: 30 pictures a second, a keyframe when asked (and when one did not go).
  let forceKey = true;
  let id = 0;
  let seen = 0;
  const keys = [];
  const pageTimer = clock.every(1 / 30, () => {
    const asked = ofType(out, "keyframe_request").length;
    if (asked > seen) {
      forceKey = true;
      seen = asked;
    }
    const key = forceKey;
    const data = new Uint8Array(key ? 40000 : 3000).fill(id & 0xff);
    if (session.send(picture(id, key, data))) {
      forceKey = false;
      if (key) keys.push(id);
    } else {
      forceKey = true;
    }
    id += 1;
  });
  await clock.advance(10, 1 / 60);
  robotTimer();
  pageTimer();
  assert.ok(seen >= 2, `keyframe requests reached the page: ${seen}`);
  assert.ok(keys.length >= 2, `the page answered with keyframes: ${keys.length}`);
  assert.ok(decoded.length > 150, `the robot decoded most pictures: ${decoded.length} of ${id}`);
  assert.ok(gate.skipped > 0, "some deltas waited for a keyframe (the loss was real)");
  for (const f of decoded) assert.equal(f.camera, "user");
  assert.ok(decoded.at(-1).completedAt > last + 8, "still decoding at the end");
});

test("malformed page media: one error each naming the fault, counted, never thrown", async () => {
  const { out, session, call } = await started();
  const bad = [
    [{ type: "video", header: { kind: "video", codec: "jpeg", key: true, frame_id: 1, capture_time: 1 }, data: Uint8Array.of(1) }, /video codec "jpeg" not offered/],
    [{ type: "video", header: { kind: "video", codec: "vp8", key: 1, frame_id: 1, capture_time: 1 }, data: Uint8Array.of(1) }, /key must be true or false/],
    [{ type: "video", header: { kind: "video", codec: "vp8", key: true, frame_id: -1, capture_time: 1 }, data: Uint8Array.of(1) }, /frame_id must be an integer/],
    [{ type: "video", header: { kind: "video", codec: "vp8", key: true, frame_id: 1, capture_time: 1 }, data: new Uint8Array(0) }, /a video frame must be 1\.\.2000000 bytes, got 0/],
    [{ type: "video", header: { kind: "video", codec: "vp8", key: true, frame_id: 1, capture_time: -1 }, data: Uint8Array.of(1) }, /capture_time must be finite and >= 0/],
    [{ type: "audio", header: { kind: "video", seq: 1, capture_time: 1 }, data: Uint8Array.of(1) }, /header of kind "video"/],
    [{ type: "audio" }, /header of kind null/],
    [new Uint8Array(3), /4-byte header length/],
    [new Uint8Array([0, 0, 0, 9, 123]), /bad media header length 9/],
  ];
  for (const [msg, pattern] of bad) {
    const before = out.length;
    assert.equal(session.send(msg), false);
    assert.equal(out.length, before + 1);
    assert.equal(out.at(-1).type, "error");
    assert.match(out.at(-1).text, pattern);
    assert.ok(!out.at(-1).text.includes("\n"));
  }
  assert.equal(session.mediaErrors, bad.length);
  assert.equal(call().sent("video/user").length + call().sent("audio/user").length, 0);
  // Today's binary message of a page written for the local websocket goes too.
  assert.equal(session.send(new Uint8Array(packMedia({ kind: "video", codec: "vp8", key: true, frame_id: 0, capture_time: 2 }, Uint8Array.of(5)))), true);
  assert.equal(call().sent("video/user").length, 1);
});

test("seeded fuzz: the page's media decoders and the robot's reports never throw anything else", async () => {
  const random = seeded(2024);
  const valid = new Uint8Array(packMedia({ kind: "video", codec: "vp8", key: true, frame_id: 3, capture_time: 1.5 }, Uint8Array.of(1, 2, 3)));
  let accepted = 0;
  for (let i = 0; i < 5000; i++) {
    const bytes = random() < 0.5 ? valid.slice() : new Uint8Array(Math.floor(random() * 64));
    const flips = 1 + Math.floor(random() * 4);
    for (let f = 0; f < flips && bytes.length; f++) bytes[Math.floor(random() * bytes.length)] = Math.floor(random() * 256);
    try {
      const { header, data } = unpackMedia(bytes);
      parseMediaMessage(header, data);
      accepted += 1;
    } catch (err) {
      assert.ok(err instanceof DecodeError, `${err}`);
      assert.ok(!err.message.includes("\n"));
    }
  }
  assert.ok(accepted > 0 && accepted < 5000);
  for (let i = 0; i < 2000; i++) {
    const header = { kind: ["video", "audio", 3, null][Math.floor(random() * 4)], codec: ["vp8", "h264", "x", 1][Math.floor(random() * 4)], key: [true, 0][Math.floor(random() * 2)], frame_id: [0, 2 ** 32, 1.5, "1"][Math.floor(random() * 4)], seq: [0, -1][Math.floor(random() * 2)], capture_time: [0, NaN, Infinity, "1", 1e12][Math.floor(random() * 5)] };
    try {
      parseMediaMessage(random() < 0.1 ? null : header, random() < 0.1 ? "x" : new Uint8Array(Math.floor(random() * 3)));
    } catch (err) {
      assert.ok(err instanceof DecodeError, `${err}`);
    }
  }
  const { clock, out, session, call } = await started({ seed: 3 });
  const before = out.length;
  for (let i = 0; i < 3000; i++) {
    const r = report({ receiverMs: i, keyframe: random() < 0.5, codecs: random() < 0.5 ? [4, 3] : [] });
    const bytes = random() < 0.3 ? r : new Uint8Array(Math.floor(random() * 40));
    for (let f = 0; f < 2 && bytes.length; f++) bytes[Math.floor(random() * bytes.length)] = Math.floor(random() * 256);
    const name = random() < 0.5 ? "video/user" : "audio/user";
    assert.doesNotThrow(() => call().channels.get(name).onmessage(random() < 0.05 ? "text" : bytes));
  }
  await clock.advance(0.1);
  assert.ok(session.drops.userMedia > 1000, `counted: ${JSON.stringify(session.drops)}`);
  for (const m of out.slice(before)) assert.ok(["media", "keyframe_request", "uplink_report", "link", "error"].includes(m.type), m.type);
  session.send({ type: "ping", t: 2 });
  assert.deepEqual(out.at(-1), { type: "pong", t: 2 }, "the session still works");
});
