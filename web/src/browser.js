/**
 * The browser bundle's entry (web/build.mjs): telebot's client API on `window.telebot`.
 * Pages extend it; keep this file to the exports.
 * @module browser
 */
import * as errors from "./errors.js";
import * as identity from "./identity.js";
import { Call, Channel, Endpoint } from "./call.js";

export const telebot = { ...errors, ...identity, Endpoint, Call, Channel };
/** @type {any} */ (globalThis).telebot = telebot;
