/**
 * The sliding replay window over 64-bit DATA counters (docs/protocol.md §7): each
 * counter is accepted once, within the last 2048 below and including the highest.
 * Check before decryption, accept only after the AEAD tag verified.
 * @module proto/replay
 */

export const WINDOW = 2048;
const WORDS = WINDOW / 32;

export class ReplayWindow {
  constructor() {
    /** Highest counter accepted so far; -1n when none. */
    this.highest = -1n;
    // Bit i of the window (word i>>5, bit i&31) set = counter (highest - i) was accepted.
    this.bits = new Uint32Array(WORDS);
  }

  /**
   * Whether `counter` would be accepted (fresh and inside the window); changes nothing.
   * @param {bigint} counter @returns {boolean}
   */
  check(counter) {
    if (counter > this.highest) return true;
    const offset = this.highest - counter;
    if (offset >= BigInt(WINDOW)) return false;
    const i = Number(offset);
    return !((this.bits[i >> 5] >>> (i & 31)) & 1);
  }

  /**
   * Mark `counter` as accepted; only after check() and authentication passed.
   * @param {bigint} counter
   */
  accept(counter) {
    if (counter > this.highest) {
      const shift = counter - this.highest;
      if (shift >= BigInt(WINDOW)) {
        this.bits.fill(0);
      } else {
        this.shift(Number(shift));
      }
      this.highest = counter;
      this.bits[0] |= 1;
    } else {
      const i = Number(this.highest - counter);
      this.bits[i >> 5] |= 1 << (i & 31);
    }
  }

  /** Move every bit up by `n` (0 < n < WINDOW): the older counters' offsets grow. */
  shift(/** @type {number} */ n) {
    const words = n >> 5;
    const bits = n & 31;
    const b = this.bits;
    for (let w = WORDS - 1; w >= 0; w--) {
      const from = w - words;
      let value = 0;
      if (from >= 0) {
        value = bits ? (b[from] << bits) : b[from];
        if (bits && from - 1 >= 0) value |= b[from - 1] >>> (32 - bits);
      }
      b[w] = value >>> 0;
    }
  }
}
