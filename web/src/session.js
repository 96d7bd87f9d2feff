/**
 * The page's session with one robot, in the browser: what `telebot-user ui`'s Python
 * process does for the page today (docs/protocol.md §19), on top of a {@link Call}.
 *
 *     const session = new RobotSession({ connect: () => endpoint.call(name, key), emit, user });
 *     await session.start();          // the first call (throws: KEY MISMATCH, refused, …)
 *     session.send({ type: "stop", how: "key" });   // §19 page → client messages
 *     session.send({ type: "video", header, data }); // the user's camera / mic (§19.1)
 *     // emit(msg) gets the §19 client → page messages; pictures and voice as
 *     // {type: "video"|"audio", header, data} (packMedia(header, data) makes today's
 *     // binary websocket message of them).
 *
 * A dropped call is called again as the Python client does (same key; back-off 0.1 s
 * doubling to 2 s with jitter; give up after 300 s; a refusal ends it), with `connection`
 * messages `reconnecting` / `reconnected` (seconds) / `ended`. Requests in flight at the
 * drop fail (a goal is never resumed: the robot latched stopped); requests made while
 * reconnecting wait for the new call. The robot stays stopped until its driver re-arms it.
 *
 * Bad input from the network never throws out of here: decoders drop and count
 * ({@link RobotSession#drops}).
 * @module session
 */
import {
  AudioService,
  ChatService,
  ConferenceService,
  ConferenceState,
  GoalService,
  MapService,
  RelayService,
  SafetyService,
  StreamService,
  UNMEASURED_RETRIES,
  UNMEASURED_WAIT,
  VideoService,
} from "./services/services.js";
import { STOP_HOWS, sayText } from "./services/messages.js";
import { DriveService } from "./services/drive.js";
import { CODEC_IDS, CODEC_NAMES, packMedia } from "./services/video.js";
import { PAGE_CODECS, UserMediaService, chooseCodec, parseMediaMessage, unpackMedia } from "./services/uplink.js";
import { RequestFailed } from "./services/util.js";

export { packMedia };
export { RelayRefused, TopicStream } from "./services/relay.js";

/** Seconds between the services' ticks (the stop repeats after 20 ms, 20 ms, then every 50 ms). */
export const TICK = 0.02;
/** Seconds between `link` messages. */
export const LINK_EVERY = 0.5;
/** Conference messages a page gets when it opens (§19). */
const GREET_MESSAGES = 50;

/** The default clock: seconds from performance.now(), timers from setTimeout. */
export const realClock = {
  now: () => performance.now() / 1000,
  every(seconds, fn) {
    const handle = setInterval(fn, seconds * 1000);
    return () => clearInterval(handle);
  },
  sleep: (seconds) => new Promise((resolve) => setTimeout(resolve, seconds * 1000)),
};

function defaultMapUrl(png) {
  if (typeof URL !== "undefined" && typeof URL.createObjectURL === "function" && typeof Blob !== "undefined") {
    return URL.createObjectURL(new Blob([png], { type: "image/png" }));
  }
  return "map.png";
}

function revokeMapUrl(url) {
  if (url && url.startsWith("blob:") && typeof URL.revokeObjectURL === "function") URL.revokeObjectURL(url);
}

/** Longest text id a page may use in `chat`, `say`, `camera` (as the Python client). */
const MAX_ID = 64;

/** Why a page message's `id` is not a number, a short text or null ("" when it is). */
function badId(msg) {
  const id = msg.id ?? null;
  if (id === null || (typeof id === "number" && Number.isFinite(id))) return "";
  if (typeof id === "string" && id.length <= MAX_ID) return "";
  return `${msg.type}: 'id' must be a number, a text of at most ${MAX_ID} characters or null`;
}

/** Seconds before reconnection attempt `attempt` (0 first): base doubled, capped, jittered. */
export function backoffDelay(attempt, { base = 0.1, cap = 2.0 } = {}, random = Math.random) {
  const ceiling = Math.min(cap, base * 2 ** Math.min(attempt, 32));
  return ceiling * (1 - 0.5 * random());
}

const DRIVING_ROLES = ["driver", "admin"];

