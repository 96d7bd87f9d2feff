/**
 * Decoders and encoders of the JSON channels a user receives (docs/protocol.md §14, §16,
 * §18, §20, §23): each decoder takes one datagram and returns a plain object, or throws a
 * one-line {@link DecodeError}; unknown keys are ignored (newer robots may add some).
 * @module services/messages
 */
import {
  DecodeError,
  MAX_SAFE,
  decodeCode,
  decodeObject,
  encodeObject,
  finiteNumber,
  flag,
  isFiniteNumber,
  optionalNumber,
  optionalText,
  requireInt,
  text,
} from "./util.js";

// ------------------------------------------------------------------------------ chat §14

/** Longest chat request text (characters). */
export const MAX_CHAT_TEXT = 1000;

/** The request datagram `{"id", "text"}`. */
export function encodeChatRequest(id, line) {
  return encodeObject({ id, text: line });
}

/**
 * A chat reply: {id, seq, text, final, ok, attachment, code}.
 * @param {string|Uint8Array} payload
 */
export function decodeChatReply(payload) {
  const what = "chat reply";
  const msg = decodeObject(payload, what);
  const id = requireInt(msg, "id", what);
  const seq = requireInt(msg, "seq", what);
  const replyText = text(msg, "text", what);
  const final = flag(msg, "final", what);
  const ok = flag(msg, "ok", what);
  const attachment = msg.attachment ?? null;
  if (attachment !== null && typeof attachment !== "string") {
    throw new DecodeError(`${what}: 'attachment' must be a string`);
  }
  return { id, seq, text: replyText, final, ok, attachment, code: decodeCode(msg, what) };
}

/** The message of a chat line `say TEXT`, or null when the line is no say (§19). */
export function sayText(line) {
  const trimmed = line.trim();
  const space = trimmed.search(/\s/);
  const word = space < 0 ? trimmed : trimmed.slice(0, space);
  if (word.toLowerCase() !== "say") return null;
  return space < 0 ? "" : trimmed.slice(space).trim();
}

// ------------------------------------------------------------------------- pose §16.1

/** A `pose` datagram: {t, x, y, yaw, cov, v, w, state, detail, goal}. */
export function decodePose(payload) {
  const what = "pose";
  const msg = decodeObject(payload, what);
  const cov = msg.cov;
  if (!Array.isArray(cov) || cov.length !== 3 || !cov.every(isFiniteNumber)) {
    throw new DecodeError("pose: 'cov' must be a list of 3 numbers");
  }
  const goal = msg.goal == null ? null : requireInt(msg, "goal", what);
  return {
    t: finiteNumber(msg, "t", what),
    x: finiteNumber(msg, "x", what),
    y: finiteNumber(msg, "y", what),
    yaw: finiteNumber(msg, "yaw", what),
    cov: [cov[0], cov[1], cov[2]],
    v: finiteNumber(msg, "v", what),
    w: finiteNumber(msg, "w", what),
    state: text(msg, "state", what),
    detail: text(msg, "detail", what, ""),
    goal,
  };
}

// ------------------------------------------------------------------------ goals §16.2

export const GOAL_STATES = ["active", "succeeded", "failed", "cancelled", "refused", "unknown"];

/** A user → robot `goals` request: type goal (x, y, yaw|null), cancel or query. */
export function encodeGoalCommand(type, id, x = 0, y = 0, yaw = null) {
  if (type !== "goal") return encodeObject({ type, id });
  const msg = { type: "goal", id, x, y };
  if (yaw != null) msg.yaw = yaw;
  return encodeObject(msg);
}

