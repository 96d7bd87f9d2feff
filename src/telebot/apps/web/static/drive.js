// telebot web UI: driving by hand (docs/protocol.md §19 `drive`, §27). Hold to drive:
//   - the arrow keys or WASD (by position: ZQSD on an AZERTY keyboard), keydown starts,
//     keyup releases; any other key still stops the robot (app.js), and in the chat box
//     the keys are the chat box's (they never drive);
//   - a gamepad (the browser Gamepad API): the left stick, while LB or RB (a shoulder
//     button, the deadman) is held; letting go of it releases;
//   - on a touch screen, an on-screen joystick at the bottom left (STOP stays at the
//     bottom right); lifting the finger releases.
// While held the page sends {"type": "drive", linear, angular} to its port at 20 Hz, and
// once {"type": "drive", linear: 0, angular: 0} on release; the robot obeys only while
// fresh commands arrive (stale after 0.3 s: it stops by itself) and clamps the speed.
// The page loses focus, is hidden or goes away: released. The robot's `drive_state` is
// shown beside the safety state (driving, refused and why, stale, ...).
"use strict";

(function () {
  const ui = window.telebotUI;
  if (!ui || !ui.send) return;

  /** Full stick / key: the robot clamps to its own cap anyway. */
  const MAX_LINEAR = 0.5; // m/s
  const MAX_ANGULAR = 1.0; // rad/s
  const EVERY_MS = 50; // 20 Hz
  const DEADZONE = 0.15; // of a stick's travel
  const DEADMAN = [4, 5]; // LB, RB in the standard gamepad mapping
  /** No drive_state for this long while the page drives: say the robot does not answer. */
  const SILENT_MS = 1000;
  // KeyboardEvent.code → [forward, counter-clockwise]
  const KEYS = {
    ArrowUp: [1, 0], KeyW: [1, 0],
    ArrowDown: [-1, 0], KeyS: [-1, 0],
    ArrowLeft: [0, 1], KeyA: [0, 1],
    ArrowRight: [0, -1], KeyD: [0, -1],
  };

  const held = new Set(); // drive keys down now
  let stick = null; // the on-screen joystick: {x, y} in -1..1 (y down), or null
  let pad = null; // the gamepad's command [linear, angular] while its deadman is held
  let padHalted = false; // a stop while the deadman was held: wait for it to be let go
  let active = false; // a non-zero command was the last one sent
  let lastState = 0; // when the last drive_state came (ms)
  // For tests: datagrams sent, timer ticks, the robot's last drive_state.
  const drive = { sent: 0, ticks: 0, state: null, deadman: "LB or RB" };
  ui.drive = drive;
  ui.state.drive = null;

  const clamp = (v) => Math.max(-1, Math.min(1, v));
  const round = (v) => Math.round(v * 1000) / 1000;

  // What the user holds now: keys first, then the joystick, then the gamepad.
  function command() {
    if (held.size) {
      let f = 0, t = 0;
      for (const code of held) { f += KEYS[code][0]; t += KEYS[code][1]; }
      return [clamp(f) * MAX_LINEAR, clamp(t) * MAX_ANGULAR];
    }
    if (stick) return [-stick.y * MAX_LINEAR, -stick.x * MAX_ANGULAR];
    return pad;
  }
  drive.command = command;

  function send(linear, angular) {
    linear = round(linear) || 0;
    angular = round(angular) || 0;
    if (ui.send({ type: "drive", linear, angular })) drive.sent += 1;
  }

  // Send what is held now (at once on every change, and every 50 ms from the timer); a
  // command that became nothing (or zero) is one release.
  function update() {
    const c = ui.state.mayDrive ? command() : null;
    if (c && (c[0] !== 0 || c[1] !== 0)) {
      if (!active) lastState = Date.now();
      active = true;
      send(c[0], c[1]);
    } else if (active) {
      active = false;
      send(0, 0);
    }
    show();
  }
  drive.update = update;

  // Everything let go, with one release if the page was driving (focus lost, hidden).
  function release() {
    held.clear();
    stickEnd();
    if (pad) padHalted = true;
    pad = null;
    update();
  }
  // A stop was sent (another key, STOP, the video touched): nothing more goes out until
  // the user lets go and starts again; the stop itself ends direct driving on the robot.
  function halt() {
    held.clear();
    stickEnd();
    if (pad) padHalted = true;
    pad = null;
    active = false;
    show();
  }
  drive.release = release;

  // ---------------------------------------------------------------- keys
  function typing(target) {
    if (!target || !target.tagName) return false;
    if (target.isContentEditable || target.tagName === "TEXTAREA") return true;
    return target.tagName === "INPUT" && !["checkbox", "radio", "button", "range"].includes(target.type);
  }
  function driveKey(ev) {
    return Object.prototype.hasOwnProperty.call(KEYS, ev.code) && !ev.ctrlKey && !ev.altKey && !ev.metaKey;
  }
  // On window in the capture phase: before app.js's any-key stop (on document), which a
  // drive key must not reach; every other key goes on to it and stops the robot.
  window.addEventListener("keydown", (ev) => {
    if (typing(ev.target)) return; // the chat box's keys: app.js's rule (Escape stops)
    if (!driveKey(ev) || !ui.state.mayDrive) { halt(); return; }
    ev.preventDefault();
    ev.stopPropagation();
    if (held.has(ev.code) || ev.repeat) return; // auto-repeat: a stop in between ends it
    held.add(ev.code);
    update();
  }, true);
  window.addEventListener("keyup", (ev) => {
    if (!held.delete(ev.code)) return;
    ev.preventDefault();
    update();
  }, true);

  // ---------------------------------------------------------------- gamepad
  function axis(v) {
    if (typeof v !== "number" || !Number.isFinite(v) || Math.abs(v) < DEADZONE) return 0;
    return clamp(Math.sign(v) * (Math.abs(v) - DEADZONE) / (1 - DEADZONE));
  }
  function pressed(b) {
    return !!b && (b.pressed === true || (typeof b.value === "number" && b.value > 0.5));
  }
  function pollPad() {
    const pads = navigator.getGamepads ? Array.from(navigator.getGamepads() || []) : [];
    const gp = pads.find((p) => p && p.connected !== false && p.axes && p.buttons);
    const deadman = !!gp && DEADMAN.some((i) => pressed(gp.buttons[i]));
    if (!deadman) { pad = null; padHalted = false; return; }
    if (padHalted) { pad = null; return; }
    pad = [-axis(gp.axes[1]) * MAX_LINEAR, -axis(gp.axes[0]) * MAX_ANGULAR];
  }

  // ---------------------------------------------------------------- joystick
  const joy = document.createElement("div");
  joy.id = "joystick";
  joy.title = "drag to drive; lift your finger to stop";
  joy.hidden = true;
  const knob = document.createElement("div");
  knob.id = "joystick-knob";
  joy.appendChild(knob);
  document.body.appendChild(joy);
  const touchScreen = (window.matchMedia && window.matchMedia("(pointer: coarse)").matches) ||
    navigator.maxTouchPoints > 0;
  let stickId = null;
  function stickMove(ev) {
    const r = joy.getBoundingClientRect();
    const radius = r.width / 2;
    let x = (ev.clientX - (r.left + radius)) / radius;
    let y = (ev.clientY - (r.top + radius)) / radius;
    const len = Math.hypot(x, y);
    if (len > 1) { x /= len; y /= len; }
    knob.style.transform = "translate(" + (x * radius * 0.6).toFixed(1) + "px, " + (y * radius * 0.6).toFixed(1) + "px)";
    stick = { x: Math.abs(x) < DEADZONE ? 0 : x, y: Math.abs(y) < DEADZONE ? 0 : y };
  }
  function stickEnd() {
    stickId = null;
    stick = null;
    knob.style.transform = "";
    joy.classList.remove("on");
  }
  joy.addEventListener("pointerdown", (ev) => {
    ev.preventDefault();
    if (!ui.state.mayDrive || stickId !== null) return;
    stickId = ev.pointerId;
    joy.setPointerCapture(ev.pointerId);
    joy.classList.add("on");
    stickMove(ev);
    update();
  });
  joy.addEventListener("pointermove", (ev) => {
    if (ev.pointerId !== stickId) return;
    stickMove(ev);
    update();
  });
  for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
    joy.addEventListener(type, (ev) => {
      if (ev.pointerId !== stickId) return;
      stickEnd();
      update();
    });
  }
  joy.addEventListener("contextmenu", (ev) => ev.preventDefault());

  // ---------------------------------------------------------------- stops, focus
  // app.js sends the stop for these; here only: nothing more goes out after it.
  for (const id of ["stop", "video-box"]) {
    const el = document.getElementById(id);
    if (el) el.addEventListener("pointerdown", (ev) => { if (id === "stop" || !ev.target.closest("button, label, input")) halt(); }, true);
  }
  const stopButton = document.getElementById("stop");
  if (stopButton) stopButton.addEventListener("click", halt, true);
  window.addEventListener("blur", release); // the key-ups would go elsewhere
  window.addEventListener("pagehide", release);
  document.addEventListener("visibilitychange", () => { if (document.visibilityState === "hidden") release(); });
  document.addEventListener("freeze", release);

  setInterval(() => {
    drive.ticks += 1;
    pollPad();
    update();
  }, EVERY_MS);

  // ---------------------------------------------------------------- the robot's answer
  const box = document.createElement("div");
  box.id = "drive-box";
  box.innerHTML = 'hand drive: <b id="drive-state">–</b>' +
    '<div class="note" id="drive-help">hold ↑ ↓ ← → or WASD · a gamepad: left stick with LB or RB held</div>';
  const safetyBox = document.getElementById("safety-box");
  if (safetyBox) safetyBox.parentNode.insertBefore(box, safetyBox.nextSibling);
  else document.body.appendChild(box);
  const stateEl = box.querySelector("#drive-state");
  if (touchScreen) {
    box.querySelector("#drive-help").textContent =
      "drag the joystick (bottom left) · lift your finger to stop · or a keyboard or gamepad";
  }

  const ENDED = {
    released: "released",
    stale: "stale: commands stopped arriving, the robot stopped",
    replaced: "ended: a goal or a command took over",
    stopped: "ended: the robot was stopped",
  };
  function describe(m) {
    if (m.active && m.code === "ok") {
      return ["driving " + m.linear.toFixed(2) + " m/s, " + m.angular.toFixed(2) + " rad/s (cap " + m.cap.toFixed(2) + ")", "good"];
    }
    if (m.code in ENDED) return [ENDED[m.code], m.code === "stale" ? "bad" : ""];
    if (m.code === "obstacle") return ["obstacle: " + (m.text || "the robot stopped"), "bad"];
    if (m.code === "invalid") return ["invalid command: " + m.text, "bad"];
    return ["refused: " + (m.text || m.code), "bad"];
  }
  function show() {
    const touch = touchScreen && ui.state.mayDrive;
    if (joy.hidden === touch) joy.hidden = !touch;
    box.hidden = !ui.state.mayDrive;
    const m = ui.state.drive;
    let [text, cls] = m ? describe(m) : ["–", ""];
    if (active && Date.now() - lastState > SILENT_MS) { text = "no answer from the robot"; cls = "bad"; }
    if (stateEl.textContent !== text) stateEl.textContent = text;
    stateEl.className = cls;
  }
  ui.handlers.drive_state = (m) => {
    ui.state.drive = m;
    drive.state = m;
    lastState = Date.now();
    show();
  };
  show();
})();
