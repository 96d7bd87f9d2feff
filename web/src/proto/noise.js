/**
 * The Noise IK initiator (docs/protocol.md §5): Noise_IK_25519_{ChaChaPoly,AESGCM}_BLAKE2s,
 * Noise Protocol Framework revision 34, no PSK. Sans-IO, built only from the primitives
 * of @noble (X25519, BLAKE2s, HMAC, ChaCha20-Poly1305, AES-256-GCM).
 *
 *     <- s
 *     ...
 *     -> e, es, s, ss      (HELLO)
 *     <- e, ee, se         (WELCOME)
 * @module proto/noise
 */
import { x25519 } from "@noble/curves/ed25519";
import { blake2s } from "@noble/hashes/blake2";
import { hmac } from "@noble/hashes/hmac";
import { chacha20poly1305 } from "@noble/ciphers/chacha";
import { gcm } from "@noble/ciphers/aes";
import { ProtocolError } from "../errors.js";
import { concat, randomBytes, utf8 } from "../bytes.js";

const HASH_LEN = 32;
export const DH_LEN = 32;
export const TAG_LEN = 16;

/** Cipher suites by wire number (§5.2). */
export const CHACHAPOLY = 1;
export const AESGCM = 2;
/** @type {Record<string, number>} */
export const SUITE_NUMBERS = { chachapoly: CHACHAPOLY, aesgcm: AESGCM };
/** @type {Record<number, string>} */
export const SUITE_LABELS = { [CHACHAPOLY]: "chachapoly", [AESGCM]: "aesgcm" };
/** @type {Record<number, string>} */
const PROTOCOL_NAMES = {
  [CHACHAPOLY]: "Noise_IK_25519_ChaChaPoly_BLAKE2s",
  [AESGCM]: "Noise_IK_25519_AESGCM_BLAKE2s",
};

/** Authentication of a handshake message failed (a forgery, or not the robot). */
export class AuthenticationError extends ProtocolError {
  /** @param {string} message */
  constructor(message) {
    super(message);
    this.name = "AuthenticationError";
  }
}

/**
 * The suite's 12-byte nonce for a 64-bit counter: 4 zero bytes, then the counter
 * little-endian (ChaChaPoly) or big-endian (AESGCM).
 * @param {number} suite @param {bigint} counter @returns {Uint8Array}
 */
export function nonce(suite, counter) {
  const out = new Uint8Array(12);
  new DataView(out.buffer).setBigUint64(4, counter, suite === CHACHAPOLY);
  return out;
}

/**
 * The AEAD of a suite under a 32-byte key: {seal(counter, plaintext, ad), open(counter,
 * ciphertext, ad)}; open throws AuthenticationError when the tag does not verify.
 * @param {number} suite @param {Uint8Array} key
 */
export function aead(suite, key) {
  if (!(suite in PROTOCOL_NAMES)) throw new ProtocolError(`unknown cipher suite ${suite}`);
  const make = suite === CHACHAPOLY ? chacha20poly1305 : gcm;
  return {
    /** @param {bigint} counter @param {Uint8Array} plaintext @param {Uint8Array} ad */
    seal(counter, plaintext, ad) {
      return make(key, nonce(suite, counter), ad).encrypt(plaintext);
    },
    /** @param {bigint} counter @param {Uint8Array} ciphertext @param {Uint8Array} ad */
    open(counter, ciphertext, ad) {
      if (ciphertext.length < TAG_LEN) throw new AuthenticationError("ciphertext shorter than its tag");
      try {
        return make(key, nonce(suite, counter), ad).decrypt(ciphertext);
      } catch {
        throw new AuthenticationError("message failed authentication");
      }
    },
  };
}

/** @param {Uint8Array} data */
const hash = (data) => blake2s(data);
/** @param {Uint8Array} key @param {Uint8Array} data */
const hmacB2s = (key, data) => hmac(blake2s, key, data);

