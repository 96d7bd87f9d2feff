/**
 * The bytes on the wire (docs/protocol.md §4, §6): outer frames and the messages sealed
 * inside DATA frames. Sans-IO. Every decoder is strict and throws only ProtocolError.
 *
 *     HELLO    ver=2 | type=4 | call_id[8] | name_len | name | instance[8]
 *                    | suite | offer_len | offers | noise_msg1
 *     WELCOME  ver=2 | type=2 | call_id[8] | noise_msg2
 *     DATA     ver=2 | type=3 | call_id[8] | counter u64 BE | AEAD ciphertext + tag
 *     RETRY    ver=2 | type=5 | call_id[8] | suite
 *
 *     DATAGRAM   kind=1 | flags (bit 0 text) | name_len | channel | payload
 *     HEARTBEAT  kind=2 | seq u32 | sent_us u64 | echo_us u64 | echo_delay_us u32
 *     HANGUP     kind=3 | reason (UTF-8)
 *     BUNDLE     kind=4 | 2 or more of (len u16 | DATAGRAM)
 * @module proto/frames
 */
import { ProtocolError } from "../errors.js";
import { concat, fromUtf8, utf8 } from "../bytes.js";

export const VERSION = 2;
export const TYPE_WELCOME = 2;
export const TYPE_DATA = 3;
export const TYPE_HELLO = 4;
export const TYPE_RETRY = 5;
export const CALL_ID_LEN = 8;
export const INSTANCE_LEN = 8;
export const MAX_OFFERS = 8;
export const MAX_DATAGRAM = 32768;
export const MAX_CHANNEL_NAME = 255;
export const DATA_HEADER_LEN = 18;
export const TAG_LEN = 16;
/** The largest DATA frame: header, a full datagram with the longest name, tag. */
export const MAX_FRAME = DATA_HEADER_LEN + 3 + MAX_CHANNEL_NAME + MAX_DATAGRAM + TAG_LEN;
/** The largest BUNDLE plaintext: that of the largest single datagram. */
export const MAX_BUNDLE = 3 + MAX_CHANNEL_NAME + MAX_DATAGRAM;
export const MAX_NOISE_MESSAGE = 2048;
export const KIND_DATAGRAM = 1;
export const KIND_HEARTBEAT = 2;
export const KIND_HANGUP = 3;
export const KIND_BUNDLE = 4;
export const FLAG_TEXT = 1;
const HEARTBEAT_LEN = 25;
const NAME_PATTERN = /^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$/;

/**
 * Check a robot or user name (a zenoh key chunk, §1); returns it or throws ProtocolError.
 * @param {string} name @param {string} [what] @returns {string}
 */
export function validateName(name, what = "name") {
  if (typeof name !== "string" || !NAME_PATTERN.test(name)) {
    const shown = typeof name === "string" ? JSON.stringify(name.slice(0, 70)) : typeof name;
    throw new ProtocolError(
      `invalid ${what} ${shown}: use 1-64 letters, digits, '.', '_' or '-', starting with a letter or digit`,
    );
  }
  return name;
}

/**
 * A channel name's UTF-8 bytes; ProtocolError when empty or over 255 bytes.
 * @param {string} name @returns {Uint8Array}
 */
export function channelNameBytes(name) {
  if (typeof name !== "string" || !name) throw new ProtocolError("a channel name is a non-empty string");
  const encoded = utf8(name);
  if (encoded.length > MAX_CHANNEL_NAME) {
    throw new ProtocolError(`channel name longer than ${MAX_CHANNEL_NAME} bytes`);
  }
  return encoded;
}

/**
 * @typedef {{type: "hello", callId: Uint8Array, caller: string, instance: Uint8Array,
 *   suite: number, offers: number[], noiseMessage: Uint8Array, prologue: Uint8Array}} Hello
 * @typedef {{type: "welcome", callId: Uint8Array, noiseMessage: Uint8Array}} Welcome
 * @typedef {{type: "data", callId: Uint8Array, counter: bigint, header: Uint8Array,
 *   ciphertext: Uint8Array}} DataFrame
 * @typedef {{type: "retry", callId: Uint8Array, suite: number}} Retry
 * @typedef {Hello|Welcome|DataFrame|Retry} Frame
 */

/**
 * The HELLO header, which is also the Noise prologue (§4.2).
 * @param {{callId: Uint8Array, caller: string, instance: Uint8Array, suite: number, offers: number[]}} h
 * @returns {Uint8Array}
 */
