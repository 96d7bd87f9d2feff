// telebot web UI: the conference (everyone in the robot's calls). Shows who is in the
// call and who drives, and the messages of the other users and of the robot in the chat
// log. "say TEXT" in the chat box speaks to everyone (server.py turns it into a say).
"use strict";

(function () {
  const ui = window.telebotUI;
  ui.state.roster = [];
  ui.state.messages = [];

  function showRoster() {
    const parts = ui.state.roster.map((u) =>
      u.name + (u.you ? " (you)" : "") + " · " + u.role + (u.driving ? " · driving" : ""));
    document.getElementById("roster").textContent = parts.join(", ") || "nobody";
  }

  ui.handlers.roster = (m) => { ui.state.roster = m.users; showRoster(); };
  ui.handlers.msg = (m) => {
    if (ui.state.messages.some((x) => x.seq === m.seq)) return; // sent again on reload
    ui.state.messages.push(m);
    if (ui.state.messages.length > 500) ui.state.messages.shift();
    const me = ui.state.roster.find((u) => u.you);
    if (m.kind === "robot") ui.addChat("[" + m.from + ": " + m.text + "]", "note");
    else ui.addChat("[" + m.from + "] " + m.text, me && me.name === m.from ? "cmd" : "say");
  };
  ui.handlers.said = (m) => {
    if (!m.ok) ui.addChat("say refused: " + m.text, "fail");
  };
})();
