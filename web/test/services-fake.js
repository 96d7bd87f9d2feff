// A fake Call/Channel pair (the API of web/src/call.js, BROWSER.md) that a test drives
// as the robot would, with seeded loss both ways, and a manual clock for the session.
// No test of its own: the services-*.test.js files use it.

/** A seeded PRNG in [0, 1) (mulberry32). */
export function seeded(seed) {
  let a = seed >>> 0;
  return () => {
    a = (a + 0x6d2b79f5) >>> 0;
    let t = a;
    t = Math.imul(t ^ (t >>> 15), t | 1);
    t ^= t + Math.imul(t ^ (t >>> 7), t | 61);
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
}

class FakeChannel {
  constructor(call, name, lane) {
    this.call = call;
    this.name = name;
    this.lane = lane;
    this.onmessage = null;
  }
  send(payload) {
    if (this.call.over) throw new Error("the call ended");
    if (typeof payload !== "string" && !(payload instanceof Uint8Array)) throw new TypeError("payload");
    // A congested link (gateway-link.js) drops DATA/BULK datagrams and says so.
    if (this.call.congested && this.lane !== "control") {
      this.call.refused += 1;
      return false;
    }
    const copy = typeof payload === "string" ? payload : payload.slice();
    this.call.sentLog.push([this.name, copy]);
    if (this.call.lose(this.call.upLoss)) return true;
    queueMicrotask(() => {
      if (!this.call.over) this.call.robotHandlers.get(this.name)?.(copy);
    });
    return true;
  }
}

/** The user's side of a call as web/src/call.js gives it, and the robot's hooks. */
export class FakeCall {
  constructor({ robot = "guiabot", role = "driver", seed = 1, upLoss = 0, downLoss = 0 } = {}) {
    this.id = "0123456789abcdef";
    this.robot = robot;
    this.role = role;
    this.suite = "chachapoly";
    this.stats = { rtt: 0.01, loss: 0, rejected: {} };
    this.random = seeded(seed);
    this.upLoss = upLoss;
    this.downLoss = downLoss;
    this.channels = new Map();
    this.robotHandlers = new Map();
    this.sentLog = [];
    /** Set to make the link refuse DATA/BULK datagrams, as a congested websocket does. */
    this.congested = false;
    this.refused = 0;
    this.over = false;
    this.ended = new Promise((resolve) => {
      this.endWith = (kind, detail = "", byPeer = true) => {
        this.over = true;
        resolve({ kind, detail, byPeer });
      };
    });
  }
  lose(p) {
    return p > 0 && this.random() < p;
  }
  channel(name, { lane = "data" } = {}) {
    if (!this.channels.has(name)) this.channels.set(name, new FakeChannel(this, name, lane));
    return this.channels.get(name);
  }
  async hangup() {
    if (!this.over) this.endWith("hung_up", "", false);
  }
  // -- the robot's side
  /** The robot's handler of what the user sends on `name`. */
  onUser(name, handler) {
    this.robotHandlers.set(name, handler);
  }
  /** The robot sends on `name` (lost with `downLoss`, delivered in a microtask). */
  toUser(name, payload, { lossless = false } = {}) {
    if (this.over) return;
    if (!lossless && this.lose(this.downLoss)) return;
    queueMicrotask(() => {
      if (!this.over) this.channels.get(name)?.onmessage?.(payload);
    });
  }
  /** What the user sent on `name` (text parsed as JSON). */
  sent(name) {
    return this.sentLog.filter(([n]) => n === name).map(([, p]) => (typeof p === "string" ? JSON.parse(p) : p));
  }
}

/** Let queued microtasks (deliveries, promise callbacks) run. */
export async function settle(rounds = 20) {
  for (let i = 0; i < rounds; i++) await Promise.resolve();
}

/** A clock the test advances: `every` and `sleep` fire as time passes. */
export class ManualClock {
  constructor() {
    this.t = 1000;
    this.timers = new Set();
    this.sleepers = [];
  }
  now() {
    return this.t;
  }
  every(seconds, fn) {
    const timer = { seconds, fn, next: this.t + seconds };
    this.timers.add(timer);
    return () => this.timers.delete(timer);
  }
  sleep(seconds) {
    return new Promise((resolve) => this.sleepers.push({ at: this.t + seconds, resolve }));
  }
  /** Advance by `seconds` in steps of `step`, firing timers and settling after each. */
  async advance(seconds, step = 0.01) {
    const end = this.t + seconds;
    while (this.t < end - 1e-9) {
      this.t = Math.min(end, this.t + step);
      for (const timer of [...this.timers]) {
        while (this.timers.has(timer) && timer.next <= this.t) {
          timer.next += timer.seconds;
          timer.fn();
        }
      }
      const due = this.sleepers.filter((s) => s.at <= this.t);
      this.sleepers = this.sleepers.filter((s) => s.at > this.t);
      for (const s of due) s.resolve();
      await settle();
    }
  }
  /** Advance until `condition()` holds (at most `limit` seconds); returns whether it did. */
  async until(condition, limit = 30, step = 0.01) {
    const end = this.t + limit;
    while (!condition()) {
      if (this.t >= end) return false;
      await this.advance(step, step);
    }
    return true;
  }
}
