/**
 * The user's side of the map channel (docs/protocol.md §15), sans-IO: {@link MapReceiver}
 * takes datagrams and `now` (seconds) and returns the datagrams to send; the transfer
 * completes over loss (repeated `get`, `resend` of missing chunks, SHA-256 check).
 * Also the PNG helpers the page needs: the IHDR size and a decoder of the §15.5 image
 * (8-bit greyscale) into RGBA pixels.
 * @module services/map
 */
import { sha256 } from "@noble/hashes/sha2";
import { DecodeError, MAX_SAFE, U32, concatBytes, decodeObject, encodeObject, finiteNumber, requireInt, toHex } from "./util.js";

export const CHUNK_KIND = 0x01;
export const CHUNK_HEADER = 9;
export const MAX_CHUNK_DATA = 32768 - CHUNK_HEADER;
export const MAX_MAP_BYTES = 64 * 1024 * 1024;
export const MAX_CHUNKS = 65536;
export const MAX_MAP_CELLS = 100_000_000;
export const MAX_RESEND_INDICES = 1000;
export const MAX_RESEND_MESSAGES = 8;
/** `get` repeat (s); after an offer-less chunk the next one comes RESEND_AFTER after it. */
export const REQUEST_INTERVAL = 0.25;
export const RESEND_AFTER = 0.08;
export const MAX_RESEND_WAIT = 1.0;
export const EARLY_BUFFER_BYTES = 8 * 1024 * 1024;
/** Copies of `done` / `cancel` (not acknowledged). */
export const REPEATS = 3;
const MAX_TEXT = 256;

/** A control message of the map channel. */
function message(type, xfer, fields = {}) {
  return encodeObject({ type, xfer, ...fields });
}

/**
 * Validate an `offer` object (§15.1); DecodeError names the first bad field.
 * @returns {{xfer:number,name:string,size:number,chunks:number,chunk_size:number,sha256:string,width:number,height:number,resolution:number,origin_x:number,origin_y:number,version:number}}
 */
export function parseOffer(msg) {
  const what = "map offer";
  const xfer = requireInt(msg, "xfer", what);
  const name = msg.name;
  if (typeof name !== "string" || name.length === 0 || name.length > MAX_TEXT) {
    throw new DecodeError(`${what}: 'name' must be a string of 1..${MAX_TEXT} characters`);
  }
  const size = requireInt(msg, "size", what, 1, MAX_MAP_BYTES);
  const chunkSize = requireInt(msg, "chunk_size", what, 1, MAX_CHUNK_DATA);
  const chunks = requireInt(msg, "chunks", what, 1, MAX_CHUNKS);
  if (chunks !== Math.ceil(size / chunkSize)) {
    throw new DecodeError(`${what}: ${chunks} chunks cannot hold ${size} bytes in chunks of ${chunkSize}`);
  }
  if (typeof msg.sha256 !== "string" || !/^[0-9a-f]{64}$/.test(msg.sha256)) {
    throw new DecodeError(`${what}: 'sha256' must be 64 lowercase hex digits`);
  }
  const width = requireInt(msg, "width", what, 1);
  const height = requireInt(msg, "height", what, 1);
  if (width * height > MAX_MAP_CELLS) throw new DecodeError(`${what}: the map is too large`);
  const resolution = finiteNumber(msg, "resolution", what);
  if (resolution <= 0) throw new DecodeError(`${what}: 'resolution' must be positive`);
  const origin = msg.origin;
  if (!Array.isArray(origin) || origin.length !== 2) throw new DecodeError(`${what}: 'origin' must be [x, y]`);
  const originX = finiteNumber({ x: origin[0] }, "x", `${what} origin`);
  const originY = finiteNumber({ y: origin[1] }, "y", `${what} origin`);
  const version = "version" in msg ? requireInt(msg, "version", what, 0, MAX_SAFE) : 0;
  return {
    xfer, name, size, chunks, chunk_size: chunkSize, sha256: msg.sha256, width, height,
    resolution, origin_x: originX, origin_y: originY, version,
  };
}

function sameOffer(a, b) {
  return Object.keys(a).every((key) => a[key] === b[key]);
}

/**
 * One map transfer, `xfer` (a u32 the user picks at random). Send {@link request}; feed
 * every datagram of `map` to {@link onMessage}, call {@link poll} at {@link nextDeadline}
 * and send what both return. Ends `state === "done"` ({@link result}) or `"failed"`
 * ({@link error}). Time-outs are the driver's business.
 */
