/**
 * The robot's camera and microphone on the user's side (docs/protocol.md §17, §25),
 * sans-IO: FRAGMENT parsing and reassembly into whole pictures (latest frame wins, a frame
 * with a missing fragment is dropped whole), REPORTs (the subscription, with the codec list
 * and the keyframe flag), the keyframe gate of delta codecs, and AUDIO packets.
 * Every function takes `now` in seconds where time matters.
 * @module services/video
 */
import { DecodeError, U32, decodeUtf8, serialDiff } from "./util.js";

export const KIND_FRAGMENT = 0x01;
export const KIND_REPORT = 0x02;
export const KIND_AUDIO = 0x03;
export const CODEC_JPEG = 0x01;
export const CODEC_CDR = 0x02;
export const CODEC_H264 = 0x03;
export const CODEC_VP8 = 0x04;
export const CODEC_OPUS = 0x10;
export const CODEC_KEYFRAME = 0x80;
/** Codec ids by the names the page uses (§19.1). */
export const CODEC_IDS = { jpeg: CODEC_JPEG, h264: CODEC_H264, vp8: CODEC_VP8, opus: CODEC_OPUS };
export const CODEC_NAMES = { [CODEC_JPEG]: "jpeg", [CODEC_H264]: "h264", [CODEC_VP8]: "vp8", [CODEC_OPUS]: "opus" };
export const VIDEO_CODECS = [CODEC_JPEG, CODEC_H264, CODEC_VP8];
export const FLAG_BYE = 0x01;
export const FLAG_KEYFRAME = 0x02;
export const FRAGMENT_HEADER = 29;
export const REPORT_SIZE = 28;
export const AUDIO_HEADER = 14;
export const MAX_CAMERA_NAME = 32;
export const MAX_FRAGMENTS = 64;
export const MAX_FRAME_BYTES = 2_000_000;
export const MAX_IN_FLIGHT = 4;
export const MIN_HOLD = 0.005;
export const MAX_HOLD = 1.0;
export const MAX_WIRE_FPS = 240;
export const JUMP_SLACK = 64;
export const MAX_OPUS_PACKET = 3 * 1275;
/** A receiver repeats a keyframe request no faster than max(RTT, this) (s). */
export const MIN_KEYFRAME_GAP = 0.3;
/** Reports go at once and then this often (s) while the user watches or listens. */
export const REPORT_INTERVAL = 0.2;

/**
 * Microseconds of a Unix time in seconds, rounded as Python's round() does (half to
 * even), so the bytes equal the Python sender's; at least 0, at most 2^53 - 1.
 */
export function captureMicros(seconds) {
  const x = seconds * 1e6;
  if (!(x > 0)) return 0;
  let r = Math.round(x);
  if (r - x === 0.5 && r % 2 !== 0) r -= 1;
  return Math.min(r, Number.MAX_SAFE_INTEGER);
}

/** The byte range [start, end) of fragment `index` of a `size`-byte frame in `count` (§17.1). */
export function fragmentSpan(size, count, index) {
  const q = Math.floor(size / count);
  const r = size % count;
  const start = index * q + Math.min(index, r);
  return [start, start + q + (index < r ? 1 : 0)];
}

function view(bytes) {
  return new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
}

/** The u64 at `at` as a number (µs since 1970 stay exact far beyond 2²⁵³ µs... up to 2⁵³). */
function u64(dv, at) {
  return dv.getUint32(at) * 2 ** 32 + dv.getUint32(at + 4);
}

/**
 * Parse and check a FRAGMENT (§17.1) whose codec is one of `codecs`; DecodeError when
 * malformed.
 * @param {string|Uint8Array} payload @param {number[]} [codecs]
 */
