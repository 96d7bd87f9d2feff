/**
 * Driving by hand on the user's side (docs/protocol.md §27, the `drive` channel, CONTROL
 * lane), as the Python client's `client.drive(linear, angular, hold=0.25)`:
 *
 * - `drive(linear, angular)` sends the velocity at once and repeats it at 20 Hz (covering
 *   loss) for at most `hold` seconds, then stops sending, so the robot stops by itself
 *   (`drive.stale_after`, 0.3 s) unless drive() is called again: a caller keeps driving
 *   by calling it at ≥ 5 Hz while the user holds the key (a stuck caller stops the robot).
 * - `drive(0, 0)` is a release: the zero command is sent 4 times, at 0, 20, 40 and 90 ms.
 * - every datagram carries the next `seq` (a fresh counter per call, from a random start),
 *   so the robot takes each repeat as newer and a reordered old one never undoes a newer.
 * - the robot's `drive_state` is decoded strictly (a bad one is dropped and counted, as by
 *   the other services) and passed to `onState`.
 *
 * Sans-IO as the other services: `tick(now)` (the session's 20 ms tick) does the repeats.
 * @module services/drive
 */
import {
  DecodeError,
  DropCounter,
  QUICK_REPEATS,
  callSafely,
  decodeCode,
  decodeObject,
  encodeObject,
  finiteNumber,
  flag,
  idCounter,
  requireInt,
  safeSend,
  text,
} from "./util.js";

export const DRIVE = "drive";
/** Seconds between repeats of a command (20 Hz). */
export const DRIVE_REPEAT = 0.05;
/** Seconds a command is repeated for when the caller says nothing else. */
export const DRIVE_HOLD = 0.25;
/** Copies of the release (zero) command: at once, after QUICK_REPEATS, then at 20 Hz. */
export const RELEASE_COPIES = 4;
/** Longest `reason` taken from the robot (characters). */
export const MAX_REASON = 2000;

const WHAT = "drive_state";

/** The user → robot command datagram. */
export function encodeDrive(seq, linear, angular) {
  return encodeObject({ type: "drive", seq, linear, angular });
}

/**
 * A robot → user `drive_state`: {seq, active, code, reason, linear, angular, cap}.
 * Throws a one-line {@link DecodeError} when it is anything else.
 * @param {string|Uint8Array} payload
 */
export function decodeDriveState(payload) {
  const msg = decodeObject(payload, WHAT);
  if (msg.type !== "drive_state") throw new DecodeError(`${WHAT}: unknown type`);
  const reason = text(msg, "reason", WHAT, "");
  if (reason.length > MAX_REASON) throw new DecodeError(`${WHAT}: 'reason' is longer than ${MAX_REASON} characters`);
  const cap = finiteNumber(msg, "cap", WHAT);
  if (cap < 0) throw new DecodeError(`${WHAT}: 'cap' must not be negative`);
  return {
    seq: requireInt(msg, "seq", WHAT),
    active: flag(msg, "active", WHAT),
    code: decodeCode(msg, WHAT),
    reason,
    linear: finiteNumber(msg, "linear", WHAT),
    angular: finiteNumber(msg, "angular", WHAT),
    cap,
  };
}

/** The `drive` channel on one call. */
export class DriveService {
  /**
   * @param {import("../call.js").Call} theCall
   * @param {{random?: () => number, onState?: (state: object) => void}} [options]
   */
  constructor(theCall, { random = Math.random, onState = null } = {}) {
    this.channel = theCall.channel(DRIVE, { lane: "control" });
    this.channel.onmessage = (payload) => this.onMessage(payload);
    this.nextSeq = idCounter(random);
    this.onState = onState;
    this.drops = new DropCounter();
    /** The latest decoded drive_state (null until one came). */
    this.state = null;
    /** What is being repeated: {linear, angular, until, due, copies} or null. */
    this.command = null;
    /** Command datagrams sent (tests count them). */
    this.sent = 0;
    this.now = 0;
  }

  /**
   * Command this velocity now (m/s, rad/s; the robot clamps it): sent at once, repeated
   * at 20 Hz for `hold` s. The same velocity again while it repeats only extends the hold
   * (the 20 Hz cadence stays: a page calling at 20 Hz does not double the rate); a new
   * one is sent at once. (0, 0) releases: sent 4 times (0, 20, 40, 90 ms).
   * @param {number} linear @param {number} angular
   * @param {{hold?: number, now?: number}} [options]
   */
  drive(linear, angular, { hold = DRIVE_HOLD, now = this.now } = {}) {
    if (!Number.isFinite(linear) || !Number.isFinite(angular)) {
      throw new RangeError("drive: linear and angular must be finite numbers");
    }
    if (!Number.isFinite(hold) || hold < 0) throw new RangeError("drive: hold must be a finite number ≥ 0");
    linear = linear || 0; // -0 is 0 on the wire
    angular = angular || 0;
    if (linear === 0 && angular === 0) {
      const quick = [...QUICK_REPEATS];
      this.command = { linear: 0, angular: 0, until: Infinity, due: now + quick.shift(), copies: RELEASE_COPIES - 1, quick };
      this.send(0, 0);
      return;
    }
    const c = this.command;
    if (c && c.copies === null && c.linear === linear && c.angular === angular) {
      c.until = Math.max(c.until, now + hold);
      return;
    }
    this.command = { linear, angular, until: now + hold, due: now + DRIVE_REPEAT, copies: null };
    this.send(linear, angular);
  }

  /** Stop repeating (a stop was sent: it ends direct driving on the robot by itself). */
  cancel() {
    this.command = null;
  }

  /** Whether a non-zero command is being repeated now. */
  get driving() {
    return this.command !== null && this.command.copies === null;
  }

  send(linear, angular) {
    if (safeSend(this.channel, encodeDrive(this.nextSeq(), linear, angular))) this.sent += 1;
  }

  onMessage(payload) {
    let state;
    try {
      state = decodeDriveState(payload);
    } catch {
      this.drops.add("malformed");
      return;
    }
    this.state = state;
    callSafely(this.onState, state);
  }

  tick(now) {
    this.now = now;
    const c = this.command;
    if (!c || now < c.due) return;
    if (c.copies === null && now > c.until) {
      this.command = null; // the hold is over: the robot stops itself 0.3 s later
      return;
    }
    // From the schedule, not from now: the session ticks every 20 ms, so `now + 0.05`
    // would make 60 ms. A caller far behind (a throttled tab) starts a fresh schedule.
    const every = c.quick?.length > 0 ? c.quick.shift() : DRIVE_REPEAT;
    c.due = now - c.due > every ? now + every : c.due + every;
    this.send(c.linear, c.angular);
    if (c.copies !== null && --c.copies <= 0) this.command = null;
  }

  close() {
    this.channel.onmessage = null;
    this.command = null;
  }
}
