/**
 * The gateway over WebTransport (HTTP/3 over QUIC; docs/protocol.md §26.5), the page's
 * first choice: the same messages as the gateway's WebSocket, but a lost packet holds up
 * only its own message. PUTs and SAMPLEs go as one datagram each when they fit (lost, never
 * late: a call resends what matters), larger ones on a unidirectional stream of their own;
 * text messages (admission, `sub`, `alive`, …) on one bidirectional stream, in order.
 *
 * {@link WebTransportSocket} looks like a WebSocket to {@link GatewayLink}, so admission,
 * budgets and the link's API are the WebSocket's. {@link connectBest} tries it first and
 * falls back to the two WebSockets of {@link connectSplit}.
 * @module webtransport
 */
import { GatewayError, connectGateway, connectSplit } from "./gateway-link.js";

const encoder = new TextEncoder();
const decoder = new TextDecoder();

/** What opens the bidirectional stream, before its first text message (§26.5). */
export const PREAMBLE = encoder.encode("TBG1");
/** The largest message a gateway takes on a stream (a PUT's header, key and payload). */
export const MAX_MESSAGE = 3 + 256 + 33060 + 1024 + 8;
/** Datagrams the browser keeps for the page until it reads them (it drops the oldest beyond). */
export const INCOMING_DATAGRAMS = 1024;
/** Seconds a WebTransport admission may take before the page uses WebSockets instead. */
export const TRY_FOR = 5;
/** Seconds after a failed WebTransport attempt during which the page goes straight to WebSockets. */
export const FALLBACK_FOR = 60;
/**
 * Seconds a WebTransport admission may take once WebTransport has worked for this page:
 * UDP passes here, so a slow try is the network's loss (on `bad`, 5 %, two new QUIC
 * connections right after an outage took over 5 s now and then), not a block.
 */
export const RETRY_FOR = 15;

/** `u32 length ‖ UTF-8`: one text message on the bidirectional stream. */
export function textFrame(text) {
  const bytes = encoder.encode(text);
  const frame = new Uint8Array(4 + bytes.length);
  new DataView(frame.buffer).setUint32(0, bytes.length);
  frame.set(bytes, 4);
  return frame;
}

/**
 * Splits the bidirectional stream's bytes into text messages (`push(chunk)` returns those
 * completed; a message longer than `max` throws).
 */
export class TextFrames {
  constructor(max = 4096) {
    this.max = max;
    this.buffer = new Uint8Array(0);
  }

  /** @param {Uint8Array} chunk @returns {string[]} */
  push(chunk) {
    const joined = new Uint8Array(this.buffer.length + chunk.length);
    joined.set(this.buffer);
    joined.set(chunk, this.buffer.length);
    const texts = [];
    let at = 0;
    while (joined.length - at >= 4) {
      const length = new DataView(joined.buffer, at, 4).getUint32(0);
      if (length > this.max) throw new GatewayError(`a text message of ${length} bytes from the gateway`, "garbage");
      if (joined.length - at < 4 + length) break;
      texts.push(decoder.decode(joined.subarray(at + 4, at + 4 + length)));
      at += 4 + length;
    }
    this.buffer = joined.slice(at);
    return texts;
  }
}

function fromBase64(text) {
  return Uint8Array.from(atob(text), (c) => c.charCodeAt(0));
}

/** Read a stream to its end (at most `max` bytes: more throws). */
async function readAll(readable, max) {
  const chunks = [];
  let size = 0;
  const reader = readable.getReader();
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    size += value.length;
    if (size > max) {
      reader.cancel().catch(() => {});
      throw new GatewayError(`a message of more than ${max} bytes`, "too_large");
    }
    chunks.push(value);
  }
  if (chunks.length === 1) return chunks[0];
  const all = new Uint8Array(size);
  let at = 0;
  for (const chunk of chunks) { all.set(chunk, at); at += chunk.length; }
  return all;
}