export function parseFragment(payload, codecs = VIDEO_CODECS) {
  const what = "video fragment";
  if (!(payload instanceof Uint8Array)) throw new DecodeError(`${what}: expected a binary datagram`);
  if (payload.length < FRAGMENT_HEADER) throw new DecodeError(`${what}: shorter than its header`);
  const dv = view(payload);
  const kind = payload[0];
  const codecByte = payload[1];
  const codec = codecByte & ~CODEC_KEYFRAME;
  const seq = dv.getUint32(2);
  const frameId = dv.getUint32(6);
  const index = dv.getUint16(10);
  const count = dv.getUint16(12);
  const size = dv.getUint32(14);
  const captureUs = u64(dv, 18);
  const intervalMs = dv.getUint16(26);
  const nameLength = payload[28];
  if (kind !== KIND_FRAGMENT) throw new DecodeError(`${what}: not a fragment`);
  if (!codecs.includes(codec)) throw new DecodeError(`${what}: unknown codec ${codec}`);
  if (count < 1 || count > MAX_FRAGMENTS || index >= count) throw new DecodeError(`${what}: index ${index} of ${count} fragments`);
  if (size < count || size > MAX_FRAME_BYTES) throw new DecodeError(`${what}: frame size ${size} for ${count} fragments`);
  if (nameLength < 1 || nameLength > MAX_CAMERA_NAME) throw new DecodeError(`${what}: camera name of ${nameLength} bytes`);
  const dataAt = FRAGMENT_HEADER + nameLength;
  if (payload.length < dataAt) throw new DecodeError(`${what}: truncated camera name`);
  const camera = decodeUtf8(payload.subarray(FRAGMENT_HEADER, dataAt), `${what}: camera name`);
  const [start, end] = fragmentSpan(size, count, index);
  if (payload.length - dataAt !== end - start) throw new DecodeError(`${what}: wrong data length for fragment ${index}`);
  return {
    seq, frameId, index, count, size, captureUs, intervalMs, camera, codec,
    keyframe: (codecByte & CODEC_KEYFRAME) !== 0 || codec === CODEC_JPEG,
    data: payload.subarray(dataAt),
  };
}

/**
 * Cut one frame into FRAGMENT datagrams (the robot's side; tests and the user's camera).
 * @returns {Uint8Array[]}
 */
export function fragmentFrame({ frameId, camera, captureTime, data, seq = 0, interval = 1 / 30, codec = CODEC_JPEG, keyframe = false, maxPayload = 32768 }) {
  const name = new TextEncoder().encode(camera);
  if (name.length < 1 || name.length > MAX_CAMERA_NAME) throw new RangeError("camera name must be 1..32 UTF-8 bytes");
  const room = Math.min(maxPayload, 32768) - FRAGMENT_HEADER - name.length;
  const size = data.length;
  if (size < 1 || size > MAX_FRAME_BYTES) throw new RangeError(`a frame must be 1..${MAX_FRAME_BYTES} bytes`);
  const count = Math.ceil(size / room);
  if (count > MAX_FRAGMENTS) throw new RangeError("a frame of more than 64 fragments");
  const captureUs = captureMicros(captureTime);
  const intervalMs = Math.max(1, Math.min(Math.round(interval * 1000), 0xffff));
  const out = [];
  for (let index = 0; index < count; index++) {
    const [start, end] = fragmentSpan(size, count, index);
    const datagram = new Uint8Array(FRAGMENT_HEADER + name.length + end - start);
    const dv = view(datagram);
    datagram[0] = KIND_FRAGMENT;
    datagram[1] = codec | (keyframe ? CODEC_KEYFRAME : 0);
    dv.setUint32(2, (seq + index) % U32);
    dv.setUint32(6, frameId % U32);
    dv.setUint16(10, index);
    dv.setUint16(12, count);
    dv.setUint32(14, size);
    dv.setUint32(18, Math.floor(captureUs / 2 ** 32));
    dv.setUint32(22, captureUs % 2 ** 32);
    dv.setUint16(26, intervalMs);
    datagram[28] = name.length;
    datagram.set(name, FRAGMENT_HEADER);
    datagram.set(data.subarray(start, end), FRAGMENT_HEADER + name.length);
    out.push(datagram);
  }
  return out;
}

