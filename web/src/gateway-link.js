// The browser's link to zenoh: the gateway's WebSocket (docs/protocol.md §26).
//
// A link moves sealed frames by key; it holds the user's key only to answer the
// gateway's admission challenge (an X25519 + HMAC-SHA256 proof, §26.1). Everything the
// protocol seals is sealed above this module (call.js), never here.
//
//   const link = await connectGateway("wss://router:8443/gateway", { name, privateKey, publicKey });
//   const sub = link.subscribe("telebot/user/alice/**", (key, payload) => { ... });
//   link.publish("telebot/robot/guiabot/in/alice", hello, "control");
//   const token = link.declareToken("telebot/presence/user/alice/0123456789abcdef");
//   const watch = link.watch("telebot/presence/robot/*/*", (key, alive) => { ... });
//   link.onclose = ({ code, text }) => { ... };   // cut off, refused later, or closed
//   link.close();

import { x25519 } from "@noble/curves/ed25519";
import { hmac } from "@noble/hashes/hmac";
import { sha256 } from "@noble/hashes/sha2";
import { decodeKey as decodeIdentityKey, encodeKey } from "./identity.js";

/** Why the gateway refused, cut off or could not be reached: one line for people. */
export class GatewayError extends Error {
  /**
   * @param {string} message one line
   * @param {string} [code] the gateway's code ("wrong_key", "flood", ...), if it gave one
   */
  constructor(message, code = "") {
    super(message);
    this.name = "GatewayError";
    this.code = code;
  }
}

const LABEL = new TextEncoder().encode("telebot-gateway-v1");
const LANES = { control: 0, data: 1, bulk: 2 };
/** The lane byte's flag of a PUT that carries a copy id (§26.2). */
const COPY_FLAG = 0x80;
const MAX_ID = 0xffff;
/**
 * Bytes the websocket may hold unsent before DATA and BULK frames are dropped (the local
 * port's bound for pictures, src/telebot/apps/web/static/app.js): a STOP on CONTROL then
 * waits behind at most this much in the one TCP stream.
 */
export const MAX_BUFFERED = 256 * 1024;
/** The largest payload the gateway takes (a DATA frame with a 32 KB datagram). */
export const MAX_PAYLOAD = 33060;
const encoder = new TextEncoder();
const decoder = new TextDecoder();

/** @param {string} text at most a few hundred characters of it, on one line */
function excerpt(text, limit = 200) {
  const line = String(text).replace(/\s+/g, " ").trim();
  return line.length <= limit ? line : `${line.slice(0, limit - 1)}… (${line.length} characters)`;
}

/** A 32-byte key as 43 URL-safe base64 characters without padding (§3.1). */
export { encodeKey };

/**
 * The 32 bytes of a key in the form of {@link encodeKey}; GatewayError if it is not one.
 * @param {string} text
 */
export function decodeKey(text) {
  try {
    return decodeIdentityKey(text);
  } catch (err) {
    throw new GatewayError(excerpt(err?.message ?? err));
  }
}

/**
 * The admission proof (§26.1): HMAC-SHA256(X25519(user private, gateway ephemeral),
 * label ‖ nonce ‖ gateway ephemeral ‖ user public ‖ UTF-8(name)).
 * @param {Uint8Array} privateKey @param {Uint8Array} publicKey @param {string} name
 * @param {Uint8Array} gateway @param {Uint8Array} nonce
 */
export function admissionProof(privateKey, publicKey, name, gateway, nonce) {
  const shared = x25519.getSharedSecret(privateKey, gateway);
  const nameBytes = encoder.encode(name);
  const message = new Uint8Array(LABEL.length + 96 + nameBytes.length);
  message.set(LABEL, 0);
  message.set(nonce, LABEL.length);
  message.set(gateway, LABEL.length + 32);
  message.set(publicKey, LABEL.length + 64);
  message.set(nameBytes, LABEL.length + 96);
  return hmac(sha256, shared, message);
}

