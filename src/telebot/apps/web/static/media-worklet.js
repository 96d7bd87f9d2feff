// telebot audio playback: a jitter buffer in an AudioWorklet (see media.js).
//
// The main thread posts decoded 48 kHz mono PCM blocks ({pcm, seq}); this processor plays
// them in order once `target` seconds are buffered (40–80 ms, set by the main thread from
// the measured arrival jitter). An underrun plays silence and buffers up to the target
// again; a buffer grown past target + 40 ms (a burst after a stall) drops its oldest
// samples, so the delay never creeps up. When the first sample of a block is played it
// reports {seq, frame} (the context frame at which it left) for the mouth-to-ear measure.
"use strict";

class TelebotJitter extends AudioWorkletProcessor {
  constructor() {
    super();
    this.blocks = []; // [{pcm: Float32Array, seq, pos}]
    this.buffered = 0; // samples queued
    this.target = 0.06 * sampleRate;
    this.playing = false;
    this.underruns = 0;
    this.dropped = 0;
    this.port.onmessage = (ev) => {
      const m = ev.data;
      if (m.pcm) {
        this.blocks.push({ pcm: m.pcm, seq: m.seq, pos: 0 });
        this.buffered += m.pcm.length;
        const max = this.target + 0.04 * sampleRate;
        // Too much queued: drop whole old blocks down to the target (latency stays bounded).
        while (this.buffered > max && this.blocks.length > 1) {
          const old = this.blocks.shift();
          this.buffered -= old.pcm.length - old.pos;
          this.dropped += 1;
        }
      } else if (m.target !== undefined) {
        this.target = Math.max(0.04, Math.min(0.08, m.target)) * sampleRate;
      } else if (m.flush) {
        this.blocks = []; this.buffered = 0; this.playing = false;
      }
    };
  }

  process(inputs, outputs) {
    const out = outputs[0][0];
    if (!out) return true;
    if (!this.playing && this.buffered >= this.target) this.playing = true;
    let i = 0;
    if (this.playing) {
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
      if (i < out.length) { this.playing = false; this.underruns += 1; }
    }
    for (; i < out.length; i++) out[i] = 0;
    for (let c = 1; c < outputs[0].length; c++) outputs[0][c].set(out);
    return true;
  }
}

registerProcessor("telebot-jitter", TelebotJitter);