/**
 * A REPORT (§17.2, §25.2): 28 bytes, then the codec list when `codecs` is not empty.
 * @param {{receiverMs:number, highestSeq:number, fragments:number, bytes:number, frames:number, dropped:number, queueDelayMs:number, bye?:boolean, keyframe?:boolean, codecs?:number[]}} r
 */
export function encodeReport(r) {
  const codecs = r.codecs ?? [];
  const out = new Uint8Array(REPORT_SIZE + (codecs.length ? 1 + codecs.length : 0));
  const dv = view(out);
  out[0] = KIND_REPORT;
  out[1] = (r.bye ? FLAG_BYE : 0) | (r.keyframe ? FLAG_KEYFRAME : 0);
  const u32 = (at, value) => dv.setUint32(at, ((Math.floor(value) % U32) + U32) % U32);
  u32(2, r.receiverMs);
  u32(6, r.highestSeq);
  u32(10, r.fragments);
  u32(14, r.bytes);
  u32(18, r.frames);
  u32(22, r.dropped);
  dv.setUint16(26, Math.max(0, Math.min(Math.round(r.queueDelayMs), 0xffff)));
  if (codecs.length) {
    out[REPORT_SIZE] = codecs.length;
    out.set(codecs, REPORT_SIZE + 1);
  }
  return out;
}

/** Parse a REPORT (for tests and the robot's side); DecodeError when malformed. */
export function parseReport(payload) {
  if (!(payload instanceof Uint8Array) || payload.length < REPORT_SIZE) throw new DecodeError("video: a report is at least 28 bytes");
  if (payload[0] !== KIND_REPORT) throw new DecodeError("video: not a report");
  const dv = view(payload);
  let codecs = [];
  if (payload.length > REPORT_SIZE) {
    const n = payload[REPORT_SIZE];
    if (n < 1 || n > 8 || payload.length !== REPORT_SIZE + 1 + n) throw new DecodeError("video: a report's codec list");
    codecs = [...payload.subarray(REPORT_SIZE + 1)];
    if (!codecs.every((c) => c > 0 && c < 128) || new Set(codecs).size !== n) throw new DecodeError("video: a report's codec list has bad or repeated ids");
  }
  return {
    bye: (payload[1] & FLAG_BYE) !== 0,
    keyframe: (payload[1] & FLAG_KEYFRAME) !== 0,
    receiverMs: dv.getUint32(2),
    highestSeq: dv.getUint32(6),
    fragments: dv.getUint32(10),
    bytes: dv.getUint32(14),
    frames: dv.getUint32(18),
    dropped: dv.getUint32(22),
    queueDelayMs: dv.getUint16(26),
    codecs,
  };
}

/**
 * Rebuilds frames from fragments, bounded, latest frame wins (§17.3). Bad input is
 * dropped and counted in {@link stats}, never thrown.
 */
export class Reassembler {
  constructor({ codecs = VIDEO_CODECS, maxInFlight = MAX_IN_FLIGHT } = {}) {
    this.codecs = codecs;
    this.maxInFlight = maxInFlight;
    this.stats = {
      fragments: 0, bytes: 0, frames: 0, incomplete: 0, late: 0, duplicates: 0,
      malformed: 0, inconsistent: 0, absurd: 0,
    };
    /** @type {Map<number, any>} frame id -> partial frame, in opening order */
    this.partials = new Map();
    this.newestReturned = null;
    this.newestSeen = null;
    this.newestSeenAt = 0;
    this.highestSeq = null;
    this.transits = [];
    this.queueDelay = 0;
  }

  /** One datagram; returns the frame it completes, or null. */
  onDatagram(payload, now) {
    this.poll(now);
    let frag;
    try {
      frag = parseFragment(payload, this.codecs);
    } catch {
      this.stats.malformed += 1;
      return null;
    }
    return this.onFragment(frag, now);
  }

