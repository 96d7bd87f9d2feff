/**
 * The user side of telebot calls over a `link` (docs/protocol.md §2, §5.7, §8): a thin
 * driver of the sans-IO state machines in proto/session.js, with setTimeout for timers.
 *
 * A link reaches zenoh (the gateway's WebSocket, or an in-memory link in tests):
 *
 *     link.subscribe(keyExpr, (key, payload) => void) -> { close() }
 *     link.publish(key, payload, lane)                 // lane: "control"|"data"|"bulk"
 *     link.declareToken(key) -> { close() }
 *     link.watch(keyExpr, (key, alive) => void) -> { close() }   // liveliness, with history
 *
 * Reconnecting after a drop is the caller's policy (§8), built on Endpoint.call.
 * @module call
 */
import { CallError, CallEnded, ProtocolError } from "./errors.js";
import { randomBytes, toHex } from "./bytes.js";
import { decodeKey, encodeKey, publicKeyOf } from "./identity.js";
import { channelNameBytes, validateName } from "./proto/frames.js";
import { SUITE_LABELS } from "./proto/noise.js";
import { CallSession, CallSetup, EARLY_FRAMES, checkRobotKey, describeEnd, suiteNumbers } from "./proto/session.js";

const LANES = new Set(["control", "data", "bulk"]);
const NAMESPACE = /^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$/;
/** A HANGUP is published this many times (§6.3). */
const HANGUP_COPIES = 3;
/** The presence token is withdrawn this long after the last HANGUP (§2.1). */
const TOKEN_GRACE_MS = 50;

/** Seconds on a monotonic clock. */
const monotonic = () => performance.now() / 1000;

let lastTs = 0n;
/** The wall clock in ns, strictly increasing within this page (the robot's `ts` rule). */
function wallTimeNs() {
  let ts = BigInt(Math.floor((performance.timeOrigin + performance.now()) * 1e3)) * 1000n;
  if (ts <= lastTs) ts = lastTs + 1n;
  lastTs = ts;
  return ts;
}

/** @param {Uint8Array|string} key @param {string} what */
function keyBytes(key, what) {
  if (typeof key === "string") return decodeKey(key);
  if (key instanceof Uint8Array && key.length === 32) return key;
  throw new ProtocolError(`${what} is 32 bytes or its 43-character text`);
}

/**
 * One user client instance: an inbox, a presence token, and its calls.
 */
export class Endpoint {
  /**
   * @param {{link: any, name: string, privateKey: Uint8Array|string, ns?: string,
   *   suites?: string[], heartbeatHz?: number, timeout?: number}} options
   *   `suites`: the cipher suites offered, preferred first. `heartbeatHz` (20) and
   *   `timeout` (0.5 s without an authentic frame drops a call) as in §8.
   */
  constructor({ link, name, privateKey, ns = "telebot", suites = ["aesgcm", "chachapoly"], heartbeatHz = 20, timeout = 0.5 }) {
    validateName(name, "user name");
    if (!NAMESPACE.test(ns)) throw new ProtocolError(`invalid namespace ${JSON.stringify(String(ns).slice(0, 70))}`);
    if (!(heartbeatHz > 0) || !(timeout > 0)) throw new ProtocolError("heartbeatHz and timeout are positive numbers");
    this.link = link;
    this.name = name;
    this.ns = ns;
    this.privateKey = keyBytes(privateKey, "a private key");
    this.publicKey = publicKeyOf(this.privateKey);
    this.offers = suiteNumbers(suites);
    this.heartbeatInterval = 1 / heartbeatHz;
    this.timeout = timeout;
    /** This client instance's random id, 16 hex digits. */
    this.instance = toHex(randomBytes(8));
    this.base = `${ns}/user/${name}/${this.instance}`;
    this.presenceKey = `${ns}/presence/user/${name}/${this.instance}`;
    /** @type {Map<string, (payload: Uint8Array, sender: string) => void>} pending set-ups by call id */
    this.pending = new Map();
    /** @type {Map<string, (error: Error) => void>} how to fail each pending set-up */
    this.failPending = new Map();
    /** @type {Set<Call>} */
    this.calls = new Set();
    /** Drops on the inbox, by reason. @type {Record<string, number>} */
    this.rejected = {};
    this.closed = false;
    this.lastHangup = 0;
    // The inbox first, then the token (§2.1).
    this.inbox = link.subscribe(`${this.base}/in/*`, (/** @type {string} */ key, /** @type {Uint8Array} */ payload) =>
      this.onInbox(key, payload),
    );
    /** @type {Map<string, (key: string, payload: Uint8Array) => void>} each call's DATA frames, by `robot/callId` */
    this.dataRoutes = new Map();
    /** @type {Map<string, {close: () => void}>} one subscription per robot for its calls' DATA keys */
    this.dataSubscriptions = new Map();
    this.token = link.declareToken(this.presenceKey);
  }

