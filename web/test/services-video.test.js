// Video (§17, §25): fragments reassembled into whole pictures, a lost fragment drops the
// picture whole and, for a delta codec, brings a keyframe request; REPORTs every 200 ms.
import { test } from "node:test";
import assert from "node:assert/strict";
import { VideoService, AudioService } from "../src/services/services.js";
import {
  CODEC_H264, CODEC_JPEG, CODEC_OPUS, Reassembler, encodeAudio, fragmentFrame, packMedia, parseFragment, parseReport,
} from "../src/services/video.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

function picture(n, size) {
  const data = new Uint8Array(size);
  for (let i = 0; i < size; i++) data[i] = (i * 7 + n) & 0xff;
  return data;
}

test("the §17.1 example fragment parses, and fragmentFrame writes it byte for byte", () => {
  const hex = "0101000000290000000700000001000000040006 0a2418221090 0021 06 6e617663616d ffd8ffd9".replace(/ /g, "");
  const bytes = Uint8Array.from(hex.match(/../g).map((h) => parseInt(h, 16)));
  const frag = parseFragment(bytes);
  assert.deepEqual([frag.seq, frag.frameId, frag.index, frag.count, frag.size, frag.intervalMs, frag.camera, frag.keyframe], [41, 7, 0, 1, 4, 33, "navcam", true]);
  assert.equal(frag.captureUs, 1_700_000_000_250_000);
  const [again] = fragmentFrame({ frameId: 7, camera: "navcam", captureTime: 1_700_000_000.25, data: Uint8Array.of(0xff, 0xd8, 0xff, 0xd9), seq: 41 });
  assert.deepEqual(again, bytes);
});

test("the §25.2 report example: keyframe flag and codec list", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const video = new VideoService(call, { codecs: [0x04, 0x03] });
  video.reassembler.highestSeq = 44;
  Object.assign(video.reassembler.stats, { fragments: 40, bytes: 160000, frames: 9, incomplete: 1 });
  video.sendReport(123.456, { keyframe: true });
  const report = call.sent("video").at(-1);
  const hex = [...report].map((b) => b.toString(16).padStart(2, "0")).join("");
  assert.equal(hex, "0202" + "0001e240" + "0000002c" + "00000028" + "00027100" + "00000009" + "00000001" + "0000" + "020403");
  void clock;
});

test("whole pictures in order; a lost fragment drops its picture whole and asks for a keyframe", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const frames = [];
  const video = new VideoService(call, { codecs: [CODEC_H264, CODEC_JPEG], onFrame: (f) => frames.push(f) });
  clock.every(0.01, () => video.tick(clock.now()));
  await clock.advance(0.05);
  const reports = () => call.sent("video").map(parseReport);
  assert.ok(reports().length >= 1, "a report at once: the subscription");
  assert.deepEqual(reports()[0].codecs, [CODEC_H264, CODEC_JPEG]);
  let seq = 0;
  const send = (frameId, size, keyframe, drop = -1) => {
    const datagrams = fragmentFrame({ frameId, camera: "navcam", captureTime: 1e9 + frameId / 30, data: picture(frameId, size), seq, codec: CODEC_H264, keyframe, maxPayload: 1000 });
    seq += datagrams.length;
    datagrams.forEach((d, i) => { if (i !== drop) call.toUser("video", d, { lossless: true }); });
    return datagrams.length;
  };
  assert.ok(send(1, 3000, true) > 1);
  await clock.advance(0.02);
  send(2, 2500, false);
  await clock.advance(0.02);
  assert.deepEqual(frames.map((f) => f.frameId), [1, 2]);
  assert.deepEqual(frames[0].data, picture(1, 3000));
  assert.deepEqual([frames[0].keyframe, frames[1].keyframe, frames[0].codec], [true, false, CODEC_H264]);
  const before = reports().filter((r) => r.keyframe).length;
  send(3, 2500, false, 1); // fragment 1 lost
  await clock.advance(0.02);
  send(4, 2500, false); // a delta after the lost picture: not decodable
  await clock.advance(0.05);
  assert.deepEqual(frames.map((f) => f.frameId), [1, 2], "no half picture, no undecodable delta");
  assert.ok(reports().filter((r) => r.keyframe).length > before, "a keyframe was asked for");
  assert.ok(video.stats.incomplete >= 1);
  send(5, 3000, true);
  await clock.advance(0.3);
  assert.deepEqual(frames.map((f) => f.frameId), [1, 2, 5]);
  const after = reports().at(-1);
  assert.equal(after.keyframe, false, "the flag clears once the keyframe came");
  assert.equal(after.frames, 5 - 1, "frames 1, 2, 4, 5 completed (4 skipped by the gate)");
});

