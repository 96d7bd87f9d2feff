// Which port the page talks through (app.js, "the port"): without `?robot=NAME` in its
// address, nothing here (app.js uses its websocket to the local `telebot-user ui`, §19).
// With it (the page served by a gateway at `call?robot=NAME`, opened from gateway.html),
// the in-browser client: static/telebot-client.js (the bundle, window.telebot) is loaded
// and its robotPort(NAME) calls the pinned robot with this browser's key through the
// gateway; the page then gets the same §19 messages as from the local client.
"use strict";

(function () {
  const robot = new URLSearchParams(location.search).get("robot");
  if (!robot) return;
  let inner = null;
  function load() {
    if (window.telebot) return Promise.resolve();
    return new Promise((resolve, reject) => {
      const s = document.createElement("script");
      s.src = "static/telebot-client.js";
      s.onload = () => resolve();
      s.onerror = () => reject(new Error("could not load static/telebot-client.js"));
      document.head.appendChild(s);
    });
  }
  window.telebotPort = {
    connect(h) {
      load().then(() => {
        inner = window.telebot.robotPort(robot);
        inner.connect(h);
      }).catch((e) => h.message({ type: "error", text: e.message }));
    },
    send: (msg) => (inner ? inner.send(msg) : false),
    sendMedia: (header, data, isVideo) => (inner ? inner.sendMedia(header, data, isVideo) : false),
    // How the call reaches the gateway: "webtransport", "websocket" (null: not yet).
    linkKind: () => (inner ? inner.linkKind() : null),
  };
})();
