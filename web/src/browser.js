/**
 * The browser bundle's entry (web/build.mjs): telebot's client API on `window.telebot`.
 * Pages extend it; keep this file to the exports.
 *
 * - the protocol core: Endpoint, Call, Channel, the identity helpers and the errors;
 * - the page's session with a robot (docs/protocol.md §19): RobotSession, with
 *   packMedia (a {type: "video"|"audio", header, data} message as today's binary
 *   websocket message), backoffDelay and realClock;
 * - what a page draws with: decodeMapPng / pngSize (the map's PNG), STOP_HOWS (a stop's
 *   `how`), sayText (a chat line that is a `say`), CODEC_IDS / CODEC_NAMES (video codecs),
 *   RequestFailed (what a service request rejects with: `code`, one-line `message`);
 * - the gateway (docs/protocol.md §26): connectGateway, GatewayError, and the pages'
 *   entry points startPage / robotPort (page-entry.js).
 * @module browser
 */
import * as errors from "./errors.js";
import * as identity from "./identity.js";
import { Call, Channel, Endpoint } from "./call.js";
import { RobotSession, backoffDelay, packMedia, realClock } from "./session.js";
import { RequestFailed } from "./services/services.js";
import { STOP_HOWS, sayText } from "./services/messages.js";
import { decodeMapPng, pngSize } from "./services/map.js";
import { CODEC_IDS, CODEC_NAMES } from "./services/video.js";
import { GatewayError, SplitLink, connectGateway, connectSplit } from "./gateway-link.js";
import { WebTransportSocket, connectBest } from "./webtransport.js";
import { pageApi } from "./page-entry.js";

export const telebot = {
  ...errors,
  ...identity,
  Endpoint,
  Call,
  Channel,
  RobotSession,
  backoffDelay,
  packMedia,
  realClock,
  RequestFailed,
  STOP_HOWS,
  sayText,
  decodeMapPng,
  pngSize,
  CODEC_IDS,
  CODEC_NAMES,
  GatewayError,
  connectGateway,
  connectSplit,
  connectBest,
  SplitLink,
  WebTransportSocket,
  // The pages served by a gateway: the start page (gateway.html) and the robot page's
  // port (static/port.js), each through an admitted link to the gateway beside the page:
  // two WebTransport sessions when the gateway offers them and the browser reaches it, else
  // two websockets; either way control on one (what the page sends of it on both), pictures
  // and sound on the other (webtransport.js and gateway-link.js's SplitLink say why).
  ...pageApi({ Endpoint, RobotSession, openLink: (a) => connectBest(a.url, a) }),
};
/** @type {any} */ (globalThis).telebot = telebot;
