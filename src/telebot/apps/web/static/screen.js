// The robot's own screen (served by telebot-robot run, telebot/apps/web/screen.py): the
// remote user's video full screen, their name, the call state, their voice. Decoding is
// media.js's (the same code as the user's page).
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const M = window.telebotMedia;
  const screen = { state: { user: "", text: "connecting…", call: false, video: false } };
  window.telebotScreen = screen;
  let ws = null;
  const sink = new M.VideoSink($("video"), () => send({ type: "keyframe" }));
  M.video = sink;
  let audio = null;
  // A picture is shown only while the robot says the user's camera is coming: one still in
  // flight when it went off must not bring back a frozen face.
  sink.onPicture = () => {
    if (screen.state.call && screen.state.video) $("idle").style.display = "none";
    else blank();
  };

  function blank() {
    const c = $("video");
    sink.ctx.clearRect(0, 0, c.width, c.height);
  }

  function send(m) {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(m));
  }
  function show(m) {
    const was = screen.state;
    screen.state = { user: m.user || "", text: m.text || "", call: !!m.call, video: !!m.video };
    $("name").textContent = m.user || "";
    $("state").textContent = m.text || "";
    if (!m.call) {
      // No one on the line: no stale face on the robot.
      blank();
      $("idle").style.display = "flex";
      $("idle").textContent = m.text || "telebot";
    } else if (!m.video) {
      // The user's camera is off (or its pictures stopped coming): people at the robot
      // must not take the last picture for live.
      blank();
      $("idle").style.display = "flex";
      $("idle").textContent = (m.user ? m.user + "'s" : "the caller's") + " camera is off";
    } else if (!was.video || !was.call) {
      // The camera is back: the next picture hides this (none is shown until one comes).
      $("idle").textContent = "";
    }
  }
  function connect() {
    ws = new WebSocket("ws://" + location.host + "/ws");
    ws.binaryType = "arraybuffer";
    ws.onclose = () => { show({ user: "", text: "connecting…", call: false, video: false }); setTimeout(connect, 1000); };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") {
        const m = JSON.parse(ev.data);
        if (m.type === "state") show(m);
        return;
      }
      const { header, data } = M.unpack(ev.data);
      if (header.kind === "audio") {
        if (!audio) { audio = new M.AudioSink(); M.audio = audio; }
        audio.push(header, data);
      } else {
        sink.push(header, data);
      }
    };
  }
  connect();
})();