export function helloPrologue({ callId, caller, instance, suite, offers }) {
  validateName(caller, "caller name");
  if (callId.length !== CALL_ID_LEN || instance.length !== INSTANCE_LEN) {
    throw new ProtocolError("call id and instance are 8 bytes each");
  }
  checkOffers(offers, suite);
  const name = utf8(caller);
  return concat(
    Uint8Array.of(VERSION, TYPE_HELLO),
    callId,
    Uint8Array.of(name.length),
    name,
    instance,
    Uint8Array.of(suite, offers.length),
    Uint8Array.from(offers),
  );
}

/** @param {number[]} offers @param {number} suite */
function checkOffers(offers, suite) {
  const valid =
    offers.length >= 1 &&
    offers.length <= MAX_OFFERS &&
    new Set(offers).size === offers.length &&
    offers.every((n) => Number.isInteger(n) && n >= 1 && n <= 255);
  if (!valid) throw new ProtocolError(`invalid list of cipher suites [${offers.slice(0, 9)}]`);
  if (!offers.includes(suite)) {
    throw new ProtocolError(`HELLO written with cipher suite ${suite}, which it does not offer`);
  }
}

/**
 * The 18-byte DATA header (also the AEAD's associated data).
 * @param {Uint8Array} callId @param {bigint} counter @returns {Uint8Array}
 */
export function dataHeader(callId, counter) {
  const header = new Uint8Array(DATA_HEADER_LEN);
  header[0] = VERSION;
  header[1] = TYPE_DATA;
  header.set(callId, 2);
  new DataView(header.buffer).setBigUint64(10, counter);
  return header;
}

/** @param {Uint8Array} callId @param {Uint8Array} noiseMessage @returns {Uint8Array} */
export function encodeWelcome(callId, noiseMessage) {
  return concat(Uint8Array.of(VERSION, TYPE_WELCOME), callId, noiseMessage);
}

/** @param {Uint8Array} callId @param {number} suite @returns {Uint8Array} */
export function encodeRetry(callId, suite) {
  return concat(Uint8Array.of(VERSION, TYPE_RETRY), callId, Uint8Array.of(suite));
}

/**
 * Parse an outer frame (§4); ProtocolError when it is not one.
 * @param {Uint8Array} data @returns {Frame}
 */
export function decodeFrame(data) {
  if (!(data instanceof Uint8Array)) throw new ProtocolError("a frame is bytes");
  if (data.length < 2 + CALL_ID_LEN) throw new ProtocolError(`frame too short (${data.length} bytes)`);
  if (data.length > MAX_FRAME) throw new ProtocolError(`frame too long (${data.length} bytes)`);
  const version = data[0];
  const kind = data[1];
  if (version !== VERSION) throw new ProtocolError(`unsupported protocol version ${version}`);
  const callId = data.slice(2, 10);
  if (kind === TYPE_DATA) {
    if (data.length < DATA_HEADER_LEN + TAG_LEN) throw new ProtocolError("DATA frame too short");
    const counter = new DataView(data.buffer, data.byteOffset, data.length).getBigUint64(10);
    return {
      type: "data",
      callId,
      counter,
      header: data.slice(0, DATA_HEADER_LEN),
      ciphertext: data.slice(DATA_HEADER_LEN),
    };
  }
  if (kind === TYPE_HELLO) return decodeHello(data, callId);
  if (kind === TYPE_RETRY) {
    if (data.length !== 2 + CALL_ID_LEN + 1) throw new ProtocolError("RETRY frame of the wrong size");
    return { type: "retry", callId, suite: data[10] };
  }
  if (kind === TYPE_WELCOME) {
    const noiseMessage = data.slice(10);
    if (!noiseMessage.length || noiseMessage.length > MAX_NOISE_MESSAGE) {
      throw new ProtocolError("WELCOME handshake message missing or too long");
    }
    return { type: "welcome", callId, noiseMessage };
  }
  throw new ProtocolError(`unknown frame type ${kind}`);
}

