/**
 * The topic relay on the user's side (docs/protocol.md §17.5), as the Python client's
 * `RelayReceiver` / `TopicStream` (src/telebot/services/relay.py): `list`, `start` and
 * `stop` on `relay` (JSON, DATA lane; repeated every 0.3 s until answered), the robot's
 * answers and its `ended`, and `relay/data` (BULK lane): CDR messages cut into §17.1
 * FRAGMENTs (codec 0x02, the stream number in decimal as the camera name), reassembled per
 * stream, the newest message winning. Data of a stream this side does not know is
 * answered with a `stop` (at most once a second per stream). Every stream ends with its
 * call. Driven by `tick(now)`; bad input is dropped and counted, never thrown.
 * @module services/relay
 */
import {
  CALL_ENDED,
  DecodeError,
  DropCounter,
  RESEND_AFTER,
  RequestFailed,
  callSafely,
  decodeObject,
  encodeObject,
  idCounter,
  requireInt,
  safeSend,
} from "./util.js";
import { CODEC_CDR, Reassembler, parseFragment } from "./video.js";

export const RELAY = "relay";
export const RELAY_DATA = "relay/data";
export const MAX_TOPIC_NAME = 256;
export const MAX_SCHEMA = 24_000;
export const MAX_PARTS = 64;
export const MAX_RATE = 1000;
export const MAX_TEXT = 2000;
export const MAX_NEAR = 10;
/** Messages a {@link TopicStream} holds for a slow reader (the oldest is dropped beyond). */
export const STREAM_QUEUE = 64;
/** Data for an unknown stream is answered with a stop at most this often (s). */
export const STRAY_STOP_EVERY = 1.0;
/** Streams whose stray stop time is remembered. */
const STRAY_KEEP = 256;
const WHAT = "relay message";

/** A start the robot refused: `code` (§13.1: `unknown_topic`, `topic_not_allowed`, …), `near` names. */
export class RelayRefused extends Error {
  constructor(message, code, near = []) {
    super(message);
    this.name = "RelayRefused";
    this.code = code;
    this.near = near;
  }
}

function codePoints(value) {
  let n = 0;
  for (const _ of value) n += 1; // eslint-disable-line no-unused-vars
  return n;
}

function textField(msg, key, limit, { empty = false } = {}) {
  const value = msg[key];
  if (typeof value !== "string" || (value.length > limit && codePoints(value) > limit) || (!empty && !value)) {
    throw new DecodeError(`${WHAT}: '${key}' must be text of ${empty ? "0" : "1"}..${limit} characters`);
  }
  return value;
}

function topicInfo(value) {
  if (value === null || typeof value !== "object" || Array.isArray(value)) {
    throw new DecodeError(`${WHAT}: a topic must be a JSON object`);
  }
  return {
    name: textField(value, "name", MAX_TOPIC_NAME),
    type: textField(value, "type", MAX_TOPIC_NAME),
    schema: textField(value, "schema", MAX_SCHEMA, { empty: true }),
    encoding: textField(value, "encoding", 32),
  };
}

const streamNumber = (msg) => requireInt(msg, "stream", WHAT, 1, 2 ** 31 - 1);

/**
 * One datagram of `relay` from the robot (§17.5): `topics`, `started`, `refused`,
 * `stopped` or `ended`, checked as the Python decoder does; DecodeError otherwise.
 * @param {string|Uint8Array} payload
 */
