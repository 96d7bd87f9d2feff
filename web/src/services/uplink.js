/**
 * The user's camera and microphone to the robot (docs/protocol.md §19.1, §25), as the
 * Python web UI's relay does it (src/telebot/apps/web/media_relay.py): the page's encoded
 * pictures and Opus packets, never decoded or re-encoded here, become `video/user`
 * FRAGMENTs (§17.1/§25.1: camera `user`, the keyframe bit, this side's own frame ids and
 * seq) and `audio/user` AUDIO packets (§25.3: this side's own seq) on the call.
 *
 * The robot's REPORTs on each are the subscription (§25): before the call's first report
 * the user sends unasked for {@link USER_MEDIA_PROBE} s from its first picture (packet),
 * then while reports come (a `BYE` or 2 s without one stops it). A report of `video/user`
 * carries the robot's codec list (the page's codec is chosen from it) and its KEYFRAME
 * flag, passed to the page as a keyframe request at most once per max(RTT, 300 ms).
 * Its counters go to the page as they came (`onReport`, the page's `uplink_report`
 * message, as the Python relay passes them on): the page's encoder sets its bit rate from
 * them (static/uplink-rate.js).
 *
 * Sans-IO parts ({@link parseMediaMessage}, {@link unpackMedia}, {@link VideoUplink},
 * {@link AudioUplink}) take `now` in seconds; {@link UserMediaService} puts them on a call.
 * @module services/uplink
 */
import { DecodeError, DropCounter, U32, callSafely, decodeUtf8, serialDiff } from "./util.js";
import { CODEC_IDS, CODEC_JPEG, CODEC_NAMES, encodeAudio, fragmentFrame, parseReport } from "./video.js";

export const USER_VIDEO = "video/user";
export const USER_AUDIO = "audio/user";
/** The camera name of the user's pictures on `video/user` (the reference user's). */
export const USER_CAMERA = "user";
/** Seconds the user sends unasked from its first picture (packet) before any report. */
export const USER_MEDIA_PROBE = 2.0;
/** The robot stops asking this long after its last report (s). */
export const IDLE_AFTER = 2.0;
/** A keyframe request of the robot goes to the page at most this often (s; or the RTT). */
export const KEY_GAP = 0.3;
/** Longest JSON header of a page's binary media message (bytes). */
export const MAX_HEADER = 1024;
/** Largest picture a page may send (bytes). */
export const MAX_VIDEO_FRAME = 2_000_000;
/** Largest Opus packet a page may send (bytes). */
export const MAX_AUDIO_PACKET = 1500;
/** Codecs a page may send its camera in (what WebCodecs encodes; never JPEG). */
export const PAGE_CODECS = ["vp8", "h264"];

function isNumber(value) {
  return typeof value === "number" && Number.isFinite(value);
}

function u32Field(header, name) {
  const value = header[name];
  if (!Number.isInteger(value) || value < 0 || value >= U32) {
    throw new DecodeError(`${name} must be an integer 0..2^32-1, got ${String(JSON.stringify(value)).slice(0, 40)}`);
  }
  return value;
}

function asBytes(data) {
  if (data instanceof Uint8Array) return data;
  if (data instanceof ArrayBuffer) return new Uint8Array(data);
  if (ArrayBuffer.isView(data)) return new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  return null;
}

/**
 * Check one of the page's media messages (§19.1) as the Python relay's `parse_media`
 * does: `{kind: "video", codec, key, frame_id, capture_time, camera?}` with one encoded
 * picture, or `{kind: "audio", seq, capture_time}` with one Opus packet. `codecs` are the
 * video codecs accepted (those the page said it encodes). Returns {kind, number, captureTime,
 * data, codec, key}; DecodeError (one line naming the fault) when not as above.
 * @param {any} header @param {Uint8Array|ArrayBuffer} data @param {string[]} [codecs]
 */