export class MapReceiver {
  /** @param {number} xfer */
  constructor(xfer, { resendAfter = RESEND_AFTER, requestInterval = REQUEST_INTERVAL } = {}) {
    if (!Number.isInteger(xfer) || xfer < 0 || xfer >= U32) throw new RangeError("xfer must be a u32");
    this.xfer = xfer;
    this.resendAfter = resendAfter;
    this.requestInterval = requestInterval;
    /** @type {"new"|"requesting"|"receiving"|"done"|"failed"} */
    this.state = "new";
    this.offer = null;
    /** The verified map: the offer's fields and `png` (Uint8Array). */
    this.result = null;
    this.error = null;
    this.resent = 0;
    this.requests = 0;
    this.duplicates = 0;
    /** Datagrams dropped, by reason. */
    this.rejected = {};
    this.chunks = [];
    this.missing = 0;
    this.received = 0;
    this.early = new Map();
    this.earlyBytes = 0;
    this.earlyAt = null;
    this.lastRequest = 0;
    this.quietSince = 0;
    this.lastChunkAt = null;
    this.resendSentAt = null;
    this.interval = null;
    this.rtt = null;
  }

  /** Seconds without a new chunk after which the missing ones are asked for (§15.4.5). */
  get resendWait() {
    let wait = this.resendAfter;
    if (this.interval !== null) wait = Math.max(wait, 3 * this.interval);
    if (this.rtt !== null) wait = Math.max(wait, 2 * this.rtt);
    return Math.min(Math.max(this.resendAfter, MAX_RESEND_WAIT), wait);
  }

  /** [bytes received, bytes in the map] ([0, 0] before the offer). */
  get progress() {
    if (!this.offer) return [0, 0];
    return [this.state === "done" ? this.offer.size : this.received, this.offer.size];
  }

  /** The `get` that starts (or repeats) the transfer. */
  request(now) {
    if (this.state === "new") this.state = "requesting";
    this.lastRequest = now;
    this.requests += 1;
    return message("get", this.xfer);
  }

  /** Give up: the `cancel` copies to send ([] once ended). */
  cancel() {
    if (this.state !== "requesting" && this.state !== "receiving") return [];
    this.fail("cancelled");
    return Array(REPEATS).fill(message("cancel", this.xfer));
  }

  /** What is due at `now`: a repeated `get`, or `resend`s. */
  poll(now) {
    if (this.state === "requesting" && now >= this.requestDue()) return [this.request(now)];
    if (this.state === "receiving" && now >= this.quietSince + this.resendWait) {
      const missing = [];
      for (let i = 0; i < this.chunks.length && missing.length < MAX_RESEND_INDICES * MAX_RESEND_MESSAGES; i++) {
        if (this.chunks[i] === null) missing.push(i);
      }
      this.resent += missing.length;
      this.quietSince = this.resendSentAt = now;
      const out = [];
      for (let i = 0; i < missing.length; i += MAX_RESEND_INDICES) {
        out.push(message("resend", this.xfer, { missing: missing.slice(i, i + MAX_RESEND_INDICES) }));
      }
      return out;
    }
    return [];
  }

  /** When {@link poll} has something to do (null once ended). */
  nextDeadline() {
    if (this.state === "requesting") return this.requestDue();
    if (this.state === "receiving") return this.quietSince + this.resendWait;
    return null;
  }

  requestDue() {
    let due = this.lastRequest + this.requestInterval;
    if (this.earlyAt !== null) due = Math.min(due, Math.max(this.lastRequest, this.earlyAt) + this.resendAfter);
    return due;
  }

  /**
   * One datagram of the map channel; returns what to send now.
   * @param {string|Uint8Array} payload @param {number} now
   * @returns {string[]}
   */
  onMessage(payload, now) {
    if (this.state === "done" || this.state === "failed") {
      if (typeof payload !== "string") this.duplicates += 1;
      return [];
    }
    if (typeof payload !== "string") return this.onChunk(payload, now);
    let msg;
    try {
      msg = decodeObject(payload, "map reply");
    } catch {
      return this.reject("malformed");
    }
    if (typeof msg.type !== "string" || !Number.isInteger(msg.xfer)) return this.reject("malformed");
    if (msg.xfer !== this.xfer) return this.reject("unknown_xfer");
    if (msg.type === "offer") return this.onOffer(msg, now);
    if (msg.type === "error") {
      if (this.state === "new") return this.reject("unrequested");
      const reason = typeof msg.reason === "string" && msg.reason ? msg.reason
        : "the robot refused the map transfer without a reason";
      this.fail(reason.slice(0, MAX_TEXT));
      return [];
    }
    return this.reject("unknown_type");
  }

