// The conference (§20): roster, messages once each in the robot's order, `since` for a gap.
import { test } from "node:test";
import assert from "node:assert/strict";
import { ConferenceState } from "../src/services/services.js";

const msg = (seq) => JSON.stringify({ type: "msg", seq, from: "bob", kind: "user", text: `m${seq}` });

test("a gap is asked for with since (at most every 0.3 s), filled in order, each message once", () => {
  const seen = [];
  const rosters = [];
  const state = new ConferenceState({ onMessage: (m) => seen.push(m.seq), onRoster: (r) => rosters.push(r) });
  assert.equal(state.deliver(JSON.stringify({ type: "roster", seq: 4, users: [{ name: "bob", role: "observer", driving: false, you: false }] }), 0), null);
  assert.equal(state.deliver(msg(5), 0.1), null);
  const since = state.deliver(msg(7), 0.2);
  assert.deepEqual(JSON.parse(since), { type: "since", seq: 5 });
  assert.equal(state.deliver(msg(8), 0.3), null, "not again within 0.3 s");
  assert.equal(state.deliver(msg(7), 0.4), null, "a repeat: nothing new");
  state.deliver(msg(6), 0.6);
  assert.deepEqual(seen, [5, 7, 8, 6]);
  assert.deepEqual(state.messages.map((m) => m.seq), [5, 6, 7, 8]);
  assert.equal(state.missing(1.0), null, "no gap left");
  assert.equal(rosters.length, 1);
  assert.equal(state.deliver("{garbage", 1), null);
  assert.equal(state.drops.total, 1);
});

test("a roster seq below the floor is a restarted robot: start over", () => {
  const state = new ConferenceState();
  state.deliver(JSON.stringify({ type: "roster", seq: 40, users: [] }), 0);
  state.deliver(JSON.stringify({ type: "roster", seq: 2, users: [] }), 1);
  assert.equal(state.floor, 2);
  state.deliver(msg(3), 1.1);
  assert.deepEqual(state.messages.map((m) => m.seq), [3]);
});