  /**
   * Listen to every call's DATA key with `robot` (once per robot, kept while the endpoint
   * lives): a redialled call's pose and pictures then need no subscription of their own,
   * whose `sub` (on the link's bulk half) waited after a network outage until that half's
   * own QUIC or TCP retransmissions got through, seconds after the call was back. Only
   * `robot` may publish on these keys (protocol §22.2).
   * @param {string} robot
   */
  listenToDataOf(robot) {
    if (this.dataSubscriptions.has(robot)) return;
    const keyExpr = `${this.base}/call/${robot}/*/data`;
    this.dataSubscriptions.set(robot, this.link.subscribe(keyExpr, (/** @type {string} */ key, /** @type {Uint8Array} */ payload) => this.onData(key, payload)));
  }

  /** @param {string} key @param {Uint8Array} payload */
  onData(key, payload) {
    const [robot, idHex] = key.slice(this.base.length + "/call/".length).split("/");
    const route = this.dataRoutes.get(`${robot}/${idHex}`);
    if (route) route(key, payload);
    else this.reject("unknown_call"); // a call that ended (or never was): its frames go nowhere
  }

  /** @param {string} reason */
  reject(reason) {
    this.rejected[reason] = (this.rejected[reason] ?? 0) + 1;
  }

  /** @param {string} key @param {Uint8Array} payload */
  onInbox(key, payload) {
    const sender = key.slice(key.lastIndexOf("/") + 1);
    const handler = payload.length >= 10 ? this.pending.get(toHex(payload.subarray(2, 10))) : undefined;
    if (!handler) {
      this.reject(payload.length >= 10 ? "unexpected_welcome" : "malformed");
      return;
    }
    handler(payload, sender);
  }