  onOffer(msg, now) {
    let offer;
    try {
      offer = parseOffer(msg);
    } catch {
      return this.reject("bad_offer");
    }
    if (this.offer) return sameOffer(offer, this.offer) ? [] : this.reject("conflicting_offer");
    if (this.state !== "requesting") return this.reject("unrequested");
    this.offer = offer;
    this.state = "receiving";
    this.chunks = new Array(offer.chunks).fill(null);
    this.missing = offer.chunks;
    this.rtt = now - this.lastRequest;
    this.quietSince = now;
    const early = [...this.early.entries()].sort((a, b) => a[0] - b[0]);
    this.early = new Map();
    this.earlyBytes = 0;
    for (const [index, data] of early) this.store(index, data);
    return this.missing === 0 ? this.finish() : [];
  }

  onChunk(payload, now) {
    if (!(payload instanceof Uint8Array) || payload.length < CHUNK_HEADER) return this.reject("short_chunk");
    const view = new DataView(payload.buffer, payload.byteOffset, payload.byteLength);
    if (payload[0] !== CHUNK_KIND) return this.reject("unknown_kind");
    if (view.getUint32(1) !== this.xfer) return this.reject("unknown_xfer");
    const index = view.getUint32(5);
    const data = payload.subarray(CHUNK_HEADER);
    if (!this.offer) return this.keepEarly(index, data, now);
    if (!this.store(index, data)) return [];
    if (this.resendSentAt !== null) {
      const sample = now - this.resendSentAt;
      this.rtt = this.rtt === null ? sample : 0.75 * this.rtt + 0.25 * sample;
      this.resendSentAt = null;
    } else if (this.lastChunkAt !== null) {
      const gap = now - this.lastChunkAt;
      this.interval = this.interval === null ? gap : 0.75 * this.interval + 0.25 * gap;
    }
    this.lastChunkAt = this.quietSince = now;
    return this.missing === 0 ? this.finish() : [];
  }

  keepEarly(index, data, now) {
    if (this.state !== "requesting") return this.reject("unrequested");
    if (this.early.has(index)) {
      this.duplicates += 1;
      return [];
    }
    if (index >= MAX_CHUNKS || data.length > MAX_CHUNK_DATA || this.earlyBytes + data.length > EARLY_BUFFER_BYTES) {
      return this.reject("early_overflow");
    }
    this.early.set(index, data.slice());
    this.earlyBytes += data.length;
    this.earlyAt = now;
    return [];
  }

  store(index, data) {
    const offer = this.offer;
    if (index >= offer.chunks) {
      this.reject("index_out_of_range");
      return false;
    }
    const length = index === offer.chunks - 1 ? offer.size - (offer.chunks - 1) * offer.chunk_size : offer.chunk_size;
    if (data.length !== length) {
      this.reject("bad_length");
      return false;
    }
    if (this.chunks[index] !== null) {
      this.duplicates += 1;
      return false;
    }
    this.chunks[index] = data.slice();
    this.missing -= 1;
    this.received += data.length;
    return true;
  }

  finish() {
    const offer = this.offer;
    const png = new Uint8Array(offer.size);
    let at = 0;
    for (const chunk of this.chunks) {
      png.set(chunk, at);
      at += chunk.length;
    }
    this.chunks = [];
    const digest = toHex(sha256(png));
    if (digest !== offer.sha256) {
      this.fail(`map hash mismatch: received ${digest}, the offer said ${offer.sha256}`);
      return Array(REPEATS).fill(message("cancel", this.xfer));
    }
    const size = pngSize(png);
    if (!size || size[0] !== offer.width || size[1] !== offer.height) {
      // The offer's georeference would misplace every click on the map: refuse it.
      this.fail(`the map's PNG is not the ${offer.width} × ${offer.height} image its offer says`);
      return Array(REPEATS).fill(message("done", this.xfer));
    }
    this.result = { ...offer, png };
    this.state = "done";
    return Array(REPEATS).fill(message("done", this.xfer));
  }

  fail(error) {
    this.state = "failed";
    this.error = error;
    this.chunks = [];
    this.early.clear();
    this.earlyBytes = 0;
  }

