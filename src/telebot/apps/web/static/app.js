// telebot web UI: map, click-to-goal, stop, video, chat, status. No build step, no
// network access beyond this page's own server (see telebot/apps/web/server.py for the
// websocket protocol).
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const now = () => performance.timeOrigin + performance.now();

  const ui = {
    state: {
      robot: "", user: "", role: "", mayDrive: false, map: null, pose: null, goal: null,
      safety: null, telemetry: null, link: null, connected: false, call: null,
      frames: 0, camera: "", fps: 0, chat: [], plan: null, places: [],
    },
    // What the last draw() put on the map, for tests: points of the planned path drawn
    // and the names of the places labelled.
    drawn: { plan: 0, labels: [] },
    // Measurements for tests and benchmarks (wall-clock ms).
    stats: { keyTimes: [], poseDraw: [], frameTimes: [], hides: [], reconnected: 0 },
  };
  ui.handlers = {};
  window.telebotUI = ui;
  // Extensions (static/people.js, …): called with each websocket message and after each
  // map draw (ctx, worldToScreen, pixels per metre).
  ui.hooks = { message: [], draw: [] };

  // ------------------------------------------------------------------ the port
  // The page talks to "a port": today's websocket to the user's own `telebot-user ui`
  // (docs/protocol.md §19), or, when a gateway serves the page, the in-browser client
  // (static/port.js sets window.telebotPort before this script runs). Both carry the same
  // §19 messages as objects; media (video and audio, both ways) as a parsed header and its
  // bytes. A port: connect(handlers) with handlers {open(), close(), message(obj),
  // media(header, bytes)}; send(obj) -> bool; sendMedia(header, bytes, isVideo) -> bool.
  function websocketPort() {
    let ws = null;
    return {
      connect(h) {
        // Relative to the page: it may live under a prefix (the fleet page's /robot/NAME/).
        const url = new URL("ws", location.href);
        url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
        ws = new WebSocket(url.href);
        ws.binaryType = "arraybuffer";
        ws.onopen = () => h.open();
        ws.onclose = () => { h.close(); setTimeout(() => this.connect(h), 1000); };
        ws.onmessage = (ev) => {
          if (typeof ev.data === "string") { h.message(JSON.parse(ev.data)); return; }
          const view = new DataView(ev.data);
          const hlen = view.getUint32(0);
          const header = JSON.parse(new TextDecoder().decode(new Uint8Array(ev.data, 4, hlen)));
          h.media(header, new Uint8Array(ev.data, 4 + hlen));
        };
      },
      send(msg) {
        if (ws && ws.readyState === WebSocket.OPEN) { ws.send(JSON.stringify(msg)); return true; }
        return false;
      },
      sendMedia(header, data, isVideo) {
        // Video waits for nothing: a picture the socket cannot take now is skipped.
        if (!ws || ws.readyState !== WebSocket.OPEN || (isVideo && ws.bufferedAmount > 256 * 1024)) return false;
        ws.send(window.telebotMedia.pack(header, data));
        return true;
      },
    };
  }
  const port = window.telebotPort || websocketPort();
  ui.port = port;
  let chatId = 0;
  function connect() {
    port.connect({
      open: () => { ui.state.connected = true; showConn(); linkBack(); if (media) media.open(); },
      close: () => { if (ui.state.connected) linkLost(); ui.state.connected = false; showConn(); },
      message: (m) => onMessage(m),
      media: (header, data) => onFrame(header, data),
    });
  }
  const send = (msg) => port.send(msg);
  ui.send = send;
  // Two links: this page to the local client (websocket), the client to the robot (the
  // call, which the client re-establishes by itself after a drop).
  function showConn() {
    const el = $("conn");
    const call = ui.state.call;
    let text = ui.state.connected ? "connected" : "disconnected";
    let cls = ui.state.connected ? "good" : "bad";
    if (ui.state.connected && call) {
      if (call.state === "reconnecting") { text = "reconnecting…"; cls = "bad"; }
      else if (call.state === "reconnected") {
        text = "reconnected after " + call.seconds.toFixed(1) + " s";
      } else if (call.state === "ended") { text = call.detail || "call ended"; cls = "bad"; }
    }
    el.textContent = text;
    el.className = cls;
  }

  // how: "button" or "key", for the robot's audit log (who stopped it, and how).
  function stop(source, how) {
    send({ type: "stop", how: how });
    ui.stats.keyTimes.push(now());
    addChat("[" + source + ": stop]", "cmd");
  }
  ui.stop = stop;

  function onMessage(m) {
    switch (m.type) {
      case "hello":
        ui.state.robot = m.robot; ui.state.role = m.role; ui.state.mayDrive = m.may_drive;
        ui.state.user = m.user;
        $("robot-name").textContent = m.robot;
        document.title = "telebot · " + m.robot;
        $("role").textContent = m.role + (m.may_drive ? "" : " (observer: watch and stop)");
        for (const b of document.querySelectorAll(".drive")) b.disabled = !m.may_drive;
        if (m.map) loadMap(m.map);
        break;
      case "map": loadMap(m); break;
      case "pose": {
        ui.state.pose = m;
        draw();
        ui.stats.poseDraw.push(now() - m.recv);
        if (ui.stats.poseDraw.length > 5000) ui.stats.poseDraw.shift();
        showPose();
        break;
      }
      case "telemetry": ui.state.telemetry = m; showTelemetry(); break;
      case "safety": ui.state.safety = m; showSafety(); safetyAfterLoss(); break;
      case "link": ui.state.link = m; showLink(); break;
      case "connection":
        if (m.state === "reconnecting" || m.state === "ended") linkLost();
        ui.state.call = m;
        if (m.state === "reconnected") { ui.stats.reconnected += 1; linkBack(); }
        showConn();
        showAlert();
        if (m.state !== "connected") addChat("[" + (m.state === "reconnected" ? "reconnected after " + m.seconds.toFixed(1) + " s" : m.detail || m.state) + "]", m.state === "reconnected" ? "" : "fail");
        break;
      case "goal": ui.state.goal = m; showGoal(); draw(); break;
      case "plan": ui.state.plan = m; planAt = 0; draw(); break;
      case "places": ui.state.places = m.places; draw(); break;
      case "chat": {
        addChat(m.text, m.ok || !m.final ? "" : "fail");
        ui.state.chat.push(m);
        break;
      }
      case "ack":
        if (!m.ok) addChat(m.what + " refused: " + m.text, "fail");
        break;
      case "error": addChat("error: " + m.text, "fail"); break;
      default: {
        // Messages other page scripts handle (conference.js, people.js): ui.handlers[type]
        // = fn; the rest are media.js's.
        const handler = ui.handlers[m.type];
        if (handler) handler(m);
        else if (media) media.text(m);
        break;
      }
    }
    for (const hook of ui.hooks.message) hook(m);
  }

  // ------------------------------------------------------------------ status
  function showPose() {
    const p = ui.state.pose;
    $("pose-text").textContent = "x " + p.x.toFixed(2) + " m, y " + p.y.toFixed(2) + " m, " +
      (p.yaw * 180 / Math.PI).toFixed(0) + "°";
    $("moving").textContent = p.state + (p.v || p.w ? " " + p.v.toFixed(2) + " m/s" : "");
  }
  function showTelemetry() {
    const t = ui.state.telemetry;
    $("battery").textContent = Math.round(t.battery) + "%" + (t.battery_low ? " LOW" : "");
    $("battery").className = t.battery_low ? "bad" : "";
    $("camera").textContent = t.camera;
    $("holder").textContent = t.holder || "nobody";
  }
  function showLink() {
    const l = ui.state.link;
    $("link").textContent = (l.rtt == null ? "rtt –" : "rtt " + (l.rtt * 1000).toFixed(1) + " ms") +
      ", loss " + (l.loss * 100).toFixed(0) + "%";
  }
  function showSafety() {
    const s = ui.state.safety;
    const el = $("safety");
    el.textContent = s.armed ? "armed" : "stopped";
    el.className = s.armed ? "armed" : "stopped";
    const parts = [];
    if (!s.armed && s.text) parts.push(s.text);
    if (s.blocked) parts.push("blocked by an obstacle");
    parts.push("speed cap " + s.cap.toFixed(2) + " m/s");
    $("safety-reason").textContent = parts.join(" · ");
    $("holder").textContent = s.holder || "nobody";
  }
  function showGoal() {
    const g = ui.state.goal;
    $("goal").textContent = "(" + g.x.toFixed(2) + ", " + g.y.toFixed(2) + ") " + g.status +
      (g.status === "active" ? " " + Math.round(g.progress * 100) + "%" : "") +
      (g.text ? " — " + g.text : "");
  }

  // ------------------------------------------------------------------ map
  const canvas = $("map");
  const ctx = canvas.getContext("2d");
  const mapImg = new Image();
  let mapReady = false;
  const view = { s: 1, tx: 0, ty: 0, follow: false };

  function loadMap(m) {
    ui.state.map = m;
    mapImg.onload = () => { mapReady = true; fit(); };
    // A served map is fetched afresh (same URL, new picture); a blob: or data: URL (the
    // in-browser client's) is new each time already.
    mapImg.src = /^(blob|data):/.test(m.url) ? m.url : m.url + "?t=" + Date.now();
  }
  // World (map frame, metres) <-> map image pixels <-> canvas CSS pixels.
  function worldToScreen(x, y) {
    const m = ui.state.map;
    const px = (x - m.origin_x) / m.resolution;
    const py = m.height - (y - m.origin_y) / m.resolution;
    return [px * view.s + view.tx, py * view.s + view.ty];
  }
  function screenToWorld(sx, sy) {
    const m = ui.state.map;
    const px = (sx - view.tx) / view.s;
    const py = (sy - view.ty) / view.s;
    return [m.origin_x + px * m.resolution, m.origin_y + (m.height - py) * m.resolution];
  }
  ui.worldToScreen = worldToScreen;
  ui.screenToWorld = screenToWorld;
  ui.mapReady = () => mapReady;

  function resize() {
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.round(canvas.clientWidth * dpr);
    canvas.height = Math.round(canvas.clientHeight * dpr);
    draw();
  }
  function fit() {
    const m = ui.state.map;
    if (!m) return;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    view.s = Math.min(w / m.width, h / m.height) * 0.95;
    view.tx = (w - m.width * view.s) / 2;
    view.ty = (h - m.height * view.s) / 2;
    draw();
  }
  function zoomAt(factor, sx, sy) {
    const old = view.s;
    view.s = Math.max(0.05, Math.min(old * factor, 100));
    const ns = view.s / old;
    view.tx = sx - (sx - view.tx) * ns;
    view.ty = sy - (sy - view.ty) * ns;
    draw();
  }

  let drag = null; // {kind: "goal"|"pan", x0, y0, x, y, tx, ty}
  function draw() {
    const dpr = window.devicePixelRatio || 1;
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#444";
    ctx.fillRect(0, 0, canvas.clientWidth, canvas.clientHeight);
    const m = ui.state.map;
    if (!m || !mapReady) return;
    const p = ui.state.pose;
    if (view.follow && p) {
      const [sx, sy] = worldToScreen(p.x, p.y);
      view.tx += canvas.clientWidth / 2 - sx;
      view.ty += canvas.clientHeight / 2 - sy;
    }
    ctx.imageSmoothingEnabled = view.s < 1;
    ctx.drawImage(mapImg, view.tx, view.ty, m.width * view.s, m.height * view.s);
    const pxm = view.s / m.resolution; // screen pixels per metre
    // Map origin (0, 0): a red dot.
    const [ox, oy] = worldToScreen(0, 0);
    ctx.fillStyle = "#e00";
    ctx.beginPath(); ctx.arc(ox, oy, 4, 0, 2 * Math.PI); ctx.fill();
    // Named places: a dot and the name (only those in view: the page stays fast).
    const labels = [];
    ctx.font = "12px sans-serif"; ctx.textBaseline = "middle"; ctx.lineJoin = "round";
    for (const pl of ui.state.places) {
      const [lx, ly] = worldToScreen(pl.x, pl.y);
      if (lx < -50 || ly < -20 || lx > canvas.clientWidth + 50 || ly > canvas.clientHeight + 20) continue;
      ctx.fillStyle = "#a0a";
      ctx.beginPath(); ctx.arc(lx, ly, 3, 0, 2 * Math.PI); ctx.fill();
      ctx.strokeStyle = "rgba(255,255,255,0.85)"; ctx.lineWidth = 3;
      ctx.strokeText(pl.name, lx + 6, ly);
      ctx.fillStyle = "#606"; ctx.fillText(pl.name, lx + 6, ly);
      labels.push(pl.name);
    }
    ui.drawn.labels = labels;
    // The robot's planned path, from where the robot is on it now to the goal.
    const g = ui.state.goal;
    const plan = ui.state.plan;
    ui.drawn.plan = 0;
    if (plan && plan.points.length >= 2) {
      const pts = plan.points;
      let first = 0;
      if (p) { planAt = nearestSegment(pts, p.x, p.y, planAt); first = planAt + 1; }
      ctx.strokeStyle = PLAN_COLOR; ctx.lineWidth = 3; ctx.lineJoin = "round";
      ctx.beginPath();
      let [sx, sy] = p ? worldToScreen(p.x, p.y) : worldToScreen(pts[0][0], pts[0][1]);
      ctx.moveTo(sx, sy);
      for (let i = first; i < pts.length; i++) {
        [sx, sy] = worldToScreen(pts[i][0], pts[i][1]);
        ctx.lineTo(sx, sy);
      }
      ctx.stroke();
      ui.drawn.plan = pts.length - first;
    }
    if (g) {
      const [gx, gy] = worldToScreen(g.x, g.y);
      ctx.strokeStyle = g.status === "succeeded" ? "#0a0" : (g.status === "active" || g.status === "sent") ? "#0c0" : "#c60";
      ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(gx, gy, 7, 0, 2 * Math.PI); ctx.stroke();
      ctx.beginPath(); ctx.moveTo(gx - 10, gy); ctx.lineTo(gx + 10, gy);
      ctx.moveTo(gx, gy - 10); ctx.lineTo(gx, gy + 10); ctx.stroke();
      if (g.yaw != null) arrow(gx, gy, g.yaw, 22, ctx.strokeStyle);
    }
    // The robot: a circle with a heading line.
    if (p) {
      const [rx, ry] = worldToScreen(p.x, p.y);
      const r = Math.max(5, 0.25 * pxm);
      ctx.fillStyle = "rgba(30,120,255,0.6)"; ctx.strokeStyle = "#05f"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(rx, ry, r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      ctx.strokeStyle = "#fff";
      ctx.beginPath(); ctx.moveTo(rx, ry);
      ctx.lineTo(rx + Math.cos(p.yaw) * r * 1.6, ry - Math.sin(p.yaw) * r * 1.6); ctx.stroke();
    }
    for (const hook of ui.hooks.draw) hook(ctx, worldToScreen, pxm);
    // A goal being dragged: where, and the heading.
    if (drag && drag.kind === "goal") {
      ctx.strokeStyle = "#ff0"; ctx.lineWidth = 2;
      ctx.beginPath(); ctx.arc(drag.x0, drag.y0, 7, 0, 2 * Math.PI); ctx.stroke();
      if (Math.hypot(drag.x - drag.x0, drag.y - drag.y0) > 8) {
        ctx.beginPath(); ctx.moveTo(drag.x0, drag.y0); ctx.lineTo(drag.x, drag.y); ctx.stroke();
      }
    }
  }
  ui.draw = draw;
  // The path segment the robot is on: searched from the last one forwards (a few
  // segments), so a path that passes near itself does not make the drawing jump back.
  const PLAN_COLOR = "#00a0a0";
  let planAt = 0;
  function nearestSegment(pts, x, y, from) {
    let best = from, bestD = Infinity;
    const last = Math.min(pts.length - 1, from + 8);
    for (let i = from; i < last; i++) {
      const [ax, ay] = pts[i], [bx, by] = pts[i + 1];
      const dx = bx - ax, dy = by - ay, len2 = dx * dx + dy * dy;
      const t = len2 > 0 ? Math.max(0, Math.min(1, ((x - ax) * dx + (y - ay) * dy) / len2)) : 0;
      const d = Math.hypot(ax + t * dx - x, ay + t * dy - y);
      if (d < bestD) { bestD = d; best = i; }
    }
    return best;
  }
  function arrow(x, y, yaw, len, color) {
    const ex = x + Math.cos(yaw) * len, ey = y - Math.sin(yaw) * len;
    ctx.strokeStyle = color;
    ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(ex, ey);
    ctx.lineTo(ex - Math.cos(yaw - 0.5) * 7, ey + Math.sin(yaw - 0.5) * 7);
    ctx.moveTo(ex, ey);
    ctx.lineTo(ex - Math.cos(yaw + 0.5) * 7, ey + Math.sin(yaw + 0.5) * 7);
    ctx.stroke();
  }

  function local(ev) {
    const r = canvas.getBoundingClientRect();
    return [ev.clientX - r.left, ev.clientY - r.top];
  }
  canvas.addEventListener("contextmenu", (ev) => ev.preventDefault());
  // Pointer events: a mouse, a finger and a pen alike. A press (a tap on a phone) is a goal
  // there, a drag from it gives the heading; right/middle drag (or a second finger) pans.
  const fingers = new Set();
  canvas.addEventListener("pointerdown", (ev) => {
    const [x, y] = local(ev);
    fingers.add(ev.pointerId);
    canvas.setPointerCapture(ev.pointerId);
    if (fingers.size > 1) {
      drag = { kind: "pan", id: ev.pointerId, x0: x, y0: y, x, y, tx: view.tx, ty: view.ty };
      view.follow = false;
    } else if (ev.button === 0 && ui.state.mayDrive && ui.state.map) {
      drag = { kind: "goal", id: ev.pointerId, x0: x, y0: y, x, y };
    } else if (ev.button === 1 || ev.button === 2 || ev.button === 0) {
      drag = { kind: "pan", id: ev.pointerId, x0: x, y0: y, x, y, tx: view.tx, ty: view.ty };
      view.follow = false;
    }
    ev.preventDefault();
  });
  canvas.addEventListener("pointermove", (ev) => {
    if (!drag || drag.id !== ev.pointerId) return;
    const [x, y] = local(ev);
    drag.x = x; drag.y = y;
    if (drag.kind === "pan") { view.tx = drag.tx + x - drag.x0; view.ty = drag.ty + y - drag.y0; }
    draw();
  });
  const pointerEnd = (ev) => {
    fingers.delete(ev.pointerId);
    if (!drag || drag.id !== ev.pointerId) return;
    const d = drag; drag = null;
    if (d.kind === "goal" && ev.type === "pointerup") {
      const [x, y] = local(ev);
      const [wx, wy] = screenToWorld(d.x0, d.y0);
      let yaw = null;
      if (Math.hypot(x - d.x0, y - d.y0) > 8) yaw = Math.atan2(-(y - d.y0), x - d.x0);
      sendGoal(wx, wy, yaw);
    }
    draw();
  };
  canvas.addEventListener("pointerup", pointerEnd);
  canvas.addEventListener("pointercancel", pointerEnd);
  function sendGoal(x, y, yaw) {
    ui.state.goal = { type: "goal", x, y, yaw, status: "sent", progress: 0, text: "" };
    showGoal();
    send({ type: "goal", x, y, yaw });
  }
  ui.sendGoal = sendGoal;
  canvas.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    const [x, y] = local(ev);
    zoomAt(ev.deltaY < 0 ? 1.2 : 1 / 1.2, x, y);
  }, { passive: false });
  $("zoom-in").onclick = () => zoomAt(1.25, canvas.clientWidth / 2, canvas.clientHeight / 2);
  $("zoom-out").onclick = () => zoomAt(0.8, canvas.clientWidth / 2, canvas.clientHeight / 2);
  $("zoom-fit").onclick = () => { view.follow = false; fit(); };
  $("follow").onclick = () => { view.follow = !view.follow; draw(); };
  window.addEventListener("resize", resize);

  // ------------------------------------------------------------------ stop & safety
  // Any key stops (in the chat input only Escape does, so commands can be typed). Capture
  // phase, before anything else on the page sees the key.
  document.addEventListener("keydown", (ev) => {
    if (ev.target === $("chat-input")) {
      if (ev.key === "Escape") { ev.preventDefault(); stop("Escape", "key"); }
      return;
    }
    ev.preventDefault();
    stop("key " + ev.key, "key");
  }, true);
  // STOP acts on the press (a finger down), not on the click that follows its release;
  // a click without a press (keyboard, assistive tools) stops too.
  let pressedAt = -1e9;
  $("stop").addEventListener("pointerdown", () => { pressedAt = now(); stop("STOP button", "button"); });
  $("stop").onclick = () => { if (now() - pressedAt > 1000) stop("STOP button", "button"); };
  // Whether the robot may be moving or about to (the local client's rule for a page that
  // closes, server.py _page_closed): moving, a goal running, blocked, or armed.
  function mightMove() {
    const p = ui.state.pose, g = ui.state.goal, s = ui.state.safety;
    return !!((p && (p.v || p.w || p.state === "moving" || p.state === "blocked")) ||
      (g && (g.status === "sent" || g.status === "active")) || (s && s.armed));
  }
  ui.mightMove = mightMove;
  // Whether this page's user drives: may drive, and holds the drive (or nobody does).
  function driving() {
    const s = ui.state.safety;
    return ui.state.mayDrive && (!s || !s.holder || s.holder === ui.state.user);
  }
  // Touching the video (the picture a phone is mostly filled with) while the robot moves
  // stops it: the quickest thing to hit when something looks wrong.
  $("video-box").addEventListener("pointerdown", (ev) => {
    if (ev.target.closest("button, label, input")) return;
    const p = ui.state.pose;
    if (p && (p.v || p.w || p.state === "moving")) stop("touched the video", "touch");
  });
  // Fail safe: a page hidden (another tab or app, the phone locked) or frozen cannot show
  // what the robot does, so it stops a robot it drives that may move. The local client
  // also stops it when this page's websocket closes (tab_closed); through a gateway this
  // is the page's own job.
  // Hiding fires visibilitychange and pagehide both: one stop until the page shows again.
  let hideStopped = false;
  function hidden(what) {
    ui.stats.hides.push(what);
    if (hideStopped || !driving() || !mightMove()) return;
    hideStopped = true;
    stop("page " + what, "page_hidden");
  }
  window.addEventListener("pagehide", () => hidden("hidden"));
  window.addEventListener("pageshow", () => { hideStopped = false; });
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "hidden") hidden("hidden");
    else hideStopped = false;
  });
  document.addEventListener("freeze", () => hidden("frozen"));
  // The link lost while this page drove a robot that might move (the call dropped, or the
  // page lost its local client): the robot's deadman stops it whatever the page does (its
  // driver's call went silent), and the page says so at once. Once the call is back, the
  // robot's state shows; latched, re-arm is the one action offered. Phases: "down" (lost),
  // "back" (called again, waiting for the robot's safety state), "latched" (stopped).
  let lost = null;
  const LOST_TEXT = "connection lost — the robot stopped itself (deadman); re-arm when back";
  function linkLost() {
    if (!lost && !(driving() && mightMove())) return;
    if (lost !== "down") addChat("[" + LOST_TEXT + "]", "fail");
    lost = "down";
    showAlert();
  }
  function linkBack() {
    if (lost === "down") { lost = "back"; showAlert(); }
  }
  function safetyAfterLoss() {
    noteSelfStop();
    if (lost === "back" || lost === "latched") lost = ui.state.safety.armed ? null : "latched";
    showAlert();
  }
  // The robot stopped itself (issue 26: a blip is cheap to recover from): its deadman
  // after a silent link, its driver's call dropped, or the driver's video froze (§18 state
  // `code` link_silent, dropped, video_stale). The page says what happened in one sentence
  // and offers one action, a big Re-arm (to the drive holder); a stop someone made shows
  // the plain stopped state. Robots before the state's `code`: told apart by its text.
  function selfStop(s) {
    if (!s || s.armed) return "";
    if (s.code) return SELF_STOP_WORDS[s.code] ? s.code : "";
    const r = s.text || "";
    if (/^driver .*'s link lost/.test(r)) return "link_silent";
    if (/^driver .* (dropped|called again)/.test(r)) return "dropped";
    if (/video froze|video frozen/.test(r)) return "video_stale";
    return "";
  }
  const SELF_STOP_WORDS = {
    link_silent: "link went silent for a moment, so the robot stopped itself (deadman)",
    dropped: "call dropped, so the robot stopped itself",
    video_stale: "video froze, so the robot stopped itself rather than drive blind",
  };
  // Whose link, call or video: the driver the robot's text names (this user: "your").
  function selfStopText(code, s) {
    const named = /^driver (.+?)(?:'s link lost| dropped| called again)/.exec(s.text || "");
    const who = named ? named[1] : code === "video_stale" ? s.holder : null;
    const whose = who === ui.state.user ? "Your" : who ? who + "'s" : "The driver's";
    return whose + " " + SELF_STOP_WORDS[code] + ": re-arm to drive on";
  }
  ui.selfStop = () => selfStop(ui.state.safety);
  let selfStopped = "";
  function noteSelfStop() {
    const s = ui.state.safety;
    const code = driving() ? selfStop(s) : "";
    if (code && code !== selfStopped) addChat("[" + selfStopText(code, s) + "]", "fail");
    selfStopped = code;
  }
  function showAlert() {
    const box = $("alert");
    const s = ui.state.safety;
    const self = lost === "down" || lost === "back" || !driving() ? "" : selfStop(s);
    const shown = !!(lost || self);
    box.hidden = !shown;
    // Re-arm is the holder's (the robot refuses anyone else's); the drive is free after
    // the holder's call dropped until its next call joins and takes it.
    const mine = !!(s && s.holder && s.holder === ui.state.user);
    $("alert-arm").hidden = !(lost === "latched" || self) || (!!self && !mine);
    $("alert-arm").disabled = !ui.state.mayDrive;
    if (!shown) return;
    const ended = ui.state.call && ui.state.call.state === "ended";
    box.className = lost === "down" ? "" : "back";
    $("alert-text").textContent =
      self ? selfStopText(self, s) + (mine ? "" : " (take the drive first)") :
      lost === "latched" ? "connection back — the robot is stopped (latched since the link was lost): re-arm to drive on" :
      lost === "back" ? "connection back — waiting for the robot's state…" :
      ended ? "connection lost — the robot stopped itself (deadman); the call ended: reload the page to call again" :
      LOST_TEXT;
  }
  ui.lost = () => lost;
  $("alert-arm").onclick = () => send({ type: "arm" });
  $("arm").onclick = () => send({ type: "arm" });
  $("take").onclick = () => send({ type: "take" });
  $("release").onclick = () => send({ type: "release" });

  // ------------------------------------------------------------------ video
  const video = $("video");
  let videoUrl = null;
  // Codec video and audio go to media.js (static/media.js); JPEG is shown here.
  const media = window.telebotMedia ? window.telebotMedia.attachPage({
    sendMedia: (header, data, isVideo) => port.sendMedia(header, data, isVideo),
    sendText: send, canvas: $("video-canvas"),
    onNote: (text) => { $("media-note").textContent = text; },
    controls: { mute: $("mute"), camera: $("camera-off"), ptt: $("ptt"), pttMode: $("ptt-mode") },
  }) : null;
  function onFrame(header, data) {
    const kind = media ? media.frame(header, data) : "";
    if (kind === "audio") return;
    video.hidden = kind === "video";
    $("video-canvas").hidden = kind !== "video";
    if (kind !== "video") {
      const blob = new Blob([data], { type: "image/jpeg" });
      const url = URL.createObjectURL(blob);
      const old = videoUrl;
      videoUrl = url;
      video.src = url;
      if (old) setTimeout(() => URL.revokeObjectURL(old), 1000);
      pictureShown();
    }
    const t = now();
    ui.stats.frameTimes.push(t);
    while (ui.stats.frameTimes.length && ui.stats.frameTimes[0] < t - 1000) ui.stats.frameTimes.shift();
    ui.state.frames += 1;
    ui.state.camera = header.camera;
    ui.state.fps = ui.stats.frameTimes.length;
    $("camera").textContent = header.camera;
    $("fps").textContent = ui.state.fps;
  }
  setInterval(() => {
    const t = now();
    while (ui.stats.frameTimes.length && ui.stats.frameTimes[0] < t - 1000) ui.stats.frameTimes.shift();
    ui.state.fps = ui.stats.frameTimes.length;
    $("fps").textContent = ui.state.fps;
  }, 500);
  // ------------------------------------------------------------------ frozen picture
  // A picture that stopped moving is marked at once (issue 26: no driving blind): no new
  // picture shown for FROZEN_MS (more at a low frame rate: 2.5 frame intervals, at most
  // FROZEN_MAX_MS) puts "picture frozen — N s" over the video until the next one. Only
  // once pictures came: a robot that sends no video (none yet, or none at all) is not a
  // frozen picture. Codec pictures count when decoded and drawn (media.js), not when they
  // arrive: a picture waiting for a keyframe is frozen too.
  const FROZEN_MS = 500, FROZEN_MAX_MS = 1000;
  const frozen = { shownAt: null, gapMs: 0, on: false, marks: 0, checks: 0 };
  ui.frozen = frozen;
  function pictureShown() {
    const t = now();
    // The usual gap between pictures (a freeze's own gap is not usual).
    if (frozen.shownAt !== null && !frozen.on) {
      const gap = Math.min(t - frozen.shownAt, FROZEN_MAX_MS);
      frozen.gapMs = frozen.gapMs ? 0.9 * frozen.gapMs + 0.1 * gap : gap;
    }
    frozen.shownAt = t;
    if (frozen.on) markFrozen(false, 0);
  }
  function markFrozen(on, ageMs) {
    const el = $("frozen");
    if (on) {
      if (!frozen.on) frozen.marks += 1;
      const secs = ageMs / 1000;
      el.textContent = "picture frozen — " + (secs < 10 ? secs.toFixed(1) : Math.round(secs)) + " s";
    }
    frozen.on = on;
    el.hidden = !on;
  }
  function checkFrozen() {
    frozen.checks += 1;
    if (frozen.shownAt === null) return;
    const age = now() - frozen.shownAt;
    const limit = Math.min(FROZEN_MAX_MS, Math.max(FROZEN_MS, 2.5 * frozen.gapMs));
    if (age >= limit) markFrozen(true, age);
    else if (frozen.on) markFrozen(false, 0);
  }
  if (window.telebotMedia && window.telebotMedia.video) window.telebotMedia.video.onPicture = pictureShown;
  setInterval(checkFrozen, 100);

  $("navcam").onclick = () => send({ type: "camera", id: ++chatId, name: "navcam" });
  $("usercam").onclick = () => send({ type: "camera", id: ++chatId, name: "usercam" });

  // ------------------------------------------------------------------ chat
  function addChat(text, cls) {
    const log = $("chat-log");
    const div = document.createElement("div");
    div.textContent = text;
    if (cls) div.className = cls;
    log.appendChild(div);
    while (log.childNodes.length > 500) log.removeChild(log.firstChild);
    log.scrollTop = log.scrollHeight;
  }
  ui.addChat = addChat;
  $("chat-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const input = $("chat-input");
    const text = input.value.trim();
    input.value = "";
    if (!text) return;
    sendChat(text);
  });
  // A chat command from page code (static/follow.js), shown in the log like a typed one;
  // returns its request id (replies carry it), or 0 when the page is not connected.
  function sendChat(text) {
    addChat("> " + text, "cmd");
    const id = ++chatId;
    return send({ type: "chat", id, text }) ? id : 0;
  }
  ui.chat = sendChat;

  resize();
  connect();
})();
