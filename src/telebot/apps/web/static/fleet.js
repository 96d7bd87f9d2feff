// telebot fleet page: every robot online, open several side by side (each in a frame with
// its own page, call and STOP), stop all. Websocket protocol: telebot/apps/web/fleet.py.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const fleet = {
    state: { user: "", robots: [], opened: [], stopped: {}, stopAll: null, errors: [], connected: false },
  };
  window.telebotFleet = fleet;

  let ws = null;
  function connect() {
    const url = new URL("fleet/ws", location.href);
    url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    ws = new WebSocket(url.href);
    ws.onopen = () => { fleet.state.connected = true; showConn(); };
    ws.onclose = () => { fleet.state.connected = false; showConn(); setTimeout(connect, 1000); };
    ws.onmessage = (ev) => onMessage(JSON.parse(ev.data));
  }
  function send(msg) {
    if (ws && ws.readyState === WebSocket.OPEN) { ws.send(JSON.stringify(msg)); return true; }
    return false;
  }
  fleet.send = send;
  function showConn() {
    $("conn").textContent = fleet.state.connected ? "connected" : "disconnected";
    $("conn").className = fleet.state.connected ? "good" : "bad";
  }

  function onMessage(m) {
    switch (m.type) {
      case "hello": fleet.state.user = m.user; $("user").textContent = m.user; break;
      case "fleet": fleet.state.robots = m.robots; showList(); syncFrames(); break;
      case "opened": addFrame(m.robot, m.url); break;
      case "closed": removeFrame(m.robot); break;
      case "stopped": fleet.state.stopped[m.robot] = m; showStops(); break;
      case "stop_all": fleet.state.stopAll = m.results; showStops(); break;
      case "error": showError(m.text); break;
      default: break;
    }
  }

  function cell(tr, text, cls) {
    const td = document.createElement("td");
    td.textContent = text;
    if (cls) td.className = cls;
    tr.appendChild(td);
    return td;
  }
  function linkText(r) {
    if (r.connection && r.connection !== "connected") return r.connection;
    if (r.rtt == null) return r.called ? "rtt –" : "–";
    return "rtt " + (r.rtt * 1000).toFixed(0) + " ms, loss " + Math.round((r.loss || 0) * 100) + "%";
  }
  function showList() {
    const body = $("robots").tBodies[0];
    body.textContent = "";
    for (const r of fleet.state.robots) {
      const tr = document.createElement("tr");
      tr.id = "row-" + r.name;
      if (!r.online) tr.className = "offline";
      cell(tr, r.name + (r.online ? "" : " (offline)"));
      cell(tr, r.battery == null ? "–" : Math.round(r.battery) + "%" + (r.battery_low ? " LOW" : ""));
      cell(tr, r.state == null ? "–" : r.state + (r.armed === false ? " · stopped" : r.armed ? " · armed" : ""));
      cell(tr, r.called ? (r.holder || "nobody") : "–");
      cell(tr, linkText(r));
      if (r.problem) cell(tr, r.problem, "problem");
      else cell(tr, r.role || "–");
      const td = cell(tr, "");
      const button = document.createElement("button");
      button.id = (r.open ? "close-" : "open-") + r.name;
      button.textContent = r.open ? "close" : "open";
      button.disabled = !r.called && !r.open;
      button.onclick = () => send({ type: r.open ? "close" : "open", robot: r.name });
      td.appendChild(button);
      body.appendChild(tr);
    }
  }

  function frameOf(name) { return document.getElementById("frame-" + name); }
  function addFrame(name, url) {
    if (frameOf(name)) return;
    const box = document.createElement("div");
    box.className = "robot-frame";
    box.id = "frame-" + name;
    const bar = document.createElement("div");
    bar.className = "bar";
    const title = document.createElement("b");
    title.textContent = name;
    const close = document.createElement("button");
    close.textContent = "close";
    close.onclick = () => send({ type: "close", robot: name });
    bar.appendChild(title); bar.appendChild(close);
    const frame = document.createElement("iframe");
    frame.src = url;
    frame.title = "robot " + name;
    frame.name = "robot-" + name;
    box.appendChild(bar); box.appendChild(frame);
    $("opened").appendChild(box);
    fleet.state.opened.push(name);
  }
  function removeFrame(name) {
    const box = frameOf(name);
    if (box) box.remove();
    fleet.state.opened = fleet.state.opened.filter((n) => n !== name);
  }
  // After a reload of this page: frames for the robots the server has open.
  function syncFrames() {
    for (const r of fleet.state.robots) {
      if (r.open && !frameOf(r.name)) addFrame(r.name, r.url);
    }
  }

  function showStops() {
    const results = fleet.state.stopAll || Object.values(fleet.state.stopped);
    const parts = results.map((r) => r.robot + (r.ok ? " stopped" : ": " + r.text));
    const failed = results.some((r) => !r.ok);
    $("stop-result").textContent = parts.join(" · ");
    $("stop-result").className = failed ? "bad" : "good";
  }
  function showError(text) {
    fleet.state.errors.push(text);
    const div = document.createElement("div");
    div.textContent = text;
    $("fleet-errors").appendChild(div);
    while ($("fleet-errors").childNodes.length > 5) $("fleet-errors").removeChild($("fleet-errors").firstChild);
  }

  function stopAll() {
    fleet.state.stopped = {};
    fleet.state.stopAll = null;
    $("stop-result").textContent = "stopping all…";
    send({ type: "stop_all" });
  }
  fleet.stopAll = stopAll;
  $("stop-all").onclick = stopAll;
  // The paper's rule on this page too: any key stops (all robots; keys inside a robot's
  // frame go to that robot's page, which stops that robot).
  document.addEventListener("keydown", (ev) => { ev.preventDefault(); stopAll(); }, true);

  connect();
})();
