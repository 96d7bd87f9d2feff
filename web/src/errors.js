/**
 * The errors of telebot's browser client. Every message is one line, never a dump of
 * the input, so a page can show it as it is.
 * @module errors
 */

/** Bytes that are not a valid frame, message or key (a decoder's only error). */
export class ProtocolError extends Error {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "ProtocolError";
  }
}

/** A call could not be set up, or was used wrongly (the base of the call errors). */
export class CallError extends Error {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "CallError";
  }
}

/** The robot refused the call; the message is the robot's reason. */
export class CallRejected extends CallError {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "CallRejected";
  }
}

/** The robot did not answer within the connect timeout. */
export class CallTimeout extends CallError {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "CallTimeout";
  }
}

/** The robot is online with another key than the one the user stored (§2.2). */
export class KeyMismatch extends CallError {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "KeyMismatch";
  }
}

/** The call was hung up or dropped: sending on it is an error. */
export class CallEnded extends CallError {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "CallEnded";
  }
}
