// telebot web UI: follow-me. A "follow person" button (the nearest person in front), an
// "unfollow" button, and following a person clicked on the map: the people layer
// (static/people.js) calls telebotUI.followPerson(id), or dispatches the DOM event
//   document.dispatchEvent(new CustomEvent("telebot:follow", { detail: { id: 3 } }))
// Both only send chat commands (`follow`, `follow ID`, `unfollow`): the robot decides,
// and refuses observers, a stopped robot, nobody tracked or an unknown id with the reason.
// Any key and the STOP button stop a follow like any motion (app.js).
"use strict";

(function () {
  const ui = window.telebotUI;
  if (!ui || !ui.chat) return;

  const row = document.createElement("div");
  row.className = "row";
  row.id = "follow-box";
  const start = document.createElement("button");
  start.id = "follow-person";
  start.className = "drive";
  start.title = "follow the nearest person in front of the robot (any key stops)";
  start.textContent = "follow person";
  const end = document.createElement("button");
  end.id = "unfollow";
  end.className = "drive";
  end.title = "stop following (the robot stops)";
  end.textContent = "unfollow";
  const status = document.createElement("span");
  status.id = "follow-status";
  row.append(start, end, status);
  const goalBox = document.getElementById("goal-box");
  goalBox.parentNode.insertBefore(row, goalBox.nextSibling);

  // Request ids of this file's commands: their replies are shown beside the buttons.
  const mine = new Set();
  function ask(text) {
    const id = ui.chat(text);
    if (id) mine.add(id);
    return id !== 0;
  }

  // id: a track id (a number), or null for the nearest person in front.
  function followPerson(id) {
    if (!ui.state.mayDrive) return false;
    const n = id == null ? null : Number(id);
    if (n != null && !(Number.isInteger(n) && n >= 0)) return false;
    status.textContent = n == null ? "asking to follow…" : "asking to follow " + n + "…";
    return ask(n == null ? "follow" : "follow " + n);
  }
  ui.followPerson = followPerson;
  start.onclick = () => followPerson(null);
  end.onclick = () => ask("unfollow");
  document.addEventListener("telebot:follow", (ev) => followPerson(ev.detail && ev.detail.id));

  // The robot's replies say whether it follows, and why it stopped.
  let index = ui.state.chat.length;
  setInterval(() => {
    const replies = ui.state.chat;
    for (; index < replies.length; index++) {
      const m = replies[index];
      if (mine.has(m.id)) status.textContent = m.text;
    }
  }, 250);
})();