  reject(reason) {
    this.rejected[reason] = (this.rejected[reason] ?? 0) + 1;
    return [];
  }
}

// ---------------------------------------------------------------------------- PNG

const PNG_SIGNATURE = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];

/** [width, height] from a PNG's IHDR, or null when it is not a PNG. @param {Uint8Array} png */
export function pngSize(png) {
  if (png.length < 24 || !PNG_SIGNATURE.every((b, i) => png[i] === b)) return null;
  if (String.fromCharCode(...png.subarray(12, 16)) !== "IHDR") return null;
  const view = new DataView(png.buffer, png.byteOffset, png.byteLength);
  return [view.getUint32(16), view.getUint32(20)];
}

async function inflate(bytes) {
  const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

/**
 * Decode the map's PNG (§15.5: 8-bit greyscale, non-interlaced; also 8-bit RGB, RGBA and
 * grey+alpha) into `{width, height, rgba}` (an ImageData's shape: `new ImageData(rgba,
 * width, height)` draws it). Uses the platform's DecompressionStream (browsers, node ≥ 18).
 * DecodeError when the PNG is not one of those.
 * @param {Uint8Array} png
 * @returns {Promise<{width:number, height:number, rgba:Uint8ClampedArray}>}
 */
export async function decodeMapPng(png) {
  const size = pngSize(png);
  if (!size) throw new DecodeError("map image: not a PNG");
  const [width, height] = size;
  if (width < 1 || height < 1 || width * height > MAX_MAP_CELLS) throw new DecodeError("map image: bad size");
  const view = new DataView(png.buffer, png.byteOffset, png.byteLength);
  const depth = png[24];
  const colour = png[25];
  const interlace = png[28];
  const channels = { 0: 1, 2: 3, 4: 2, 6: 4 }[colour];
  if (depth !== 8 || !channels || interlace !== 0) {
    throw new DecodeError("map image: only 8-bit, non-interlaced PNGs are read");
  }
  const parts = [];
  let at = 8;
  while (at + 12 <= png.length) {
    const length = view.getUint32(at);
    const type = String.fromCharCode(...png.subarray(at + 4, at + 8));
    if (at + 12 + length > png.length) throw new DecodeError("map image: truncated chunk");
    if (type === "IDAT") parts.push(png.subarray(at + 8, at + 8 + length));
    if (type === "IEND") break;
    at += 12 + length;
  }
  let raw;
  try {
    raw = await inflate(concatBytes(parts));
  } catch {
    throw new DecodeError("map image: the pixel data does not inflate");
  }
  const stride = width * channels;
  if (raw.length < height * (stride + 1)) throw new DecodeError("map image: too little pixel data");
  const pixels = new Uint8Array(height * stride);
  for (let y = 0; y < height; y++) {
    const filter = raw[y * (stride + 1)];
    const line = raw.subarray(y * (stride + 1) + 1, (y + 1) * (stride + 1));
    const out = pixels.subarray(y * stride, (y + 1) * stride);
    const prev = y > 0 ? pixels.subarray((y - 1) * stride, y * stride) : null;
    for (let i = 0; i < stride; i++) {
      const a = i >= channels ? out[i - channels] : 0;
      const b = prev ? prev[i] : 0;
      const c = prev && i >= channels ? prev[i - channels] : 0;
      let value = line[i];
      switch (filter) {
        case 0: break;
        case 1: value += a; break;
        case 2: value += b; break;
        case 3: value += (a + b) >> 1; break;
        case 4: {
          const p = a + b - c;
          const pa = Math.abs(p - a), pb = Math.abs(p - b), pc = Math.abs(p - c);
          value += pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
          break;
        }
        default: throw new DecodeError(`map image: unknown filter ${filter}`);
      }
      out[i] = value & 0xff;
    }
  }
  const rgba = new Uint8ClampedArray(width * height * 4);
  for (let p = 0; p < width * height; p++) {
    const src = p * channels;
    if (channels <= 2) {
      rgba[p * 4] = rgba[p * 4 + 1] = rgba[p * 4 + 2] = pixels[src];
      rgba[p * 4 + 3] = channels === 2 ? pixels[src + 1] : 255;
    } else {
      rgba[p * 4] = pixels[src];
      rgba[p * 4 + 1] = pixels[src + 1];
      rgba[p * 4 + 2] = pixels[src + 2];
      rgba[p * 4 + 3] = channels === 4 ? pixels[src + 3] : 255;
    }
  }
  return { width, height, rgba };
}
