// The map channel (§15): a download completes over 10 % seeded loss both ways, its hash
// checks, and the decoded image is the robot's grid.
import { test } from "node:test";
import assert from "node:assert/strict";
import { createHash } from "node:crypto";
import { deflateSync } from "node:zlib";
import { MapService } from "../src/services/services.js";
import { MapReceiver, decodeMapPng, pngSize } from "../src/services/map.js";
import { FakeCall, ManualClock, seeded } from "./services-fake.js";

function crc32(bytes) {
  let c = ~0;
  for (const b of bytes) {
    c ^= b;
    for (let k = 0; k < 8; k++) c = (c >>> 1) ^ (0xedb88320 & -(c & 1));
  }
  return ~c >>> 0;
}
function chunk(type, data) {
  const out = Buffer.alloc(12 + data.length);
  out.writeUInt32BE(data.length, 0);
  out.write(type, 4, "latin1");
  Buffer.from(data).copy(out, 8);
  out.writeUInt32BE(crc32(out.subarray(4, 8 + data.length)), 8 + data.length);
  return out;
}
/** An 8-bit greyscale PNG of `pixels` (rows top first), with a mix of row filters. */
export function greyPng(width, height, pixels) {
  const raw = Buffer.alloc(height * (width + 1));
  for (let y = 0; y < height; y++) {
    const filter = y % 3 === 1 ? 1 : y % 3 === 2 ? 2 : 0; // none, sub, up
    raw[y * (width + 1)] = filter;
    for (let x = 0; x < width; x++) {
      const v = pixels[y * width + x];
      const a = x > 0 ? pixels[y * width + x - 1] : 0;
      const b = y > 0 ? pixels[(y - 1) * width + x] : 0;
      raw[y * (width + 1) + 1 + x] = (v - (filter === 1 ? a : filter === 2 ? b : 0)) & 0xff;
    }
  }
  const ihdr = Buffer.alloc(13);
  ihdr.writeUInt32BE(width, 0);
  ihdr.writeUInt32BE(height, 4);
  ihdr[8] = 8; // depth
  ihdr[9] = 0; // greyscale
  return new Uint8Array(Buffer.concat([
    Buffer.from([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a]),
    chunk("IHDR", ihdr), chunk("IDAT", deflateSync(raw)), chunk("IEND", Buffer.alloc(0)),
  ]));
}

/** The robot's side of §15.3 (one transfer; resend queue), sending 8 chunks per tick. */
function mapRobot(call, clock, png, { chunkSize = 500, width, height, version = 3 }) {
  const chunks = Math.ceil(png.length / chunkSize);
  const sha = createHash("sha256").update(png).digest("hex");
  let xfer = null;
  let queue = [];
  const log = { gets: 0, resends: 0, done: 0 };
  const offer = (x) => JSON.stringify({ type: "offer", xfer: x, name: "demo", size: png.length, chunks, chunk_size: chunkSize, sha256: sha, width, height, resolution: 0.05, origin: [-0.95, 2.05], version });
  call.onUser("map", (payload) => {
    const msg = JSON.parse(payload);
    if (msg.type === "get") {
      log.gets += 1;
      if (xfer === msg.xfer) return call.toUser("map", offer(xfer));
      xfer = msg.xfer;
      call.toUser("map", offer(xfer));
      queue = [...Array(chunks).keys()];
    } else if (msg.type === "resend" && msg.xfer === xfer) {
      log.resends += 1;
      for (const i of msg.missing) if (!queue.includes(i)) queue.push(i);
    } else if (msg.type === "done") {
      log.done += 1;
    }
  });
  clock.every(0.01, () => {
    for (const index of queue.splice(0, 8)) {
      const data = png.subarray(index * chunkSize, (index + 1) * chunkSize);
      const datagram = new Uint8Array(9 + data.length);
      const dv = new DataView(datagram.buffer);
      datagram[0] = 1;
      dv.setUint32(1, xfer);
      dv.setUint32(5, index);
      datagram.set(data, 9);
      call.toUser("map", datagram);
    }
  });
  return log;
}

function testMap(width, height) {
  const pixels = new Uint8Array(width * height);
  const random = seeded(99);
  for (let i = 0; i < pixels.length; i++) pixels[i] = [0, 205, 254][Math.floor(random() * 3)];
  return pixels;
}

