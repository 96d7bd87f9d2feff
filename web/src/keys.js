/**
 * The browser user's key and the robots it trusts (docs/protocol.md §3; issue 24 §1 Keys):
 * the browser's counterpart of `~/.telebot/id_telebot` and `known_robots.toml`.
 *
 * The key is made here (X25519 from the platform's random source, through @noble/curves)
 * and never leaves the browser: it is kept in IndexedDB (store.js), readable only by pages
 * of this origin. It is stored as its raw 32 bytes, not as a non-extractable WebCrypto key:
 * Chromium has WebCrypto X25519 (generateKey({name: "X25519"}, false, ["deriveBits"])), and
 * deriveBits would do for the gateway's admission proof, but the Noise IK handshake of every
 * call (§5: the `ss` and `se` DH with the static key) runs in @noble inside the sans-IO
 * protocol code, which needs the private key's bytes, synchronously; a non-extractable key
 * cannot give them, by design. So the protection is the origin's storage (as a file of mode
 * 0600 is the CLI's), and a browser profile that is not the user's own should not hold one.
 *
 * Robots are pinned by name and key, as `known_robots.toml` pins them: from the robot's
 * contact line (pasted or scanned), or from an invite link (`#invite=TOKEN&robot=NAME&key=KEY`,
 * `telebot-robot invite`). Unlike `telebot-user known add`, pinning a name already pinned
 * with another key is refused: a link must not be able to swap a robot's key silently (unpin
 * it first, knowingly).
 * @module keys
 */
import { contactLine, encodeKey, decodeKey, fingerprint, generateKeyPair, parseContactLine } from "./identity.js";
import { memoryStore, indexedDbStore } from "./store.js";

/** Most robots one browser pins (a bound on what a page lists and stores). */
export const MAX_ROBOTS = 256;
/** Longest invite token accepted from a link (characters). */
export const MAX_INVITE = 256;

const KEY_PREFIX = "telebot-x25519";

/**
 * A robot's name and key checked as `parseContactLine` checks them (one rule for both).
 * @param {string} name @param {string} keyText
 * @returns {{name: string, publicKey: Uint8Array}}
 */
function checked(name, keyText) {
  if (typeof name !== "string" || !name) throw new Error("a robot needs a name");
  if (typeof keyText !== "string") throw new Error("a robot needs a key");
  return parseContactLine(`${KEY_PREFIX} ${keyText.trim()} ${name.trim()}`);
}

/** A short, one-line form of a key for messages (its first 8 characters). */
const short = (keyText) => keyText.slice(0, 8) + "…";

/**
 * The invite in a page address's fragment (`#invite=TOKEN&robot=NAME&key=KEY`), or null
 * when there is none; an Error (one line) when it is there but malformed.
 * @param {string} hash  location.hash (with or without its "#")
 * @returns {{invite: string, robot: string, key: string} | null}
 */