export class RobotSession {
  /**
   * @param {object} options
   * @param {() => Promise<any>} options.connect calls the robot (the same key each time)
   * @param {(msg: object) => void} options.emit gets every client → page message
   * @param {string} [options.user] this user's name (the hello's `user`)
   * @param {string} [options.robot] the robot's name until the call says it
   * @param {typeof realClock} [options.clock]
   * @param {() => number} [options.random]
   * @param {{enabled?: boolean, base?: number, cap?: number, giveUpAfter?: number}} [options.reconnect]
   * @param {(png: Uint8Array) => string} [options.mapUrl] the map message's `url` for a PNG
   *   (default: a blob: URL in a browser; a page must not add a query to it)
   * @param {number} [options.mapTimeout] seconds for one map download (120)
   */
  constructor({ connect, emit, user = "", robot = "", clock = realClock, random = Math.random, reconnect = {}, mapUrl = defaultMapUrl, mapTimeout = 120 }) {
    this.connect = connect;
    this.emitFn = emit;
    this.user = user;
    this.robot = robot;
    this.clock = clock;
    this.random = random;
    this.reconnect = { enabled: true, base: 0.1, cap: 2.0, giveUpAfter: 300, ...reconnect };
    this.mapUrl = mapUrl;
    this.mapTimeout = mapTimeout;
    this.call = null;
    /** The services of the current call (null while reconnecting). */
    this.services = null;
    this.role = "";
    this.closing = false;
    this.finished = false;
    this.reconnects = 0;
    this.conference = new ConferenceState({
      onRoster: (roster) => this.onRoster(roster),
      onMessage: (msg) => this.emit({ type: "msg", seq: msg.seq, from: msg.from, kind: msg.kind, text: msg.text }),
    });
    /** The newest of each stream, for a page that (re)opens: {@link greet}. */
    this.latest = { pose: null, telemetry: null, safety: null, goal: null, plan: null, places: null, people: null, map: null, drive: null };
    this.connection = { type: "connection", state: "connected", detail: "", seconds: 0 };
    this.lastRoster = null;
    this.goalId = null;
    this.mapVersion = null;
    this.mapFetching = false;
    this.waiting = []; // requests made while no call is up: {run, fail, deadline}
    this.videoCodecs = [CODEC_IDS.jpeg];
    this.videoWanted = true;
    this.audioWanted = true;
    this.stopTimers = [];
    /** Page messages that could not be read (the page was told by an `error`). */
    this.pageErrors = 0;
    this.greeted = false;
    /** Datagrams dropped by the services of earlier calls, by service. */
    this.pastDrops = {};
    /** What the page encodes (its `media` message; null until it said). */
    this.mediaEncode = null;
    this.mediaTold = null;
    /** The page's media messages dropped as malformed (the page got an `error` each). */
    this.mediaErrors = 0;
  }

  // ---------------------------------------------------------------- lifecycle

  /** Call the robot, open the services, greet the page. Throws what `connect` throws. */
  async start() {
    const theCall = await this.connect();
    this.open(theCall);
    this.stopTimers.push(this.clock.every(TICK, () => this.tick()));
    this.stopTimers.push(this.clock.every(LINK_EVERY, () => this.emitLink()));
    this.greet();
    return this;
  }

  /** Hang up (no reconnection follows) and stop every timer. */
  async close({ hangup = true } = {}) {
    if (this.closing) return;
    this.closing = true;
    for (const stop of this.stopTimers) stop();
    this.stopTimers = [];
    const theCall = this.call;
    this.closeServices();
    if (hangup && theCall) {
      try {
        await theCall.hangup("");
      } catch {
        // already over
      }
    }
    this.finish("hung up");
  }