  onFragment(frag, now) {
    const fid = frag.frameId;
    if (this.newestReturned !== null && serialDiff(fid, this.newestReturned) <= 0) {
      this.stats.late += 1;
      return null;
    }
    if (this.newestSeen !== null) {
      const allowed = MAX_WIRE_FPS * Math.max(0, now - this.newestSeenAt) + JUMP_SLACK;
      if (serialDiff(fid, this.newestSeen) > allowed) {
        this.stats.absurd += 1;
        return null;
      }
    }
    let partial = this.partials.get(fid);
    if (!partial) {
      partial = this.open(frag, now);
    } else if (
      partial.count !== frag.count || partial.size !== frag.size || partial.camera !== frag.camera ||
      partial.captureUs !== frag.captureUs || partial.codec !== frag.codec || partial.keyframe !== frag.keyframe
    ) {
      this.stats.inconsistent += 1;
      return null;
    }
    if (partial.have[frag.index]) {
      this.stats.duplicates += 1;
      return null;
    }
    if (this.highestSeq === null || serialDiff(frag.seq, this.highestSeq) > 0) this.highestSeq = frag.seq;
    if (this.newestSeen === null || serialDiff(fid, this.newestSeen) > 0) {
      this.newestSeen = fid;
      this.newestSeenAt = now;
    }
    const [start] = fragmentSpan(partial.size, partial.count, frag.index);
    partial.buffer.set(frag.data, start);
    partial.have[frag.index] = 1;
    partial.missing -= 1;
    this.stats.fragments += 1;
    this.stats.bytes += frag.data.length;
    if (partial.missing) return null;
    return this.complete(fid, partial, now);
  }

  /** Drop partial frames whose time (one frame interval) is up. */
  poll(now) {
    for (const [fid, p] of this.partials) {
      if (p.deadline <= now) {
        this.partials.delete(fid);
        this.stats.incomplete += 1;
      }
    }
  }

  /** A report of the counters now (`receiverMs`: this side's clock in ms). */
  report(receiverMs, { bye = false, keyframe = false, codecs = [] } = {}) {
    return encodeReport({
      receiverMs, highestSeq: this.highestSeq ?? 0, fragments: this.stats.fragments,
      bytes: this.stats.bytes, frames: this.stats.frames, dropped: this.stats.incomplete,
      queueDelayMs: this.queueDelay * 1000, bye, keyframe, codecs,
    });
  }

  open(frag, now) {
    while (this.partials.size >= this.maxInFlight) {
      const oldest = this.partials.keys().next().value;
      this.partials.delete(oldest);
      this.stats.incomplete += 1;
    }
    const hold = Math.min(Math.max(frag.intervalMs / 1000, MIN_HOLD), MAX_HOLD);
    const partial = {
      count: frag.count, size: frag.size, camera: frag.camera, captureUs: frag.captureUs,
      intervalMs: frag.intervalMs, codec: frag.codec, keyframe: frag.keyframe,
      buffer: new Uint8Array(frag.size), have: new Uint8Array(frag.count), missing: frag.count,
      deadline: now + hold,
    };
    this.partials.set(frag.frameId, partial);
    this.noteTransit(frag.captureUs / 1e6, now);
    return partial;
  }

  complete(fid, partial, now) {
    this.partials.delete(fid);
    for (const older of [...this.partials.keys()]) {
      if (serialDiff(older, fid) < 0) {
        this.partials.delete(older);
        this.stats.incomplete += 1;
      }
    }
    this.newestReturned = fid;
    this.stats.frames += 1;
    return {
      frameId: fid, camera: partial.camera, captureTime: partial.captureUs / 1e6,
      interval: partial.intervalMs / 1000, data: partial.buffer, fragments: partial.count,
      completedAt: now, codec: partial.codec, keyframe: partial.keyframe,
    };
  }

  /**
   * Queueing delay (§17.2): transit = arrival − capture, minus its minimum over 5 s.
   * `now` is the receiver's clock; the clocks' offset cancels.
   */
  noteTransit(captureTime, now) {
    const transit = now - captureTime;
    while (this.transits.length && this.transits[this.transits.length - 1][1] >= transit) this.transits.pop();
    this.transits.push([now, transit]);
    while (this.transits[0][0] < now - 5) this.transits.shift();
    this.queueDelay = transit - this.transits[0][1];
  }
}