/** @param {Uint8Array} ck @param {Uint8Array} ikm @returns {[Uint8Array, Uint8Array]} */
function hkdf2(ck, ikm) {
  const temp = hmacB2s(ck, ikm);
  const out1 = hmacB2s(temp, Uint8Array.of(1));
  const out2 = hmacB2s(temp, concat(out1, Uint8Array.of(2)));
  return [out1, out2];
}

/** X25519; a low-order point (all-zero result) is an authentication failure. */
function dh(/** @type {Uint8Array} */ priv, /** @type {Uint8Array} */ pub) {
  let shared;
  try {
    shared = x25519.getSharedSecret(priv, pub);
  } catch {
    throw new AuthenticationError("invalid X25519 public key in handshake");
  }
  if (shared.every((b) => b === 0)) throw new AuthenticationError("invalid X25519 public key in handshake");
  return shared;
}

/** Noise's SymmetricState with its CipherState (spec §5.2). */
class SymmetricState {
  /** @param {Uint8Array} prologue @param {number} suite */
  constructor(prologue, suite) {
    const name = utf8(PROTOCOL_NAMES[suite]);
    // Names longer than HASHLEN are hashed (ChaChaPoly's, 33 bytes), others zero-padded.
    if (name.length <= HASH_LEN) {
      this.h = new Uint8Array(HASH_LEN);
      this.h.set(name);
    } else {
      this.h = hash(name);
    }
    this.ck = this.h;
    this.suite = suite;
    /** @type {Uint8Array|null} */
    this.key = null;
    this.n = 0n;
    this.mixHash(prologue);
  }

  /** @param {Uint8Array} data */
  mixHash(data) {
    this.h = hash(concat(this.h, data));
  }

  /** @param {Uint8Array} ikm */
  mixKey(ikm) {
    [this.ck, this.key] = hkdf2(this.ck, ikm);
    this.n = 0n;
  }

  /** @param {Uint8Array} plaintext */
  encryptAndHash(plaintext) {
    if (!this.key) throw new Error("IK always has a key before the first encryption");
    const ciphertext = aead(this.suite, this.key).seal(this.n, plaintext, this.h);
    this.n += 1n;
    this.mixHash(ciphertext);
    return ciphertext;
  }

  /** @param {Uint8Array} ciphertext */
  decryptAndHash(ciphertext) {
    if (!this.key) throw new Error("IK always has a key before the first decryption");
    let plaintext;
    try {
      plaintext = aead(this.suite, this.key).open(this.n, ciphertext, this.h);
    } catch {
      throw new AuthenticationError("handshake message failed authentication");
    }
    this.n += 1n;
    this.mixHash(ciphertext);
    return plaintext;
  }

  split() {
    return hkdf2(this.ck, new Uint8Array(0));
  }

  copy() {
    const clone = Object.create(SymmetricState.prototype);
    Object.assign(clone, this);
    return clone;
  }
}

/**
 * @typedef {{suite: number, sendKey: Uint8Array, receiveKey: Uint8Array,
 *   handshakeHash: Uint8Array}} TransportKeys
 */

/** The caller's side of the handshake: writes HELLO's Noise message, reads WELCOME's. */
export class InitiatorHandshake {
  /**
   * @param {{staticPrivate: Uint8Array, responderStatic: Uint8Array, prologue: Uint8Array,
   *   suite: number, ephemeralPrivate?: Uint8Array}} options
   *   `ephemeralPrivate` is for test vectors only; by default a fresh random key.
   */
  constructor({ staticPrivate, responderStatic, prologue, suite, ephemeralPrivate }) {
    if (!(suite in PROTOCOL_NAMES)) throw new ProtocolError(`unknown cipher suite ${suite}`);
    if (responderStatic.length !== DH_LEN || staticPrivate.length !== DH_LEN) {
      throw new ProtocolError("X25519 keys are 32 bytes");
    }
    this.suite = suite;
    this.s = staticPrivate;
    this.rs = responderStatic;
    this.e = ephemeralPrivate ?? randomBytes(32);
    this.state = new SymmetricState(prologue, suite);
    this.state.mixHash(responderStatic); // pre-message "<- s"
    this.written = false;
  }

