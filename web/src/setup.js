/**
 * The start page a gateway serves at `/` (static/gateway.html): the browser user's setup
 * without a terminal (issue 24 §1 Keys, §4 invites). Make the key (named), show it as the
 * contact line `telebot-user keygen` prints and as a QR code (for the robot's admin to add
 * with `telebot-robot contacts add`), pin robots (paste a robot's contact line, or accept
 * an invite link `#invite=TOKEN&robot=NAME&key=KEY` from `telebot-robot invite`), list
 * them, and call one (the robot page, `call?robot=NAME`, then talks through page-port.js).
 * @module setup
 */
import qrcode from "qrcode-generator";
import { parseInvite } from "./keys.js";

/**
 * `text` as a QR code, an SVG element's markup (error correction M, scalable).
 * @param {string} text
 * @returns {string}
 */
export function qrSvg(text) {
  const qr = qrcode(0, "M");
  qr.addData(text);
  qr.make();
  return qr.createSvgTag({ cellSize: 4, margin: 4, scalable: true });
}

/** The robot page's address for robot `name`, relative to the start page. */
export const callUrl = (name) => "call?robot=" + encodeURIComponent(name);

/**
 * Run the start page in `doc` (gateway.html's elements, by id).
 * @param {object} opts
 * @param {import("./keys.js").Keys} opts.keys
 * @param {(a: {invite: string, robot: string, key: string, me: object}) => Promise<void>} opts.redeem
 *   registers this browser's key with the robot through the gateway (the invite's one use)
 * @param {Document} [opts.doc]
 * @param {{hash: string, href: string}} [opts.loc]
 * @param {(name: string) => void} [opts.go]  open the robot page
 */
export async function startSetup({ keys, redeem, doc = document, loc = location, go }) {
  const $ = (id) => doc.getElementById(id);
  const state = { me: null, line: "", robots: [], invite: null, error: "", busy: false };
  const open = go || ((name) => { loc.href = callUrl(name); });
  globalThis.telebotSetup = state; // for tests: what the page shows

  function error(text) {
    state.error = text;
    $("setup-error").textContent = text;
    $("setup-error").hidden = !text;
  }
  /** Run `fn`, showing its error (one line) instead of throwing. */
  async function guard(fn) {
    error("");
    try { await fn(); } catch (e) { error(String(e.message || e).split("\n")[0]); }
    await render();
  }

  async function render() {
    state.me = await keys.me();
    $("no-key").hidden = !!state.me;
    $("my-key").hidden = !state.me;
    if (state.me) {
      state.line = await keys.contactLine();
      $("my-name").value = state.me.name;
      $("contact-line").textContent = state.line;
      $("qr").innerHTML = qrSvg(state.line);
    }
    $("store-note").hidden = keys.store.persistent !== false;
    state.robots = await keys.robots();
    const list = $("robot-list");
    list.replaceChildren();
    for (const r of state.robots) {
      const li = doc.createElement("li");
      li.dataset.robot = r.name;
      const name = doc.createElement("b");
      name.textContent = r.name;
      const fp = doc.createElement("span");
      fp.className = "fp";
      fp.textContent = r.fingerprint.slice(0, 20) + "…";
      const call = doc.createElement("button");
      call.className = "call";
      call.textContent = "call";
      call.disabled = !state.me;
      call.onclick = () => open(r.name);
      const unpin = doc.createElement("button");
      unpin.className = "unpin";
      unpin.textContent = "unpin";
      unpin.onclick = () => guard(() => keys.unpin(r.name));
      li.append(name, " ", fp, " ", call, " ", unpin);
      list.appendChild(li);
    }
    $("no-robots").hidden = state.robots.length > 0;
    $("invite").hidden = !state.invite;
    if (state.invite) {
      $("invite-robot").textContent = state.invite.robot;
      $("accept-invite").disabled = !state.me || state.busy;
    }
  }

  $("create-key").onclick = () => guard(() => keys.create($("new-name").value.trim()));
  $("rename").onclick = () => guard(() => keys.rename($("my-name").value.trim()));
  $("copy-line").onclick = () => guard(() => navigator.clipboard.writeText(state.line));
  $("pin").onclick = () => guard(async () => {
    await keys.pinLine($("pin-line").value);
    $("pin-line").value = "";
  });
  $("accept-invite").onclick = () => guard(async () => {
    const inv = state.invite;
    const me = await keys.me();
    if (!me) throw new Error("make your key first");
    state.busy = true;
    try {
      // Pin first: a KEY MISMATCH with a robot pinned before stops here, before the
      // one-time invite is spent on the gateway.
      const pinned = await keys.pin(inv.robot, inv.key, "invite");
      try {
        await redeem({ ...inv, me });
      } catch (e) {
        if (pinned.added) await keys.unpin(inv.robot);
        throw e;
      }
    } finally {
      state.busy = false;
    }
    state.invite = null;
    history.replaceState(null, "", loc.href.split("#")[0]); // the token is spent: off the address
  });

  // The invite in the address, on opening and whenever another link is opened in this tab.
  async function readInvite() {
    error("");
    try {
      state.invite = parseInvite(loc.hash);
    } catch (e) {
      state.invite = null;
      error(e.message);
    }
    await render();
  }
  if (globalThis.addEventListener) globalThis.addEventListener("hashchange", () => readInvite());
  await readInvite();
  return state;
}
