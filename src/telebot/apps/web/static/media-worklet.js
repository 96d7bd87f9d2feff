// telebot audio playback: a jitter buffer in an AudioWorklet (see media.js).
//
// The main thread posts decoded 48 kHz mono PCM blocks ({pcm, seq}); this processor plays
// them in order once `target` seconds are buffered (40–80 ms, set by the main thread from
// the measured arrival jitter). An underrun plays silence and buffers up to the target
// again. The delay must not creep up: a burst after a stall leaves more queued than the
// target, and since sender and player run at the same rate it would stay queued for good.
// So every half second, when even the lowest level of that half second was more than
// 10 ms over the target, the excess is skipped from the head of the queue. When the
// first sample of a block is played it reports {played: seq, frame} (the context frame at
// which it left) for the mouth-to-ear measure, and every half second {level, target} (ms).
"use strict";

const WINDOW = 0.5; // seconds over which the lowest buffer level is watched

class TelebotJitter extends AudioWorkletProcessor {
  constructor() {
    super();
    this.blocks = []; // [{pcm: Float32Array, seq, pos}]
    this.buffered = 0; // samples queued
    this.target = 0.04 * sampleRate;
    this.playing = false;
    this.underruns = 0;
    this.skipped = 0; // samples skipped to bring the delay back to the target
    this.low = Infinity; // lowest level in this window
    this.windowLeft = WINDOW * sampleRate;
    this.port.onmessage = (ev) => {
      const m = ev.data;
      if (m.pcm) {
        this.blocks.push({ pcm: m.pcm, seq: m.seq, pos: 0 });
        this.buffered += m.pcm.length;
      } else if (m.target !== undefined) {
        this.target = Math.max(0.04, Math.min(0.08, m.target)) * sampleRate;
      } else if (m.flush) {
        this.blocks = []; this.buffered = 0; this.playing = false;
      }
    };
  }

  skip(n) {
    while (n > 0 && this.blocks.length) {
      const b = this.blocks[0];
      const k = Math.min(n, b.pcm.length - b.pos);
      b.pos += k; n -= k; this.buffered -= k; this.skipped += k;
      if (b.pos >= b.pcm.length) this.blocks.shift();
    }
  }

  process(inputs, outputs) {
    const out = outputs[0][0];
    if (!out) return true;
    if (!this.playing && this.buffered >= this.target) this.playing = true;
    let i = 0;
    if (this.playing) {
      this.low = Math.min(this.low, this.buffered);
      while (i < out.length && this.blocks.length) {
        const b = this.blocks[0];
        if (b.pos === 0 && b.seq !== undefined) {
          this.port.postMessage({ played: b.seq, frame: currentFrame + i });
        }
        const n = Math.min(out.length - i, b.pcm.length - b.pos);
        out.set(b.pcm.subarray(b.pos, b.pos + n), i);
        b.pos += n; i += n; this.buffered -= n;
        if (b.pos >= b.pcm.length) this.blocks.shift();
      }
      if (i < out.length) { this.playing = false; this.underruns += 1; this.low = Infinity; }
    }
    for (let k = i; k < out.length; k++) out[k] = 0;
    for (let c = 1; c < outputs[0].length; c++) outputs[0][c].set(out);
    this.windowLeft -= out.length;
    if (this.windowLeft <= 0) {
      this.windowLeft = WINDOW * sampleRate;
      if (this.playing && this.low !== Infinity && this.low > this.target + 0.01 * sampleRate) {
        this.skip(this.low - this.target);
      }
      this.port.postMessage({
        level: (this.buffered / sampleRate) * 1000, target: (this.target / sampleRate) * 1000,
        underruns: this.underruns, skipped: this.skipped,
      });
      this.low = Infinity;
    }
    return true;
  }
}

registerProcessor("telebot-jitter", TelebotJitter);