  open(theCall) {
    this.call = theCall;
    if (theCall.robot) this.robot = theCall.robot;
    const random = this.random;
    const s = {};
    s.chat = new ChatService(theCall, { random });
    s.safety = new SafetyService(theCall, {
      random,
      onState: (state) => {
        const msg = { type: "safety", armed: state.armed, text: state.reason, code: state.code, holder: state.holder, cap: state.cap, blocked: state.blocked };
        this.latest.safety = msg;
        this.emit(msg);
      },
    });
    s.goals = new GoalService(theCall, { random });
    s.streams = new StreamService(theCall, {
      onPose: (pose) => this.onPose(pose),
      onTelemetry: (t) => this.onTelemetry(t),
      onPlan: (plan) => {
        const msg = { type: "plan", seq: plan.seq, goal: plan.goal, points: plan.points };
        this.latest.plan = msg;
        this.emit(msg);
      },
      onPlaces: (places) => {
        const msg = { type: "places", places };
        this.latest.places = msg;
        this.emit(msg);
      },
      onPeople: (people) => {
        this.latest.people = people;
        this.emit(people);
      },
      onAlert: (alert) => this.emit({ ...alert, type: "people_alert" }),
    });
    s.conference = new ConferenceService(theCall, this.conference);
    s.map = new MapService(theCall, { random });
    s.video = new VideoService(theCall, {
      codecs: this.videoCodecs,
      wanted: this.videoWanted,
      rtt: () => theCall.stats?.rtt ?? null,
      onFrame: (frame) => this.emit({
        type: "video",
        header: { kind: "video", codec: CODEC_NAMES[frame.codec] ?? "jpeg", key: frame.keyframe, camera: frame.camera, frame_id: frame.frameId, capture_time: frame.captureTime },
        data: frame.data,
      }),
    });
    s.audio = new AudioService(theCall, {
      wanted: this.audioWanted,
      onPacket: (packet) => this.emit({
        type: "audio", header: { kind: "audio", seq: packet.seq, capture_time: packet.captureUs / 1e6 }, data: packet.data,
      }),
    });
    s.relay = new RelayService(theCall, { random });
    s.drive = new DriveService(theCall, { random, onState: (state) => this.onDriveState(state) });
    s.userMedia = new UserMediaService(theCall, {
      rtt: () => theCall.stats?.rtt ?? null,
      onKeyframe: () => this.emit({ type: "keyframe_request" }),
      onChange: () => this.tellMedia(),
      onReport: (msg) => this.emit(msg),
    });
    this.services = s;
    const now = this.clock.now();
    for (const service of Object.values(s)) service.tick(now);
    if (theCall.role) this.setRole(theCall.role);
    const waiting = this.waiting;
    this.waiting = [];
    for (const w of waiting) w.run();
    if (!this.latest.map || this.mapFetching) this.fetchMap();
    this.tellMedia(); // a new call: the robot has not said which codecs it takes yet
    Promise.resolve(theCall.ended).then((end) => this.onEnded(theCall, end), () => this.onEnded(theCall, { kind: "dropped", detail: "" }));
  }

  closeServices() {
    const s = this.services;
    if (!s) return;
    this.services = null;
    for (const [name, service] of Object.entries(s)) {
      const drops = service.drops?.total ?? service.stats?.malformed ?? 0;
      this.pastDrops[name] = (this.pastDrops[name] ?? 0) + drops;
      try {
        service.close();
      } catch {
        // a send on a call that is over
      }
    }
  }

  onEnded(theCall, end) {
    if (theCall !== this.call || this.closing) return;
    this.closeServices();
    const kind = end?.kind ?? "dropped";
    const detail = end?.detail ?? "";
    if (kind !== "dropped" || !this.reconnect.enabled) {
      this.finish(kind === "hung_up" ? `${this.robot} hung up${detail ? ": " + detail : ""}` : detail || "the call ended");
      return;
    }
    this.redial(detail);
  }

  async redial(detail) {
    const started = this.clock.now();
    this.setConnection("reconnecting", detail ? `reconnecting… (${detail})` : "reconnecting…", 0);
    for (let attempt = 0; ; attempt++) {
      await this.clock.sleep(backoffDelay(attempt, this.reconnect, this.random));
      if (this.closing) return;
      const waited = this.clock.now() - started;
      if (this.reconnect.giveUpAfter && waited >= this.reconnect.giveUpAfter) {
        this.finish(`gave up reconnecting after ${Math.round(waited)} s`);
        return;
      }
      let theCall;
      try {
        theCall = await this.connect();
      } catch (err) {
        if (err?.name === "CallRejected") {
          this.finish(`${this.robot} refused the call: ${err.message}`);
          return;
        }
        continue; // not answering yet, a KEY MISMATCH a forger can fake, a link hiccup
      }
      if (this.closing) {
        try {
          await theCall.hangup("");
        } catch {
          // over anyway
        }
        return;
      }
      this.reconnects += 1;
      this.open(theCall);
      this.setConnection("reconnected", "", this.clock.now() - started);
      return;
    }
  }