export function decodeRelayMessage(payload) {
  const msg = decodeObject(payload, WHAT);
  const type = msg.type;
  if (type === "ended") return { type, stream: streamNumber(msg), text: textField(msg, "text", MAX_TEXT, { empty: true }) };
  const id = requireInt(msg, "id", WHAT);
  switch (type) {
    case "topics": {
      const parts = requireInt(msg, "parts", WHAT, 1, MAX_PARTS);
      const part = requireInt(msg, "part", WHAT, 0, parts - 1);
      if (!Array.isArray(msg.topics)) throw new DecodeError(`${WHAT}: 'topics' must be a list`);
      return { type, id, part, parts, topics: msg.topics.map(topicInfo) };
    }
    case "started":
      return { type, id, stream: streamNumber(msg), topic: topicInfo(msg.topic) };
    case "refused": {
      const near = msg.near ?? [];
      if (!Array.isArray(near) || near.length > MAX_NEAR) throw new DecodeError(`${WHAT}: 'near' must be a list of at most ${MAX_NEAR} names`);
      return {
        type, id, code: textField(msg, "code", 64), text: textField(msg, "text", MAX_TEXT, { empty: true }),
        near: near.map((n) => textField({ n }, "n", MAX_TOPIC_NAME)),
      };
    }
    case "stopped":
      return {
        type, id, stream: streamNumber(msg),
        sent: requireInt(msg, "sent", WHAT, 0, 2 ** 53 - 1), dropped: requireInt(msg, "dropped", WHAT, 0, 2 ** 53 - 1),
      };
    default:
      throw new DecodeError(`${WHAT}: unexpected type ${JSON.stringify(String(type)).slice(0, 40)}`);
  }
}

/** A `start` request (`rate`: messages/s in (0, 1000], or null: as they come). */
export function encodeStart(id, topic, rate = null, latestOnly = false) {
  if (typeof topic !== "string" || !topic || codePoints(topic) > MAX_TOPIC_NAME) throw new RangeError("a topic name is 1..256 characters");
  if (rate !== null && !(typeof rate === "number" && Number.isFinite(rate) && rate > 0 && rate <= MAX_RATE)) {
    throw new RangeError(`rate must be null or a number in (0, ${MAX_RATE}]`);
  }
  return encodeObject({ type: "start", id, topic, rate, latest_only: Boolean(latestOnly) });
}

/** A `stop` request. */
export function encodeStop(id, stream) {
  return encodeObject({ type: "stop", id, stream });
}

/** The stream number a `relay/data` fragment's name carries, or null (§17.5). */
export function streamOf(camera) {
  if (!/^[0-9]{1,32}$/.test(camera)) return null;
  const value = Number(camera);
  return value >= 1 && value < 2 ** 31 ? value : null;
}

/**
 * One relayed topic: `onmessage({topic, type, data, stamp})` (CDR bytes as on the robot;
 * `stamp` the robot's Unix seconds when it had the message), or `for await (const m of
 * stream)`; ends with the relay, the robot's `ended` or the call (`ended`, `endReason`,
 * `onend(reason)`). `close()` stops the relay.
 */
export class TopicStream {
  constructor(info, stream, { latestOnly = false, service = null } = {}) {
    /** {name, type, schema, encoding} */
    this.info = info;
    /** The robot's number of this relay. */
    this.stream = stream;
    this.latestOnly = latestOnly;
    this.service = service;
    this.listener = null;
    this.onend = null;
    this.ended = false;
    this.endReason = "";
    this.received = 0;
    /** Messages dropped here because the reader was slow. */
    this.dropped = 0;
    /** Messages lost on the way (fragments missing), as the reassembler counts them. */
    this.incomplete = 0;
    this.queue = [];
    this.waiter = null;
  }

  /** The listener of each message; set, it first gets the messages queued so far. */
  get onmessage() {
    return this.listener;
  }

  set onmessage(fn) {
    this.listener = fn;
    while (fn && this.queue.length) callSafely(fn, this.queue.shift());
  }

  deliver(message) {
    if (this.ended) return;
    this.received += 1;
    if (this.listener) {
      callSafely(this.listener, message);
      return;
    }
    if (this.queue.length >= (this.latestOnly ? 1 : STREAM_QUEUE)) {
      this.queue.shift();
      this.dropped += 1;
    }
    this.queue.push(message);
    this.wake();
  }

  end(why) {
    if (this.ended) return;
    this.ended = true;
    this.endReason = why;
    callSafely(this.onend, why);
    this.wake();
  }

  wake() {
    const waiter = this.waiter;
    this.waiter = null;
    waiter?.();
  }