/**
 * Receiver (§25.1): decode a delta-coded frame only if the frame before it was decoded.
 * After a gap in frame ids, a frame that did not decode or a change of codec, only a
 * keyframe passes until one comes; JPEG always passes.
 */
export class KeyframeGate {
  constructor() {
    this.skipped = 0;
    this.waits = 0;
    this.last = null;
    this.codec = null;
    this.needKeyframe = true;
  }
  admit(frameId, codec, keyframe) {
    if (this.codec !== null && codec !== this.codec) this.lose();
    this.codec = codec;
    const contiguous = this.last !== null && serialDiff(frameId, this.last) === 1;
    this.last = frameId;
    if (keyframe || codec === CODEC_JPEG) {
      this.needKeyframe = false;
      return true;
    }
    if (this.needKeyframe || !contiguous) {
      this.lose();
      this.skipped += 1;
      return false;
    }
    return true;
  }
  /** The frame just admitted did not decode (or one was lost): wait for a keyframe. */
  lose() {
    if (!this.needKeyframe) this.waits += 1;
    this.needKeyframe = true;
  }
}

/** Receiver: when to send an extra REPORT asking for a keyframe (§25.1). */
export class KeyframeRequests {
  constructor(minGap = MIN_KEYFRAME_GAP) {
    this.minGap = minGap;
    this.sent = 0;
    this.last = null;
  }
  due(need, now, rtt = null) {
    if (!need) {
      this.last = null;
      return false;
    }
    if (this.last !== null && now - this.last < Math.max(this.minGap, rtt ?? 0)) return false;
    this.last = now;
    this.sent += 1;
    return true;
  }
}

/**
 * Parse an AUDIO datagram (§25.3): {seq, captureUs, data}; DecodeError when malformed.
 * @param {string|Uint8Array} payload
 */
export function parseAudio(payload) {
  if (!(payload instanceof Uint8Array)) throw new DecodeError("audio: expected a binary datagram");
  if (payload.length <= AUDIO_HEADER) throw new DecodeError("audio: no longer than its header");
  if (payload[0] !== KIND_AUDIO) throw new DecodeError("audio: not an audio packet");
  if (payload[1] !== CODEC_OPUS) throw new DecodeError("audio: unknown codec");
  if (payload.length - AUDIO_HEADER > MAX_OPUS_PACKET) throw new DecodeError("audio: packet too long");
  const dv = view(payload);
  return { seq: dv.getUint32(2), captureUs: u64(dv, 6), data: payload.subarray(AUDIO_HEADER) };
}

/** An AUDIO datagram (the robot's side in tests; the user's microphone). */
export function encodeAudio(seq, captureTime, packet) {
  if (packet.length < 1 || packet.length > MAX_OPUS_PACKET) throw new RangeError("an audio packet must be 1..3825 bytes");
  const out = new Uint8Array(AUDIO_HEADER + packet.length);
  const dv = view(out);
  const us = captureMicros(captureTime);
  out[0] = KIND_AUDIO;
  out[1] = CODEC_OPUS;
  dv.setUint32(2, seq % U32);
  dv.setUint32(6, Math.floor(us / 2 ** 32));
  dv.setUint32(10, us % 2 ** 32);
  out.set(packet, AUDIO_HEADER);
  return out;
}

/**
 * The binary websocket message of §19/§19.1 for a header and bytes: a 4-byte big-endian
 * header length, the UTF-8 JSON header, the bytes. A page written for the local client's
 * websocket takes it as it is.
 * @param {object} header @param {Uint8Array} data @returns {ArrayBuffer}
 */
export function packMedia(header, data) {
  const raw = new TextEncoder().encode(JSON.stringify(header));
  const out = new Uint8Array(4 + raw.length + data.length);
  view(out).setUint32(0, raw.length);
  out.set(raw, 4);
  out.set(data, 4 + raw.length);
  return out.buffer;
}
