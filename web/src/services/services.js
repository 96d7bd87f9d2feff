/**
 * The user's services on one call (docs/protocol.md §13–§25): each opens its channels on a
 * {@link Call}, takes the robot's datagrams through the channel's `onmessage`, and is
 * driven by `tick(now)` (seconds, any origin) for its repeats and time-outs. No timers
 * here: the session ticks them (a test ticks them with a fake clock).
 *
 * Requests on lossy channels repeat until answered, as the Python client does (§13):
 * chat 0.3 s then every 2 s while a long request runs, safety stop after 20 ms, 20 ms, then every 50 ms, and
 * arm/take/release every 0.3 s, goals 0.3 s then a `query` every 2 s, conference `say`
 * every 0.3 s, relay `list` every 0.3 s. A request in flight when its call ends fails
 * with `CALL_ENDED` (it is never sent on the next call, §18).
 * @module services/services
 */
import {
  CALL_ENDED,
  DecodeError,
  DropCounter,
  QUICK_REPEATS,
  RESEND_AFTER,
  RequestFailed,
  callSafely as call,
  safeSend,
  encodeObject,
  idCounter,
  isFiniteNumber,
  serialDiff,
} from "./util.js";
import {
  decodeChatReply,
  decodeConferenceReply,
  decodeGoalUpdate,
  decodePeopleMessage,
  decodePlanMessage,
  decodePose,
  decodeSafetyReply,
  decodeTelemetry,
  encodeChatRequest,
  encodeGoalCommand,
  encodeSafetyRequest,
} from "./messages.js";
import { MapReceiver } from "./map.js";
import {
  CODEC_OPUS,
  KeyframeGate,
  KeyframeRequests,
  REPORT_INTERVAL,
  Reassembler,
  encodeReport,
  parseAudio,
} from "./video.js";

export { CALL_ENDED, QUICK_REPEATS, RESEND_AFTER, RequestFailed };
export const REFRESH_AFTER = 2.0;
export const STOP_REPEAT = 0.05;
/** Motion refused as `rtt_unmeasured` just after set-up: asked again this often, this many times. */
export const UNMEASURED_WAIT = 0.1;
export const UNMEASURED_RETRIES = 20;

// ---------------------------------------------------------------------------- chat §14