/** @param {Uint8Array} data @param {Uint8Array} callId @returns {Hello} */
function decodeHello(data, callId) {
  const nameLen = data[10];
  const nameEnd = 11 + nameLen;
  const suiteAt = nameEnd + INSTANCE_LEN;
  if (data.length < suiteAt + 2) throw new ProtocolError("HELLO frame truncated");
  let caller;
  try {
    caller = validateName(fromUtf8(data.subarray(11, nameEnd), "caller name"), "caller name");
  } catch {
    throw new ProtocolError("HELLO frame with an invalid caller name");
  }
  const suite = data[suiteAt];
  const offerLen = data[suiteAt + 1];
  const noiseStart = suiteAt + 2 + offerLen;
  if (data.length <= noiseStart) throw new ProtocolError("HELLO frame truncated");
  const offers = Array.from(data.subarray(suiteAt + 2, noiseStart));
  if (offerLen < 1 || offerLen > MAX_OFFERS || new Set(offers).size !== offerLen || offers.includes(0)) {
    throw new ProtocolError(`HELLO with an invalid list of cipher suites [${offers.slice(0, 9)}]`);
  }
  if (!offers.includes(suite)) {
    throw new ProtocolError(`HELLO written with cipher suite ${suite}, which it does not offer`);
  }
  const noiseMessage = data.slice(noiseStart);
  if (noiseMessage.length > MAX_NOISE_MESSAGE) throw new ProtocolError("HELLO handshake message too long");
  return {
    type: "hello",
    callId,
    caller,
    instance: data.slice(nameEnd, suiteAt),
    suite,
    offers,
    noiseMessage,
    prologue: data.slice(0, noiseStart),
  };
}

// ------------------------------------------------------------------ messages inside DATA

/**
 * @typedef {{kind: "datagram", channel: string, payload: string|Uint8Array, text: boolean}} Datagram
 * @typedef {{kind: "heartbeat", seq: number, sentUs: bigint, echoUs: bigint, echoDelayUs: number}} Heartbeat
 * @typedef {{kind: "hangup", reason: string}} Hangup
 * @typedef {{kind: "bundle", datagrams: Datagram[]}} Bundle
 * @typedef {Datagram|Heartbeat|Hangup|Bundle} Message
 */

/**
 * Plaintext of a DATAGRAM: a string goes as UTF-8 with the TEXT flag, bytes as they are.
 * Throws ProtocolError before anything is sent if the payload is over 32,768 bytes.
 * @param {string} channel @param {string|Uint8Array} payload @returns {Uint8Array}
 */
export function encodeDatagram(channel, payload) {
  const name = channelNameBytes(channel);
  let body;
  let flags;
  if (typeof payload === "string") {
    body = utf8(payload);
    flags = FLAG_TEXT;
  } else if (payload instanceof Uint8Array) {
    body = payload;
    flags = 0;
  } else {
    throw new ProtocolError("a datagram is a string or a Uint8Array");
  }
  if (body.length > MAX_DATAGRAM) {
    throw new ProtocolError(`datagram of ${body.length} bytes is larger than the ${MAX_DATAGRAM}-byte limit`);
  }
  return concat(Uint8Array.of(KIND_DATAGRAM, flags, name.length), name, body);
}

/**
 * Plaintext of a BUNDLE of DATAGRAM plaintexts (§6.4): at least two, at most MAX_BUNDLE.
 * @param {Uint8Array[]} datagrams @returns {Uint8Array}
 */
export function encodeBundle(datagrams) {
  if (datagrams.length < 2) throw new ProtocolError("a BUNDLE carries at least two datagrams");
  const parts = [Uint8Array.of(KIND_BUNDLE)];
  for (const d of datagrams) {
    if (d.length < 1 || d.length > 0xffff || d[0] !== KIND_DATAGRAM) {
      throw new ProtocolError("a BUNDLE entry is a DATAGRAM");
    }
    parts.push(Uint8Array.of(d.length >> 8, d.length & 0xff), d);
  }
  const plaintext = concat(...parts);
  if (plaintext.length > MAX_BUNDLE) {
    throw new ProtocolError(`BUNDLE of ${plaintext.length} bytes is over ${MAX_BUNDLE}`);
  }
  return plaintext;
}

/**
 * Plaintext of a HEARTBEAT (§6.2); fields are masked to their widths, the delay clamped.
 * @param {{seq: number, sentUs: bigint, echoUs: bigint, echoDelayUs: number}} beat
 * @returns {Uint8Array}
 */