/** `https://host:port/` (the page's own address) or `wss://…/gateway` -> the websocket URL. */
function websocketUrl(url) {
  const parsed = new URL(url);
  if (parsed.protocol === "https:") parsed.protocol = "wss:";
  else if (parsed.protocol === "http:") parsed.protocol = "ws:";
  if (parsed.protocol !== "wss:" && parsed.protocol !== "ws:") {
    throw new GatewayError(`not a gateway address: ${excerpt(url, 120)}`);
  }
  if (!parsed.pathname.endsWith("/gateway")) parsed.pathname = parsed.pathname.replace(/\/?$/, "/gateway");
  parsed.hash = "";
  return parsed.toString();
}

/**
 * Open the gateway's websocket and be admitted (or redeem an invite, then be admitted).
 *
 * @param {string} url `wss://HOST:PORT/gateway`, or the page's `https://HOST:PORT/`
 * @param {{name: string, privateKey: Uint8Array, publicKey: Uint8Array, invite?: string,
 *          WebSocket?: typeof WebSocket, timeout?: number, maxBuffered?: number}} options
 *   `timeout`: seconds to wait for admission (default 10); `maxBuffered`: see {@link GatewayLink}
 * @returns {Promise<GatewayLink>} rejects with a GatewayError (one line) when refused
 */
export function connectGateway(url, options) {
  const { name, privateKey, publicKey, invite, timeout = 10, maxBuffered = MAX_BUFFERED } = options;
  const Impl = options.WebSocket ?? globalThis.WebSocket;
  if (!Impl) return Promise.reject(new GatewayError("this JavaScript runtime has no WebSocket"));
  let ws;
  try {
    ws = new Impl(websocketUrl(url));
  } catch (err) {
    return Promise.reject(err instanceof GatewayError ? err : new GatewayError(`cannot open ${excerpt(url, 120)}: ${excerpt(err?.message ?? err)}`));
  }
  ws.binaryType = "arraybuffer";
  return new Promise((resolve, reject) => {
    let stage = "challenge";
    const timer = setTimeout(() => fail(new GatewayError(`no admission by ${url} within ${timeout} s`, "timeout")), timeout * 1000);
    const fail = (error) => {
      if (stage === "done") return;
      stage = "done";
      clearTimeout(timer);
      try { ws.close(); } catch { /* closing anyway */ }
      reject(error);
    };
    ws.onerror = () => fail(new GatewayError(`cannot reach the gateway at ${excerpt(url, 120)}`, "unreachable"));
    ws.onclose = (event) => fail(new GatewayError(`the gateway closed the connection (${event.code})${event.reason ? `: ${excerpt(event.reason)}` : ""}`, event.reason || "closed"));
    ws.onmessage = (event) => {
      let message;
      try {
        if (typeof event.data !== "string") throw new Error("binary");
        message = JSON.parse(event.data);
      } catch {
        fail(new GatewayError("the gateway sent something that is not its protocol", "garbage"));
        return;
      }
      if (stage === "challenge" && message.op === "challenge") {
        let proof;
        try {
          proof = admissionProof(privateKey, publicKey, name, decodeKey(message.gateway), decodeKey(message.nonce));
        } catch (err) {
          fail(err instanceof GatewayError ? err : new GatewayError(`bad challenge: ${excerpt(err?.message ?? err)}`));
          return;
        }
        const answer = { op: invite ? "redeem" : "admit", name, key: encodeKey(publicKey), proof: encodeKey(proof) };
        if (invite) answer.invite = invite;
        ws.send(JSON.stringify(answer));
        stage = "answer";
      } else if (stage === "answer" && message.op === "admitted") {
        stage = "done";
        clearTimeout(timer);
        resolve(new GatewayLink(ws, name, message, { maxBuffered }));
      } else if (message.op === "refused") {
        fail(new GatewayError(`gateway refused ${name}: ${excerpt(message.code)}: ${excerpt(message.text)}`, String(message.code)));
      } else {
        fail(new GatewayError(`unexpected ${excerpt(String(message.op), 40)} during admission`, "garbage"));
      }
    };
  });
}