/**
 * A WebTransport session to a gateway, shaped as the part of a WebSocket that
 * {@link GatewayLink} and {@link connectGateway} use: `send`, `bufferedAmount` (bytes of
 * stream messages not yet taken by QUIC), `close(code)`, `onmessage({data})` (a string or
 * bytes), `onerror()`, `onclose({code, reason})`.
 */
export class WebTransportSocket {
  /**
   * @param {string} url the gateway's `wss://HOST:PORT/gateway` (its host is used)
   * @param {{port: number, path: string, hashes: string[]}} offer the gateway's `/webtransport`
   * @param {typeof WebTransport} [Impl]
   */
  constructor(url, offer, Impl = globalThis.WebTransport) {
    this.bufferedAmount = 0;
    this.binaryType = "arraybuffer";
    this.onmessage = (/** @type {{data: string|Uint8Array}} */ _event) => {};
    this.onerror = () => {};
    this.onclose = (/** @type {{code: number, reason: string}} */ _event) => {};
    this.ended = false;
    const host = new URL(url).host.replace(/:\d+$/, "");
    this.wt = new Impl(`https://${host}:${offer.port}${offer.path}`, {
      serverCertificateHashes: offer.hashes.map((hash) => ({ algorithm: "sha-256", value: fromBase64(hash) })),
    });
    this.wt.closed.then(
      (info) => this._end(info?.closeCode ?? 1000, info?.reason ?? ""),
      () => this._end(1006, ""),
    );
    this.opened = this._open();
    // For whoever looks into a page (devtools, tests): the session's own counters.
    this.getStats = () => this.wt.getStats?.();
  }

  async _open() {
    const wt = this.wt;
    try {
      await wt.ready;
      const bidi = await wt.createBidirectionalStream();
      this.text = bidi.writable.getWriter();
      this.text.write(PREAMBLE).catch(() => {});
      // Browsers keep few datagrams for a page that is busy (one, or a few): a heartbeat
      // arriving while the page decodes a picture would drop the one before it.
      try {
        wt.datagrams.incomingMaxBufferedDatagrams = INCOMING_DATAGRAMS;
      } catch { /* an older browser: the next line */ }
      try {
        wt.datagrams.incomingHighWaterMark = INCOMING_DATAGRAMS;
      } catch { /* a newer one: the line before */ }
      this.datagrams = wt.datagrams.writable.getWriter();
      this._readText(bidi.readable);
      this._readDatagrams(wt.datagrams.readable);
      this._readStreams(wt.incomingUnidirectionalStreams);
    } catch {
      this.onerror();
      this.close(1006);
    }
  }

  async _readText(readable) {
    const frames = new TextFrames();
    const reader = readable.getReader();
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        for (const text of frames.push(value)) this.onmessage({ data: text });
      }
    } catch (error) {
      // Framing broken: our end. Anything else is the session ending: `closed` says how.
      if (error instanceof GatewayError) this.close(1002);
    }
  }

  async _readDatagrams(readable) {
    const reader = readable.getReader();
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        this.onmessage({ data: value });
      }
    } catch { /* the session ended: closed says why */ }
  }

  async _readStreams(streams) {
    const reader = streams.getReader();
    try {
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return;
        readAll(value, MAX_MESSAGE).then((data) => this.onmessage({ data }), () => {});
      }
    } catch { /* the session ended */ }
  }

  /** A text message on the bidirectional stream; bytes as a datagram, or a stream when too large. */
  send(data) {
    if (this.ended || !this.text) return;
    if (typeof data === "string") {
      this.text.write(textFrame(data)).catch(() => {});
    } else if (data.length <= (this.wt.datagrams.maxDatagramSize ?? 0)) {
      this.datagrams.write(data).catch(() => {});
    } else {
      const size = data.length;
      this.bufferedAmount += size;
      this.wt.createUnidirectionalStream().then(async (stream) => {
        const writer = stream.getWriter();
        await writer.write(data);
        await writer.close();
      }).catch(() => { /* the session ended: closed says so */ })
        .finally(() => { this.bufferedAmount -= size; });
    }
  }

  _end(code, reason) {
    if (this.ended) return;
    this.ended = true;
    this.onclose({ code, reason });
  }

  /** End the session (`onclose` follows). */
  close(code = 1000) {
    try { this.wt.close({ closeCode: code, reason: "" }); } catch { /* closed already */ }
    this._end(code, "");
  }
}