  finish(detail) {
    if (this.finished) return;
    this.finished = true;
    for (const stop of this.stopTimers) stop();
    this.stopTimers = [];
    for (const w of this.waiting) w.fail("the call ended");
    this.waiting = [];
    this.setConnection("ended", `disconnected: ${detail}`, 0);
  }

  setConnection(state, detail, seconds) {
    this.connection = { type: "connection", state, detail, seconds: Math.round(seconds * 100) / 100 };
    this.emit(this.connection);
  }

  /** Run `run()` on the current call, or when the next one comes within `timeout` s. */
  onCall(run, fail, timeout = 5) {
    if (this.services) {
      run();
    } else if (this.finished) {
      fail("the call ended");
    } else {
      this.waiting.push({ run, fail, deadline: this.clock.now() + timeout });
    }
  }

  tick() {
    const now = this.clock.now();
    const s = this.services;
    if (s) {
      for (const service of Object.values(s)) {
        try {
          service.tick(now);
        } catch {
          // a send on a call that just ended: onEnded follows
        }
      }
    }
    if (this.waiting.length) {
      const due = this.waiting.filter((w) => now >= w.deadline);
      this.waiting = this.waiting.filter((w) => now < w.deadline);
      for (const w of due) w.fail("no answer");
    }
  }

  emit(msg) {
    try {
      this.emitFn(msg);
    } catch {
      // the page's handler failed: the session goes on
    }
  }

  emitLink() {
    const stats = this.call?.stats ?? {};
    this.emit({ type: "link", rtt: stats.rtt ?? null, loss: stats.loss ?? 0 });
  }

  // ------------------------------------------------------------ what the page gets

  get mayDrive() {
    return DRIVING_ROLES.includes(this.role);
  }

  setRole(role) {
    if (role === this.role) return;
    this.role = role;
    if (this.greeted) this.emit(this.hello()); // the page enables its driving controls on a hello
  }

  hello() {
    return { type: "hello", robot: this.robot, user: this.user, role: this.role, may_drive: this.mayDrive, map: this.latest.map };
  }

  /**
   * Everything a page that just opened needs at once (the Python server's greeting):
   * hello, then the newest pose, safety, telemetry, goal, plan, places, connection,
   * roster and the last 50 conference messages.
   */
  greet() {
    this.greeted = true;
    this.emit(this.hello());
    const l = this.latest;
    for (const msg of [l.pose, l.safety, l.telemetry, l.goal, l.plan, l.places]) if (msg) this.emit(msg);
    this.emit(this.connection);
    if (this.lastRoster) this.emit(this.lastRoster);
    for (const m of this.conference.messages.slice(-GREET_MESSAGES)) {
      this.emit({ type: "msg", seq: m.seq, from: m.from, kind: m.kind, text: m.text });
    }
  }

  onPose(pose) {
    const msg = { type: "pose", x: pose.x, y: pose.y, yaw: pose.yaw, v: pose.v, w: pose.w, state: pose.state, detail: pose.detail, goal: pose.goal, t: pose.t, cov: pose.cov, recv: Date.now() };
    this.latest.pose = msg;
    this.emit(msg);
  }

  onTelemetry(t) {
    const msg = { type: "telemetry", ...t };
    this.latest.telemetry = msg;
    if (!this.call?.role && t.role) this.setRole(t.role);
    this.emit(msg);
    // The map follows the robot's (§15.10): a new version is fetched again.
    if (this.latest.map && t.map_version !== this.latest.map.version && !this.mapFetching) this.fetchMap();
  }