/** A robot → user `status`: {id, status, progress, text (the wire's reason), code, final}. */
export function decodeGoalUpdate(payload) {
  const what = "goals";
  const msg = decodeObject(payload, what);
  if (msg.type !== "status") throw new DecodeError("goals: unknown type");
  const status = text(msg, "status", what);
  if (!GOAL_STATES.includes(status)) throw new DecodeError("goals: unknown status");
  return {
    id: requireInt(msg, "id", what),
    status,
    progress: finiteNumber(msg, "progress", what),
    text: text(msg, "reason", what, ""),
    code: decodeCode(msg, what),
    final: status !== "active",
  };
}

// -------------------------------------------------------------------- telemetry §16.3

/**
 * A `telemetry` datagram with every field of §16.3 (optional ones filled in as absent
 * means), in the order the Python client's page message has them.
 */
export function decodeTelemetry(payload) {
  const what = "telemetry";
  const msg = decodeObject(payload, what);
  const diagnostics = msg.diagnostics ?? {};
  if (
    diagnostics === null ||
    typeof diagnostics !== "object" ||
    Array.isArray(diagnostics) ||
    !Object.values(diagnostics).every((v) => typeof v === "string")
  ) {
    throw new DecodeError("telemetry: 'diagnostics' must map names to text");
  }
  const int = (key, high) => (key in msg ? requireInt(msg, key, what, 0, high) : 0);
  return {
    t: finiteNumber(msg, "t", what),
    battery: finiteNumber(msg, "battery", what),
    battery_low: flag(msg, "battery_low", what),
    state: text(msg, "state", what),
    detail: text(msg, "detail", what, ""),
    goal: optionalText(msg, "goal", what),
    progress: optionalNumber(msg, "progress", what),
    camera: text(msg, "camera", what),
    speed_limit: finiteNumber(msg, "speed_limit", what),
    rtt: optionalNumber(msg, "rtt", what),
    loss: finiteNumber(msg, "loss", what),
    role: text(msg, "role", what),
    diagnostics: { ...diagnostics },
    armed: flag(msg, "armed", what),
    stop_reason: text(msg, "stop_reason", what, ""),
    holder: optionalText(msg, "holder", what),
    video_fps: "video_fps" in msg ? finiteNumber(msg, "video_fps", what) : 0,
    video_width: int("video_width", 65535),
    video_height: int("video_height", 65535),
    video_quality: int("video_quality", 100),
    map_version: int("map_version", MAX_SAFE),
    rx_dropped: int("rx_dropped", MAX_SAFE),
  };
}

// -------------------------------------------------------------------------- safety §18

/**
 * The stop `how`s of §18's table (another value from the page becomes `button`): the
 * page's own `touch` (its video touched) and `page_hidden` (hidden or frozen) among them.
 */
export const STOP_HOWS = ["button", "key", "tab_closed", "page_hidden", "touch", "exit", "api"];

/** A user → robot safety request. */
export function encodeSafetyRequest(type, id, how = "") {
  return encodeObject(type === "stop" && how ? { type, id, how } : { type, id });
}

/**
 * A robot → user `safety` datagram: {type: "ack", id, ok, reason, code} |
 * {type: "state", armed, reason, code, holder, cap, blocked} | {type: "error", reason, code}.
 * A state's `code` is the reason code of the latest stop (§18: `ok` while armed;
 * `link_silent` the deadman, `video_stale` a frozen picture, `dropped` the holder's call
 * dropped — the robot stopped itself — `stopped` someone's stop, …; "" from an older robot).
 */
export function decodeSafetyReply(payload) {
  const what = "safety";
  const msg = decodeObject(payload, what);
  switch (msg.type) {
    case "ack":
      return {
        type: "ack",
        id: requireInt(msg, "id", what),
        ok: flag(msg, "ok", what),
        reason: text(msg, "reason", what, ""),
        code: decodeCode(msg, what),
      };
    case "state":
      return {
        type: "state",
        armed: flag(msg, "armed", what),
        reason: text(msg, "reason", what, ""),
        code: decodeCode(msg, what),
        holder: optionalText(msg, "holder", what),
        cap: finiteNumber(msg, "cap", what),
        blocked: flag(msg, "blocked", what),
      };
    case "error":
      return { type: "error", reason: text(msg, "reason", what, ""), code: decodeCode(msg, what) };
    default:
      throw new DecodeError("safety: unknown type");
  }
}

