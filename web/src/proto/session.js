/**
 * The user side of a call, sans-IO (docs/protocol.md §5.7, §6–§8): bytes and `now`
 * (seconds on a monotonic clock) in, bytes to publish and facts out. The driver
 * (call.js) does the I/O and the timers.
 *
 * - {@link CallSetup}: the HELLO, its repeats every 0.25 s, RETRY, the WELCOME (accepted
 *   or refused), the connect timeout.
 * - {@link CallSession}: an established call: seal/open with counters and the replay
 *   window, heartbeats (rtt, loss), hang-up, drop detection.
 * @module proto/session
 */
import {
  CallEnded,
  CallError,
  CallRejected,
  CallTimeout,
  KeyMismatch,
  ProtocolError,
} from "../errors.js";
import { equalBytes, fromUtf8, utf8 } from "../bytes.js";
import {
  DATA_HEADER_LEN,
  TAG_LEN,
  dataHeader,
  decodeFrame,
  decodeMessage,
  encodeDatagram,
  encodeHangup,
  encodeHeartbeat,
  helloPrologue,
  validateName,
} from "./frames.js";
import { AuthenticationError, InitiatorHandshake, SUITE_LABELS, SUITE_NUMBERS, aead } from "./noise.js";
import { ReplayWindow } from "./replay.js";
import { decodeKey } from "../identity.js";

/** Seconds between two copies of a HELLO (§5.7). */
export const HELLO_REPEAT = 0.25;
/** Frames on a call's keys kept until its WELCOME is handled (§2.1). */
export const EARLY_FRAMES = 64;
const LOSS_WINDOW = 40;
const MAX_COUNTER = 2n ** 64n - 1n;

/**
 * Suite numbers from labels, preferred first; ProtocolError on an unknown or repeated one.
 * @param {string[]} labels @returns {number[]}
 */
export function suiteNumbers(labels) {
  if (!Array.isArray(labels) || !labels.length) throw new ProtocolError("suites: give at least one of aesgcm, chachapoly");
  const numbers = labels.map((label) => {
    const n = SUITE_NUMBERS[label];
    if (!n) throw new ProtocolError(`unknown cipher suite ${JSON.stringify(String(label).slice(0, 40))}: use aesgcm or chachapoly`);
    return n;
  });
  if (new Set(numbers).size !== numbers.length) throw new ProtocolError("suites: each suite once");
  return numbers;
}

/** @param {number} n */
function label(n) {
  return SUITE_LABELS[n] ?? `suite ${n}`;
}

/**
 * The HELLO payload p1, written as Python's json.dumps does (§5.6); `ts` is exact.
 * @param {string} user @param {bigint} ts @returns {Uint8Array}
 */
export function helloPayload(user, ts) {
  return utf8(`{"user": ${JSON.stringify(user)}, "ts": ${BigInt(ts).toString()}}`);
}

/**
 * Build a HELLO frame and its handshake state (§5.3, §5.7 step 3).
 * @param {{staticPrivate: Uint8Array, robotPublic: Uint8Array, caller: string,
 *   instance: Uint8Array, callId: Uint8Array, wallTimeNs: bigint, offers: number[],
 *   suite?: number, ephemeralPrivate?: Uint8Array}} o
 * @returns {{hello: Uint8Array, handshake: InitiatorHandshake}}
 */
export function buildHello(o) {
  const suite = o.suite ?? o.offers[0];
  const prologue = helloPrologue({ callId: o.callId, caller: o.caller, instance: o.instance, suite, offers: o.offers });
  const handshake = new InitiatorHandshake({
    staticPrivate: o.staticPrivate,
    responderStatic: o.robotPublic,
    prologue,
    suite,
    ephemeralPrivate: o.ephemeralPrivate,
  });
  const message = handshake.writeMessage(helloPayload(o.caller, o.wallTimeNs));
  const hello = new Uint8Array(prologue.length + message.length);
  hello.set(prologue);
  hello.set(message, prologue.length);
  return { hello, handshake };
}

/**
 * @typedef {{accepted: boolean, robot: string, role: string, reason: string}} Answer
 */