  onRoster(roster) {
    const msg = { type: "roster", users: roster.users.map((u) => ({ name: u.name, role: u.role, driving: u.driving, you: u.you })) };
    const key = JSON.stringify(msg);
    if (this.lastRoster && JSON.stringify(this.lastRoster) === key) return; // pushed every second: changes only
    this.lastRoster = msg;
    this.emit(msg);
  }

  fetchMap() {
    const map = this.services?.map;
    if (!map) {
      this.mapFetching = true; // fetched on the next call
      return;
    }
    this.mapFetching = true;
    map.fetch({ timeout: this.mapTimeout, now: this.clock.now() }).then(
      (result) => {
        this.mapFetching = false;
        const old = this.latest.map;
        const msg = {
          type: "map", url: this.mapUrl(result.png), resolution: result.resolution,
          origin_x: result.origin_x, origin_y: result.origin_y, width: result.width,
          height: result.height, version: result.version, png: result.png,
        };
        this.latest.map = msg;
        this.emit(msg);
        if (old) setTimeout(() => revokeMapUrl(old.url), 1000);
      },
      (err) => {
        if (err?.code === "call_ended" || err?.code === "replaced") return; // again on the next call
        this.mapFetching = false;
        this.emit({ type: "error", text: `the map did not arrive: ${err?.message ?? err}` });
      },
    );
  }

  // ---------------------------------------------------------- page → client (§19)

  /**
   * One §19 page → client message (the parsed JSON object). Never throws: a message it
   * cannot read is answered with an `error`.
   */
  send(msg) {
    if (msg instanceof ArrayBuffer || msg instanceof Uint8Array) return this.sendBinary(msg);
    if (msg === null || typeof msg !== "object" || typeof msg.type !== "string") {
      return this.pageError("not a JSON message with a type");
    }
    switch (msg.type) {
      case "stop":
        this.stop(STOP_HOWS.includes(msg.how) ? msg.how : "button").catch(() => {});
        return;
      case "arm":
      case "take":
      case "release":
        this.safety(msg.type).catch(() => {});
        return;
      case "goal":
        return this.onGoal(msg);
      case "drive":
        return this.onDrive(msg);
      case "chat": {
        if (badId(msg)) return this.pageError(badId(msg));
        const line = String(msg.text ?? "");
        const said = sayText(line);
        if (said !== null) this.say(msg.id, said);
        else this.chat(msg.id, line);
        return;
      }
      case "say":
        if (badId(msg)) return this.pageError(badId(msg));
        return this.say(msg.id, String(msg.text ?? ""));
      case "camera":
        if (msg.name !== "navcam" && msg.name !== "usercam") {
          return this.pageError("camera: 'name' must be navcam or usercam");
        }
        if (badId(msg)) return this.pageError(badId(msg));
        this.chat(msg.id, msg.name);
        return;
      case "ping":
        if (msg.t != null && !(typeof msg.t === "number" && Number.isFinite(msg.t))) {
          return this.pageError("ping: 't' must be a finite number or null");
        }
        this.emit({ type: "pong", t: msg.t ?? null });
        return;
      case "media":
        return this.onMedia(msg);
      case "video":
      case "audio":
        return this.sendMedia(msg.header, msg.data, msg.type);
      case "keyframe":
        this.services?.video.requestKeyframe(this.clock.now());
        return;
      default:
        return this.pageError(`unknown message type '${msg.type}'`);
    }
  }

  pageError(text) {
    this.pageErrors += 1;
    this.emit({ type: "error", text });
  }

  /**
   * Stop the robot now (anyone may, never refused): repeated until the robot acknowledges
   * (after 20 ms, 20 ms, then every 50 ms). Resolves with the ack as the page gets it
   * ({type: "ack", what: "stop", ok, text, code}), which is also emitted.
   * @param {string} [how] "button" | "key" | "tab_closed" | "exit" | "api"
   */
  stop(how = "button") {
    this.services?.drive.cancel(); // the stop ends direct driving: no repeat may follow it
    return this.safety("stop", how);
  }

