/**
 * Shared pieces of the browser client's services (docs/protocol.md §13–§25): the JSON
 * message rules of §13 (one compact object per text datagram, no NaN/Infinity), field
 * checks that throw one-line {@link DecodeError}s, serial arithmetic and byte helpers.
 * Sans-IO: nothing here touches a clock, a timer or the network.
 * @module services/util
 */

import { concat, toHex } from "../bytes.js";

/** A datagram from the robot that is not what its channel carries (dropped and counted). */
export class DecodeError extends Error {
  /** @param {string} message one line, never a dump of the input */
  constructor(message) {
    super(message);
    this.name = "DecodeError";
  }
}

/** Longest JSON message a service accepts (characters): a datagram's limit anyway. */
export const MAX_MESSAGE = 32768;
/** Longest reason code (§13.1). */
export const MAX_CODE = 64;
export const U32 = 2 ** 32;
export const MAX_SAFE = 2 ** 53 - 1;

const utf8 = new TextDecoder("utf-8", { fatal: true });
const utf8Encoder = new TextEncoder();

/** @param {string} text @returns {Uint8Array} */
export function encodeUtf8(text) {
  return utf8Encoder.encode(text);
}

/**
 * Strict UTF-8 decoding; DecodeError when the bytes are not UTF-8.
 * @param {Uint8Array} bytes @param {string} what
 */
export function decodeUtf8(bytes, what) {
  try {
    return utf8.decode(bytes);
  } catch {
    throw new DecodeError(`${what}: not UTF-8`);
  }
}

/**
 * Parse a text datagram holding one JSON object (§13). A binary datagram, JSON that is
 * not an object or a message over {@link MAX_MESSAGE} characters is a DecodeError.
 * (JavaScript's JSON.parse already refuses NaN and Infinity literals.)
 * @param {string|Uint8Array} payload @param {string} what
 * @returns {Record<string, any>}
 */
export function decodeObject(payload, what) {
  if (typeof payload !== "string") {
    throw new DecodeError(`${what}: expected a JSON text datagram, got ${payload?.length ?? 0} bytes`);
  }
  if (payload.length > MAX_MESSAGE) {
    throw new DecodeError(`${what}: message of ${payload.length} characters is too long`);
  }
  let value;
  try {
    value = JSON.parse(payload);
  } catch {
    throw new DecodeError(`${what}: not JSON`);
  }
  if (value === null || typeof value !== "object" || Array.isArray(value)) {
    throw new DecodeError(`${what}: expected a JSON object`);
  }
  return value;
}

/** Compact JSON of a message (throws on a non-finite number: that is a bug here). */
export function encodeObject(message) {
  return JSON.stringify(message, (key, value) => {
    if (typeof value === "number" && !Number.isFinite(value)) {
      throw new RangeError(`${key}: not a finite number`);
    }
    return value;
  });
}

/** @param {unknown} value @returns {value is number} */
export function isFiniteNumber(value) {
  return typeof value === "number" && Number.isFinite(value);
}

/** `msg[key]` as a finite number, else DecodeError. */
export function finiteNumber(msg, key, what) {
  const value = msg[key];
  if (!isFiniteNumber(value)) throw new DecodeError(`${what}: '${key}' must be a finite number`);
  return value;
}

/** `msg[key]` as a finite number or null (absent: null). */
export function optionalNumber(msg, key, what) {
  return msg[key] == null ? null : finiteNumber(msg, key, what);
}

/**
 * `msg[key]` as an integer in low..high. JSON has one number type in JavaScript, so
 * `7.0` reads as 7 here (Python refuses it); a receiver may be that lenient (§13).
 */
export function requireInt(msg, key, what, low = 0, high = U32 - 1) {
  const value = msg[key];
  if (!Number.isInteger(value) || value < low || value > high) {
    throw new DecodeError(`${what}: '${key}' must be an integer in ${low}..${high}`);
  }
  return value;
}

/** `msg[key]` as text (absent: `fallback`, or an error when none is given). */
export function text(msg, key, what, fallback = undefined) {
  const value = key in msg ? msg[key] : fallback;
  if (typeof value !== "string") throw new DecodeError(`${what}: '${key}' must be text`);
  return value;
}

/** `msg[key]` as text or null. */
export function optionalText(msg, key, what) {
  const value = msg[key];
  if (value != null && typeof value !== "string") {
    throw new DecodeError(`${what}: '${key}' must be text or null`);
  }
  return value ?? null;
}

/** `msg[key]` as a boolean. */
export function flag(msg, key, what) {
  const value = msg[key];
  if (typeof value !== "boolean") throw new DecodeError(`${what}: '${key}' must be true or false`);
  return value;
}

/** The reason code of a message (§13.1): "" when absent, kept as it is when unknown. */
export function decodeCode(msg, what) {
  const code = msg.code ?? "";
  if (typeof code !== "string" || code.length > MAX_CODE) {
    throw new DecodeError(`${what}: 'code' must be text of at most ${MAX_CODE} characters`);
  }
  return code;
}

/**
 * `a − b` in 32-bit serial arithmetic (RFC 1982, §17.2): positive when `a` is newer.
 * @param {number} a @param {number} b
 */
export function serialDiff(a, b) {
  const diff = (((a - b) % U32) + U32) % U32;
  return diff >= 2 ** 31 ? diff - U32 : diff;
}

/**
 * A counter of request ids starting at a random point in 0 … 2³¹ − 1 (§18: the chat,
 * goal and safety numbers are separate spaces; a random start keeps a reconnecting
 * client clear of answers the robot still remembers).
 * @param {() => number} [random] a source in [0, 1)
 */
export function idCounter(random = Math.random) {
  let next = Math.floor(random() * 2 ** 31);
  return () => {
    const id = next;
    next = (next + 1) % U32;
    return id;
  };
}

/** Concatenate byte arrays. @param {Uint8Array[]} parts */
export const concatBytes = (parts) => concat(...parts);

export { toHex };

/**
 * Counters of dropped input by reason: `counts.malformed`, `counts.total`.
 */
export class DropCounter {
  constructor() {
    /** @type {Record<string, number>} */
    this.byReason = {};
    this.total = 0;
  }
  /** @param {string} reason */
  add(reason) {
    this.byReason[reason] = (this.byReason[reason] ?? 0) + 1;
    this.total += 1;
  }
}

/** Why a request failed when its call ended under it. */
export const CALL_ENDED = "the call ended";
/** A request unanswered this long is sent again (s). */
export const RESEND_AFTER = 0.3;
/**
 * The first repeats of a stop (services.js) and of a release (drive.js) come sooner, s
 * after the copy before: a lossy link mostly loses one datagram at a time, and a lost
 * stop or release then costs 20 ms, not 50 (the session's 20 ms tick keeps this schedule).
 * As the Python client's `QUICK_REPEATS`.
 */
export const QUICK_REPEATS = Object.freeze([0.02, 0.02]);

/** An error a request ends with: `code` "timeout" or "call_ended". */
export class RequestFailed extends Error {
  constructor(message, code) {
    super(message);
    this.name = "RequestFailed";
    this.code = code;
  }
}

/** Send on a channel; false when it threw (the call is over, or a transient failure). */
export function safeSend(channel, payload) {
  try {
    channel.send(payload);
    return true;
  } catch {
    return false; // the next repeat tries again
  }
}

/** Calls `fn`; a throwing listener never reaches the network callback. */
export function callSafely(fn, ...args) {
  try {
    fn?.(...args);
  } catch {
    // the page's listener failed: the service goes on
  }
}