/**
 * An admitted gateway connection: the link a Call reaches zenoh through (BROWSER.md).
 * Frames the gateway sends that are not its protocol are dropped and counted
 * (`stats.malformed`), samples for a subscription closed meanwhile too (`stats.late`); the gateway's non-fatal errors go to `onerror`. Once closed (by
 * `close()`, or the gateway: `onclose` says why), whatever is sent is dropped and counted
 * (`stats.dropped`), as a lossy link drops frames: a call's timers need not know.
 *
 * Congestion: a DATA or BULK frame published while the websocket holds more than
 * `maxBuffered` bytes unsent (`ws.bufferedAmount`, default {@link MAX_BUFFERED}) is dropped
 * and counted (`stats.congested`), so the user's camera cannot queue without limit ahead
 * of a STOP; CONTROL frames are always sent. The amount is read at the first such frame of
 * a turn of the event loop and holds for the turn, so the fragments of one picture (sent in
 * one go) all go or none does, even a picture larger than the bound.
 */
export class GatewayLink {
  /**
   * @param {WebSocket} ws @param {string} name @param {object} admitted
   * @param {{maxBuffered?: number}} [options]
   */
  constructor(ws, name, admitted, { maxBuffered = MAX_BUFFERED } = {}) {
    this.ws = ws;
    this.name = name;
    this.admitted = admitted;
    /** @type {(info: {code: string, text: string, message: string}) => void} */
    this.onclose = () => {};
    /** @type {(message: string) => void} non-fatal errors the gateway reported */
    this.onerror = () => {};
    this.stats = { received: 0, malformed: 0, late: 0, sent: 0, dropped: 0, congested: 0 };
    this.maxBuffered = maxBuffered;
    /** @type {boolean|null} whether this turn's DATA/BULK frames are dropped (null: not read yet) */
    this.congestedTurn = null;
    this.closed = false;
    /** @type {Map<number, (key: string, payload: Uint8Array) => void>} */
    this.subs = new Map();
    /** @type {Map<number, (key: string, alive: boolean) => void>} */
    this.watches = new Map();
    this.tokens = new Set();
    this.nextId = { sub: 0, token: 0, watch: 0 };
    let cut = null;
    ws.onmessage = (event) => {
      if (typeof event.data === "string") {
        let message;
        try { message = JSON.parse(event.data); } catch { this.stats.malformed++; return; }
        if (message.op === "alive") {
          const cb = this.watches.get(message.id);
          if (cb && typeof message.key === "string") cb(message.key, message.alive === true);
        } else if (message.op === "cut") {
          cut = message;
        } else if (message.op === "error") {
          this.onerror(`gateway: ${excerpt(message.code)}: ${excerpt(message.text)}`);
        } else {
          this.stats.malformed++;
        }
        return;
      }
      const bytes = new Uint8Array(event.data);
      if (bytes.length < 4) { this.stats.malformed++; return; }
      const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
      const id = view.getUint16(0), length = view.getUint16(2);
      if (bytes.length < 4 + length) { this.stats.malformed++; return; }
      const cb = this.subs.get(id);
      // A sample still on its way when its subscription was closed: late, not malformed.
      if (!cb) { this.stats.late++; return; }
      this.stats.received++;
      cb(decoder.decode(bytes.subarray(4, 4 + length)), bytes.subarray(4 + length));
    };
    ws.onerror = () => {};
    ws.onclose = (event) => {
      this.closed = true;
      const code = cut?.code ?? (event.reason || String(event.code));
      const text = cut?.text ?? "connection closed";
      this.onclose({ code, text, message: `gateway: ${excerpt(code)}: ${excerpt(text)}` });
    };
  }

  _id(kind, table) {
    for (let i = 0; i <= MAX_ID; i++) {
      const id = this.nextId[kind];
      this.nextId[kind] = (id + 1) & MAX_ID;
      if (!table.has(id)) return id;
    }
    throw new GatewayError(`no free ${kind} id`);
  }

  /** Send, or drop and count once the link is closed (`onclose` has told why). */
  _send(message) {
    if (this.closed) {
      this.stats.dropped++;
      return false;
    }
    this.ws.send(message);
    return true;
  }

  /**
   * Deliver samples on keys matching `keyExpr` to `cb(key, payload)`.
   * @param {string} keyExpr @param {(key: string, payload: Uint8Array) => void} cb
   * @returns {{close(): void}}
   */
  subscribe(keyExpr, cb) {
    const id = this._id("sub", this.subs);
    this.subs.set(id, cb);
    this._send(JSON.stringify({ op: "sub", id, key: keyExpr }));
    return { close: () => { if (this.subs.delete(id) && !this.closed) this._send(JSON.stringify({ op: "unsub", id })); } };
  }

