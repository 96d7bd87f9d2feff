// The bit rate of the page's camera upload, from the robot's receiver reports on
// `video/user` (docs/protocol.md §17.2, §25; the page gets them as `uplink_report`, §19.1):
// additive increase, multiplicative decrease (AIMD) between 150 kbit/s and 1.5 Mbit/s.
// Pure: no clock (time is the reports' own `receiver_ms`), no I/O; media.js reconfigures
// its VideoEncoder with what `report()` returns. Also loadable by node (web/test).
"use strict";

(function (root) {
  const U32 = 2 ** 32;
  // RFC 1982 a − b on u32 counters (§17.2): positive when a is newer.
  function serialDiff(a, b) {
    const d = (((a - b) % U32) + U32) % U32;
    return d >= U32 / 2 ? d - U32 : d;
  }
  const isU32 = (v) => Number.isInteger(v) && v >= 0 && v < U32;

  const DEFAULTS = {
    min: 150000, // bit/s
    max: 1500000,
    start: 600000,
    // Congestion: loss over this (smoothed, by fragments) or queueing delay over this.
    lossHigh: 0.08,
    delayHighMs: 100,
    // Room to grow: loss under this and queueing delay under this.
    lossLow: 0.02,
    delayLowMs: 30,
    decrease: 0.8, // × the rate on congestion (at most once per holdMs)
    increase: 100000, // + bit/s per second of reports while there is room
    holdMs: 600, // after a decrease: neither again nor up, so its effect shows in the reports
    minFragments: 30, // a verdict on loss needs this many fragments (decayed) to go on
    decay: 0.9, // the loss average's weight on the past, per report (about 2 s of reports)
    applyStep: 0.1, // a rise is applied once it is this fraction over the applied rate
  };

  // One controller per upload. report(fields) takes one REPORT's fields (§17.2 names:
  // receiver_ms, highest_seq, fragments, queue_delay_ms, bye) and returns the bit rate to
  // configure now, or null to keep the current one. A report that goes back in time is
  // ignored; counters that jump back or absurdly far (a new call, a new sender) start
  // afresh from that report, keeping the rate.
  class UplinkRate {
    constructor(opts) {
      this.o = Object.assign({}, DEFAULTS, opts || {});
      this.target = this.o.start; // the controller's rate (continuous)
      this.bitrate = this.o.start; // the rate last returned (the encoder's)
      this.loss = 0; // smoothed loss (0..1) since the last decision
      this.delayMs = 0;
      this.last = null; // the previous report's counters
      this.lossNum = 0; // fragments lost, decayed
      this.lossDen = 0; // fragments sent, decayed
      this.heldUntil = null; // receiver_ms before which no change follows a decrease
      this.decreases = 0;
      this.increases = 0;
      this.reports = 0;
    }

    report(r) {
      if (!r || !isU32(r.receiver_ms) || !isU32(r.highest_seq) || !isU32(r.fragments)) return null;
      if (r.bye) return null;
      const last = this.last;
      if (last && serialDiff(r.receiver_ms, last.receiver_ms) <= 0) return null; // reordered, repeated
      this.last = { receiver_ms: r.receiver_ms, highest_seq: r.highest_seq, fragments: r.fragments };
      if (!last) return null; // a baseline
      const o = this.o;
      const dt = serialDiff(r.receiver_ms, last.receiver_ms);
      const sent = serialDiff(r.highest_seq, last.highest_seq);
      const got = serialDiff(r.fragments, last.fragments);
      if (sent < 0 || got < 0 || sent > 1e6 || got > 1e6 || dt > 60000) return null; // afresh
      this.reports += 1;
      this.delayMs = Number.isFinite(r.queue_delay_ms) ? r.queue_delay_ms : 0;
      if (sent === 0) return null; // nothing sent (camera off, or no picture yet): no verdict
      this.lossNum = o.decay * this.lossNum + Math.max(0, sent - got);
      this.lossDen = o.decay * this.lossDen + sent;
      this.loss = this.lossDen > 0 ? this.lossNum / this.lossDen : 0;
      const now = r.receiver_ms;
      if (this.heldUntil !== null && serialDiff(now, this.heldUntil) < 0) return null;
      this.heldUntil = null;
      if (this.lossDen < o.minFragments && this.delayMs <= o.delayHighMs) return null;
      if (this.loss > o.lossHigh || this.delayMs > o.delayHighMs) {
        this.target = Math.max(o.min, Math.min(this.target, this.bitrate) * o.decrease);
        this.decreases += 1;
        this.heldUntil = (now + o.holdMs) % U32;
        // What follows is judged on what is sent at the new rate.
        this.lossNum = this.lossDen = 0;
        return this._apply(true);
      }
      if (this.loss < o.lossLow && this.delayMs < o.delayLowMs && this.target < o.max) {
        this.target = Math.min(o.max, this.target + o.increase * dt / 1000);
        this.increases += 1;
        return this._apply(false);
      }
      return null;
    }

    // The rate to configure, or null: a fall at once, a rise in steps (each a reconfigure).
    _apply(down) {
      const rate = Math.round(this.target);
      if (rate === this.bitrate) return null;
      if (!down && rate < this.o.max && rate < this.bitrate * (1 + this.o.applyStep)) return null;
      this.bitrate = rate;
      return rate;
    }
  }

  root.telebotUplinkRate = { UplinkRate, DEFAULTS, serialDiff };
})(typeof window !== "undefined" ? window : globalThis);