// ----------------------------------------------------------------- plan, places §16.4

const MAX_PLACE_NAME = 256;
const MAX_PLAN_POINTS = Math.floor(32768 / 6);

/** A `plan` channel datagram: {type: "plan", seq, goal, points} | {type: "places", places}. */
export function decodePlanMessage(payload) {
  const what = "plan";
  const msg = decodeObject(payload, what);
  if (msg.type === "plan") {
    const goal = msg.goal == null ? null : requireInt(msg, "goal", what);
    const points = msg.points;
    if (!Array.isArray(points) || points.length > MAX_PLAN_POINTS) {
      throw new DecodeError("plan: 'points' must be a list of [x, y] pairs");
    }
    for (const p of points) {
      if (!Array.isArray(p) || p.length !== 2 || !p.every(isFiniteNumber)) {
        throw new DecodeError("plan: each point must be [x, y], two finite numbers");
      }
    }
    return {
      type: "plan",
      seq: requireInt(msg, "seq", what, 0, MAX_SAFE),
      goal,
      points: points.map((p) => [p[0], p[1]]),
    };
  }
  if (msg.type === "places") {
    if (!Array.isArray(msg.places)) throw new DecodeError("places: 'places' must be a list");
    const places = msg.places.map((entry) => {
      if (entry === null || typeof entry !== "object" || Array.isArray(entry)) {
        throw new DecodeError("places: each place must be an object");
      }
      const name = entry.name;
      if (typeof name !== "string" || name.length === 0 || name.length > MAX_PLACE_NAME) {
        throw new DecodeError(`places: 'name' must be text of 1..${MAX_PLACE_NAME} characters`);
      }
      const { x, y, yaw } = entry;
      if (!isFiniteNumber(x) || !isFiniteNumber(y) || !(yaw == null || isFiniteNumber(yaw))) {
        throw new DecodeError("places: a place needs finite numbers x, y (and yaw or null)");
      }
      return { name, x, y, yaw: yaw ?? null };
    });
    return { type: "places", places };
  }
  throw new DecodeError("plan: unknown type");
}

// ---------------------------------------------------------------------- people §23

const MAX_TRACKS = 100;
const MAX_ALERT_TEXT = 200;
const SOURCES = ["laser", "camera"];

/**
 * A `people` channel datagram, as the page gets it: {type: "people", seq, t, cams,
 * tracks: [{id, x, y, vx, vy, c, src, r, b}]} | {type: "alert", seq, kind, id, text,
 * distance, bearing}.
 */
export function decodePeopleMessage(payload) {
  const what = "people";
  const msg = decodeObject(payload, what);
  if (msg.type === "people") {
    const tracks = msg.tracks;
    if (!Array.isArray(tracks) || tracks.length > MAX_TRACKS) {
      throw new DecodeError(`people: 'tracks' must be a list of at most ${MAX_TRACKS}`);
    }
    const cams = msg.cams ?? {};
    if (cams === null || typeof cams !== "object" || Array.isArray(cams)) {
      throw new DecodeError("people: 'cams' must be an object of camera fields of view");
    }
    const cameras = {};
    for (const [name, fov] of Object.entries(cams)) {
      if (!isFiniteNumber(fov) || !(fov > 0 && fov < 180)) {
        throw new DecodeError("people: a camera needs a field of view in (0, 180)");
      }
      cameras[name] = fov;
    }
    return {
      type: "people",
      seq: requireInt(msg, "seq", what, 0, MAX_SAFE),
      t: finiteNumber(msg, "t", what),
      cams: cameras,
      tracks: tracks.map(decodeTrack),
    };
  }
  if (msg.type === "alert") {
    const w = "people alert";
    if (msg.kind !== "approaching" && msg.kind !== "screen") {
      throw new DecodeError("people alert: unknown kind");
    }
    const alertText = msg.text;
    if (typeof alertText !== "string" || alertText.length === 0 || alertText.length > MAX_ALERT_TEXT) {
      throw new DecodeError(`people alert: 'text' must be 1..${MAX_ALERT_TEXT} characters`);
    }
    return {
      type: "alert",
      seq: requireInt(msg, "seq", w, 0, MAX_SAFE),
      kind: msg.kind,
      id: requireInt(msg, "id", w, 0, MAX_SAFE),
      text: alertText,
      distance: finiteNumber(msg, "distance", w),
      bearing: finiteNumber(msg, "bearing", w),
    };
  }
  throw new DecodeError("people: unknown type");
}