/** The `chat` channel: send a command line, get each reply until the final one. */
export class ChatService {
  /** @param {import("../call.js").Call} theCall @param {{random?: () => number}} [options] */
  constructor(theCall, { random = Math.random } = {}) {
    this.channel = theCall.channel("chat", { lane: "control" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.nextId = idCounter(random);
    /** @type {Map<number, any>} */
    this.pending = new Map();
    this.drops = new DropCounter();
    this.now = 0;
  }

  /**
   * Send `line`; `onReply({id, seq, text, final, ok, attachment, code})` for each new reply.
   * Resolves with the final reply; rejects with {@link RequestFailed} on time-out or when
   * the call ends first.
   */
  request(line, onReply, { timeout = 600, now = this.now } = {}) {
    return new Promise((resolve, reject) => {
      const id = this.nextId();
      const payload = encodeChatRequest(id, line);
      this.pending.set(id, {
        payload, onReply, resolve, reject, seen: new Set(), heard: false,
        due: now + RESEND_AFTER, deadline: now + timeout,
      });
      safeSend(this.channel, payload);
    });
  }

  onMessage(payload) {
    let reply;
    try {
      reply = decodeChatReply(payload);
    } catch {
      this.drops.add("malformed");
      return;
    }
    const p = this.pending.get(reply.id);
    if (!p || p.seen.has(reply.seq)) return;
    p.seen.add(reply.seq);
    p.heard = true;
    p.due = this.now + REFRESH_AFTER;
    call(p.onReply, reply);
    if (reply.final) {
      this.pending.delete(reply.id);
      p.resolve(reply);
    }
  }

  tick(now) {
    this.now = now;
    for (const [id, p] of this.pending) {
      if (now >= p.deadline) {
        this.pending.delete(id);
        p.reject(new RequestFailed("timed out", "timeout"));
      } else if (now >= p.due) {
        p.due = now + (p.heard ? REFRESH_AFTER : RESEND_AFTER);
        safeSend(this.channel, p.payload);
      }
    }
  }

  close() {
    this.channel.onmessage = null;
    for (const p of this.pending.values()) p.reject(new RequestFailed(CALL_ENDED, "call_ended"));
    this.pending.clear();
  }
}

// -------------------------------------------------------------------------- safety §18

/** The `safety` channel: stop, arm, take, release (repeated until acked) and the state. */
export class SafetyService {
  constructor(theCall, { random = Math.random, onState = null, onError = null } = {}) {
    this.channel = theCall.channel("safety", { lane: "control" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.nextId = idCounter(random);
    this.pending = new Map();
    /** This client's stops still being repeated (promises, settled when acked or given up). */
    this.stopsInFlight = new Set();
    /** How many stops this client was asked for (an arm must not follow a later stop). */
    this.stopsAsked = 0;
    this.closed = false;
    this.onState = onState;
    this.onError = onError;
    this.drops = new DropCounter();
    this.now = 0;
    /** Datagrams sent per request type (tests count the stop's repeats). */
    this.sent = { stop: 0, arm: 0, take: 0, release: 0 };
  }

  /**
   * Send `type` ("stop" | "arm" | "take" | "release") now and again until the robot
   * acknowledges: resolves with the ack {id, ok, reason, code}. An arm or a take is sent
   * once this client's own stops are acknowledged (or given up): a copy of a stop still
   * being repeated would reach the robot after the arm and stop it again. `timeout`
   * covers that wait; a stop asked for meanwhile wins (the arm is not sent and resolves
   * not ok, code "stopped").
   */
  request(type, { how = "", timeout = 5, now = this.now } = {}) {
    if (type === "stop") this.stopsAsked += 1;
    if ((type === "arm" || type === "take") && this.stopsInFlight.size > 0) {
      const deadline = now + timeout;
      const stopsBefore = this.stopsAsked;
      return Promise.allSettled([...this.stopsInFlight]).then(() => {
        if (this.closed) throw new RequestFailed(CALL_ENDED, "call_ended");
        if (this.stopsAsked !== stopsBefore) {
          const reason = `${type} not sent: a stop was asked for after it`;
          return { type: "ack", id: null, ok: false, reason, code: "stopped" };
        }
        if (deadline - this.now <= 0) throw new RequestFailed("no answer", "timeout");
        return this.request(type, { how, timeout: deadline - this.now });
      });
    }
    const request = new Promise((resolve, reject) => {
      const id = this.nextId();
      const payload = encodeSafetyRequest(type, id, how);
      const repeat = type === "stop" ? STOP_REPEAT : RESEND_AFTER;
      const quick = type === "stop" ? [...QUICK_REPEATS] : [];
      const first = quick.length > 0 ? quick.shift() : repeat;
      this.pending.set(id, { type, payload, repeat, quick, resolve, reject, due: now + first, deadline: now + timeout });
      this.send(type, payload); // first, before anything else: the stop leaves now
    });
    if (type === "stop") {
      this.stopsInFlight.add(request);
      const ended = () => this.stopsInFlight.delete(request);
      request.then(ended, ended);
    }
    return request;
  }

  send(type, payload) {
    if (safeSend(this.channel, payload)) this.sent[type] += 1;
  }

  onMessage(payload) {
    let msg;
    try {
      msg = decodeSafetyReply(payload);
    } catch {
      this.drops.add("malformed");
      return;
    }
    if (msg.type === "state") {
      call(this.onState, msg);
    } else if (msg.type === "error") {
      call(this.onError, msg); // our own requests always decode: a robot's bug
    } else {
      const p = this.pending.get(msg.id);
      if (!p) return;
      this.pending.delete(msg.id);
      p.resolve(msg);
    }
  }

  tick(now) {
    this.now = now;
    for (const [id, p] of this.pending) {
      if (now >= p.deadline) {
        this.pending.delete(id);
        p.reject(new RequestFailed("no answer", "timeout"));
      } else if (now >= p.due) {
        // The quick repeats from the schedule (a tick a hair early must not cost 20 ms more).
        p.due = p.quick.length > 0 ? p.due + p.quick.shift() : now + p.repeat;
        this.send(p.type, p.payload);
      }
    }
  }

  close() {
    this.closed = true;
    this.channel.onmessage = null;
    for (const p of this.pending.values()) p.reject(new RequestFailed(CALL_ENDED, "call_ended"));
    this.pending.clear();
  }
}

// ------------------------------------------------------------------------- goals §16.2

/** The `goals` channel: a goal runs until its final status. */
export class GoalService {
  constructor(theCall, { random = Math.random } = {}) {
    this.channel = theCall.channel("goals", { lane: "control" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.nextId = idCounter(random);
    this.pending = new Map();
    this.drops = new DropCounter();
    this.now = 0;
  }

  /**
   * Send a goal (map frame; `yaw` null: no turn at the end); `onUpdate` gets each status
   * {id, status, progress, text, code, final}; resolves with the final one.
   */
  goto(x, y, yaw, onUpdate, { timeout = Infinity, now = this.now } = {}) {
    return new Promise((resolve, reject) => {
      const id = this.nextId();
      this.pending.set(id, {
        start: encodeGoalCommand("goal", id, x, y, yaw),
        query: encodeGoalCommand("query", id),
        onUpdate, resolve, reject, heard: false, due: now + RESEND_AFTER, deadline: now + timeout,
      });
      safeSend(this.channel, this.pending.get(id).start);
    });
  }

  /** Stop following goal `id`'s updates (a newer goal replaced it on the page). */
  forget(id) {
    this.pending.delete(id);
  }

  onMessage(payload) {
    let update;
    try {
      update = decodeGoalUpdate(payload);
    } catch {
      this.drops.add("malformed");
      return;
    }
    const p = this.pending.get(update.id);
    if (!p) return;
    if (update.status === "unknown") {
      safeSend(this.channel, p.start); // the goal itself was lost
      p.due = this.now + RESEND_AFTER;
      return;
    }
    p.heard = true;
    p.due = this.now + REFRESH_AFTER;
    call(p.onUpdate, update);
    if (update.final) {
      this.pending.delete(update.id);
      p.resolve(update);
    }
  }

  tick(now) {
    this.now = now;
    for (const [id, p] of this.pending) {
      if (now >= p.deadline) {
        this.pending.delete(id);
        p.reject(new RequestFailed("timed out", "timeout"));
      } else if (now >= p.due) {
        p.due = now + (p.heard ? REFRESH_AFTER : RESEND_AFTER);
        safeSend(this.channel, p.heard ? p.query : p.start);
      }
    }
  }

  close() {
    this.channel.onmessage = null;
    for (const p of this.pending.values()) p.reject(new RequestFailed(CALL_ENDED, "call_ended"));
    this.pending.clear();
  }
}

// ------------------------------------------------- pose, telemetry, plan, people (§16, §23)

/**
 * The robot's streams on one call: `pose` and `telemetry` (latest only: an older `t` than
 * the newest is dropped), `plan` (the highest `seq` of the call; `places` on change) and
 * `people` (the newest `seq`; each alert once). Listeners get decoded messages.
 */
export class StreamService {
  constructor(theCall, { onPose, onTelemetry, onPlan, onPlaces, onPeople, onAlert } = {}) {
    this.drops = new DropCounter();
    this.listeners = { onPose, onTelemetry, onPlan, onPlaces, onPeople, onAlert };
    this.channels = [
      this.open(theCall, "pose", (p) => this.onPose(p)),
      this.open(theCall, "telemetry", (p) => this.onTelemetry(p)),
      this.open(theCall, "plan", (p) => this.onPlan(p)),
      this.open(theCall, "people", (p) => this.onPeople(p)),
    ];
    this.poseT = null;
    this.telemetryT = null;
    this.planSeq = null;
    this.placesKey = null;
    this.peopleSeq = null;
    this.alertsSeen = new Set();
  }

  open(theCall, name, handler) {
    const channel = theCall.channel(name, { lane: "data" });
    channel.onmessage = (payload) => {
      try {
        handler(payload);
      } catch (err) {
        if (!(err instanceof DecodeError)) throw err;
        this.drops.add(name);
      }
    };
    return channel;
  }

  onPose(payload) {
    const pose = decodePose(payload);
    if (this.poseT !== null && pose.t < this.poseT) return; // overtaken on the lossy link
    this.poseT = pose.t;
    call(this.listeners.onPose, pose);
  }

  onTelemetry(payload) {
    const telemetry = decodeTelemetry(payload);
    if (this.telemetryT !== null && telemetry.t < this.telemetryT) return;
    this.telemetryT = telemetry.t;
    call(this.listeners.onTelemetry, telemetry);
  }

  onPlan(payload) {
    const msg = decodePlanMessage(payload);
    if (msg.type === "plan") {
      const seq = this.planSeq;
      // A repeat or an older plan (a seq that wrapped round is new: it cannot be that far behind).
      if (seq !== null && seq >= msg.seq && seq - msg.seq < 2 ** 31) return;
      this.planSeq = msg.seq;
      call(this.listeners.onPlan, msg);
      return;
    }
    // By name, as the Python client keeps them (a repeated name: the last one).
    const byName = new Map();
    for (const place of msg.places) byName.set(place.name, place);
    const places = [...byName.values()];
    const key = JSON.stringify(places);
    if (key === this.placesKey) return;
    this.placesKey = key;
    call(this.listeners.onPlaces, places);
  }

  onPeople(payload) {
    const msg = decodePeopleMessage(payload);
    if (msg.type === "people") {
      const seq = this.peopleSeq;
      if (seq !== null && seq >= msg.seq && seq - msg.seq < 2 ** 31) return;
      this.peopleSeq = msg.seq;
      call(this.listeners.onPeople, msg);
      return;
    }
    if (this.alertsSeen.has(msg.seq)) return; // sent three times: shown once
    this.alertsSeen.add(msg.seq);
    if (this.alertsSeen.size > 256) {
      for (const seq of this.alertsSeen) if (seq <= msg.seq - 128) this.alertsSeen.delete(seq);
    }
    call(this.listeners.onAlert, msg);
  }

  tick() {}

  close() {
    for (const channel of this.channels) channel.onmessage = null;
  }
}

// -------------------------------------------------------------------- conference §20

/** Messages kept for a page that opens later. */
export const CONFERENCE_KEEP = 200;
const HISTORY = 64;

/**
 * What the user knows of the conference, across calls: the roster, the messages (in the
 * robot's order, each once; missing ones asked for with `since`), and `say`.
 */
export class ConferenceState {
  constructor({ onRoster = null, onMessage = null } = {}) {
    this.roster = null;
    this.messages = [];
    this.onRoster = onRoster;
    this.onMessage = onMessage;
    this.floor = null;
    this.seen = new Set();
    this.top = 0;
    this.asked = -Infinity;
    this.drops = new DropCounter();
  }

  /** One datagram from the robot; returns a `since` request to send, or null. */
  deliver(payload, now, onSaid) {
    let msg;
    try {
      msg = decodeConferenceReply(payload);
    } catch {
      this.drops.add("malformed");
      return null;
    }
    if (msg.type === "said") {
      onSaid?.(msg);
      return null;
    }
    if (msg.type === "roster") {
      if (this.floor === null || msg.seq < this.floor) {
        this.floor = msg.seq; // the first, or the robot restarted
        this.seen.clear();
      }
      this.top = Math.max(this.top, msg.seq);
      this.floor = Math.max(this.floor, msg.seq - HISTORY);
      this.roster = msg;
      this.advance();
      call(this.onRoster, msg);
      return this.missing(now);
    }
    if (this.floor === null) this.floor = msg.seq - 1;
    if (msg.seq <= this.floor || this.seen.has(msg.seq)) return null;
    this.seen.add(msg.seq);
    this.top = Math.max(this.top, msg.seq);
    this.advance();
    this.messages.push(msg);
    if (this.messages.length > 1 && this.messages[this.messages.length - 2].seq > msg.seq) {
      this.messages.sort((a, b) => a.seq - b.seq);
    }
    if (this.messages.length > CONFERENCE_KEEP) this.messages.splice(0, this.messages.length - CONFERENCE_KEEP);
    call(this.onMessage, msg);
    return this.missing(now);
  }

  advance() {
    while (this.seen.has(this.floor + 1)) {
      this.floor += 1;
      this.seen.delete(this.floor);
    }
    for (const seq of this.seen) if (seq <= this.floor) this.seen.delete(seq);
  }

  missing(now) {
    if (this.floor === null || this.floor >= this.top || now - this.asked < RESEND_AFTER) return null;
    this.asked = now;
    return encodeObject({ type: "since", seq: this.floor });
  }
}

/** The `conference` channel on one call, feeding a {@link ConferenceState}. */
export class ConferenceService {
  constructor(theCall, state) {
    this.state = state;
    this.channel = theCall.channel("conference", { lane: "control" });
    this.channel.onmessage = (payload) => {
      const request = this.state.deliver(payload, this.now, (said) => this.onSaid(said));
      if (request) safeSend(this.channel, request);
    };
    this.pending = new Map();
    this.ids = 0;
    this.now = 0;
  }

  /** Say `text` to everyone: resolves with the robot's answer {id, ok, reason, code}. */
  say(sayText, { timeout = 5, now = this.now } = {}) {
    return new Promise((resolve, reject) => {
      this.ids = (this.ids + 1) % 2 ** 32;
      const payload = encodeObject({ type: "say", id: this.ids, text: sayText });
      this.pending.set(this.ids, { payload, resolve, reject, due: now + RESEND_AFTER, deadline: now + timeout });
      safeSend(this.channel, payload);
    });
  }

  onSaid(said) {
    const p = this.pending.get(said.id);
    if (!p) return;
    this.pending.delete(said.id);
    p.resolve(said);
  }

  tick(now) {
    this.now = now;
    for (const [id, p] of this.pending) {
      if (now >= p.deadline) {
        this.pending.delete(id);
        p.reject(new RequestFailed("no answer", "timeout"));
      } else if (now >= p.due) {
        p.due = now + RESEND_AFTER;
        safeSend(this.channel, p.payload);
      }
    }
    const request = this.state.missing(now);
    if (request) safeSend(this.channel, request);
  }

  close() {
    this.channel.onmessage = null;
    for (const p of this.pending.values()) p.reject(new RequestFailed(CALL_ENDED, "call_ended"));
    this.pending.clear();
  }
}

// ------------------------------------------------------------------------------ map §15

/** The `map` channel: one transfer at a time, complete over loss. */
export class MapService {
  constructor(theCall, { random = Math.random } = {}) {
    this.channel = theCall.channel("map", { lane: "bulk" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.random = random;
    this.receiver = null;
    this.job = null;
    this.drops = new DropCounter();
    this.now = 0;
  }

  /**
   * Download the map: resolves with the offer's fields and `png`; rejects with an Error
   * whose message is one line (the robot's reason, a hash mismatch, a time-out).
   */
  fetch({ timeout = 120, now = this.now, onProgress = null } = {}) {
    if (this.job) this.job.reject(new RequestFailed("replaced by a new map download", "replaced"));
    return new Promise((resolve, reject) => {
      const receiver = new MapReceiver(Math.floor(this.random() * 2 ** 32));
      this.receiver = receiver;
      this.job = { resolve, reject, deadline: now + timeout, onProgress };
      safeSend(this.channel, receiver.request(now));
    });
  }

  onMessage(payload) {
    const receiver = this.receiver;
    if (!receiver) {
      this.drops.add("no_transfer");
      return;
    }
    for (const out of receiver.onMessage(payload, this.now)) safeSend(this.channel, out);
    if (this.job?.onProgress) call(this.job.onProgress, ...receiver.progress);
    this.settle();
  }

  settle() {
    const receiver = this.receiver;
    const job = this.job;
    if (!job || !receiver) return;
    if (receiver.state === "done") {
      this.job = null;
      job.resolve(receiver.result);
    } else if (receiver.state === "failed") {
      this.job = null;
      job.reject(new RequestFailed(receiver.error, "failed"));
    }
  }

  tick(now) {
    this.now = now;
    const receiver = this.receiver;
    if (!receiver || !this.job) return;
    if (now >= this.job.deadline) {
      for (const out of receiver.cancel()) safeSend(this.channel, out);
      const job = this.job;
      this.job = null;
      job.reject(new RequestFailed("the map did not arrive in time", "timeout"));
      return;
    }
    const deadline = receiver.nextDeadline();
    if (deadline !== null && now >= deadline) {
      for (const out of receiver.poll(now)) safeSend(this.channel, out);
    }
  }

  close() {
    this.channel.onmessage = null;
    if (this.job) {
      this.job.reject(new RequestFailed(CALL_ENDED, "call_ended"));
      this.job = null;
    }
  }
}

// ----------------------------------------------------------------------- video §17, §25

/**
 * The robot's camera on one call: reassembles FRAGMENTs into whole pictures, passes a
 * delta-coded picture only when the one before it passed (else asks for a keyframe),
 * and reports every 200 ms while `wanted` (the subscription), with the codec list.
 * `onFrame(frame)` gets {frameId, camera, captureTime, codec, keyframe, data}.
 */
export class VideoService {
  constructor(theCall, { onFrame = null, codecs = [0x01], wanted = true, rtt = () => null } = {}) {
    this.call = theCall;
    this.channel = theCall.channel("video", { lane: "bulk" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.reassembler = new Reassembler();
    this.gate = new KeyframeGate();
    this.requests = new KeyframeRequests();
    this.onFrame = onFrame;
    this.codecs = codecs;
    this.wanted = wanted;
    this.rtt = rtt;
    this.nextReport = null;
    this.reports = 0;
    this.keyframeRequests = 0;
    this.now = 0;
  }

  /** The drop counters of the reassembly (malformed, late, incomplete, …) and the gate. */
  get stats() {
    return { ...this.reassembler.stats, skipped: this.gate.skipped };
  }

  setWanted(wanted, now = this.now) {
    if (wanted === this.wanted) return;
    this.wanted = wanted;
    if (wanted) this.nextReport = now;
    else this.sendReport(now, { bye: true });
  }

  setCodecs(codecs) {
    this.codecs = codecs;
    if (this.wanted) this.nextReport = this.now; // tell the robot at once
  }

  /** The page lost a picture or its decoder failed: wait for a keyframe, ask for one now. */
  requestKeyframe(now = this.now) {
    this.gate.lose();
    this.askKeyframe(now);
  }

  askKeyframe(now) {
    if (!this.wanted || !this.requests.due(this.gate.needKeyframe, now, this.rtt())) return;
    this.keyframeRequests += 1;
    this.sendReport(now, { keyframe: true });
  }

  sendReport(now, { bye = false, keyframe = this.gate.needKeyframe } = {}) {
    this.reports += 1;
    safeSend(this.channel, this.reassembler.report(Math.floor(now * 1000), { bye, keyframe, codecs: this.codecs }));
  }

  onMessage(payload) {
    if (!this.wanted) return;
    const frame = this.reassembler.onDatagram(payload, this.now);
    if (!frame) return;
    if (!this.gate.admit(frame.frameId, frame.codec, frame.keyframe)) {
      this.askKeyframe(this.now);
      return;
    }
    call(this.onFrame, frame);
  }

  tick(now) {
    this.now = now;
    this.reassembler.poll(now);
    if (!this.wanted) return;
    if (this.nextReport === null || now >= this.nextReport) {
      this.sendReport(now);
      this.nextReport = now + REPORT_INTERVAL;
    }
  }

  close() {
    this.channel.onmessage = null;
    if (this.wanted) this.sendReport(this.now, { bye: true }); // dropped if the call is over
  }
}

/**
 * The robot's microphone on one call (§25.3): valid AUDIO packets are passed on as they
 * come (the page's jitter buffer orders and conceals), a duplicate or one far behind is
 * dropped; REPORTs (codec list [Opus]) every 200 ms while `wanted`.
 */
export class AudioService {
  constructor(theCall, { onPacket = null, wanted = true } = {}) {
    this.channel = theCall.channel("audio", { lane: "bulk" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.onPacket = onPacket;
    this.wanted = wanted;
    this.stats = { packets: 0, bytes: 0, malformed: 0, late: 0 };
    this.highestSeq = null;
    this.recent = new Set();
    this.transits = [];
    this.queueDelay = 0;
    this.nextReport = null;
    this.now = 0;
  }

  setWanted(wanted, now = this.now) {
    if (wanted === this.wanted) return;
    this.wanted = wanted;
    if (wanted) this.nextReport = now;
    else this.sendReport(now, true);
  }

  onMessage(payload) {
    if (!this.wanted) return;
    let packet;
    try {
      packet = parseAudio(payload);
    } catch {
      this.stats.malformed += 1;
      return;
    }
    if (this.recent.has(packet.seq) || (this.highestSeq !== null && serialDiff(packet.seq, this.highestSeq) < -50 && serialDiff(packet.seq, this.highestSeq) > -1000)) {
      this.stats.late += 1;
      return;
    }
    this.recent.add(packet.seq);
    if (this.recent.size > 128) this.recent.delete(this.recent.values().next().value);
    if (this.highestSeq === null || serialDiff(packet.seq, this.highestSeq) > 0) this.highestSeq = packet.seq;
    this.stats.packets += 1;
    this.stats.bytes += packet.data.length;
    const transit = this.now - packet.captureUs / 1e6;
    while (this.transits.length && this.transits[this.transits.length - 1][1] >= transit) this.transits.pop();
    this.transits.push([this.now, transit]);
    while (this.transits[0][0] < this.now - 5) this.transits.shift();
    this.queueDelay = transit - this.transits[0][1];
    call(this.onPacket, packet);
  }

  sendReport(now, bye = false) {
    safeSend(this.channel, encodeReport({
      receiverMs: Math.floor(now * 1000), highestSeq: this.highestSeq ?? 0,
      fragments: this.stats.packets, bytes: this.stats.bytes, frames: this.stats.packets,
      dropped: 0, queueDelayMs: this.queueDelay * 1000, bye, codecs: [CODEC_OPUS],
    }));
  }

  tick(now) {
    this.now = now;
    if (!this.wanted) return;
    if (this.nextReport === null || now >= this.nextReport) {
      this.sendReport(now);
      this.nextReport = now + REPORT_INTERVAL;
    }
  }

  close() {
    this.channel.onmessage = null;
    if (this.wanted) this.sendReport(this.now, true);
  }
}

// ----------------------------------------------------------------------- relay §17.5

export { RelayService } from "./relay.js";

export { isFiniteNumber };