export function parseMediaMessage(header, data, codecs = PAGE_CODECS) {
  if (header === null || typeof header !== "object" || Array.isArray(header)) throw new DecodeError("the media header is not a JSON object");
  const bytes = asBytes(data);
  if (!bytes) throw new DecodeError("the media data is not bytes");
  const capture = header.capture_time;
  if (typeof capture !== "number") throw new DecodeError(`capture_time must be a number, got ${String(JSON.stringify(capture)).slice(0, 40)}`);
  if (!isNumber(capture) || capture < 0) throw new DecodeError(`capture_time must be finite and >= 0, got ${capture}`);
  const kind = header.kind;
  if (kind === "video") {
    const codec = header.codec;
    if (!codecs.includes(codec)) throw new DecodeError(`video codec ${String(JSON.stringify(codec)).slice(0, 40)} not offered (offered: ${codecs.join(", ")})`);
    if (typeof header.key !== "boolean") throw new DecodeError(`key must be true or false, got ${String(JSON.stringify(header.key)).slice(0, 40)}`);
    if (!(bytes.length > 0 && bytes.length <= MAX_VIDEO_FRAME)) throw new DecodeError(`a video frame must be 1..${MAX_VIDEO_FRAME} bytes, got ${bytes.length}`);
    return { kind, number: u32Field(header, "frame_id"), captureTime: capture, data: bytes, codec, key: header.key };
  }
  if (kind === "audio") {
    if (!(bytes.length > 0 && bytes.length <= MAX_AUDIO_PACKET)) throw new DecodeError(`an Opus packet must be 1..${MAX_AUDIO_PACKET} bytes, got ${bytes.length}`);
    return { kind, number: u32Field(header, "seq"), captureTime: capture, data: bytes, codec: "opus", key: false };
  }
  throw new DecodeError(`unknown media kind ${String(JSON.stringify(kind ?? null)).slice(0, 40)} (video or audio)`);
}

/**
 * Split today's binary websocket message (§19.1: a 4-byte big-endian header length
 * 2..1024, the UTF-8 JSON header, the bytes) into {header, data}; DecodeError if malformed.
 * @param {ArrayBuffer|Uint8Array} message
 */
export function unpackMedia(message) {
  const bytes = asBytes(message);
  if (!bytes || bytes.length < 4) throw new DecodeError("a media message needs a 4-byte header length");
  const length = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength).getUint32(0);
  if (length < 2 || length > MAX_HEADER || bytes.length < 4 + length) throw new DecodeError(`bad media header length ${length}`);
  let header;
  try {
    header = JSON.parse(decodeUtf8(bytes.subarray(4, 4 + length), "the media header"));
  } catch {
    throw new DecodeError("the media header is not JSON");
  }
  if (header === null || typeof header !== "object" || Array.isArray(header)) throw new DecodeError("the media header is not a JSON object");
  return { header, data: bytes.subarray(4 + length) };
}

/**
 * The video codec a sender uses for a receiver that accepts `accepted` (best first; empty:
 * an old receiver, JPEG), from what it can encode, `preferred` (its own first choice
 * first): the sender's first preference the receiver takes, or null (§25.2).
 */
export function chooseCodec(accepted, preferred) {
  if (!accepted.length) return preferred.includes(CODEC_JPEG) ? CODEC_JPEG : null;
  return preferred.find((c) => accepted.includes(c)) ?? null;
}

/**
 * The page's `uplink_report` message (§19.1) for a parsed REPORT of `video/user`: its
 * counters under the wire's names, as the Python relay's `uplink_report()` writes them.
 */
export function uplinkReport(report) {
  return {
    type: "uplink_report",
    receiver_ms: report.receiverMs,
    highest_seq: report.highestSeq,
    fragments: report.fragments,
    bytes: report.bytes,
    frames: report.frames,
    dropped: report.dropped,
    queue_delay_ms: report.queueDelayMs,
  };
}