  safety(what, how = "") {
    return new Promise((resolve) => {
      const answer = (ok, text, code) => {
        const msg = { type: "ack", what, ok, text, code };
        this.emit(msg);
        resolve(msg);
      };
      this.onCall(
        () => this.services.safety.request(what, { how, now: this.clock.now() }).then(
          (ack) => answer(ack.ok, ack.reason, ack.code),
          (err) => answer(false, err.message, ""),
        ),
        (reason) => answer(false, reason, ""),
      );
    });
  }

  /**
   * The fail-safe of a page going away (pagehide, frozen, hidden): stops the robot (`how`
   * tab_closed) when this user may drive and the robot moves, a goal runs, or it is armed
   * or blocked (it might move). Returns whether it sent a stop.
   */
  failSafe(how = "tab_closed") {
    if (!this.mayDrive || this.finished) return false;
    const pose = this.latest.pose;
    const moving = pose !== null && (pose.v !== 0 || pose.w !== 0 || pose.state === "moving");
    const goal = this.latest.goal;
    const goalActive = goal !== null && (goal.status === "sent" || goal.status === "active");
    const armed = this.latest.safety?.armed === true;
    const blocked = pose?.state === "blocked";
    if (!(moving || goalActive || armed || blocked)) return false;
    this.stop(how).catch(() => {});
    return true;
  }

  onGoal(msg) {
    const { x, y } = msg;
    const yaw = msg.yaw ?? null;
    if (typeof x !== "number" || typeof y !== "number" || (yaw !== null && typeof yaw !== "number")) {
      return this.pageError("a goal needs numbers x, y (and yaw)");
    }
    if (![x, y, yaw ?? 0].every(Number.isFinite)) return this.pageError("a goal needs finite numbers");
    if (!this.mayDrive) return this.pageError("observers may not send goals");
    this.services?.drive.cancel(); // the goal ends direct driving: no repeat may replace it
    const token = {};
    this.goalId = token;
    const update = (status, progress = 0, text = "", code = "") => {
      if (this.goalId !== token) return; // a newer goal is the page's goal now
      const goal = { type: "goal", x, y, yaw, status, progress, text, code };
      this.latest.goal = goal;
      this.emit(goal);
    };
    update("sent");
    const attempt = (left) => this.onCall(() => {
      if (this.goalId !== token) return;
      this.services.goals.goto(x, y, yaw, (u) => {
        if (u.status === "refused" && u.code === "rtt_unmeasured" && left > 0) return;
        update(u.status, u.progress, u.text, u.code);
      }, { now: this.clock.now() }).then(
        (final) => {
          if (final.status === "refused" && final.code === "rtt_unmeasured" && left > 0) {
            this.later(UNMEASURED_WAIT, () => attempt(left - 1));
          }
        },
        (err) => update("failed", 0, err.message, "failed"),
      );
    }, (reason) => update("failed", 0, reason, "failed"));
    attempt(UNMEASURED_RETRIES);
  }

  // ------------------------------------------------------------ driving by hand §27

  /**
   * Drive by hand (§27), as the Python client's `drive(linear, angular, hold=0.25)`: sent
   * at once and repeated at 20 Hz for `hold` s (a page holding a key calls it at 20 Hz);
   * (0, 0) releases (sent 4 times). While no call is up (reconnecting) nothing is sent
   * and nothing waits: a motion is never replayed on the next call (§18). Throws a
   * RangeError on a number that is not finite.
   * @param {number} linear m/s @param {number} angular rad/s
   * @param {{hold?: number}} [options]
   */
  drive(linear, angular, { hold } = {}) {
    if (!Number.isFinite(linear) || !Number.isFinite(angular)) {
      throw new RangeError("drive: linear and angular must be finite numbers");
    }
    this.services?.drive.drive(linear, angular, { hold, now: this.clock.now() });
  }

  /** The page's `{type: "drive", linear, angular}` (§19). */
  onDrive(msg) {
    const { linear, angular } = msg;
    if (typeof linear !== "number" || typeof angular !== "number" || !Number.isFinite(linear) || !Number.isFinite(angular)) {
      // Fail safe: a page that says nonsense stops driving (a release if it was driving).
      if (this.services?.drive.driving) this.services.drive.drive(0, 0, { now: this.clock.now() });
      return this.pageError("a drive needs finite numbers linear, angular");
    }
    if (!this.mayDrive) return this.pageError("observers may not drive");
    this.drive(linear, angular);
  }