  /**
   * `-> e, es, s, ss` with `payload` encrypted; once.
   * @param {Uint8Array} payload @returns {Uint8Array}
   */
  writeMessage(payload) {
    if (this.written) throw new Error("the first handshake message is written once");
    this.written = true;
    const st = this.state;
    const ePub = x25519.getPublicKey(this.e);
    st.mixHash(ePub);
    st.mixKey(dh(this.e, this.rs));
    const encStatic = st.encryptAndHash(x25519.getPublicKey(this.s));
    st.mixKey(dh(this.s, this.rs));
    return concat(ePub, encStatic, st.encryptAndHash(payload));
  }

  /**
   * `<- e, ee, se`: the responder's payload and this side's transport keys. Works on a
   * copy of the state, so a forged answer leaves it intact for the genuine one.
   * Throws AuthenticationError or ProtocolError.
   * @param {Uint8Array} message @returns {{payload: Uint8Array, keys: TransportKeys}}
   */
  readMessage(message) {
    if (!this.written) throw new Error("write the first message before reading the answer");
    if (message.length < DH_LEN + TAG_LEN) throw new ProtocolError("handshake answer too short");
    const st = this.state.copy();
    const re = message.slice(0, DH_LEN);
    st.mixHash(re);
    st.mixKey(dh(this.e, re));
    st.mixKey(dh(this.s, re));
    const payload = st.decryptAndHash(message.slice(DH_LEN));
    const [k1, k2] = st.split();
    return { payload, keys: { suite: this.suite, sendKey: k1, receiveKey: k2, handshakeHash: st.h } };
  }
}

/**
 * The robot's side, for tests only (the browser never answers calls): reads a HELLO's
 * Noise message and writes the WELCOME's, as §5.3–5.4 mirror it.
 */
export class ResponderHandshake {
  /**
   * @param {{staticPrivate: Uint8Array, prologue: Uint8Array, suite: number,
   *   ephemeralPrivate?: Uint8Array}} options
   */
  constructor({ staticPrivate, prologue, suite, ephemeralPrivate }) {
    this.suite = suite;
    this.s = staticPrivate;
    this.e = ephemeralPrivate ?? randomBytes(32);
    this.state = new SymmetricState(prologue, suite);
    this.state.mixHash(x25519.getPublicKey(staticPrivate));
    /** @type {Uint8Array|null} */
    this.re = null;
    /** @type {Uint8Array|null} */
    this.remoteStatic = null;
  }

  /** @param {Uint8Array} message @returns {Uint8Array} the caller's payload */
  readMessage(message) {
    if (message.length < 2 * DH_LEN + 2 * TAG_LEN) throw new ProtocolError("handshake message too short");
    const st = this.state;
    const re = message.slice(0, DH_LEN);
    st.mixHash(re);
    st.mixKey(dh(this.s, re));
    const rs = st.decryptAndHash(message.slice(DH_LEN, 2 * DH_LEN + TAG_LEN));
    st.mixKey(dh(this.s, rs));
    const payload = st.decryptAndHash(message.slice(2 * DH_LEN + TAG_LEN));
    this.re = re;
    this.remoteStatic = rs;
    return payload;
  }

  /** @param {Uint8Array} payload @returns {{message: Uint8Array, keys: TransportKeys}} */
  writeMessage(payload) {
    if (!this.re || !this.remoteStatic) throw new Error("read the first message before answering");
    const st = this.state;
    const ePub = x25519.getPublicKey(this.e);
    st.mixHash(ePub);
    st.mixKey(dh(this.e, this.re));
    st.mixKey(dh(this.e, this.remoteStatic));
    const message = concat(ePub, st.encryptAndHash(payload));
    const [k1, k2] = st.split();
    return { message, keys: { suite: this.suite, sendKey: k2, receiveKey: k1, handshakeHash: st.h } };
  }
}