test("reports every 200 ms while watching, a BYE when the page stops", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const video = new VideoService(call);
  clock.every(0.01, () => video.tick(clock.now()));
  await clock.advance(1.0);
  const count = call.sent("video").length;
  assert.ok(count >= 5 && count <= 7, `${count} reports in 1 s`);
  video.setWanted(false, clock.now());
  const last = parseReport(call.sent("video").at(-1));
  assert.equal(last.bye, true);
  await clock.advance(1.0);
  assert.equal(call.sent("video").length, count + 1);
});

test("the reassembler: latest frame wins, at most 4 partial frames, a late fragment is dropped", () => {
  const r = new Reassembler();
  const frame = (id, size = 3000) => fragmentFrame({ frameId: id, camera: "c", captureTime: 1, data: picture(id, size), maxPayload: 1000, interval: 0.5 });
  const f1 = frame(1);
  const f2 = frame(2);
  r.onDatagram(f1[0], 0);
  for (const d of f2) r.onDatagram(d, 0.01);
  assert.equal(r.newestReturned, 2);
  assert.equal(r.onDatagram(f1[1], 0.02), null);
  assert.equal(r.stats.late, 1);
  for (let id = 3; id < 9; id++) r.onDatagram(frame(id)[0], 0.03);
  assert.ok(r.partials.size <= 4);
  r.poll(10);
  assert.equal(r.partials.size, 0, "expired after their frame interval");
});

test("audio packets pass through in order of arrival; reports list Opus", async () => {
  const clock = new ManualClock();
  const call = new FakeCall();
  const packets = [];
  const audio = new AudioService(call, { onPacket: (p) => packets.push(p) });
  clock.every(0.01, () => audio.tick(clock.now()));
  await clock.advance(0.01);
  for (const seq of [7, 8, 8, 10]) call.toUser("audio", encodeAudio(seq, 1_700_000_000.25, Uint8Array.of(0xfc, 1, 2)), { lossless: true });
  call.toUser("audio", Uint8Array.of(3, 16, 0), { lossless: true });
  await clock.advance(0.25);
  assert.deepEqual(packets.map((p) => p.seq), [7, 8, 10]);
  assert.deepEqual([...packets[0].data], [0xfc, 1, 2]);
  assert.equal(packets[0].captureUs, 1_700_000_000_250_000);
  assert.deepEqual([audio.stats.malformed, audio.stats.late], [1, 1]);
  const report = parseReport(call.sent("audio").at(-1));
  assert.deepEqual(report.codecs, [CODEC_OPUS]);
  assert.equal(report.fragments, 3);
});

test("packMedia: today's binary websocket message", () => {
  const buf = new Uint8Array(packMedia({ kind: "audio", seq: 1, capture_time: 2 }, Uint8Array.of(9, 9)));
  const length = new DataView(buf.buffer).getUint32(0);
  assert.deepEqual(JSON.parse(new TextDecoder().decode(buf.subarray(4, 4 + length))), { kind: "audio", seq: 1, capture_time: 2 });
  assert.deepEqual([...buf.subarray(4 + length)], [9, 9]);
  void seeded;
});