/**
 * Authenticate a WELCOME's Noise message and validate p2 (§5.6, §5.7 step 5). Throws
 * AuthenticationError or ProtocolError; the handshake state is left as it was.
 * @param {InitiatorHandshake} handshake @param {Uint8Array} noiseMessage
 * @returns {{answer: Answer, keys: import("./noise.js").TransportKeys}}
 */
export function readWelcome(handshake, noiseMessage) {
  const { payload, keys } = handshake.readMessage(noiseMessage);
  let data;
  try {
    data = JSON.parse(fromUtf8(payload, "WELCOME payload"));
  } catch {
    throw new ProtocolError("WELCOME payload is not JSON");
  }
  if (typeof data !== "object" || data === null || Array.isArray(data)) {
    throw new ProtocolError("WELCOME payload is not a JSON object");
  }
  const { accepted, robot, role = "", reason = "" } = data;
  if (typeof accepted !== "boolean" || typeof robot !== "string") {
    throw new ProtocolError("WELCOME payload lacks 'accepted' or 'robot'");
  }
  if (typeof role !== "string" || typeof reason !== "string") {
    throw new ProtocolError("WELCOME payload has a non-text 'role' or 'reason'");
  }
  return { answer: { accepted, robot, role, reason }, keys };
}

/**
 * KEY MISMATCH (§2.2): the robot is online only with other keys than the stored one.
 * `tokens` maps the last chunk of `{ns}/presence/robot/{robot}/*` keys to aliveness.
 * @param {string} robot @param {string} expected the stored key, 43 chars
 * @param {Map<string, boolean>} tokens @returns {KeyMismatch|null}
 */
export function checkRobotKey(robot, expected, tokens) {
  const alive = [...tokens].filter(([, up]) => up).map(([key]) => key);
  if (alive.includes(expected)) return null;
  const others = alive.filter(isKey).sort();
  if (!others.length) return null;
  return new KeyMismatch(
    `KEY MISMATCH: robot ${robot} is online with key ${others[0]} but known_robots has ${expected}`,
  );
}

/** @param {string} text */
function isKey(text) {
  try {
    decodeKey(text);
    return true;
  } catch {
    return false;
  }
}

/**
 * One call being set up, from the first HELLO to the WELCOME. Sans-IO.
 *
 * Use: `hello` is due at once; `poll(now)` says what to publish and whether the connect
 * timeout expired; `receive(frameBytes, sender)` takes what came on the inbox for this
 * call (the driver routes by call id).
 */
export class CallSetup {
  /**
   * @param {{staticPrivate: Uint8Array, robotPublic: Uint8Array, caller: string,
   *   robot: string, instance: Uint8Array, callId: Uint8Array, offers: number[],
   *   now: number, connectTimeout: number, wallTimeNs: () => bigint,
   *   ephemeral?: () => Uint8Array|undefined}} o
   *   `ephemeral` gives the ephemeral private key of each HELLO (tests; default random).
   */
  constructor(o) {
    validateName(o.robot, "robot name");
    this.o = o;
    this.robot = o.robot;
    this.callId = o.callId;
    this.deadline = o.now + o.connectTimeout;
    this.retried = false;
    /** @type {null|{kind: string, error?: Error}} */
    this.outcome = null;
    const built = buildHello({ ...o, wallTimeNs: o.wallTimeNs(), ephemeralPrivate: o.ephemeral?.() });
    /** The HELLO being repeated (another one after a RETRY). */
    this.hello = built.hello;
    this.handshake = built.handshake;
    this.nextSend = o.now;
    /** When the first HELLO went out (null: not yet). */
    this.firstSent = null;
  }

  /** The suite of the HELLO being repeated. */
  get suite() {
    return this.handshake.suite;
  }

