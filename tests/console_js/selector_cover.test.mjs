// Covering the page's subscriptions with few enough selectors for one Listen (js/selector_cover.js).
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { coverSelectors, covers } from '../../gateway/console/js/selector_cover.js';

const ROBOT = [
  'location', 'speed', 'max_speed', 'max_turn_rate', 'velocity_timeout', 'velocity',
  'actuators', 'actuators.led', 'actuators.wheels',
  'sensors', 'sensors.battery', 'sensors.bumper', 'sensors.temperature', 'behaviors',
];

/** What a view of a group of `n` robots subscribes to, beside the map and the service list. */
function swarmView(n) {
  const selectors = ['registry/revision', '*/location', 'swarm/properties', 'swarm/location', 'swarm/robots'];
  for (let i = 1; i <= n; i += 1) {
    selectors.push(`swarm/robots.scout${i}`);
    for (const path of ROBOT) selectors.push(`swarm/robots.scout${i}.${path}`);
  }
  return selectors;
}

/** Whether every given selector is matched by one of the cover's, and the members say which. */
function assertCovered(given, { cover, members, left }) {
  for (const selector of given) {
    if (left.includes(selector)) continue;
    const by = cover.filter((wide) => covers(wide, selector));
    assert.ok(by.length, `${selector} is covered by none of ${cover}`);
    assert.ok(by.some((wide) => members.get(wide).includes(selector)), `${selector} is a member of its cover`);
  }
}

test('selectors within the limit are named as they are', () => {
  const given = ['registry/revision', 'scout1/location', 'scout1/speed', 'scout2/location'];
  const { cover, left } = coverSelectors(given, 64);
  assert.deepEqual(cover, [...given].sort());
  assert.deepEqual(left, []);
});

test('a selector another one already matches rides along with it', () => {
  const { cover, members } = coverSelectors(['*/location', 'scout1/location', 'scout1/speed'], 64);
  assert.deepEqual(cover, ['*/location', 'scout1/speed']);
  assert.deepEqual(members.get('*/location').sort(), ['*/location', 'scout1/location']);
});

test('a view of fifty robots is covered by one wildcard per property name', () => {
  const given = swarmView(50);
  const result = coverSelectors(given, 58);
  assert.ok(given.length > 700);
  assert.ok(result.cover.length <= 58, `${result.cover.length} selectors`);
  assert.ok(result.cover.includes('swarm/robots.*.location'));
  assert.ok(result.cover.includes('swarm/robots.*.sensors.battery'));
  assert.ok(!result.cover.some((s) => s.startsWith('*/') && s !== '*/location'), 'no service made a wildcard');
  assert.deepEqual(result.left, []);
  assertCovered(given, result);
});

test('the cover widens only as far as the limit asks', () => {
  const given = ['a/x', 'a/y', 'b/x', 'b/y', 'c/z'];
  assert.equal(coverSelectors(given, 5).cover.length, 5);
  const four = coverSelectors(given, 4);
  assert.equal(four.cover.length, 4, `one step: ${four.cover}`);
  assertCovered(given, four);
  const two = coverSelectors(given, 2);
  assert.ok(two.cover.length <= 2, `${two.cover}`);
  assertCovered(given, two);
});

test('a path name is widened within its service before the service is', () => {
  const { cover } = coverSelectors(['a/x', 'a/y', 'b/x'], 2);
  assert.deepEqual(cover, ['a/*', 'b/x']);
});

test('the service becomes a wildcard only for a path without one', () => {
  const given = ['a/p.x', 'b/p.x', 'c/p.x', 'd/q'];
  assert.deepEqual(coverSelectors(given, 2).cover, ['*/p.x', 'd/q']);
  // Two services' every property (`*/*`) is never asked for: what cannot be made one is left out.
  const { cover, left } = coverSelectors(['a/x', 'b/y'], 1);
  assert.equal(cover.length, 1);
  assert.equal(left.length, 1);
});

test('an avoided property is never matched by a wildcard', () => {
  const given = ['camera1/data', 'camera1/rate_hz', 'camera1/location'];
  const { cover, left } = coverSelectors(given, 1, { avoid: ['camera1/frame'] });
  assert.ok(!cover.some((s) => covers(s, 'camera1/frame')), `${cover}`);
  assert.equal(cover.length + left.length, 3);
  assert.deepEqual(coverSelectors(given, 1).cover, ['camera1/*'], 'without it, one wildcard');
});

test('selectors of different depths are never made one', () => {
  const { cover } = coverSelectors(['a/x', 'a/x.y', 'a/x.y.z'], 3);
  assert.equal(cover.length, 3);
});