  /**
   * Call `robot`, whose key the user stored (never one from presence). Resolves to the
   * Call once the robot accepted it; rejects with CallRejected (the robot's reason),
   * CallTimeout, KeyMismatch (at once when the robot is online with other keys only) or
   * CallError.
   * @param {string} robot @param {Uint8Array|string} robotPublicKey
   * @param {{timeout?: number, ephemeral?: () => Uint8Array}} [options] `timeout`:
   *   seconds to repeat the HELLO and wait (connect timeout).
   * @returns {Promise<Call>}
   */
  async call(robot, robotPublicKey, { timeout = 10, ephemeral } = {}) {
    if (this.closed) throw new CallError("this endpoint is closed");
    validateName(robot, "robot name");
    const robotKey = keyBytes(robotPublicKey, "a robot key");
    if (!(timeout > 0)) throw new CallError("the connect timeout is a positive number of seconds");
    const callId = randomBytes(8);
    const idHex = toHex(callId);
    const setup = new CallSetup({
      staticPrivate: this.privateKey,
      robotPublic: robotKey,
      caller: this.name,
      robot,
      instance: Uint8Array.from(this.instance.match(/../g) ?? [], (h) => parseInt(h, 16)),
      callId,
      offers: this.offers,
      now: monotonic(),
      connectTimeout: timeout,
      wallTimeNs,
      ephemeral,
    });
    const link = this.link;
    const helloKey = `${this.ns}/robot/${robot}/in/${this.name}`;
    const callBase = `${this.base}/call/${robot}/${idHex}`;
    /** @type {Uint8Array[]} */
    const early = [];
    /** @type {Call|null} set once the early frames were handed over */
    let live = null;
    /** @param {string} _key @param {Uint8Array} payload */
    const onCallFrame = (_key, payload) => {
      if (live) live.receive(payload);
      else if (early.length < EARLY_FRAMES) early.push(payload);
    };
    // The call's keys are listened on before the first HELLO goes out (§2.1): its CONTROL
    // key here, its DATA key by the endpoint's one subscription.
    const route = `${robot}/${idHex}`;
    this.dataRoutes.set(route, onCallFrame);
    this.listenToDataOf(robot);
    const subscriptions = [link.subscribe(`${callBase}/ctl`, onCallFrame), { close: () => this.dataRoutes.delete(route) }];
    /** @type {Map<string, boolean>} */
    const tokens = new Map();
    const prefix = `${this.ns}/presence/robot/${robot}/`;
    /** Called when a token of the robot appears (set once the HELLO schedule runs). */
    let appeared = () => {};
    const watch = link.watch(`${prefix}*`, (/** @type {string} */ key, /** @type {boolean} */ alive) => {
      if (!key.startsWith(prefix)) return;
      tokens.set(key.slice(prefix.length), alive);
      if (alive) appeared();
    });
    const expected = encodeKey(robotKey);
    /** @type {ReturnType<typeof setTimeout>|undefined} */
    let timer;
    let sent = 0;
    /** performance.now() when the first HELLO went out (the handshake's start) */
    let helloAt = 0;
    try {
      const accepted = await new Promise((resolve, reject) => {
        /** @param {Error} error */
        const fail = (error) => {
          setup.fail(error);
          reject(error);
        };
        this.pending.set(idHex, (payload, sender) => {
          const result = setup.receive(payload, sender);
          if (result.kind === "ignored") this.reject(result.reason ?? "ignored");
          else if (result.kind === "resend") link.publish(helloKey, result.hello, "control");
          else if (result.kind === "failed") reject(result.error);
          else resolve(result);
        });
        this.failPending.set(idHex, fail);
        const step = () => {
          if (setup.outcome) return;
          if (sent > 0) {
            // A robot online only with other keys cannot read the HELLO: say so now.
            const mismatch = checkRobotKey(robot, expected, tokens);
            if (mismatch) return fail(mismatch);
          }
          const { send, expired } = setup.poll(monotonic());
          if (expired) return reject(expired);
          if (send) {
            if (sent === 0) helloAt = performance.now();
            link.publish(helloKey, send, "control");
            sent += 1;
          }
          timer = setTimeout(step, Math.max(0, (setup.nextDeadline() - monotonic()) * 1000));
        };
        // The robot started, or the link to it is back: its HELLO goes now (§5.7 step 4).
        appeared = () => {
          setup.robotAppeared(monotonic());
          if (!setup.outcome && setup.nextDeadline() <= monotonic()) {
            clearTimeout(timer);
            step();
          }
        };
        step();
      });
      const call = new Call(this, {
        robot,
        robotKey: expected,
        callId,
        role: accepted.answer.role,
        session: new CallSession({
          callId,
          keys: accepted.keys,
          peer: robot,
          now: monotonic(),
          heartbeatInterval: this.heartbeatInterval,
          timeout: this.timeout,
        }),
        subscriptions,
        callBase: `${this.ns}/robot/${robot}/call/${this.name}/${idHex}`,
      });
      // The handshake's time in this page: first HELLO out -> WELCOME checked and the
      // keys derived (ms; repeated HELLOs included). Read as call.stats.handshakeMs.
      call.session.stats.handshakeMs = performance.now() - helloAt;
      this.calls.add(call);
      call.start();
      // Frames that came before the WELCOME are handed over once the caller has had its
      // turn to set onmessage/onDatagram; until then new ones queue behind them.
      setTimeout(() => {
        live = call;
        for (const frame of early.splice(0)) call.receive(frame);
      }, 0);
      return call;
    } catch (error) {
      for (const s of subscriptions) s.close();
      throw error;
    } finally {
      clearTimeout(timer);
      watch.close();
      this.pending.delete(idHex);
      this.failPending.delete(idHex);
    }
  }