  /** Stop the relay (the robot is told; resolves with its `stopped` counters, or null). */
  close({ timeout = 2 } = {}) {
    if (!this.service) {
      this.end("closed");
      return Promise.resolve(null);
    }
    return this.service.stopStream(this, { timeout });
  }

  async *[Symbol.asyncIterator]() {
    for (;;) {
      if (this.queue.length) {
        yield this.queue.shift();
        continue;
      }
      if (this.ended) return;
      await new Promise((resolve) => {
        this.waiter = resolve;
      });
    }
  }
}

/** The `relay` and `relay/data` channels on one call. */
export class RelayService {
  constructor(theCall, { random = Math.random } = {}) {
    this.channel = theCall.channel(RELAY, { lane: "data" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.data = theCall.channel(RELAY_DATA, { lane: "bulk" });
    this.data.onmessage = (payload) => this.onData(payload);
    this.nextId = idCounter(random);
    /** id -> {payload, accept(msg) -> bool, resolve, reject, due, deadline} */
    this.pending = new Map();
    /** start request id -> latestOnly, while it waits (the stream is made as `started` comes). */
    this.pendingStarts = new Map();
    /** @type {Map<number, TopicStream>} */
    this.streams = new Map();
    /** @type {Map<number, Reassembler>} */
    this.reassemblers = new Map();
    this.strayStops = new Map();
    this.drops = new DropCounter();
    this.closed = false;
    this.now = 0;
  }

  request(payload, accept, { timeout, now = this.now }) {
    return new Promise((resolve, reject) => {
      const id = payload.id;
      this.pending.set(id, { payload: payload.text, accept, resolve, reject, due: now + RESEND_AFTER, deadline: now + timeout });
      safeSend(this.channel, payload.text);
    });
  }

  /** Resolves with [{name, type, schema, encoding}] (every part of one answer). */
  topics({ timeout = 5, now = this.now } = {}) {
    const id = this.nextId();
    let parts = null;
    return this.request({ id, text: encodeObject({ type: "list", id }) }, (msg) => {
      if (msg.type !== "topics") return false;
      if (!parts || parts.length !== msg.parts) parts = new Array(msg.parts).fill(null);
      parts[msg.part] = msg.topics;
      return parts.every((part) => part !== null) ? parts.flat() : false;
    }, { timeout, now });
  }

  /**
   * Relay `topic`: resolves with its {@link TopicStream}; rejects with
   * {@link RelayRefused} (`code` `unknown_topic` with `near`, `topic_not_allowed`, …) or
   * RequestFailed (no answer in `timeout` s, or the call ended).
   */
  start(topic, { rate = null, latestOnly = false, onMessage = null, timeout = 5, now = this.now } = {}) {
    const id = this.nextId();
    let text;
    try {
      text = encodeStart(id, topic, rate, latestOnly);
    } catch (err) {
      return Promise.reject(err);
    }
    this.pendingStarts.set(id, { latestOnly: Boolean(latestOnly), onMessage });
    const answer = this.request({ id, text }, (msg) => (msg.type === "started" || msg.type === "refused" ? msg : false), { timeout, now });
    return answer.then(
      (msg) => {
        this.pendingStarts.delete(id);
        if (msg.type === "refused") throw new RelayRefused(msg.text || `relay of ${topic} refused (${msg.code})`, msg.code, msg.near);
        let stream = this.streams.get(msg.stream);
        if (!stream) { // the call ended as the answer came
          stream = new TopicStream(msg.topic, msg.stream, { latestOnly, service: null });
          stream.end(CALL_ENDED);
        }
        return stream;
      },
      (err) => {
        this.pendingStarts.delete(id);
        throw err;
      },
    );
  }

  /** Stop `stream` (no more of its data is delivered); resolves with `stopped` or null. */
  stopStream(stream, { timeout = 2, now = this.now } = {}) {
    this.forget(stream);
    if (this.closed) return Promise.resolve(null);
    const id = this.nextId();
    return this.request({ id, text: encodeStop(id, stream.stream) }, (msg) => (msg.type === "stopped" ? msg : false), { timeout, now })
      .then((msg) => ({ sent: msg.sent, dropped: msg.dropped }), () => null);
  }

  /** Deliver nothing more to `stream`. */
  forget(stream) {
    if (this.streams.get(stream.stream) === stream) {
      this.streams.delete(stream.stream);
      this.reassemblers.delete(stream.stream);
    }
    stream.end("closed");
  }

  onMessage(payload) {
    let msg;
    try {
      msg = decodeRelayMessage(payload);
    } catch (err) {
      if (!(err instanceof DecodeError)) throw err;
      this.drops.add("malformed");
      return;
    }
    if (msg.type === "ended") {
      const stream = this.streams.get(msg.stream);
      if (stream) {
        this.streams.delete(msg.stream);
        this.reassemblers.delete(msg.stream);
        stream.end(msg.text || "the robot ended the relay");
      }
      return;
    }
    const p = this.pending.get(msg.id);
    if (msg.type === "started" && !this.streams.has(msg.stream)) {
      if (p && this.pendingStarts.has(msg.id)) {
        const { latestOnly, onMessage } = this.pendingStarts.get(msg.id);
        const stream = new TopicStream(msg.topic, msg.stream, { latestOnly, service: this });
        if (onMessage) stream.onmessage = onMessage;
        this.streams.set(msg.stream, stream);
      } else if (!p) {
        this.stopStray(msg.stream); // a start whose asker gave up: end the relay nobody reads
        return;
      }
    }
    if (!p) return;
    const result = p.accept(msg);
    if (result === false) return;
    this.pending.delete(msg.id);
    p.resolve(result);
  }

  onData(payload) {
    let frag;
    try {
      frag = parseFragment(payload, [CODEC_CDR]);
    } catch {
      this.drops.add("malformed_data");
      return;
    }
    const number = streamOf(frag.camera);
    const stream = number === null ? undefined : this.streams.get(number);
    if (!stream) {
      if (number !== null) this.stopStray(number);
      else this.drops.add("malformed_data");
      return;
    }
    let reassembler = this.reassemblers.get(number);
    if (!reassembler) {
      reassembler = new Reassembler({ codecs: [CODEC_CDR] });
      this.reassemblers.set(number, reassembler);
    }
    reassembler.poll(this.now);
    const complete = reassembler.onFragment(frag, this.now);
    stream.incomplete = reassembler.stats.incomplete;
    if (complete) stream.deliver({ topic: stream.info.name, type: stream.info.type, data: complete.data, stamp: complete.captureTime });
  }

  stopStray(number) {
    const last = this.strayStops.get(number);
    if (last !== undefined && this.now - last < STRAY_STOP_EVERY) return;
    this.strayStops.delete(number);
    this.strayStops.set(number, this.now);
    if (this.strayStops.size > STRAY_KEEP) this.strayStops.delete(this.strayStops.keys().next().value);
    safeSend(this.channel, encodeStop(this.nextId(), number));
  }

  tick(now) {
    this.now = now;
    for (const [number, reassembler] of this.reassemblers) {
      reassembler.poll(now);
      const stream = this.streams.get(number);
      if (stream) stream.incomplete = reassembler.stats.incomplete;
    }
    for (const [id, p] of this.pending) {
      if (now >= p.deadline) {
        this.pending.delete(id);
        p.reject(new RequestFailed("no answer", "timeout"));
      } else if (now >= p.due) {
        p.due = now + RESEND_AFTER;
        safeSend(this.channel, p.payload);
      }
    }
  }

  close() {
    this.closed = true;
    this.channel.onmessage = null;
    this.data.onmessage = null;
    for (const p of this.pending.values()) p.reject(new RequestFailed(CALL_ENDED, "call_ended"));
    this.pending.clear();
    for (const stream of this.streams.values()) stream.end(CALL_ENDED);
    this.streams.clear();
    this.reassemblers.clear();
  }
}
