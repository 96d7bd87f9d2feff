// telebot web UI: people near the robot (the robot's `people` stream, see
// telebot/apps/web/server.py). Draws each tracked person on the map (a disc, its id and
// where it walks), marks them in the video (a box at the person's bearing, sized by the
// distance), lists them under the video with a "follow" button each (the follow-me page
// code, static/follow.js, listens for the "telebot:follow" event), and shows alerts in the
// chat and as a banner over the video.
"use strict";

(function () {
  const ui = window.telebotUI;
  if (!ui || !ui.hooks) return;
  const $ = (id) => document.getElementById(id);
  ui.state.people = null;  // the latest "people" message
  ui.state.peopleAlerts = [];
  ui.drawn.people = 0;

  // An overlay canvas on the video, the same size as the picture.
  const video = $("video");
  const box = $("video-box");
  const overlay = document.createElement("canvas");
  overlay.id = "people-overlay";
  overlay.style.cssText = "position:absolute;left:0;top:0;pointer-events:none;";
  const banner = document.createElement("div");
  banner.id = "people-banner";
  banner.style.cssText = "position:absolute;left:0;right:0;top:0;padding:2px 6px;" +
    "background:rgba(200,40,0,0.8);color:#fff;font:13px sans-serif;display:none;";
  if (box && video) {
    box.style.position = "relative";
    box.appendChild(overlay);
    box.appendChild(banner);
  }
  let bannerTimer = null;

  // One row per tracked person, kept while the id lives (a row rebuilt under the pointer
  // would swallow the click on its button).
  const list = document.createElement("div");
  list.id = "people-list";
  if (box) box.parentNode.insertBefore(list, box.nextSibling);
  const rows = new Map();
  function side(b) {
    const deg = b * 180 / Math.PI;
    if (Math.abs(deg) <= 30) return "ahead";
    if (Math.abs(deg) >= 150) return "behind";
    return deg > 0 ? "left" : "right";
  }
  function showList() {
    const msg = ui.state.people;
    const live = new Set();
    for (const t of msg ? msg.tracks : []) {
      live.add(t.id);
      let row = rows.get(t.id);
      if (!row) {
        row = document.createElement("div");
        row.className = "person";
        const label = document.createElement("span");
        const follow = document.createElement("button");
        follow.textContent = "follow";
        follow.className = "drive";
        follow.disabled = !ui.state.mayDrive;
        follow.title = "follow this person (any key stops)";
        follow.onclick = () => document.dispatchEvent(
          new CustomEvent("telebot:follow", { detail: { id: t.id } }));
        row.append(label, " ", follow);
        list.appendChild(row);
        rows.set(t.id, row);
      }
      row.firstChild.textContent = "#" + t.id + " · " + t.r.toFixed(1) + " m " + side(t.b) +
        (t.src.includes("camera") ? " · seen" : "");
    }
    for (const [id, row] of rows) {
      if (!live.has(id)) { row.remove(); rows.delete(id); }
    }
  }

  function markVideo() {
    if (!video || !box) return;
    const w = video.clientWidth, h = video.clientHeight;
    overlay.width = w; overlay.height = h;
    overlay.style.width = w + "px"; overlay.style.height = h + "px";
    const ctx = overlay.getContext("2d");
    ctx.clearRect(0, 0, w, h);
    const msg = ui.state.people;
    if (!msg || !ui.state.camera) return;
    const fov = msg.cams[ui.state.camera];
    if (!fov) return;
    // The picture keeps its 4:3 aspect inside the element (object-fit: contain).
    const iw = Math.min(w, h * 4 / 3), ih = iw * 3 / 4;
    const x0 = (w - iw) / 2, y0 = (h - ih) / 2;
    const f = (iw / 2) / Math.tan(fov * Math.PI / 360);
    ctx.font = "12px sans-serif"; ctx.lineWidth = 2;
    for (const t of msg.tracks) {
      const depth = t.r * Math.cos(t.b);
      if (depth < 0.3 || Math.abs(t.b) > fov * Math.PI / 360) continue;
      const u = x0 + iw / 2 - Math.tan(t.b) * f;
      const tall = 1.75 * f / depth, wide = tall * 0.4;
      const top = y0 + ih / 2 - tall * 0.55;
      ctx.strokeStyle = "#ff0";
      ctx.strokeRect(u - wide / 2, top, wide, tall);
      ctx.fillStyle = "#ff0";
      ctx.fillText("#" + t.id + " " + t.r.toFixed(1) + " m", u - wide / 2, Math.max(top - 4, 12));
    }
  }

  ui.hooks.message.push((m) => {
    if (m.type === "people") {
      ui.state.people = m;
      markVideo();
      showList();
      ui.draw();
    } else if (m.type === "people_alert") {
      ui.state.peopleAlerts.push(m);
      ui.addChat("[" + m.text + "]", "fail");
      banner.textContent = m.text;
      banner.style.display = "block";
      clearTimeout(bannerTimer);
      bannerTimer = setTimeout(() => { banner.style.display = "none"; }, 5000);
    }
  });

  ui.hooks.draw.push((ctx, toScreen, pxm) => {
    const msg = ui.state.people;
    ui.drawn.people = 0;
    if (!msg) return;
    ctx.font = "11px sans-serif"; ctx.textBaseline = "middle";
    for (const t of msg.tracks) {
      const [sx, sy] = toScreen(t.x, t.y);
      const r = Math.max(4, 0.25 * pxm);
      ctx.fillStyle = t.src.includes("camera") ? "rgba(255,140,0,0.85)" : "rgba(255,190,0,0.7)";
      ctx.strokeStyle = "#a40";
      ctx.lineWidth = 1.5;
      ctx.beginPath(); ctx.arc(sx, sy, r, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
      // Where the person will be in a second.
      ctx.beginPath(); ctx.moveTo(sx, sy);
      ctx.lineTo(sx + t.vx * pxm, sy - t.vy * pxm); ctx.stroke();
      ctx.fillStyle = "#520";
      ctx.fillText("#" + t.id, sx + r + 2, sy);
      ui.drawn.people += 1;
    }
  });
})();
