/**
 * What the page side adds to window.telebot (browser.js merges it): the start page
 * (setup.js) and the robot page's port to a pinned robot (page-port.js), given the call,
 * session and gateway modules browser.js bundles.
 * @module page-entry
 */
import { Keys, parseInvite } from "./keys.js";
import { startSetup, qrSvg, callUrl } from "./setup.js";
import { robotPort } from "./page-port.js";

/** The gateway's WebSocket address beside this page (`gateway`, wss: on https:). */
export function gatewayUrl(loc = location) {
  const url = new URL("gateway", loc.href);
  url.protocol = loc.protocol === "https:" ? "wss:" : "ws:";
  return url.href;
}

/**
 * @param {object} deps
 * @param {Function} deps.Endpoint      call.js
 * @param {Function} deps.RobotSession  session.js
 * @param {(a: {url: string, name: string, privateKey: Uint8Array, publicKey: Uint8Array, invite?: string}) => Promise<object>} deps.openLink
 *   gateway-link.js: a link admitted as that user (or, with `invite`, registered by the invite first)
 */
export function pageApi({ Endpoint, RobotSession, openLink }) {
  let keys = null;
  const theKeys = async () => (keys ||= await Keys.open());
  return {
    Keys, parseInvite, qrSvg, callUrl,
    /** Run the start page (gateway.html). */
    startPage: async () => startSetup({
      keys: await theKeys(),
      // The invite's one use: a link that redeems it, closed again (the call opens its own).
      redeem: async ({ invite, me }) => {
        const link = await openLink({ url: gatewayUrl(), name: me.name, privateKey: me.privateKey, publicKey: me.publicKey, invite });
        if (link && link.close) link.close();
      },
    }),
    /** The robot page's port (static/port.js) to pinned robot `robot`. */
    robotPort: (robot) => robotPort(robot, {
      keys: theKeys, Endpoint, RobotSession,
      openLink: (me) => openLink({ url: gatewayUrl(), name: me.name, privateKey: me.privateKey, publicKey: me.publicKey }),
    }),
  };
}
