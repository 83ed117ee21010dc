// Reconnect delays: doubling, capped, spread by jitter, and back to the start after a success.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { Backoff } from '../../gateway/console/js/backoff.js';

test('delays double up to the cap and reset starts again', () => {
  const backoff = new Backoff({ initial: 500, max: 8000, jitter: 0.2, random: () => 0.5 });
  assert.deepEqual(Array.from({ length: 7 }, () => backoff.next()), [500, 1000, 2000, 4000, 8000, 8000, 8000]);
  assert.equal(backoff.attempts, 7);
  backoff.reset();
  assert.equal(backoff.next(), 500);
});

test('jitter spreads a delay within its bounds and never past the cap', () => {
  const low = new Backoff({ initial: 1000, max: 4000, jitter: 0.2, random: () => 0 });
  const high = new Backoff({ initial: 1000, max: 4000, jitter: 0.2, random: () => 0.999999 });
  assert.equal(low.next(), 800);
  assert.equal(high.next(), 1200);
  for (let i = 0; i < 5; i += 1) high.next();
  assert.equal(high.next(), 4000);
});

test('a gateway gone for a very long time still gets finite delays', () => {
  const backoff = new Backoff({ initial: 500, max: 30000, random: () => 0.5 });
  for (let i = 0; i < 5000; i += 1) backoff.next();
  assert.equal(backoff.next(), 30000);
});

test('nonsense settings are refused', () => {
  assert.throws(() => new Backoff({ initial: 0 }), RangeError);
  assert.throws(() => new Backoff({ initial: 100, max: 10 }), RangeError);
  assert.throws(() => new Backoff({ jitter: 1 }), RangeError);
});
