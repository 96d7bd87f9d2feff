// The page's camera upload rate (static/uplink-rate.js, used by static/media.js): AIMD on
// the robot's REPORTs of `video/user` (§17.2) between 150 kbit/s and 1.5 Mbit/s.
import { test } from "node:test";
import assert from "node:assert/strict";
import "../../src/telebot/apps/web/static/uplink-rate.js";

const { UplinkRate, DEFAULTS } = globalThis.telebotUplinkRate;
const U32 = 2 ** 32;

// Reports every 200 ms of `perReport` fragments sent, `lost` of them lost, from `start`.
function* reports({ count, perReport = 10, loss = 0, delay = 0, ms = 1000, seq = 0, got = 0 } = {}) {
  let lostSoFar = 0;
  for (let i = 0; i < count; i++) {
    seq = (seq + perReport) % U32;
    const lostNow = Math.round((i + 1) * perReport * loss) - lostSoFar;
    lostSoFar += lostNow;
    got = (got + perReport - lostNow) % U32;
    ms = (ms + 200) % U32;
    yield { receiver_ms: ms, highest_seq: seq, fragments: got, queue_delay_ms: delay };
  }
}

function run(rate, list) {
  const applied = [];
  for (const r of list) {
    const b = rate.report(r);
    if (b !== null) applied.push(b);
  }
  return applied;
}

test("a clean link raises the rate step by step to the ceiling and never past it", () => {
  const rate = new UplinkRate();
  assert.equal(rate.bitrate, 600000);
  const applied = run(rate, reports({ count: 300 }));
  assert.ok(applied.length >= 5, `reconfigured in steps, got ${applied}`);
  for (let i = 1; i < applied.length; i++) assert.ok(applied[i] > applied[i - 1]);
  assert.equal(rate.bitrate, DEFAULTS.max);
  // Each rise is at least 10 % (or the ceiling): not a reconfiguration every report.
  for (let i = 1; i < applied.length - 1; i++) assert.ok(applied[i] >= applied[i - 1] * 1.1);
});

test("loss lowers the rate multiplicatively, once per hold, down to the floor", () => {
  const rate = new UplinkRate();
  const applied = run(rate, reports({ count: 10, loss: 0.2 }));
  assert.ok(applied.length >= 1 && applied[0] === 480000, `first fall ×0.8, got ${applied}`);
  // 2 s of reports: at most one fall per 600 ms hold (plus the first).
  assert.ok(applied.length <= 4, `${applied}`);
  run(rate, reports({ count: 200, loss: 0.2, ms: 5000, seq: 100, got: 80 }));
  assert.equal(rate.bitrate, DEFAULTS.min);
});

test("queueing delay lowers the rate though nothing is lost", () => {
  const rate = new UplinkRate();
  const applied = run(rate, reports({ count: 5, delay: 250 }));
  assert.ok(applied.length >= 1 && applied.every((b) => b < 600000), `${applied}`);
});

test("light random loss and moderate delay hold the rate", () => {
  const rate = new UplinkRate();
  assert.deepEqual(run(rate, reports({ count: 50, loss: 0.04 })), []);
  assert.deepEqual(run(rate, reports({ count: 50, delay: 60, ms: 50000, seq: 10000, got: 10000 })), []);
  assert.equal(rate.bitrate, 600000);
});

test("after a fall, a clean link brings the rate back up", () => {
  const rate = new UplinkRate();
  run(rate, reports({ count: 20, loss: 0.3 }));
  const low = rate.bitrate;
  assert.ok(low < 600000);
  run(rate, reports({ count: 100, ms: 10000, seq: 1000, got: 1000 }));
  assert.ok(rate.bitrate > low);
});

test("counters wrap around 2^32 like the wire's", () => {
  const rate = new UplinkRate();
  const applied = run(rate, reports({ count: 10, loss: 0.25, ms: U32 - 500, seq: U32 - 30, got: U32 - 30 }));
  assert.ok(applied.length >= 1 && applied[0] < 600000, `${applied}`);
});

test("reordered, bye, malformed and idle reports change nothing; a new stream starts afresh", () => {
  const rate = new UplinkRate();
  const base = { receiver_ms: 1000, highest_seq: 100, fragments: 100, queue_delay_ms: 0 };
  assert.equal(rate.report(base), null);
  // Older than the last (reordered): ignored, even though it would show loss.
  assert.equal(rate.report({ ...base, receiver_ms: 900, highest_seq: 50, fragments: 10 }), null);
  for (const bad of [null, {}, { ...base, receiver_ms: -1 }, { ...base, highest_seq: 1.5 }, { ...base, fragments: "9" }]) {
    assert.equal(rate.report(bad), null);
  }
  assert.equal(rate.report({ ...base, receiver_ms: 1200, highest_seq: 200, fragments: 100, bye: true }), null);
  // Nothing sent (camera off): no verdict however long.
  for (let i = 1; i <= 20; i++) assert.equal(rate.report({ ...base, receiver_ms: 1000 + 200 * i }), null);
  // A new call's counters start again from 0: a baseline, not a 2^32 loss.
  assert.equal(rate.report({ receiver_ms: 6000, highest_seq: 5, fragments: 1, queue_delay_ms: 0 }), null);
  assert.equal(rate.report({ receiver_ms: 6200, highest_seq: 15, fragments: 11, queue_delay_ms: 0 }), null);
  assert.equal(rate.bitrate, 600000);
  assert.equal(rate.decreases, 0);
});

test("bounds and the start are options", () => {
  const rate = new UplinkRate({ min: 200000, max: 400000, start: 300000 });
  run(rate, reports({ count: 100 }));
  assert.equal(rate.bitrate, 400000);
  run(rate, reports({ count: 100, loss: 0.5, ms: 50000, seq: 10000, got: 10000 }));
  assert.equal(rate.bitrate, 200000);
});