/**
 * When a stream of the user's may go (§25): reports keep it going; before the first one,
 * {@link USER_MEDIA_PROBE} s from the first wish to send. A report older than the last
 * accepted one (by `receiver_ms`) is ignored, so it cannot undo a `BYE`.
 */
class Subscription {
  constructor() {
    this.lastReport = null;
    this.lastReportMs = null;
    this.probeFrom = null;
    this.bye = false;
    this.reports = 0;
  }

  wanted(now) {
    if (this.lastReport === null) return this.probeFrom === null || now - this.probeFrom <= USER_MEDIA_PROBE;
    return !this.bye && now - this.lastReport <= IDLE_AFTER;
  }

  /** Called just before sending: the probe starts with the first thing offered. */
  offer(now) {
    if (this.lastReport === null && this.probeFrom === null) this.probeFrom = now;
  }

  /** Take a parsed report; false when it is older than the last one taken. */
  take(report, now) {
    if (this.lastReportMs !== null && serialDiff(report.receiverMs, this.lastReportMs) < 0) return false;
    this.lastReport = now;
    this.lastReportMs = report.receiverMs;
    this.bye = report.bye;
    this.reports += 1;
    return true;
  }
}

/** The user's camera on `video/user` (sans-IO): pictures in, FRAGMENT datagrams out. */
export class VideoUplink {
  constructor() {
    this.subscription = new Subscription();
    this.seq = 0;
    /** The next frame id: +1 per picture taken while the robot asks, sent or not. */
    this.frameId = 0;
    /** The robot's codec list from its last report, best first (empty: none yet). */
    this.codecs = [];
    this.keysAskedAt = null;
    this.sent = 0;
    this.dropped = 0;
    this.keyframeRequests = 0;
  }

  wanted(now) {
    return this.subscription.wanted(now);
  }

  /**
   * One REPORT from the robot: {codecsChanged, wantedChanged, keyframe, report} (`keyframe`:
   * pass a request to the page now; `report`: the parsed REPORT), or null when it was older
   * than the last one. Throws DecodeError when malformed.
   */
  onReport(payload, now, rtt = null) {
    const report = parseReport(payload);
    const was = this.wanted(now);
    if (!this.subscription.take(report, now)) return null;
    const codecsChanged = report.codecs.length !== this.codecs.length || report.codecs.some((c, i) => c !== this.codecs[i]);
    this.codecs = report.codecs;
    let keyframe = false;
    if (report.keyframe && (this.keysAskedAt === null || now - this.keysAskedAt >= Math.max(KEY_GAP, rtt ?? 0))) {
      this.keysAskedAt = now;
      this.keyframeRequests += 1;
      keyframe = true;
    }
    return { codecsChanged, wantedChanged: was !== this.wanted(now), keyframe, report };
  }

  /**
   * One encoded picture (`codec` "vp8" | "h264" | "jpeg"): its FRAGMENT datagrams, or
   * null when the robot does not ask for it now (or it cannot be cut: over 64 fragments).
   */
  picture({ codec, key, captureTime, data }, now) {
    if (!this.wanted(now)) return null;
    this.subscription.offer(now);
    const frameId = this.frameId;
    this.frameId = (frameId + 1) % U32;
    let datagrams;
    try {
      datagrams = fragmentFrame({ frameId, camera: USER_CAMERA, captureTime, data, seq: this.seq, codec: CODEC_IDS[codec], keyframe: key });
    } catch {
      this.dropped += 1; // the robot sees the gap in frame ids and asks for a keyframe
      return null;
    }
    this.seq = (this.seq + datagrams.length) % U32;
    return datagrams;
  }
}

/** The user's microphone on `audio/user` (sans-IO): Opus packets in, AUDIO datagrams out. */
export class AudioUplink {
  constructor() {
    this.subscription = new Subscription();
    this.seq = 0;
    this.sent = 0;
    this.dropped = 0;
  }

  wanted(now) {
    return this.subscription.wanted(now);
  }