export function encodeHeartbeat({ seq, sentUs, echoUs, echoDelayUs }) {
  const out = new Uint8Array(HEARTBEAT_LEN);
  const view = new DataView(out.buffer);
  const mask = 0xffffffffffffffffn;
  out[0] = KIND_HEARTBEAT;
  view.setUint32(1, seq >>> 0);
  view.setBigUint64(5, BigInt(sentUs) & mask);
  view.setBigUint64(13, BigInt(echoUs) & mask);
  view.setUint32(21, Math.min(Math.max(Math.trunc(echoDelayUs), 0), 0xffffffff));
  return out;
}

/**
 * Plaintext of a HANGUP; the reason is cut to 200 UTF-8 bytes on a character boundary.
 * @param {string} reason @returns {Uint8Array}
 */
export function encodeHangup(reason) {
  let encoded = utf8(reason);
  if (encoded.length > 200) {
    let end = 200;
    while (end > 0 && (encoded[end] & 0xc0) === 0x80) end--; // not inside a character
    encoded = encoded.slice(0, end);
  }
  return concat(Uint8Array.of(KIND_HANGUP), encoded);
}

/** @param {Uint8Array} plaintext @param {number} start @param {number} end @returns {Datagram} */
function decodeDatagram(plaintext, start, end) {
  if (end - start < 3) throw new ProtocolError("DATAGRAM truncated");
  const flags = plaintext[start + 1];
  const nameLen = plaintext[start + 2];
  if (flags & ~FLAG_TEXT) throw new ProtocolError(`DATAGRAM with unknown flags 0x${flags.toString(16)}`);
  const nameEnd = start + 3 + nameLen;
  if (nameLen === 0 || end < nameEnd) throw new ProtocolError("DATAGRAM with a missing or truncated channel name");
  if (end - nameEnd > MAX_DATAGRAM) throw new ProtocolError("DATAGRAM payload over the limit");
  const channel = fromUtf8(plaintext.subarray(start + 3, nameEnd), "DATAGRAM channel name");
  const body = plaintext.slice(nameEnd, end);
  if (flags & FLAG_TEXT) {
    return { kind: "datagram", channel, payload: fromUtf8(body, "DATAGRAM text"), text: true };
  }
  return { kind: "datagram", channel, payload: body, text: false };
}

/** @param {Uint8Array} plaintext @returns {Bundle} */
function decodeBundle(plaintext) {
  if (plaintext.length > MAX_BUNDLE) throw new ProtocolError("BUNDLE over the limit");
  const datagrams = [];
  let position = 1;
  const total = plaintext.length;
  while (position < total) {
    if (total - position < 2) throw new ProtocolError("BUNDLE entry length truncated");
    const length = (plaintext[position] << 8) | plaintext[position + 1];
    const start = position + 2;
    const end = start + length;
    if (end > total) throw new ProtocolError("BUNDLE entry truncated");
    if (length === 0 || plaintext[start] !== KIND_DATAGRAM) throw new ProtocolError("BUNDLE entry is not a DATAGRAM");
    datagrams.push(decodeDatagram(plaintext, start, end));
    position = end;
  }
  if (datagrams.length < 2) throw new ProtocolError("BUNDLE with fewer than two datagrams");
  return { kind: "bundle", datagrams };
}

/**
 * Parse a DATA frame's plaintext (§6); ProtocolError when malformed.
 * @param {Uint8Array} plaintext @returns {Message}
 */
export function decodeMessage(plaintext) {
  if (!(plaintext instanceof Uint8Array)) throw new ProtocolError("a message is bytes");
  if (!plaintext.length) throw new ProtocolError("empty message");
  const kind = plaintext[0];
  if (kind === KIND_DATAGRAM) return decodeDatagram(plaintext, 0, plaintext.length);
  if (kind === KIND_BUNDLE) return decodeBundle(plaintext);
  if (kind === KIND_HEARTBEAT) {
    if (plaintext.length !== HEARTBEAT_LEN) throw new ProtocolError("HEARTBEAT of the wrong size");
    const view = new DataView(plaintext.buffer, plaintext.byteOffset, plaintext.length);
    return {
      kind: "heartbeat",
      seq: view.getUint32(1),
      sentUs: view.getBigUint64(5),
      echoUs: view.getBigUint64(13),
      echoDelayUs: view.getUint32(21),
    };
  }
  if (kind === KIND_HANGUP) {
    return { kind: "hangup", reason: fromUtf8(plaintext.subarray(1), "HANGUP reason") };
  }
  throw new ProtocolError(`unknown message kind ${kind}`);
}