let failedAt = -Infinity;
/** Whether a WebTransport link was admitted in this page. */
let worked = false;
/**
 * The offer that last opened a link, by gateway URL: used again for the next link, whose
 * fetch (on the page's TCP connection, after an outage still in its retransmission
 * back-off) took up to 2.6 s on `bad`; fetched afresh once it fails (the gateway
 * restarted, or renewed its certificate).
 * @type {Map<string, {port: number, path: string, hashes: string[]}>}
 */
const offers = new Map();

/**
 * The gateway's WebTransport offer (`GET /webtransport` beside `url`), or null when it has
 * none or the page cannot use it (no WebTransport in this browser).
 * @param {string} url @param {typeof fetch} [fetchImpl]
 */
export async function webTransportOffer(url, fetchImpl = globalThis.fetch) {
  if (!globalThis.WebTransport || !fetchImpl) return null;
  const where = new URL("/webtransport", url);
  where.protocol = where.protocol === "wss:" ? "https:" : where.protocol === "ws:" ? "http:" : where.protocol;
  try {
    const response = await fetchImpl(where.href, { cache: "no-store" });
    if (!response.ok) return null;
    const offer = await response.json();
    const valid = Number.isInteger(offer?.port) && typeof offer.path === "string" && Array.isArray(offer.hashes)
      && offer.hashes.every((h) => typeof h === "string");
    return valid ? offer : null;
  } catch {
    return null;
  }
}

/**
 * The page's link to its gateway: two WebTransport sessions as one {@link SplitLink} when the gateway offers it and
 * the browser reaches it within {@link TRY_FOR} s ({@link RETRY_FOR} s once it has
 * reached it), else (and for {@link FALLBACK_FOR} s after such a failure)
 * {@link connectSplit}'s two WebSockets. `link.kind` says which.
 * A refusal (a wrong key, too many connections) is the gateway's answer: it is not
 * retried. An invite is redeemed on one WebSocket (`options.invite`).
 * @param {string} url @param {Parameters<typeof connectGateway>[1]} options
 */
export async function connectBest(url, options) {
  const now = Date.now() / 1000;
  // An invite is redeemed once: on one WebSocket, never on a try that may time out after
  // the gateway used it up.
  const tryIt = !options.invite && now - failedAt > FALLBACK_FOR;
  const cached = tryIt ? offers.get(url) : undefined;
  const offer = cached ?? (tryIt ? await webTransportOffer(url) : null);
  if (offer) {
    try {
      const Socket = class extends WebTransportSocket {
        constructor(/** @type {string} */ to) { super(to, offer); }
      };
      // Two sessions, as with WebSockets: each is a QUIC connection with a congestion
      // window of its own, so pictures that fill one (Wi-Fi roaming: every packet of a
      // 0.3 s gap unacknowledged) never hold back the heartbeats and stops on the other.
      const limit = worked ? RETRY_FOR : TRY_FOR;
      const link = await connectSplit(url, { ...options, WebSocket: /** @type {any} */ (Socket), timeout: Math.min(options.timeout ?? limit, limit) });
      worked = true;
      offers.set(url, offer);
      link.kind = "webtransport";
      return link;
    } catch (error) {
      const code = error instanceof GatewayError ? error.code : "";
      // Not the gateway's answer (a refusal is): this network or browser, so WebSockets.
      if (!["", "unreachable", "timeout", "closed", "garbage", "1006", "1002"].includes(code)) throw error;
      offers.delete(url);
      if (cached) return connectBest(url, options); // once more, with the gateway's offer of now
      failedAt = Date.now() / 1000;
    }
  }
  const link = options.invite ? await connectGateway(url, options) : await connectSplit(url, options);
  link.kind = "websocket";
  return link;
}