function decodeTrack(entry) {
  const what = "people track";
  if (entry === null || typeof entry !== "object" || Array.isArray(entry)) {
    throw new DecodeError("people: each track must be an object");
  }
  const src = entry.src ?? [];
  if (!Array.isArray(src) || !src.every((s) => SOURCES.includes(s))) {
    throw new DecodeError("people track: 'src' must be a list of 'laser' / 'camera'");
  }
  const c = finiteNumber(entry, "c", what);
  if (c < 0 || c > 1) throw new DecodeError("people track: 'c' must be in 0..1");
  return {
    id: requireInt(entry, "id", what, 0, MAX_SAFE),
    x: finiteNumber(entry, "x", what),
    y: finiteNumber(entry, "y", what),
    vx: finiteNumber(entry, "vx", what),
    vy: finiteNumber(entry, "vy", what),
    c,
    src: [...src].sort(),
    r: finiteNumber(entry, "r", what),
    b: finiteNumber(entry, "b", what),
  };
}

// ------------------------------------------------------------------- conference §20

const MAX_CONF_TEXT = 1000;
const MAX_NAME = 128;

function confText(msg, key) {
  const value = msg[key] ?? "";
  if (typeof value !== "string" || value.length > MAX_CONF_TEXT) {
    throw new DecodeError(`conference: '${key}' must be text of at most ${MAX_CONF_TEXT} characters`);
  }
  return value;
}

function confName(value) {
  if (typeof value !== "string" || value.length === 0 || value.length > MAX_NAME) {
    throw new DecodeError("conference: a user name must be non-empty text");
  }
  return value;
}

/**
 * A robot → user `conference` datagram: {type: "said", id, ok, reason, code} |
 * {type: "msg", seq, from, kind, text} | {type: "roster", seq, users: [{name, role,
 * driving, you}]}.
 */
export function decodeConferenceReply(payload) {
  const what = "conference";
  const msg = decodeObject(payload, what);
  switch (msg.type) {
    case "said":
      return {
        type: "said",
        id: requireInt(msg, "id", what),
        ok: flag(msg, "ok", what),
        reason: confText(msg, "reason"),
        code: decodeCode(msg, what),
      };
    case "msg":
      return {
        type: "msg",
        seq: requireInt(msg, "seq", what, 0, MAX_SAFE),
        from: confName(msg.from),
        kind: confText(msg, "kind"),
        text: confText(msg, "text"),
      };
    case "roster": {
      if (!Array.isArray(msg.users)) throw new DecodeError("conference: 'users' must be a list");
      const users = msg.users.map((user) => {
        if (user === null || typeof user !== "object" || Array.isArray(user)) {
          throw new DecodeError("conference: each user must be an object");
        }
        return {
          name: confName(user.name),
          role: confText(user, "role"),
          driving: user.driving === true,
          you: user.you === true,
        };
      });
      return { type: "roster", seq: requireInt(msg, "seq", what, 0, MAX_SAFE), users };
    }
    default:
      throw new DecodeError("conference: unknown type");
  }
}
