// The robot's own screen (served by telebot-robot run, telebot/apps/web/screen.py): the
// remote user's video full screen, their name, the call state, their voice. Decoding is
// media.js's (the same code as the user's page).
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const M = window.telebotMedia;
  const screen = { state: { user: "", text: "connecting…", call: false } };
  window.telebotScreen = screen;
  let ws = null;
  const sink = new M.VideoSink($("video"), () => send({ type: "keyframe" }));
  M.video = sink;
  let audio = null;
  sink.onPicture = () => { $("idle").style.display = "none"; };

  function send(m) {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(m));
  }
  function show(m) {
    screen.state = { user: m.user || "", text: m.text || "", call: !!m.call };
    $("name").textContent = m.user || "";
    $("state").textContent = m.text || "";
    if (!m.call) {
      // No one on the line: no stale face on the robot.
      $("idle").style.display = "flex";
      $("idle").textContent = m.text || "telebot";
    }
  }
  function connect() {
    ws = new WebSocket("ws://" + location.host + "/ws");
    ws.binaryType = "arraybuffer";
    ws.onclose = () => { show({ user: "", text: "connecting…", call: false }); setTimeout(connect, 1000); };
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