  /** Whether DATA/BULK frames are dropped in this turn of the event loop (see the class). */
  _congested() {
    if (this.congestedTurn === null) {
      this.congestedTurn = (this.ws.bufferedAmount ?? 0) > this.maxBuffered;
      queueMicrotask(() => { this.congestedTurn = null; });
    }
    return this.congestedTurn;
  }

  /**
   * Publish `payload` on `key` with the QoS of `lane`. Returns whether it was sent (false:
   * dropped, the link closed or, DATA/BULK only, the websocket congested).
   * `copy`: the 8-byte copy id of a PUT also sent on another websocket of this user (the
   * gateway publishes the first of each copy id, §26.2).
   * @param {string} key @param {Uint8Array} payload @param {"control"|"data"|"bulk"} [lane]
   * @param {Uint8Array} [copy]
   * @returns {boolean}
   */
  publish(key, payload, lane = "data", copy = undefined) {
    const laneNumber = LANES[lane];
    if (laneNumber === undefined) throw new GatewayError(`unknown lane ${excerpt(String(lane), 40)}`);
    if (payload.length > MAX_PAYLOAD) throw new GatewayError(`a payload of ${payload.length} bytes (at most ${MAX_PAYLOAD})`);
    if (copy !== undefined && copy.length !== 8) throw new GatewayError(`a copy id of ${copy.length} bytes (8)`);
    const keyBytes = encoder.encode(key);
    const head = copy === undefined ? 1 : 9;
    const frame = new Uint8Array(head + 2 + keyBytes.length + payload.length);
    frame[0] = copy === undefined ? laneNumber : laneNumber | COPY_FLAG;
    if (copy !== undefined) frame.set(copy, 1);
    frame[head] = keyBytes.length >> 8;
    frame[head + 1] = keyBytes.length & 0xff;
    frame.set(keyBytes, head + 2);
    frame.set(payload, head + 2 + keyBytes.length);
    if (laneNumber !== LANES.control && !this.closed && this._congested()) {
      this.stats.congested++;
      return false;
    }
    if (!this._send(frame)) return false;
    this.stats.sent++;
    return true;
  }

  /** Declare a liveliness token on `key`. @param {string} key @returns {{close(): void}} */
  declareToken(key) {
    const id = this._id("token", this.tokens);
    this.tokens.add(id);
    this._send(JSON.stringify({ op: "token", id, key }));
    return { close: () => { if (this.tokens.delete(id) && !this.closed) this._send(JSON.stringify({ op: "untoken", id })); } };
  }

  /**
   * Report liveliness tokens matching `keyExpr` (existing ones at once, then changes).
   * @param {string} keyExpr @param {(key: string, alive: boolean) => void} cb
   * @returns {{close(): void}}
   */
  watch(keyExpr, cb) {
    const id = this._id("watch", this.watches);
    this.watches.set(id, cb);
    this._send(JSON.stringify({ op: "watch", id, key: keyExpr }));
    return { close: () => { if (this.watches.delete(id) && !this.closed) this._send(JSON.stringify({ op: "unwatch", id })); } };
  }

  /** Close the link (the gateway withdraws this browser's tokens and subscriptions). */
  close() {
    if (this.closed) return;
    this.closed = true;
    this.ws.close(1000);
  }
}

/**
 * Two admitted links to one gateway used as one link (the same API as {@link GatewayLink}):
 * the call's `…/ctl` keys, the inbox, tokens and watches on one websocket, DATA and BULK
 * (the call's `…/data` keys: pose, pictures, sound, the user's camera) on the other, and
 * CONTROL PUTs (HELLOs, heartbeats, stops) on both (below). A websocket is one TCP stream, delivered in
 * order: on a lossy network one lost segment of a picture holds up every byte behind it
 * for a retransmission timeout (at least 0.2 s), a STOP and the heartbeats included. Split,
 * a picture's loss holds up only pictures (bench/wan.py's `PROFILE/browser` rows). CONTROL
 * PUTs go on both, with one copy id (the gateway publishes whichever comes first, §26.2):
 * a STOP then waits for TCP only when both streams wait for a retransmission at once.
 * Closed as soon as either is (the other is closed then too): `onclose` says why, once.
 */
