/**
 * The page's port to a robot through a gateway (static/app.js, "the port"): the same §19
 * messages the local `telebot-user ui` exchanges with the page over its websocket, here
 * produced in the browser by a RobotSession (session.js) on a call (call.js) over the
 * gateway's WebSocket (gateway-link.js), with this browser's key (keys.js).
 *
 * No imports of those modules here: browser.js passes them in (`deps`), so this wiring is
 * tested in node with stand-ins, and the bundle decides what it ships.
 * @module page-port
 */

/**
 * @typedef {object} PortHandlers   what app.js gives `connect`
 * @property {() => void} open
 * @property {() => void} close
 * @property {(msg: object) => void} message          a §19 client → page message
 * @property {(header: object, data: Uint8Array) => void} media   video or audio (§19.1)
 */

/**
 * A port to pinned robot `robot`.
 * @param {string} robot
 * @param {object} deps
 * @param {() => Promise<import("./keys.js").Keys>} deps.keys   the browser's keys
 * @param {(me: {name: string, privateKey: Uint8Array, publicKey: Uint8Array}) => Promise<object>} deps.openLink
 *   a link (BROWSER.md's link API) admitted by the gateway as `me`
 * @param {new (opts: object) => {call: Function, close: Function, linkClosed: Function}} deps.Endpoint  call.js's
 * @param {new (opts: {connect: Function, emit: Function}) => {send: Function, close?: Function}} deps.RobotSession
 */
export function robotPort(robot, deps) {
  let session = null;
  /** How the page reaches its gateway now: "webtransport", "websocket" (null: not yet). */
  let kind = null;
  return {
    /** @returns {string|null} how the call's link reaches the gateway (its `kind`). */
    linkKind: () => kind,
    /** @param {PortHandlers} h */
    connect(h) {
      const fail = (text) => {
        h.message({ type: "connection", state: "ended", detail: text, seconds: 0 });
        h.message({ type: "error", text });
      };
      start(h, fail).catch((e) => fail(e.message));
    },
    send: (msg) => (session ? session.send(msg) !== false : false),
    sendMedia(header, data, isVideo) {
      if (!session) return false;
      return session.send({ type: header.kind, header, data, video: isVideo }) !== false;
    },
  };

  async function start(h, fail) {
    const keys = await deps.keys();
    const me = await keys.me();
    if (!me) throw new Error("this browser has no key yet: make one on the start page");
    const robotKey = await keys.robotKey(robot);
    if (!robotKey) throw new Error(`robot ${robot} is not pinned in this browser: pin it on the start page`);
    let link = null, endpoint = null;
    session = new deps.RobotSession({
      user: me.name,
      robot,
      // The first call, and again after a drop (the session redials as the Python client
      // does: a failed attempt is its business, not the page's).
      // A link the gateway (or the network) closed is opened again, with a new endpoint:
      // the old one's inbox and presence went with it.
      connect: async () => {
        if (link && link.closed) {
          try {
            endpoint?.close();
          } catch {
            // its hang-ups go nowhere anyway
          }
          link = endpoint = null;
        }
        if (!link) {
          const opened = (link = await deps.openLink(me));
          kind = link.kind ?? null;
          // A link that closes (the gateway cut it; Chromium ends a QUIC connection that
          // heard nothing for a few seconds) ends the call being set up on it at once, so
          // the session's next attempt opens a new link instead of waiting out the
          // attempt's 10 s (bench/wan.py's browser reconnections: 8.4 s instead of 0.3).
          opened.onclose = () => {
            if (link === opened) endpoint?.linkClosed();
          };
          // Closed already (one half went while the other was being admitted): the next
          // attempt opens another.
          if (opened.closed) throw new Error("the link to the gateway closed as it opened");
        }
        if (!endpoint) endpoint = new deps.Endpoint({ link, name: me.name, privateKey: me.privateKey });
        return endpoint.call(robot, robotKey);
      },
      emit: (msg) => {
        if ((msg.type === "video" || msg.type === "audio") && msg.header && msg.data) h.media(msg.header, msg.data);
        else h.message(msg);
      },
    });
    try {
      await session.start(); // the call, its services, the page's greeting (hello first)
    } catch (e) {
      // KEY MISMATCH, refused, no answer: the call's own one line, on the page at once.
      session = null;
      if (endpoint) endpoint.close();
      if (link && link.close) link.close();
      throw e;
    }
    h.open();
  }
}