  /**
   * What to do at `now`: a HELLO to publish (or null), and whether the call timed out.
   * @param {number} now @returns {{send: Uint8Array|null, expired: CallTimeout|null}}
   */
  poll(now) {
    if (this.outcome) return { send: null, expired: null };
    if (now >= this.deadline) {
      const seconds = Math.round(this.o.connectTimeout * 1000) / 1000;
      const error = new CallTimeout(`robot ${this.robot} did not answer within ${seconds} s (is it online?)`);
      this.outcome = { kind: "failed", error };
      return { send: null, expired: error };
    }
    if (now >= this.nextSend) {
      this.nextSend = now + HELLO_REPEAT;
      if (this.firstSent === null) this.firstSent = now;
      return { send: this.hello, expired: null };
    }
    return { send: null, expired: null };
  }

  /**
   * A presence token of the robot appeared (it started, or the link to it is back after
   * an outage): the next HELLO is due at once, not at the end of its 0.25 s (§5.7 step 4).
   * Tokens reported during the first 0.25 s are the watch's history of those already
   * there: no news.
   * @param {number} now
   */
  robotAppeared(now) {
    if (!this.outcome && this.firstSent !== null && now >= this.firstSent + HELLO_REPEAT) {
      this.nextSend = Math.min(this.nextSend, now);
    }
  }

  /** When `poll` next has something to do. */
  nextDeadline() {
    return Math.min(this.nextSend, this.deadline);
  }

  /** Fail the set-up with `error` (KEY MISMATCH, closing endpoint); idempotent. */
  fail(/** @type {Error} */ error) {
    if (!this.outcome) this.outcome = { kind: "failed", error };
  }

  /**
   * A frame from the inbox `…/in/{sender}` carrying this call's id.
   * Returns what happened:
   * - `{kind: "ignored", reason}`: dropped (counted by the driver under `reason`)
   * - `{kind: "resend", hello}`: after a RETRY: publish `hello` now (and repeat it)
   * - `{kind: "accepted", answer, keys}`: the call is up
   * - `{kind: "failed", error}`: the set-up ends with `error` (refusal, wrong robot, ...)
   * @param {Uint8Array} data @param {string} sender
   */
  receive(data, sender) {
    if (this.outcome) return { kind: "ignored", reason: "unexpected_welcome" };
    if (sender !== this.robot) return { kind: "ignored", reason: "sender_mismatch" };
    let frame;
    try {
      frame = decodeFrame(data);
    } catch {
      return { kind: "ignored", reason: "malformed" };
    }
    if (!equalBytes(frame.callId, this.callId)) return { kind: "ignored", reason: "unknown_call" };
    if (frame.type === "retry") return this.onRetry(frame.suite);
    if (frame.type !== "welcome") return { kind: "ignored", reason: "unexpected_frame" };
    let read;
    try {
      read = readWelcome(this.handshake, frame.noiseMessage);
    } catch (error) {
      return { kind: "ignored", reason: error instanceof AuthenticationError ? "forged" : "malformed" };
    }
    const { answer, keys } = read;
    if (answer.robot !== this.robot) {
      return this.finish(new CallError(`the robot with ${this.robot}'s key answered as ${JSON.stringify(answer.robot.slice(0, 70))}`));
    }
    if (!answer.accepted) {
      return this.finish(new CallRejected(answer.reason || `${this.robot} refused the call`));
    }
    this.outcome = { kind: "accepted" };
    return { kind: "accepted", answer, keys };
  }

  /** @param {Error} error */
  finish(error) {
    this.outcome = { kind: "failed", error };
    return { kind: "failed", error };
  }

  /** §5.2: write the HELLO again with the robot's pick, at most once. @param {number} suite */
  onRetry(suite) {
    if (suite === this.handshake.suite) return { kind: "ignored", reason: "retry_repeated" };
    if (!this.o.offers.includes(suite)) return { kind: "ignored", reason: "unexpected_retry" };
    if (this.retried) {
      return this.finish(
        new CallError(
          `cipher suite negotiation with ${this.robot} failed: it asked for ${label(this.handshake.suite)}, then ${label(suite)}`,
        ),
      );
    }
    this.retried = true;
    const built = buildHello({ ...this.o, suite, wallTimeNs: this.o.wallTimeNs(), ephemeralPrivate: this.o.ephemeral?.() });
    this.hello = built.hello;
    this.handshake = built.handshake;
    return { kind: "resend", hello: this.hello };
  }
}

