// Exponential backoff with jitter, for the event stream's reconnects (no DOM: tested under node).

/**
 * Delays that double from `initial` up to `max` milliseconds, each spread by +-`jitter` (a
 * fraction) so that many pages that lost the same gateway do not all come back in the same
 * instant. `reset()` after a success starts again from `initial`.
 */
export class Backoff {
  constructor({ initial = 500, max = 30000, factor = 2, jitter = 0.2, random = Math.random } = {}) {
    if (!(initial > 0) || !(max >= initial) || !(factor >= 1) || !(jitter >= 0 && jitter < 1)) {
      throw new RangeError('Backoff needs 0 < initial <= max, factor >= 1 and 0 <= jitter < 1');
    }
    Object.assign(this, { initial, max, factor, jitter, random });
    this.attempts = 0;
  }

  /** The delay before the next attempt, in milliseconds; each call counts one attempt. */
  next() {
    // The exponent is capped: factor ** attempts stays finite however long the gateway is gone.
    const base = Math.min(this.max, this.initial * this.factor ** Math.min(this.attempts, 64));
    this.attempts += 1;
    const spread = 1 - this.jitter + 2 * this.jitter * this.random();
    return Math.round(Math.min(this.max, base * spread));
  }

  reset() {
    this.attempts = 0;
  }
}