  /** One REPORT from the robot; false when older than the last; DecodeError when malformed. */
  onReport(payload, now) {
    return this.subscription.take(parseReport(payload), now);
  }

  /** One Opus packet: its AUDIO datagram, or null when the robot does not listen now. */
  packet({ captureTime, data }, now) {
    if (!this.wanted(now)) return null;
    this.subscription.offer(now);
    const datagram = encodeAudio(this.seq, captureTime, data);
    this.seq = (this.seq + 1) % U32;
    return datagram;
  }
}

/**
 * The user's camera and microphone on one call: `video/user` and `audio/user` (BULK).
 * `onKeyframe()` when the robot asks for a keyframe of the user's camera; `onChange()`
 * when its codec list (or whether it asks) changed, so the page may be told again;
 * `onReport(message)` with each of its REPORTs on `video/user` (but a `BYE`) as the page's
 * `uplink_report` message ({@link uplinkReport}).
 */
export class UserMediaService {
  constructor(theCall, { onKeyframe = null, onChange = null, onReport = null, rtt = () => null } = {}) {
    this.video = new VideoUplink();
    this.audio = new AudioUplink();
    this.videoChannel = theCall.channel(USER_VIDEO, { lane: "bulk" });
    this.audioChannel = theCall.channel(USER_AUDIO, { lane: "bulk" });
    this.videoChannel.onmessage = (payload) => this.onVideoReport(payload);
    this.audioChannel.onmessage = (payload) => this.onAudioReport(payload);
    this.onKeyframe = onKeyframe;
    this.onChange = onChange;
    this.onReport = onReport;
    this.rtt = rtt;
    this.drops = new DropCounter();
    this.now = 0;
  }

  onVideoReport(payload) {
    let result;
    try {
      result = this.video.onReport(payload, this.now, this.rtt());
    } catch (err) {
      if (!(err instanceof DecodeError)) throw err;
      this.drops.add("video_report");
      return;
    }
    if (!result) return;
    if (result.codecsChanged || result.wantedChanged) callSafely(this.onChange);
    if (result.keyframe) callSafely(this.onKeyframe);
    if (!result.report.bye) callSafely(this.onReport, uplinkReport(result.report));
  }

  onAudioReport(payload) {
    try {
      this.audio.onReport(payload, this.now);
    } catch (err) {
      if (!(err instanceof DecodeError)) throw err;
      this.drops.add("audio_report");
    }
  }

  /**
   * Send one checked picture ({@link parseMediaMessage}); whether all of it went. False
   * also when the link dropped a fragment (its websocket congested: the rest is not sent,
   * `video.dropped` counts it): the page makes its next picture a keyframe then.
   */
  sendPicture(msg, now = this.now) {
    const datagrams = this.video.picture(msg, now);
    if (!datagrams) return false;
    try {
      for (const d of datagrams) {
        if (this.videoChannel.send(d) === false) {
          this.video.dropped += 1; // the rest of the frame is a gap the robot sees
          return false;
        }
      }
    } catch {
      this.video.dropped += 1; // the rest of the frame is a gap the robot sees
      return false;
    }
    this.video.sent += 1;
    return true;
  }

  /** Send one checked Opus packet; whether it went (`audio.dropped` counts the link's drops). */
  sendPacket(msg, now = this.now) {
    const datagram = this.audio.packet(msg, now);
    if (!datagram) return false;
    try {
      if (this.audioChannel.send(datagram) === false) {
        this.audio.dropped += 1;
        return false;
      }
    } catch {
      return false;
    }
    this.audio.sent += 1;
    return true;
  }

  /** The codec names the robot decodes on `video/user`, best first ([] before its first report). */
  get robotCodecs() {
    return this.video.codecs.map((c) => CODEC_NAMES[c]).filter(Boolean);
  }

  tick(now) {
    this.now = now;
  }

  close() {
    this.videoChannel.onmessage = null;
    this.audioChannel.onmessage = null;
  }
}