/** @typedef {{kind: "hung_up"|"dropped", detail: string, byPeer: boolean}} CallEnd */

/**
 * One established call, the user's side: sealing, opening, heartbeats, the end. Sans-IO.
 */
export class CallSession {
  /**
   * @param {{callId: Uint8Array, keys: import("./noise.js").TransportKeys, peer: string,
   *   now: number, heartbeatInterval?: number, timeout?: number}} o
   */
  constructor({ callId, keys, peer, now, heartbeatInterval = 0.05, timeout = 0.5 }) {
    this.callId = callId;
    this.peer = peer;
    this.suite = keys.suite;
    this.sealer = aead(keys.suite, keys.sendKey);
    this.opener = aead(keys.suite, keys.receiveKey);
    this.replay = new ReplayWindow();
    this.prefix = dataHeader(callId, 0n).subarray(0, 10);
    this.sendCounter = 0n;
    this.heartbeatInterval = heartbeatInterval;
    this.timeout = timeout;
    this.lastHeard = now;
    this.nextHeartbeat = now;
    this.heartbeatSeq = 0;
    /** @type {null|{sentUs: bigint, at: number}} the peer's latest heartbeat */
    this.peerBeat = null;
    /** @type {number[]} */
    this.peerSeqs = [];
    /** @type {CallEnd|null} */
    this.ended = null;
    this.stats = {
      framesSent: 0,
      framesReceived: 0,
      /** @type {number|null} latest round-trip time, seconds */
      rtt: null,
      loss: 0,
      /** @type {Record<string, number>} drops by reason */
      rejected: {},
      unrouted: 0,
    };
  }

  /** @param {string} reason */
  reject(reason) {
    this.stats.rejected[reason] = (this.stats.rejected[reason] ?? 0) + 1;
  }

  /**
   * A DATA frame carrying `plaintext` under the next counter.
   * @param {Uint8Array} plaintext @returns {Uint8Array}
   */
  seal(plaintext) {
    if (this.ended) throw new CallEnded(`the call with ${this.peer} ${describeEnd(this.ended)}`);
    const counter = this.sendCounter;
    if (counter >= MAX_COUNTER) throw new ProtocolError("call counter exhausted");
    this.sendCounter = counter + 1n;
    const header = dataHeader(this.callId, counter);
    const sealed = this.sealer.seal(counter, plaintext, header);
    const frame = new Uint8Array(header.length + sealed.length);
    frame.set(header);
    frame.set(sealed, header.length);
    this.stats.framesSent += 1;
    return frame;
  }

  /**
   * A DATA frame with one datagram; CallEnded when the call is over, ProtocolError when
   * the payload is too large (nothing is sent then).
   * @param {string} channel @param {string|Uint8Array} payload
   */
  sealDatagram(channel, payload) {
    return this.seal(encodeDatagram(channel, payload));
  }

  /**
   * Heartbeat and drop timing at `now`: a heartbeat frame to publish on CONTROL if one
   * is due, and the call's end if the peer was silent for longer than the timeout.
   * @param {number} now @returns {{heartbeat: Uint8Array|null, ended: CallEnd|null}}
   */
  tick(now) {
    if (this.ended) return { heartbeat: null, ended: null };
    const silence = now - this.lastHeard;
    if (silence > this.timeout) {
      this.ended = { kind: "dropped", byPeer: true, detail: `nothing from ${this.peer} for ${silence.toFixed(2)} s` };
      return { heartbeat: null, ended: this.ended };
    }
    if (now < this.nextHeartbeat) return { heartbeat: null, ended: null };
    // Keep the cadence; after a stall start afresh rather than send a burst.
    this.nextHeartbeat += this.heartbeatInterval;
    if (this.nextHeartbeat <= now) this.nextHeartbeat = now + this.heartbeatInterval;
    let echoUs = 0n;
    let echoDelayUs = 0;
    if (this.peerBeat) {
      echoUs = this.peerBeat.sentUs;
      echoDelayUs = Math.trunc((now - this.peerBeat.at) * 1e6);
    }
    this.heartbeatSeq = (this.heartbeatSeq + 1) >>> 0;
    const beat = { seq: this.heartbeatSeq, sentUs: BigInt(Math.trunc(now * 1e6)), echoUs, echoDelayUs };
    return { heartbeat: this.seal(encodeHeartbeat(beat)), ended: null };
  }