export function parseInvite(hash) {
  const params = new URLSearchParams(String(hash || "").replace(/^#/, ""));
  if (!params.has("invite")) return null;
  const invite = params.get("invite") || "";
  if (!invite) throw new Error("the invite link has no token");
  if (invite.length > MAX_INVITE || !/^[A-Za-z0-9_-]+$/.test(invite)) {
    throw new Error("the invite link's token is not one (URL-safe characters, at most " + MAX_INVITE + ")");
  }
  const robot = params.get("robot") || "";
  const key = params.get("key") || "";
  if (!robot || !key) throw new Error("the invite link needs the robot's name and key (robot=…&key=…)");
  let parsed;
  try {
    parsed = checked(robot, key);
  } catch (e) {
    throw new Error("the invite link's robot is not valid: " + e.message);
  }
  return { invite, robot: parsed.name, key: encodeKey(parsed.publicKey) };
}

/** The user's key and pinned robots, in a store (IndexedDB in a browser). */
export class Keys {
  /**
   * The browser's keys (IndexedDB), or in memory when `store` says so.
   * @param {import("./store.js").Store} [store]
   */
  static async open(store) {
    return new Keys(store || (await indexedDbStore()));
  }

  /** @param {import("./store.js").Store} [store] */
  constructor(store = memoryStore()) {
    this.store = store;
  }

  /**
   * The user's identity, or null before one is made.
   * @returns {Promise<{name: string, privateKey: Uint8Array, publicKey: Uint8Array} | null>}
   */
  async me() {
    const me = await this.store.get("me");
    if (!me) return null;
    if (!(me.privateKey instanceof Uint8Array) || me.privateKey.length !== 32 ||
        !(me.publicKey instanceof Uint8Array) || me.publicKey.length !== 32 || typeof me.name !== "string") {
      throw new Error("the key stored in this browser is damaged: make a new one (robots must then be told it)");
    }
    return me;
  }

  /**
   * Make the user's key, named `name`. Refused when there is one: a key is never replaced
   * silently (the robots know it); `forget()` first.
   * @param {string} name
   */
  async create(name) {
    if (await this.store.get("me")) throw new Error("this browser has a key already");
    const { privateKey, publicKey } = generateKeyPair();
    contactLine(name, publicKey); // checks the name (one line if it is not one)
    const me = { name, privateKey, publicKey, created: Date.now() };
    await this.store.put("me", me);
    return me;
  }

  /** Rename the user (the key stays; robots know the user by the contact name they gave). */
  async rename(name) {
    const me = await this.me();
    if (!me) throw new Error("no key yet: make one first");
    contactLine(name, me.publicKey);
    me.name = name;
    await this.store.put("me", me);
    return me;
  }

  /** Forget the user's key (robots that trust it must be told a new one). */
  async forget() {
    await this.store.delete("me");
  }

  /**
   * The line `telebot-user keygen` prints, for a robot's admin: `telebot-x25519 KEY NAME`.
   * @returns {Promise<string>}
   */
  async contactLine() {
    const me = await this.me();
    if (!me) throw new Error("no key yet: make one first");
    return contactLine(me.name, me.publicKey);
  }

  /** @returns {Promise<Record<string, {key: string, via: string, added: number}>>} */
  async _robots() {
    return (await this.store.get("robots")) || {};
  }

  /**
   * The pinned robots, by name.
   * @returns {Promise<Array<{name: string, key: string, fingerprint: string, via: string, added: number}>>}
   */
  async robots() {
    const all = await this._robots();
    return Object.keys(all).sort().map((name) => ({
      name, ...all[name], fingerprint: fingerprint(decodeKey(all[name].key)),
    }));
  }

  /**
   * One pinned robot's key (32 bytes), or null when it is not pinned.
   * @param {string} name
   * @returns {Promise<Uint8Array | null>}
   */
  async robotKey(name) {
    const entry = (await this._robots())[name];
    return entry ? decodeKey(entry.key) : null;
  }

  /**
   * Pin robot `name` with key `keyText` (43 characters). The same key again is no change;
   * another key for a pinned name is refused with KEY MISMATCH.
   * @param {string} name @param {string} keyText @param {string} [via] "pasted", "invite", …
   * @returns {Promise<{name: string, key: string, added: boolean}>}
   */
  async pin(name, keyText, via = "pasted") {
    const parsed = checked(name, keyText);
    const key = encodeKey(parsed.publicKey);
    const all = await this._robots();
    const old = all[parsed.name];
    if (old && old.key === key) return { name: parsed.name, key, added: false };
    if (old) {
      throw new Error(`KEY MISMATCH: robot ${parsed.name} is pinned with key ${short(old.key)}, ` +
        `this one is ${short(key)}; unpin it first if its key really changed`);
    }
    if (Object.keys(all).length >= MAX_ROBOTS) throw new Error(`at most ${MAX_ROBOTS} robots may be pinned`);
    all[parsed.name] = { key, via, added: Date.now() };
    await this.store.put("robots", all);
    return { name: parsed.name, key, added: true };
  }

  /**
   * Pin a robot from its contact line (`telebot-x25519 KEY NAME`, what the robot prints).
   * @param {string} text
   */
  async pinLine(text) {
    const { name, publicKey } = parseContactLine(text);
    return this.pin(name, encodeKey(publicKey), "pasted");
  }

  /** Unpin robot `name`; false when it was not pinned. */
  async unpin(name) {
    const all = await this._robots();
    if (!(name in all)) return false;
    delete all[name];
    await this.store.put("robots", all);
    return true;
  }
}