test("a map download completes at 10 % loss both ways and the image is the robot's", async () => {
  const clock = new ManualClock();
  const call = new FakeCall({ seed: 2024, upLoss: 0.1, downLoss: 0.1 });
  const [width, height] = [200, 150];
  const pixels = testMap(width, height);
  const png = greyPng(width, height, pixels);
  assert.ok(png.length > 20 * 200, "at least 20 chunks");
  const log = mapRobot(call, clock, png, { width, height, chunkSize: 200 });
  const service = new MapService(call, { random: seeded(4) });
  clock.every(0.01, () => service.tick(clock.now()));
  let result = null;
  let failure = null;
  service.fetch({ now: clock.now() }).then((r) => { result = r; }, (e) => { failure = e; });
  assert.ok(await clock.until(() => result || failure, 60));
  assert.equal(failure, null);
  assert.deepEqual(result.png, png);
  assert.deepEqual([result.width, result.height, result.version, result.origin_x, result.origin_y, result.resolution], [width, height, 3, -0.95, 2.05, 0.05]);
  assert.ok(log.resends >= 1, "some chunks were lost and asked for again");
  await clock.advance(0.1);
  assert.ok(log.done >= 1, "done sent (3 copies, some may be lost)");
  const image = await decodeMapPng(result.png);
  assert.deepEqual([image.width, image.height], [width, height]);
  for (let i = 0; i < pixels.length; i++) {
    assert.deepEqual([...image.rgba.subarray(i * 4, i * 4 + 4)], [pixels[i], pixels[i], pixels[i], 255]);
  }
});

test("a lost offer: chunks kept, the get repeated soon, the map completes", async () => {
  const png = greyPng(10, 10, testMap(10, 10));
  const r = new MapReceiver(42);
  r.request(0);
  const sha = createHash("sha256").update(png).digest("hex");
  const chunkDatagram = new Uint8Array(9 + png.length);
  chunkDatagram[0] = 1;
  new DataView(chunkDatagram.buffer).setUint32(1, 42);
  chunkDatagram.set(png, 9);
  assert.deepEqual(r.onMessage(chunkDatagram, 0.01), []);
  assert.ok(r.nextDeadline() <= 0.01 + 0.08 + 1e-9, "the get comes again 0.08 s after the chunk");
  assert.equal(JSON.parse(r.poll(0.1)[0]).type, "get");
  const offer = { type: "offer", xfer: 42, name: "m", size: png.length, chunks: 1, chunk_size: 32759, sha256: sha, width: 10, height: 10, resolution: 0.1, origin: [0, 0] };
  const out = r.onMessage(JSON.stringify(offer), 0.12);
  assert.equal(r.state, "done");
  assert.deepEqual(out.map((m) => JSON.parse(m).type), ["done", "done", "done"]);
  assert.equal(r.result.version, 0, "absent version reads 0");
  assert.deepEqual(pngSize(r.result.png), [10, 10]);
});

test("a hash mismatch fails with cancel ×3; an error from the robot fails the transfer", () => {
  const png = greyPng(4, 4, testMap(4, 4));
  const r = new MapReceiver(7);
  r.request(0);
  r.onMessage(JSON.stringify({ type: "offer", xfer: 7, name: "m", size: png.length, chunks: 1, chunk_size: 32759, sha256: "0".repeat(64), width: 4, height: 4, resolution: 0.1, origin: [0, 0] }), 0.01);
  const datagram = new Uint8Array(9 + png.length);
  datagram[0] = 1;
  new DataView(datagram.buffer).setUint32(1, 7);
  datagram.set(png, 9);
  const out = r.onMessage(datagram, 0.02);
  assert.equal(r.state, "failed");
  assert.match(r.error, /^map hash mismatch/);
  assert.deepEqual(out.map((m) => JSON.parse(m).type), ["cancel", "cancel", "cancel"]);
  const e = new MapReceiver(8);
  e.request(0);
  e.onMessage(JSON.stringify({ type: "error", xfer: 8, reason: "a map transfer is already running" }), 0.01);
  assert.deepEqual([e.state, e.error], ["failed", "a map transfer is already running"]);
});

test("offers that break a rule are dropped and counted, the transfer waits on", () => {
  const r = new MapReceiver(1);
  r.request(0);
  const good = { type: "offer", xfer: 1, name: "m", size: 100, chunks: 1, chunk_size: 100, sha256: "a".repeat(64), width: 2, height: 2, resolution: 0.1, origin: [0, 0] };
  const bad = [
    { ...good, chunks: 2 }, { ...good, sha256: "A".repeat(64) }, { ...good, size: 0 },
    { ...good, resolution: 0 }, { ...good, origin: [0] }, { ...good, width: 20000, height: 20000 },
    { ...good, name: "" }, { ...good, version: -1 },
  ];
  for (const offer of bad) r.onMessage(JSON.stringify(offer), 0.01);
  assert.equal(r.state, "requesting");
  assert.equal(r.rejected.bad_offer, bad.length);
});
