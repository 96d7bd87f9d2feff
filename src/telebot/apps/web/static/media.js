// telebot browser media: WebCodecs video decode (JPEG fallback), Opus playback through an
// AudioWorklet jitter buffer, camera + mic capture encoded with WebCodecs. Used by the user's
// page (index.html, through app.js) and by the robot's screen (screen.html). No build step.
//
// Binary websocket messages, both ways (docs/protocol.md §19): a 4-byte big-endian header
// length, a UTF-8 JSON header, then the encoded bytes exactly as they travel on the call:
//   {"kind": "video", "codec": "h264"|"vp8"|"jpeg", "key": bool, "frame_id", "capture_time",
//    "camera"?}                                   one encoded picture (Annex B for H.264)
//   {"kind": "audio", "seq", "capture_time"}       one Opus packet (48 kHz mono, 20 ms)
// capture_time is Unix seconds (the sender's clock). A header without "kind" is JPEG video.
"use strict";

(function () {
  const now = () => performance.timeOrigin + performance.now(); // wall ms
  const CODEC_STRINGS = { h264: "avc1.42E01F", vp8: "vp8" };
  const KEY_RETRY_MS = 500; // a keyframe request unanswered this long is sent again
  const MAX_BACK = 64; // frame ids this far behind the last are late; further, a new stream
  const KEEP = 2000; // samples kept in the stats arrays

  const M = {
    // Everything a test or benchmark reads (the page never branches on it).
    stats: {
      videoDecoded: 0, videoDropped: 0, videoErrors: 0, freezes: 0, keyRequests: 0,
      recoveries: [], // ms the picture stood still because of a loss (last good -> next shown)
      recoveredAt: [], // wall ms at which each of those ended
      frameNumbers: [], // numbers read from decoded pictures (when readStamps is on)
      glassMs: [], // capture -> decoded, ms (sender's clock vs ours: same machine in tests)
      codec: "", width: 0, height: 0, jpegFallback: false,
      audioPackets: 0, audioLost: 0, audioErrors: 0, audioFreq: 0, audioMs: [], audioTransitMs: [], audioUnderruns: 0, audioLevel: 0, audioTarget: 0, audioSkippedMs: 0,
      sentVideo: 0, sentVideoKeys: 0, sentAudio: 0, sentBytes: 0, keyframesAsked: 0,
      captureNote: "",
      // The camera upload's rate (static/uplink-rate.js): the target from the robot's
      // reports, what the encoder is configured with, and what the reports said last.
      sendBitrate: 0, encoderBitrate: 0, bitrateChanges: 0, uplinkReports: 0, uplinkLoss: 0, uplinkDelayMs: 0,
    },
    readStamps: false,
  };
  window.telebotMedia = M;
  function keep(arr, v) { arr.push(v); if (arr.length > KEEP) arr.shift(); }

  // ------------------------------------------------------------------ wire helpers
  function pack(header, data) {
    const h = new TextEncoder().encode(JSON.stringify(header));
    const out = new Uint8Array(4 + h.length + data.byteLength);
    new DataView(out.buffer).setUint32(0, h.length);
    out.set(h, 4);
    out.set(data instanceof Uint8Array ? data : new Uint8Array(data), 4 + h.length);
    return out.buffer;
  }
  function unpack(buf) {
    const hlen = new DataView(buf).getUint32(0);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, hlen)));
    return { header, data: new Uint8Array(buf, 4 + hlen) };
  }
  M.pack = pack;
  M.unpack = unpack;

  // The frame number a test camera stamps into its pictures (telebot.services.codecs
  // stamp_number): cells of width/32 pixels along the top edge, a white-black start pair,
  // then 24 bits, most significant first, white = 1. Read back from the canvas the picture
  // was just drawn on (one row of pixels: works whatever decoded it); null without a stamp.
  function readStamp(ctx, w, h) {
    const cell = Math.max(2, Math.floor(w / 32));
    if (h < cell || w < 26 * cell) return null;
    const margin = Math.max(1, Math.floor(cell / 4)), side = cell - 2 * margin;
    const px = ctx.getImageData(0, margin, 26 * cell, side).data;
    // The mean luma of cell i's inside (as read_number reads it: codecs blur the edges).
    const bit = (i) => {
      let sum = 0;
      for (let y = 0; y < side; y++) {
        for (let x = i * cell + margin; x < (i + 1) * cell - margin; x++) {
          const o = 4 * (y * 26 * cell + x);
          sum += 0.299 * px[o] + 0.587 * px[o + 1] + 0.114 * px[o + 2];
        }
      }
      return sum / (side * side);
    };
    if (!(bit(0) > 160 && bit(1) < 96)) return null;
    let n = 0;
    for (let i = 0; i < 24; i++) n = n * 2 + (bit(i + 2) > 128 ? 1 : 0);
    return n;
  }
  M.readStamp = readStamp;

  // ------------------------------------------------------------------ video in
  // Decodes what arrives and draws each picture at once on `canvas`. After a gap (a frame id
  // skipped, a decoder error, a codec change) it keeps the last picture (freeze), asks for a
  // keyframe (`requestKey()`, again every KEY_RETRY_MS while none comes: the request itself
  // may be lost) and skips deltas until a keyframe arrives.
  class VideoSink {
    constructor(canvas, requestKey) {
      this.canvas = canvas;
      this.ctx = canvas.getContext("2d");
      this.requestKey = requestKey || (() => {});
      this.decoder = null;
      this.codec = "";
      this.lastId = null;
      this.needKey = true;
      this.frozenAt = null; // when the picture last moved before a loss
      this.shownAt = null; // when the last picture was shown
      this.askedAt = 0;
      this.pending = new Map(); // timestamp -> capture_time ms
      this.seq = 0;
      this.jpegBusy = false;
      this.timer = setInterval(() => this._retry(), KEY_RETRY_MS / 2);
    }

    _decoder(codec) {
      if (this.decoder && this.codec === codec) return this.decoder;
      if (this.decoder) { try { this.decoder.close(); } catch (e) { /* already closed */ } }
      this.codec = codec;
      M.stats.codec = codec;
      this.decoder = new VideoDecoder({
        output: (frame) => this._show(frame),
        error: (e) => { M.stats.videoErrors += 1; this.decoder = null; this._freeze("decoder: " + e.message); },
      });
      this.decoder.configure({ codec: CODEC_STRINGS[codec], optimizeForLatency: true });
      return this.decoder;
    }

    _freeze(why) {
      if (!this.needKey && this.frozenAt === null) { M.stats.freezes += 1; this.frozenAt = this.shownAt !== null ? this.shownAt : now(); }
      this.needKey = true;
      this.why = why;
      this._ask();
    }

    _ask() {
      this.askedAt = now();
      M.stats.keyRequests += 1;
      this.requestKey();
    }

    _retry() {
      if (this.needKey && this.lastId !== null && now() - this.askedAt > KEY_RETRY_MS) this._ask();
    }

    push(header, data) {
      const codec = header.codec || "jpeg";
      const id = header.frame_id;
      const back = this.lastId === null ? 0 : (this.lastId - id) | 0;
      // Late: older than the last picture shown (never shown after it). Much older is a new
      // stream (a new call or sender counts from 0 again): followed from its keyframe.
      if (this.lastId !== null && back >= 0 && back <= MAX_BACK) { M.stats.videoDropped += 1; return; }
      const gap = this.lastId !== null && id !== ((this.lastId + 1) >>> 0);
      this.lastId = id;
      if (codec === "jpeg") {
        // A JPEG interlude (a page without WebCodecs joined): the H.264 / VP8 decoder's
        // state is stale after it, so drop it; the stream that comes back starts at a
        // keyframe on a new decoder.
        if (this.decoder) { try { this.decoder.close(); } catch (e) { /* already closed */ } }
        this.decoder = null;
        this.codec = "jpeg";
        this._jpeg(header, data);
        return;
      }
      if (typeof VideoDecoder === "undefined") { M.stats.videoDropped += 1; return; }
      if (gap && this.frozenAt === null && this.shownAt !== null) { M.stats.freezes += 1; this.frozenAt = this.shownAt; }
      if (!header.key && (gap || codec !== this.codec || !this.decoder)) {
        this._freeze(gap ? "frame " + id + " after a gap" : "no keyframe yet");
      }
      if (this.needKey && !header.key) { M.stats.videoDropped += 1; return; }
      let decoder;
      try { decoder = this._decoder(codec); } catch (e) { M.stats.videoErrors += 1; return; }
      if (decoder.decodeQueueSize > 3 && !header.key) {
        // The decoder is behind: skip, and since the next delta needs this one, wait for a key.
        M.stats.videoDropped += 1;
        this._freeze("decoder behind");
        return;
      }
      const ts = (this.seq += 1) * 1000;
      this.pending.set(ts, header.capture_time * 1000);
      if (this.pending.size > 64) this.pending.delete(this.pending.keys().next().value);
      try {
        decoder.decode(new EncodedVideoChunk({ type: header.key ? "key" : "delta", timestamp: ts, data }));
        if (header.key) this.needKey = false;
      } catch (e) {
        M.stats.videoErrors += 1;
        this._freeze("decode: " + e.message);
      }
    }

    _shown(captureMs, w, h) {
      const t = now();
      M.stats.videoDecoded += 1;
      keep(M.stats.glassMs, t - captureMs);
      if (this.frozenAt !== null) {
        keep(M.stats.recoveries, t - this.frozenAt);
        keep(M.stats.recoveredAt, t);
        this.frozenAt = null;
      }
      this.shownAt = t;
      M.stats.width = w; M.stats.height = h;
      if (M.readStamps) { const n = readStamp(this.ctx, w, h); if (n !== null) keep(M.stats.frameNumbers, n); }
      if (this.onPicture) this.onPicture(w, h);
    }

    _show(frame) {
      const capture = this.pending.get(frame.timestamp);
      this.pending.delete(frame.timestamp);
      try {
        const w = frame.displayWidth, h = frame.displayHeight;
        if (this.canvas.width !== w || this.canvas.height !== h) { this.canvas.width = w; this.canvas.height = h; }
        this.ctx.drawImage(frame, 0, 0);
        this._shown(capture === undefined ? now() : capture, w, h);
      } finally {
        frame.close();
      }
    }

    // JPEG: decoded by the browser's image decoder; latest wins while one is decoding.
    async _jpeg(header, data) {
      M.stats.codec = "jpeg";
      if (typeof VideoDecoder === "undefined") M.stats.jpegFallback = true;
      if (this.jpegBusy) { M.stats.videoDropped += 1; return; }
      this.jpegBusy = true;
      try {
        const bitmap = await createImageBitmap(new Blob([data], { type: "image/jpeg" }));
        if (this.canvas.width !== bitmap.width || this.canvas.height !== bitmap.height) {
          this.canvas.width = bitmap.width; this.canvas.height = bitmap.height;
        }
        this.ctx.drawImage(bitmap, 0, 0);
        bitmap.close();
        this._shown(header.capture_time * 1000, this.canvas.width, this.canvas.height);
      } catch (e) {
        M.stats.videoErrors += 1;
      } finally {
        this.jpegBusy = false;
      }
    }

    close() {
      clearInterval(this.timer);
      if (this.decoder) { try { this.decoder.close(); } catch (e) { /* closed */ } }
    }
  }
  M.VideoSink = VideoSink;

  // ------------------------------------------------------------------ audio in
  // Opus packets -> AudioDecoder -> the worklet's jitter buffer -> speakers. The buffer's
  // target is 20 ms + 2 × the arrival jitter (RFC 3550's estimate), within 40–80 ms.
  class AudioSink {
    constructor() {
      this.ctx = null;
      this.node = null;
      this.decoder = null;
      this.lastSeq = null;
      this.jitter = 0;
      this.lastTransit = null;
      this.captures = new Map(); // seq -> capture ms
      this.zc = { n: 0, crossings: 0, last: 0 };
      this.ready = this._start();
    }

    async _start() {
      if (typeof AudioDecoder === "undefined") return false;
      // The smallest output buffer the device allows ("interactive" is about 40 ms in
      // Chromium, 0 about 11 ms): the jitter buffer already absorbs the network's jitter.
      this.ctx = new AudioContext({ sampleRate: 48000, latencyHint: 0 });
      await this.ctx.audioWorklet.addModule("static/media-worklet.js");
      this.node = new AudioWorkletNode(this.ctx, "telebot-jitter", { outputChannelCount: [1] });
      this.node.connect(this.ctx.destination);
      this.node.port.onmessage = (ev) => this._played(ev.data);
      this.decoder = new AudioDecoder({
        output: (data) => this._decoded(data),
        error: () => { M.stats.audioErrors += 1; this.decoder = null; },
      });
      this.decoder.configure({ codec: "opus", sampleRate: 48000, numberOfChannels: 1 });
      // Autoplay may hold the context until the user touches the page.
      const resume = () => { if (this.ctx.state !== "running") this.ctx.resume(); };
      resume();
      document.addEventListener("pointerdown", resume);
      return true;
    }

    push(header, data) {
      if (!this.decoder || this.decoder.state !== "configured") return;
      const seq = header.seq;
      if (this.lastSeq !== null) {
        const d = (seq - this.lastSeq) | 0;
        if (d <= 0 && d >= -50) return; // late: its time has passed (further back: a new call)
        if (d > 1) M.stats.audioLost += d - 1;
      }
      this.lastSeq = seq;
      M.stats.audioPackets += 1;
      const capture = header.capture_time * 1000;
      const transit = now() - capture;
      keep(M.stats.audioTransitMs, transit);
      if (this.lastTransit !== null) {
        this.jitter += (Math.abs(transit - this.lastTransit) - this.jitter) / 16;
        this.node.port.postMessage({ target: (20 + 2 * this.jitter) / 1000 });
      }
      this.lastTransit = transit;
      this.captures.set(seq, capture);
      if (this.captures.size > 200) this.captures.delete(this.captures.keys().next().value);
      try {
        this.decoder.decode(new EncodedAudioChunk({ type: "key", timestamp: seq * 20000, data }));
      } catch (e) { /* a bad packet: dropped */ }
    }

    _decoded(data) {
      const n = data.numberOfFrames;
      const pcm = new Float32Array(n);
      data.copyTo(pcm, { planeIndex: 0, format: "f32-planar" });
      const seq = Math.round(data.timestamp / 20000);
      data.close();
      this._frequency(pcm);
      this.node.port.postMessage({ pcm, seq }, [pcm.buffer]);
    }

    // What the page hears: the tone's frequency from rising zero crossings over 0.2 s.
    _frequency(pcm) {
      const z = this.zc;
      for (let i = 0; i < pcm.length; i++) {
        if (z.last < 0 && pcm[i] >= 0) z.crossings += 1;
        z.last = pcm[i];
      }
      z.n += pcm.length;
      if (z.n >= 9600) { M.stats.audioFreq = z.crossings * 48000 / z.n; z.n = 0; z.crossings = 0; }
    }

    _played(m) {
      if (m.level !== undefined) {
        M.stats.audioLevel = m.level; M.stats.audioTarget = m.target;
        M.stats.audioUnderruns = m.underruns; M.stats.audioSkippedMs = m.skipped / 48;
        M.stats.audioOutputMs = (this.ctx.baseLatency + (this.ctx.outputLatency || 0)) * 1000;
        return;
      }
      if (m.played === undefined) return;
      const capture = this.captures.get(m.played);
      if (capture === undefined) return;
      // The context frame at which the sample left -> our wall clock.
      const ts = this.ctx.getOutputTimestamp();
      const at = performance.timeOrigin + ts.performanceTime + (m.frame / 48000 - ts.contextTime) * 1000;
      keep(M.stats.audioMs, at - capture);
    }

    close() {
      if (this.ctx) this.ctx.close();
      if (this.decoder && this.decoder.state !== "closed") this.decoder.close();
    }
  }
  M.AudioSink = AudioSink;

  // ------------------------------------------------------------------ capture out
  // Camera and mic -> WebCodecs encoders -> `send(arrayBuffer)`. Video: VP8 or H.264
  // (Annex B), realtime, a keyframe when the robot asks and every 5 s, at a bit rate that
  // follows the robot's receiver reports (`report()`: 150 kbit/s–1.5 Mbit/s, from 0.6).
  // Audio: Opus 48 kHz mono 20 ms with in-band FEC; echo cancellation on. A missing or
  // refused device leaves the call going, with a note (`onNote`).
  class Capture {
    constructor(send, opts) {
      this.send = send; // (header, bytes, isVideo) -> bool (false: not sent, e.g. the link is busy)
      this.opts = Object.assign({ codec: "vp8", bitrate: 600000, width: 640, height: 480, fps: 30 }, opts || {});
      this.muted = false;
      this.cameraOff = false;
      this.pushToTalk = false;
      this.talking = false;
      this.forceKey = true;
      this.videoId = 0;
      this.audioSeq = 0;
      this.stream = null;
      this.onNote = () => {};
      this.running = false;
      const R = window.telebotUplinkRate; // absent on pages that only receive (screen.html)
      this.rate = R ? new R.UplinkRate({ start: this.opts.bitrate }) : null;
      this.rateChanged = false;
      M.stats.sendBitrate = this.opts.bitrate;
    }

    // One of the robot's REPORTs on the user's video (an `uplink_report` message, §19.1):
    // the rate controller may lower or raise the bit rate; the encoder takes it at its
    // next picture.
    report(fields) {
      if (!this.rate) return;
      M.stats.uplinkReports += 1;
      const bitrate = this.rate.report(fields);
      M.stats.uplinkLoss = this.rate.loss;
      M.stats.uplinkDelayMs = this.rate.delayMs;
      if (bitrate === null) return;
      this.opts.bitrate = bitrate;
      M.stats.sendBitrate = bitrate;
      this.rateChanged = true;
    }

    async start() {
      this.running = true;
      const notes = [];
      const audio = { echoCancellation: true, noiseSuppression: this.opts.noiseSuppression !== false, autoGainControl: this.opts.autoGainControl !== false, channelCount: 1, sampleRate: 48000 };
      const video = { width: this.opts.width, height: this.opts.height, frameRate: this.opts.fps };
      const gum = navigator.mediaDevices && navigator.mediaDevices.getUserMedia;
      if (!gum || typeof VideoEncoder === "undefined" || typeof MediaStreamTrackProcessor === "undefined") {
        this._note("this browser cannot send camera or microphone (needs getUserMedia and WebCodecs); the call continues without them");
        return;
      }
      let stream = null, lastErr = null;
      for (const want of [{ video, audio }, { video }, { audio }]) {
        try { stream = await navigator.mediaDevices.getUserMedia(want); break; } catch (e) { lastErr = e; }
      }
      if (!stream) {
        const why = lastErr && lastErr.name === "NotAllowedError" ? "permission denied" : "no camera or microphone found";
        this._note("camera and microphone off (" + why + "): the call continues; you still see and hear the robot");
        return;
      }
      this.stream = stream;
      const v = stream.getVideoTracks()[0], a = stream.getAudioTracks()[0];
      if (!v) notes.push("no camera: the robot does not see you");
      if (!a) notes.push("no microphone: the robot does not hear you");
      this._note(notes.join(" · "));
      if (v) this._video(v);
      if (a) this._audio(a);
    }

    _note(text) { M.stats.captureNote = text; this.onNote(text); }

    keyframe() { this.forceKey = true; M.stats.keyframesAsked += 1; }

    async _video(track) {
      const o = this.opts;
      let encoder = null, size = "", cfg = null;
      const make = (w, h) => {
        encoder = new VideoEncoder({
          output: (chunk) => this._sendChunk(chunk),
          error: () => { encoder = null; this.forceKey = true; },
        });
        cfg = { codec: CODEC_STRINGS[o.codec], width: w, height: h, bitrate: o.bitrate, framerate: o.fps, latencyMode: "realtime" };
        if (o.codec === "h264") cfg.avc = { format: "annexb" };
        encoder.configure(cfg);
        M.stats.encoderBitrate = o.bitrate;
        this.rateChanged = false;
        size = w + "x" + h;
        this.forceKey = true;
      };
      // The reports moved the bit rate: the same encoder, configured again.
      const retune = () => {
        this.rateChanged = false;
        cfg = Object.assign({}, cfg, { bitrate: o.bitrate });
        encoder.configure(cfg);
        M.stats.encoderBitrate = o.bitrate;
        M.stats.bitrateChanges += 1;
      };
      this.captureTimes = new Map();
      const reader = new MediaStreamTrackProcessor({ track }).readable.getReader();
      while (this.running) {
        const { value: frame, done } = await reader.read();
        if (done) break;
        try {
          if (this.cameraOff) continue;
          if (!encoder || encoder.state === "closed" || size !== frame.displayWidth + "x" + frame.displayHeight) {
            if (encoder && encoder.state !== "closed") encoder.close();
            make(frame.displayWidth, frame.displayHeight);
          } else if (this.rateChanged) {
            retune();
          }
          if (encoder.encodeQueueSize > 2) continue; // the encoder is behind: skip, never queue
          const key = this.forceKey || this.videoId % (o.fps * 5) === 0;
          this.forceKey = false;
          this.captureTimes.set(frame.timestamp, now());
          if (this.captureTimes.size > 32) this.captureTimes.delete(this.captureTimes.keys().next().value);
          encoder.encode(frame, { keyFrame: key });
        } catch (e) {
          this.forceKey = true;
        } finally {
          frame.close();
        }
      }
    }

    _sendChunk(chunk) {
      const data = new Uint8Array(chunk.byteLength);
      chunk.copyTo(data);
      const capture = this.captureTimes.get(chunk.timestamp) || now();
      const key = chunk.type === "key";
      const header = { kind: "video", codec: this.opts.codec, key, frame_id: this.videoId, capture_time: capture / 1000 };
      // A frame not sent would break the chain of deltas: the next one is a keyframe.
      if (this.send(header, data, true)) {
        this.videoId = (this.videoId + 1) >>> 0;
        M.stats.sentVideo += 1; M.stats.sentBytes += data.length;
        if (key) M.stats.sentVideoKeys += 1;
      } else {
        this.forceKey = true;
      }
    }

    async _audio(track) {
      let encoder = null;
      const reader = new MediaStreamTrackProcessor({ track }).readable.getReader();
      while (this.running) {
        const { value: data, done } = await reader.read();
        if (done) break;
        try {
          if (this.muted || (this.pushToTalk && !this.talking)) continue;
          if (!encoder || encoder.state === "closed") {
            encoder = new AudioEncoder({ output: (chunk) => this._sendAudio(chunk), error: () => { encoder = null; } });
            encoder.configure({ codec: "opus", sampleRate: data.sampleRate, numberOfChannels: 1, bitrate: 32000, opus: { frameDuration: 20000, useinbandfec: true, packetlossperc: 10, complexity: 5 } });
            this.audioClock = null;
          }
          encoder.encode(data.numberOfChannels === 1 ? data : mono(data));
        } catch (e) {
          encoder = null;
        } finally {
          data.close();
        }
      }
    }

    _sendAudio(chunk) {
      const data = new Uint8Array(chunk.byteLength);
      chunk.copyTo(data);
      // The packet's first sample was captured its duration (20 ms) before it was finished.
      const header = { kind: "audio", seq: this.audioSeq, capture_time: (now() - 20) / 1000 };
      this.audioSeq = (this.audioSeq + 1) >>> 0;
      if (this.send(header, data, false)) M.stats.sentAudio += 1;
    }

    stop() {
      this.running = false;
      if (this.stream) for (const t of this.stream.getTracks()) t.stop();
    }
  }
  function mono(data) {
    const pcm = new Float32Array(data.numberOfFrames);
    data.copyTo(pcm, { planeIndex: 0, format: "f32-planar" });
    return new AudioData({ format: "f32-planar", sampleRate: data.sampleRate, numberOfFrames: data.numberOfFrames, numberOfChannels: 1, timestamp: data.timestamp, data: pcm });
  }
  M.Capture = Capture;

  // ------------------------------------------------------------------ the user's page
  // Called by app.js with its websocket's send functions and the elements to use; returns
  // the handler of binary messages and text messages of the media kinds.
  M.attachPage = function (opts) {
    const sendText = opts.sendText; // (obj) -> bool
    const canvas = opts.canvas;
    const sink = new VideoSink(canvas, () => sendText({ type: "keyframe" }));
    M.video = sink;
    let audio = null;
    // (header, bytes, isVideo) -> bool: the page's port (websocket or in-browser client).
    const capture = new Capture((header, data, isVideo) => opts.sendMedia(header, data, isVideo), opts.capture);
    M.capture = capture;
    // Two sources of notes, both shown: the devices (capture) and the call (the client).
    const notes = { devices: "", call: "" };
    const showNote = () => (opts.onNote || (() => {}))([notes.call, notes.devices].filter(Boolean).join(" · "));
    capture.onNote = (text) => { notes.devices = text; showNote(); };
    const controls = opts.controls || {};
    if (controls.mute) controls.mute.onclick = () => {
      capture.muted = !capture.muted;
      controls.mute.textContent = capture.muted ? "unmute" : "mute";
    };
    if (controls.camera) controls.camera.onclick = () => {
      capture.cameraOff = !capture.cameraOff;
      if (!capture.cameraOff) capture.keyframe();
      controls.camera.textContent = capture.cameraOff ? "camera on" : "camera off";
    };
    if (controls.ptt) {
      const down = (ev) => { ev.preventDefault(); capture.talking = true; controls.ptt.classList.add("on"); };
      const up = () => { capture.talking = false; controls.ptt.classList.remove("on"); };
      controls.ptt.addEventListener("pointerdown", down);
      controls.ptt.addEventListener("pointerup", up);
      controls.ptt.addEventListener("pointerleave", up);
      if (controls.pttMode) controls.pttMode.onchange = () => { capture.pushToTalk = controls.pttMode.checked; controls.ptt.disabled = !capture.pushToTalk; };
    }
    let started = false;
    return {
      // Tell the client what this browser decodes and encodes (on every websocket open).
      open() {
        const codecs = typeof VideoDecoder === "undefined" ? ["jpeg"] : ["h264", "vp8", "jpeg"];
        const encode = typeof VideoEncoder === "undefined" ? [] : ["vp8", "h264"];
        sendText({ type: "media", decode: codecs, encode });
      },
      // A media message (parsed: its header and bytes): codec video and audio are handled
      // here; returns "audio", "video" (decoded here) or "" (JPEG: the caller shows it).
      frame(header, data) {
        if (header.kind === "audio") {
          if (!audio) { audio = new AudioSink(); M.audio = audio; }
          audio.push(header, data);
          return "audio";
        }
        if (!header.codec || header.codec === "jpeg") return "";
        sink.push(header, data);
        return "video";
      },
      // A text message of the media kinds; true when it was one.
      text(m) {
        if (m.type === "keyframe_request") { capture.keyframe(); return true; }
        if (m.type === "uplink_report") { capture.report(m); return true; }
        if (m.type === "media") {
          if (m.codec) capture.opts.codec = m.codec;
          notes.call = m.note || ""; showNote();
          if (m.send && !started) { started = true; capture.start(); }
          return true;
        }
        return false;
      },
    };
  };
})();