  /** The link closed under this endpoint: every call being set up fails now (CallError). */
  linkClosed() {
    for (const fail of [...this.failPending.values()]) fail(new CallError("the link to the gateway closed"));
  }

  /**
   * Hang up every call ("shutting down"), then withdraw the presence token 50 ms after
   * the last HANGUP (so the robot sees the hang-up, not a drop), then the inbox.
   * @param {string} [reason]
   */
  async close(reason = "shutting down") {
    if (this.closed) return;
    this.closed = true;
    for (const fail of [...this.failPending.values()]) fail(new CallError("the endpoint closed while calling"));
    for (const call of [...this.calls]) await call.hangup(reason);
    const wait = this.lastHangup + TOKEN_GRACE_MS - performance.now();
    if (wait > 0) await new Promise((resolve) => setTimeout(resolve, wait));
    this.token.close();
    for (const subscription of this.dataSubscriptions.values()) subscription.close();
    this.inbox.close();
  }
}

/**
 * An established call with one robot. Open channels with {@link Call#channel}.
 */
export class Call {
  /**
   * @param {Endpoint} endpoint
   * @param {{robot: string, robotKey: string, callId: Uint8Array, role: string,
   *   session: CallSession, subscriptions: {close(): void}[], callBase: string}} o
   */
  constructor(endpoint, { robot, robotKey, callId, role, session, subscriptions, callBase }) {
    this.endpoint = endpoint;
    /** The call id, 16 hex digits. */
    this.id = toHex(callId);
    this.robot = robot;
    /** The robot's key (43 chars): its presence token is watched during the call. */
    this.robotKey = robotKey;
    /** The role the robot gave ("driver", "observer", "admin"), or "" if unknown. */
    this.role = ["driver", "observer", "admin"].includes(role) ? role : "";
    this.session = session;
    /** "aesgcm" or "chachapoly" */
    this.suite = SUITE_LABELS[session.suite];
    this.subscriptions = subscriptions;
    this.callBase = callBase;
    /** @type {Map<string, Channel>} */
    this.channels = new Map();
    /** Called with (channelName, payload, isText) for datagrams of channels not opened. @type {null|((name: string, payload: string|Uint8Array, isText: boolean) => void)} */
    this.onDatagram = null;
    /** @type {(end: import("./proto/session.js").CallEnd) => void} */
    let settle = () => {};
    /** Resolves with {kind, detail, byPeer} when the call ends. */
    this.ended = new Promise((resolve) => {
      settle = resolve;
    });
    this.settle = settle;
    /** @type {ReturnType<typeof setTimeout>|undefined} */
    this.timer = undefined;
    /** @type {{close(): void}|null} */
    this.presence = null;
  }

  /** {rtt (s or null), loss (0..1), rejected: {reason: count}, framesSent, framesReceived,
   * unrouted, handshakeMs (first HELLO sent -> WELCOME accepted, ms)} */
  get stats() {
    return this.session.stats;
  }

  /** Watch the robot's presence token and start the heartbeats. */
  start() {
    let seen = false;
    const key = `${this.endpoint.ns}/presence/robot/${this.robot}/${this.robotKey}`;
    this.presence = this.endpoint.link.watch(key, (/** @type {string} */ _key, /** @type {boolean} */ alive) => {
      if (alive) seen = true;
      else if (seen) {
        const end = this.session.peerGone();
        if (end) this.finish(end);
      }
    });
    this.tick();
  }

  tick() {
    if (this.session.ended) return;
    const now = monotonic();
    const { heartbeat, ended } = this.session.tick(now);
    if (heartbeat) this.publish(heartbeat, "control");
    if (ended) return this.finish(ended);
    this.timer = setTimeout(() => this.tick(), Math.max(0, (this.session.nextDeadline() - monotonic()) * 1000));
  }