export class SplitLink {
  /** @param {GatewayLink} control @param {GatewayLink} bulk */
  constructor(control, bulk) {
    this.control = control;
    this.bulk = bulk;
    this.name = control.name;
    this.admitted = control.admitted;
    /** @type {(info: {code: string, text: string, message: string}) => void} */
    this.onclose = () => {};
    /** @type {(message: string) => void} non-fatal errors either gateway link reported */
    this.onerror = () => {};
    let told = false;
    for (const [link, other] of [[control, bulk], [bulk, control]]) {
      link.onclose = (info) => {
        other.close();
        if (!told) {
          told = true;
          this.onclose(info);
        }
      };
      link.onerror = (message) => this.onerror(message);
    }
    // One closed before it was handed over (while the other was admitted): no use alone.
    if (this.closed) this.close();
    /** The next copy id: 4 random bytes of this link, then a counter (§26.2). */
    this.copyId = new Uint8Array(8);
    crypto.getRandomValues(this.copyId.subarray(0, 4));
    this.copies = new DataView(this.copyId.buffer);
  }

  /** Whether either websocket is closed (the link is of no use then). */
  get closed() {
    return this.control.closed || this.bulk.closed;
  }

  /** Both links' counters, added up. */
  get stats() {
    /** @type {Record<string, number>} */
    const sum = {};
    for (const link of [this.control, this.bulk]) {
      for (const [name, value] of Object.entries(link.stats)) sum[name] = (sum[name] ?? 0) + value;
    }
    return sum;
  }

  /** See {@link GatewayLink#subscribe}: a call's `…/data` keys on the bulk link. */
  subscribe(/** @type {string} */ keyExpr, /** @type {(key: string, payload: Uint8Array) => void} */ cb) {
    return (keyExpr.endsWith("/data") ? this.bulk : this.control).subscribe(keyExpr, cb);
  }

  /**
   * See {@link GatewayLink#publish}: CONTROL on both links with one copy id (sent if either
   * took it), DATA and BULK on the bulk link.
   */
  publish(/** @type {string} */ key, /** @type {Uint8Array} */ payload, /** @type {"control"|"data"|"bulk"} */ lane = "data") {
    if (lane !== "control") return this.bulk.publish(key, payload, lane);
    const copy = this.copyId.slice();
    this.copies.setUint32(4, (this.copies.getUint32(4) + 1) >>> 0);
    const sent = this.control.publish(key, payload, lane, copy);
    return this.bulk.publish(key, payload, lane, copy) || sent;
  }

  /** See {@link GatewayLink#declareToken}. */
  declareToken(/** @type {string} */ key) {
    return this.control.declareToken(key);
  }

  /** See {@link GatewayLink#watch}. */
  watch(/** @type {string} */ keyExpr, /** @type {(key: string, alive: boolean) => void} */ cb) {
    return this.control.watch(keyExpr, cb);
  }

  /** Close both websockets. */
  close() {
    this.control.close();
    this.bulk.close();
  }
}

/**
 * {@link connectGateway} twice, as one {@link SplitLink}, both admitted with the same key:
 * at once, or with `options.invite` the second after the first redeemed it.
 * @param {string} url @param {Parameters<typeof connectGateway>[1]} options
 * @returns {Promise<SplitLink>} rejects with the GatewayError of a link that failed (the
 *   other one is closed)
 */
export async function connectSplit(url, options) {
  if (options.invite) {
    const control = await connectGateway(url, options);
    try {
      return new SplitLink(control, await connectGateway(url, { ...options, invite: undefined }));
    } catch (error) {
      control.close();
      throw error;
    }
  }
  const both = await Promise.allSettled([connectGateway(url, options), connectGateway(url, options)]);
  const failed = both.find((r) => r.status === "rejected");
  if (failed) {
    for (const r of both) if (r.status === "fulfilled") r.value.close();
    throw failed.reason;
  }
  const [control, bulk] = both.map((r) => /** @type {PromiseFulfilledResult<GatewayLink>} */ (r).value);
  return new SplitLink(control, bulk);
}