  onDriveState(state) {
    // The page's message calls the robot's words `text` (its wire field is `reason`).
    const { reason, ...fields } = state;
    const msg = { type: "drive_state", ...fields, text: reason };
    this.latest.drive = msg;
    this.emit(msg);
  }

  chat(id, line) {
    line = line.trim();
    if (!line) return;
    this.services?.drive.cancel(); // a chat motion ends direct driving: no repeat may replace it
    const reply = (r) => this.emit({ type: "chat", id, text: r.text, ok: r.ok, final: r.final, code: r.code });
    const attempt = (left) => this.onCall(() => {
      let first = true;
      this.services.chat.request(line, (r) => {
        // Just after set-up the robot may refuse a motion until it measured the round trip.
        if (first && r.final && !r.ok && r.code === "rtt_unmeasured" && left > 0) {
          this.later(UNMEASURED_WAIT, () => attempt(left - 1));
          return;
        }
        first = false;
        reply(r);
      }, { now: this.clock.now() }).catch((err) => {
        reply({ text: err.code === "timeout" ? "timed out" : err.message, ok: false, final: true, code: "" });
      });
    }, (reason) => reply({ text: reason, ok: false, final: true, code: "" }));
    attempt(UNMEASURED_RETRIES);
  }

  say(id, text) {
    const answer = (ok, text, code) => this.emit({ type: "said", id, ok, text, code });
    this.onCall(
      () => this.services.conference.say(text, { now: this.clock.now() }).then(
        (said) => answer(said.ok, said.reason, said.code),
        (err) => answer(false, err.code === "timeout" ? "no answer" : err.message, ""),
      ),
      (reason) => answer(false, reason, ""),
    );
  }

  /**
   * The page's `media` message (§19.1, on every open): what it decodes (the robot's
   * codec list on `video`) and encodes. Answered with `{type: "media", send, codec, note}`,
   * and again whenever the answer changes (the robot's codec list on `video/user`).
   */
  onMedia(msg) {
    const names = Array.isArray(msg.decode) ? msg.decode.filter((c) => c === "h264" || c === "vp8" || c === "jpeg") : [];
    const ids = [...new Set(names.length ? names : ["jpeg"])].map((c) => CODEC_IDS[c]);
    this.videoCodecs = ids;
    this.services?.video.setCodecs(ids);
    const encode = Array.isArray(msg.encode) ? msg.encode.filter((c) => PAGE_CODECS.includes(c)) : [];
    this.mediaEncode = [...new Set(encode)];
    this.mediaTold = null; // a page that (re)opened is told at once
    this.tellMedia();
  }

  /** The `media` answer for the page now (the Python relay's, for its sending page). */
  mediaMessage() {
    const mine = (this.mediaEncode ?? []).map((c) => CODEC_IDS[c]);
    if (!mine.length) {
      return {
        type: "media", send: false, codec: "",
        note: "this browser cannot send your camera or microphone (it has no WebCodecs): the call goes on without them",
      };
    }
    const robot = this.services?.userMedia.video.codecs ?? [];
    const chosen = robot.length ? chooseCodec(robot, mine) : mine[0];
    if (chosen === null) {
      return { type: "media", send: false, codec: "", note: "the robot decodes none of the video codecs this browser encodes" };
    }
    return { type: "media", send: true, codec: CODEC_NAMES[chosen], note: "" };
  }

  /** Tell the page whether and in which codec to send, when that changed (or never told). */
  tellMedia() {
    if (this.mediaEncode === null) return; // the page has not said what it can do yet
    const msg = this.mediaMessage();
    const key = JSON.stringify(msg);
    if (key === this.mediaTold) return;
    this.mediaTold = key;
    this.emit(msg);
  }

