/**
 * Identities (docs/protocol.md §3): X25519 key pairs, their 43-character text form,
 * the public line `telebot-user keygen` prints, and fingerprints.
 * @module identity
 */
import { x25519 } from "@noble/curves/ed25519";
import { sha256 } from "@noble/hashes/sha2";
import { ProtocolError } from "./errors.js";
import { randomBytes } from "./bytes.js";
import { validateName } from "./proto/frames.js";

/** First word of a public line (`id_telebot.pub`). */
export const PUBLIC_KEY_PREFIX = "telebot-x25519";

/** @param {Uint8Array} bytes @returns {string} standard base64 with padding */
function base64(bytes) {
  let binary = "";
  for (const b of bytes) binary += String.fromCharCode(b);
  return btoa(binary);
}

/**
 * A 32-byte key as 43 URL-safe base64 characters without padding (§3.1).
 * @param {Uint8Array} bytes32
 * @returns {string}
 */
export function encodeKey(bytes32) {
  if (!(bytes32 instanceof Uint8Array) || bytes32.length !== 32) {
    throw new ProtocolError("a key is 32 bytes");
  }
  return base64(bytes32).replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "");
}

/**
 * The 32 bytes of a key in its text form; ProtocolError (one line) if it is not one.
 * Surrounding whitespace is stripped; only the canonical encoding is accepted.
 * @param {string} text
 * @returns {Uint8Array}
 */
export function decodeKey(text) {
  if (typeof text !== "string") throw new ProtocolError("a key is a text of 43 characters");
  const trimmed = text.trim();
  if (trimmed.length !== 43) {
    throw new ProtocolError(`a public key is 43 base64 characters, got ${trimmed.length}`);
  }
  if (!/^[A-Za-z0-9_-]{43}$/.test(trimmed)) {
    throw new ProtocolError("a public key is URL-safe base64 (A-Z a-z 0-9 - _)");
  }
  const binary = atob(trimmed.replace(/-/g, "+").replace(/_/g, "/") + "=");
  const raw = Uint8Array.from(binary, (c) => c.charCodeAt(0));
  if (raw.length !== 32 || encodeKey(raw) !== trimmed) {
    throw new ProtocolError("not a 32-byte key in canonical base64");
  }
  return raw;
}

/**
 * The X25519 public key (32 bytes) of a 32-byte private key.
 * @param {Uint8Array} privateKey
 * @returns {Uint8Array}
 */
export function publicKeyOf(privateKey) {
  if (!(privateKey instanceof Uint8Array) || privateKey.length !== 32) {
    throw new ProtocolError("a private key is 32 bytes");
  }
  return x25519.getPublicKey(privateKey);
}

/**
 * A new random key pair (from the platform's CSPRNG).
 * @returns {{privateKey: Uint8Array, publicKey: Uint8Array}}
 */
export function generateKeyPair() {
  const privateKey = randomBytes(32);
  return { privateKey, publicKey: publicKeyOf(privateKey) };
}

/**
 * The line `telebot-user keygen` prints and `id_telebot.pub` holds:
 * `telebot-x25519 <43-char key> <name>`.
 * @param {string} name
 * @param {Uint8Array} publicKey
 * @returns {string}
 */
export function contactLine(name, publicKey) {
  validateName(name, "name");
  return `${PUBLIC_KEY_PREFIX} ${encodeKey(publicKey)} ${name}`;
}

/**
 * Parse a public line (`telebot-x25519 KEY NAME`); ProtocolError if it is not one.
 * @param {string} text
 * @returns {{name: string, publicKey: Uint8Array}}
 */
export function parseContactLine(text) {
  if (typeof text !== "string") throw new ProtocolError("a contact line is text");
  const parts = text.trim().split(/\s+/);
  if (parts.length !== 3 || parts[0] !== PUBLIC_KEY_PREFIX) {
    throw new ProtocolError(`a contact line reads '${PUBLIC_KEY_PREFIX} KEY NAME'`);
  }
  const publicKey = decodeKey(parts[1]);
  return { name: validateName(parts[2], "name"), publicKey };
}

/**
 * `SHA256:` + standard base64 (no padding) of SHA-256 of the public key (§3.1).
 * @param {Uint8Array} publicKey
 * @returns {string}
 */
export function fingerprint(publicKey) {
  return "SHA256:" + base64(sha256(publicKey)).replace(/=+$/, "");
}