  /** When `tick` may next have something to do. */
  nextDeadline() {
    return Math.min(this.nextHeartbeat, this.lastHeard + this.timeout);
  }

  /**
   * A frame that came on one of this call's keys. Returns the datagrams it carries (a
   * BUNDLE's one by one), and the call's end if it was a HANGUP. Anything that fails is
   * dropped and counted (`not_this_call`, `replayed`, `forged`, `malformed`).
   * @param {Uint8Array} data @param {number} now
   * @returns {{datagrams: import("./frames.js").Datagram[], ended: CallEnd|null}}
   */
  receive(data, now) {
    const none = { datagrams: [], ended: null };
    if (this.ended) return none;
    if (data.length < DATA_HEADER_LEN + TAG_LEN || !equalBytes(data.subarray(0, 10), this.prefix) || data.length > 33060) {
      this.reject("not_this_call");
      return none;
    }
    const counter = new DataView(data.buffer, data.byteOffset, data.length).getBigUint64(10);
    if (!this.replay.check(counter)) {
      this.reject("replayed");
      return none;
    }
    let plaintext;
    try {
      plaintext = this.opener.open(counter, data.subarray(DATA_HEADER_LEN), data.subarray(0, DATA_HEADER_LEN));
    } catch {
      this.reject("forged");
      return none;
    }
    // Authentic: a sign of life even if the content is unusable.
    this.replay.accept(counter);
    this.lastHeard = Math.max(this.lastHeard, now);
    this.stats.framesReceived += 1;
    let message;
    try {
      message = decodeMessage(plaintext);
    } catch {
      this.reject("malformed");
      return none;
    }
    switch (message.kind) {
      case "datagram":
        return { datagrams: [message], ended: null };
      case "bundle":
        return { datagrams: message.datagrams, ended: null };
      case "heartbeat":
        this.onHeartbeat(message, now);
        return none;
      case "hangup":
        this.ended = { kind: "hung_up", byPeer: true, detail: message.reason || "hung up" };
        return { datagrams: [], ended: this.ended };
    }
    return none;
  }

  /** @param {import("./frames.js").Heartbeat} beat @param {number} now */
  onHeartbeat(beat, now) {
    this.peerBeat = { sentUs: beat.sentUs, at: now };
    this.peerSeqs.push(beat.seq);
    if (this.peerSeqs.length > LOSS_WINDOW) this.peerSeqs.shift();
    const span = Math.max(...this.peerSeqs) - Math.min(...this.peerSeqs) + 1;
    this.stats.loss = Math.max(0, 1 - this.peerSeqs.length / span);
    if (beat.echoUs !== 0n) {
      const rtt = now - (Number(beat.echoUs) + beat.echoDelayUs) / 1e6;
      if (rtt >= 0 && rtt < 60) this.stats.rtt = rtt; // a garbled echo is ignored
    }
  }

  /**
   * Hang up: the one HANGUP frame to publish 3 times on CONTROL (§6.3), and the end.
   * Null if the call had already ended.
   * @param {string} reason @returns {Uint8Array|null}
   */
  hangup(reason) {
    if (this.ended) return null;
    const frame = this.seal(encodeHangup(reason));
    this.ended = { kind: "hung_up", byPeer: false, detail: reason };
    return frame;
  }

  /** The robot's presence token disappeared (§2.2): the call drops. */
  peerGone() {
    if (this.ended) return null;
    this.ended = { kind: "dropped", byPeer: true, detail: `${this.peer} went offline` };
    return this.ended;
  }
}

/** @param {CallEnd} end */
export function describeEnd(end) {
  if (end.kind === "dropped") return `dropped: ${end.detail}`;
  return `was hung up ${end.byPeer ? "by the peer" : "here"}: ${end.detail}`;
}