  /**
   * One of the page's encoded pictures or Opus packets (§19.1: `header` as the websocket's,
   * `data` the bytes) to the robot, on `video/user` or `audio/user`. Returns whether it
   * went on the call (false: not asked for now, no call, malformed; a page makes its next
   * picture a keyframe then). A malformed one is answered with an `error` naming the fault.
   * @param {object} header @param {Uint8Array|ArrayBuffer} data @param {string} [type]
   */
  sendMedia(header, data, type = header?.kind) {
    let media;
    try {
      if (header?.kind !== type) throw new Error(`a '${type}' message with a header of kind ${JSON.stringify(header?.kind ?? null)}`);
      media = parseMediaMessage(header, data, this.mediaEncode ?? PAGE_CODECS);
    } catch (err) {
      this.mediaErrors += 1;
      this.pageError(`media dropped: ${err.message}`);
      return false;
    }
    if (!this.mediaEncode?.length) return false; // this page does not send (it never said it encodes)
    const s = this.services;
    if (!s) return false; // reconnecting: a picture now is a gap the robot sees
    const now = this.clock.now();
    return media.kind === "video" ? s.userMedia.sendPicture(media, now) : s.userMedia.sendPacket(media, now);
  }

  /** The page's binary websocket message of §19.1 (a page written for the local client). */
  sendBinary(message) {
    let unpacked;
    try {
      unpacked = unpackMedia(message);
    } catch (err) {
      this.mediaErrors += 1;
      this.pageError(`media dropped: ${err.message}`);
      return false;
    }
    return this.sendMedia(unpacked.header, unpacked.data);
  }

  /** Watch the robot's camera (true, the default) or not (false: a BYE). */
  setVideo(wanted) {
    this.videoWanted = wanted;
    this.services?.video.setWanted(wanted, this.clock.now());
  }

  /** Hear the robot's microphone (true, the default) or not. */
  setAudio(wanted) {
    this.audioWanted = wanted;
    this.services?.audio.setWanted(wanted, this.clock.now());
  }

  /** The topics this user may relay (§17.5): [{name, type, schema, encoding}]. */
  topics({ timeout = 5 } = {}) {
    return new Promise((resolve, reject) => {
      this.onCall(
        () => this.services.relay.topics({ timeout, now: this.clock.now() }).then(resolve, reject),
        (reason) => reject(new RequestFailed(reason, reason === "no answer" ? "timeout" : "call_ended")),
        timeout,
      );
    });
  }

  /**
   * Relay a robot topic (§17.5), as the Python client's `robot.relay(topic, rate=…,
   * latest_only=…)`: resolves with a {@link TopicStream} (`onmessage({topic, type, data,
   * stamp})` with the CDR bytes as on the robot, or `for await`; `close()` stops it). It
   * ends (`onend(reason)`, `ended`) when the robot ends it or with the call it started on
   * (a reconnection does not resume it). Rejects with {@link RelayRefused} (`code`:
   * `unknown_topic` with `near`, `topic_not_allowed`, `too_many_relays`, `failed`) or
   * RequestFailed (no answer in `timeout` s, the call ended); a bad `rate` is a RangeError.
   * @param {string} topic @param {{rate?: number|null, latestOnly?: boolean, onMessage?: Function, timeout?: number}} [options]
   */
  relay(topic, { rate = null, latestOnly = false, onMessage = null, timeout = 5 } = {}) {
    return new Promise((resolve, reject) => {
      this.onCall(
        () => this.services.relay.start(topic, { rate, latestOnly, onMessage, timeout, now: this.clock.now() }).then(resolve, reject),
        (reason) => reject(new RequestFailed(reason, reason === "no answer" ? "timeout" : "call_ended")),
        timeout,
      );
    });
  }

  later(seconds, fn) {
    this.clock.sleep(seconds).then(() => {
      if (!this.closing) fn();
    });
  }

  /** Datagrams dropped as malformed so far, by service (this call's and earlier ones'). */
  get drops() {
    const out = { ...this.pastDrops };
    for (const [name, service] of Object.entries(this.services ?? {})) {
      out[name] = (out[name] ?? 0) + (service.drops?.total ?? service.stats?.malformed ?? 0);
    }
    out.conference = (out.conference ?? 0) + this.conference.drops.total;
    return out;
  }
}
