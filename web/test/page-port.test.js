import { test } from "node:test";
import assert from "node:assert/strict";
import { robotPort } from "../src/page-port.js";

/** Stand-ins with the BROWSER.md shapes, recording what the port does with them. */
function rig({ me = { name: "alice", privateKey: new Uint8Array(32), publicKey: new Uint8Array(32) }, pinned = new Uint8Array(32).fill(7), callError = null } = {}) {
  const seen = { links: 0, calls: [], sent: [], sessions: [], closed: [] };
  const deps = {
    keys: async () => ({ me: async () => me, robotKey: async (name) => (name === "guiabot" ? pinned : null) }),
    openLink: async (who) => { seen.links += 1; seen.linkFor = who.name; return { fake: "link", close: () => seen.closed.push("link") }; },
    Endpoint: class { constructor(o) { seen.endpoint = o; } async call(robot, key) { seen.calls.push([robot, key]); if (callError) throw callError; return { id: "c" }; } close() { seen.closed.push("endpoint"); } },
    RobotSession: class {
      constructor(o) { this.o = o; seen.sessions.push(this); }
      async start() { seen.started = (seen.started || 0) + 1; await this.o.connect(); }
      send(m) { seen.sent.push(m); return true; }
    },
  };
  const got = { opened: 0, messages: [], media: [] };
  const h = { open: () => { got.opened += 1; }, close: () => {}, message: (m) => got.messages.push(m), media: (hd, d) => got.media.push([hd, d]) };
  return { deps, seen, got, h };
}
const settle = () => new Promise((r) => setTimeout(r, 0));

test("the port opens a session, routes its messages and media, and sends the page's", async () => {
  const { deps, seen, got, h } = rig();
  const port = robotPort("guiabot", deps);
  assert.equal(port.send({ type: "stop", how: "button" }), false); // nothing to send to yet
  port.connect(h);
  await settle();
  assert.equal(got.opened, 1);
  const session = seen.sessions[0];
  // Started (the first call made) before the page hears it is open; the hello's user.
  assert.equal(seen.started, 1);
  assert.equal(seen.calls.length, 1);
  assert.equal(session.o.user, "alice");
  assert.equal(session.o.robot, "guiabot");
  const call = await session.o.connect();
  assert.deepEqual(call, { id: "c" });
  assert.equal(seen.calls[0][0], "guiabot");
  assert.equal(seen.calls[0][1][0], 7); // the pinned key
  assert.equal(seen.endpoint.name, "alice");
  await session.o.connect(); // a reconnection reuses the link
  assert.equal(seen.links, 1);
  session.o.emit({ type: "pose", x: 1 });
  const data = new Uint8Array([1, 2]);
  session.o.emit({ type: "video", header: { kind: "video", codec: "jpeg" }, data });
  assert.deepEqual(got.messages, [{ type: "pose", x: 1 }]);
  assert.deepEqual(got.media, [[{ kind: "video", codec: "jpeg" }, data]]);
  assert.equal(port.send({ type: "stop", how: "page_hidden" }), true);
  assert.equal(port.sendMedia({ kind: "audio", seq: 1 }, data, false), true);
  assert.deepEqual(seen.sent, [{ type: "stop", how: "page_hidden" }, { type: "audio", header: { kind: "audio", seq: 1 }, data, video: false }]);
});

test("a call's error (KEY MISMATCH) is on the page at once, as the call says it", async () => {
  const text = "KEY MISMATCH: robot guiabot is online with key abc but known_robots has def";
  const { deps, seen, got, h } = rig({ callError: new Error(text) });
  const port = robotPort("guiabot", deps);
  port.connect(h);
  await settle(); await settle();
  assert.equal(got.opened, 0);
  assert.equal(port.send({ type: "stop", how: "button" }), false); // no session to send to
  assert.deepEqual(seen.closed, ["endpoint", "link"]); // nothing left open behind the error
  assert.deepEqual(got.messages.map((m) => m.type), ["connection", "error"]);
  assert.equal(got.messages[0].state, "ended");
  assert.equal(got.messages[0].detail, text);
  assert.equal(got.messages[1].text, text);
});

test("no key, or a robot not pinned: one line on the page, no session", async () => {
  for (const [opts, robot, want] of [[{ me: null }, "guiabot", /no key yet/], [{}, "other", /robot other is not pinned/]]) {
    const { deps, seen, got, h } = rig(opts);
    robotPort(robot, deps).connect(h);
    await settle(); await settle();
    assert.equal(seen.sessions.length, 0);
    assert.equal(got.opened, 0);
    assert.match(got.messages.at(-1).text, want);
  }
});

test("a link the gateway closed is opened again on the session's redial, with a new endpoint", async () => {
  const { deps, seen, h } = rig();
  const links = [];
  deps.openLink = async () => {
    seen.links += 1;
    const link = { closed: false, close() { this.closed = true; } };
    links.push(link);
    return link;
  };
  robotPort("guiabot", deps).connect(h);
  await settle();
  const session = seen.sessions[0];
  const first = seen.endpoint;
  links[0].closed = true; // the websocket went (network gone, or the gateway cut it)
  await session.o.connect();
  assert.equal(seen.links, 2);
  assert.notEqual(seen.endpoint, first);
  assert.equal(seen.endpoint.link, links[1]);
  assert.deepEqual(seen.closed, ["endpoint"]); // the old endpoint closed, nothing else
  await session.o.connect(); // while the new link is open, it is reused
  assert.equal(seen.links, 2);
});

test("a link that closes while a call is being set up fails that call at once; the next opens a new link", async () => {
  const { deps, seen, h } = rig();
  const links = [];
  deps.openLink = async () => {
    const link = { closed: false, onclose: null, close() { this.closed = true; } };
    links.push(link);
    return link;
  };
  deps.Endpoint = class {
    constructor(o) { seen.endpoint = o; this.fails = []; }
    call() { return new Promise((resolve, reject) => this.fails.push(reject)); } // the robot never answers
    linkClosed() { for (const fail of this.fails.splice(0)) fail(new Error("the link to the gateway closed")); }
    close() { seen.closed.push("endpoint"); }
  };
  robotPort("guiabot", deps).connect(h);
  await settle();
  const session = seen.sessions[0];
  const attempt = session.o.connect(); // a redial, waiting for the robot on the first link
  links[0].closed = true;
  links[0].onclose({ code: "closed", text: "Connection lost" }); // Chromium ended the QUIC connection
  await assert.rejects(attempt, /the link to the gateway closed/); // at once, not after 10 s
  session.o.connect().catch(() => {});
  await settle();
  assert.equal(links.length, 2); // the next attempt is on a new link
  assert.equal(typeof links[1].onclose, "function");
});