  /**
   * @param {Uint8Array} frame @param {string} lane
   * @returns {boolean} false when the link said it dropped the frame (closed, congested)
   */
  publish(frame, lane) {
    return this.endpoint.link.publish(`${this.callBase}/${lane === "control" ? "ctl" : "data"}`, frame, lane);
  }

  /** @param {Uint8Array} payload a frame from one of the call's keys */
  receive(payload) {
    if (this.session.ended) return;
    const { datagrams, ended } = this.session.receive(payload, monotonic());
    for (const d of datagrams) {
      if (this.session.ended) break; // a handler hung up: the rest is for nobody
      const channel = this.channels.get(d.channel);
      if (channel) channel.deliver(d.payload);
      else if (this.onDatagram) this.onDatagram(d.channel, d.payload, d.text);
      else this.session.stats.unrouted += 1;
    }
    if (ended) this.finish(ended);
  }

  /**
   * The channel `name` (same name, same object). `lane` is how this side sends on it.
   * @param {string} name @param {{lane?: "control"|"data"|"bulk"}} [options]
   * @returns {Channel}
   */
  channel(name, { lane = "data" } = {}) {
    channelNameBytes(name);
    if (!LANES.has(lane)) throw new ProtocolError(`unknown lane ${JSON.stringify(String(lane).slice(0, 20))}: control, data or bulk`);
    let channel = this.channels.get(name);
    if (!channel) {
      channel = new Channel(this, name, lane);
      this.channels.set(name, channel);
    }
    return channel;
  }

  /**
   * Hang up: one HANGUP frame, published 3 times on CONTROL (§6.3).
   * @param {string} [reason]
   */
  async hangup(reason = "") {
    const frame = this.session.hangup(reason);
    if (!frame) return;
    for (let i = 0; i < HANGUP_COPIES; i++) this.publish(frame, "control");
    this.endpoint.lastHangup = performance.now();
    this.finish(/** @type {any} */ (this.session.ended));
  }

  /** @param {import("./proto/session.js").CallEnd} end */
  finish(end) {
    clearTimeout(this.timer);
    for (const s of this.subscriptions) s.close();
    this.subscriptions = [];
    this.presence?.close();
    this.presence = null;
    this.endpoint.calls.delete(this);
    this.settle({ kind: end.kind, detail: end.detail, byPeer: end.byPeer });
  }

  /** A one-line description of the end, for messages. */
  describeEnd() {
    return this.session.ended ? describeEnd(this.session.ended) : "is up";
  }
}

/**
 * A named datagram stream of a call (§1): lossy, never corrupted or duplicated.
 */
export class Channel {
  /** @param {Call} call @param {string} name @param {string} lane */
  constructor(call, name, lane) {
    this.call = call;
    this.name = name;
    this.lane = lane;
    /** Called with each payload received (string for text, Uint8Array for bytes). @type {null|((payload: string|Uint8Array) => void)} */
    this.onmessage = null;
    this.sent = 0;
    this.received = 0;
    this.dropped = 0;
  }

  /**
   * Send one datagram: a string goes as text (TEXT flag), a Uint8Array as bytes; at most
   * 32,768 bytes. CallEnded once the call is over (nothing is sent). Returns false when
   * the link dropped it (closed, or its websocket congested: gateway-link.js), as a lossy
   * network may; the sender may then send less (a picture's rest, deltas until a keyframe).
   * @param {string|Uint8Array} payload
   * @returns {boolean}
   */
  send(payload) {
    if (this.call.session.ended) {
      throw new CallEnded(`the call with ${this.call.robot} ${describeEnd(this.call.session.ended)}`);
    }
    if (this.call.publish(this.call.session.sealDatagram(this.name, payload), this.lane) === false) return false;
    this.sent += 1;
    return true;
  }

  /** @param {string|Uint8Array} payload */
  deliver(payload) {
    this.received += 1;
    if (this.onmessage) this.onmessage(payload);
    else this.dropped += 1;
  }
}
