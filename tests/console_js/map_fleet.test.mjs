// The map's pure parts for a fleet: names placed clear of each other however close their things
// stand, and trails that stay bounded, fade with age and are not joined across a gap.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { BODY_PX, RINGS, overlaps, placeLabels } from '../../gateway/console/js/labels.js';
import { TRAIL_MS, Trail } from '../../gateway/console/js/trails.js';

const name = (id, x, y, kind = 'mobile_robot', width = 7 * id.length) => ({ id, x, y, width, height: 14, kind });

function assertClear(items, placed) {
  const ids = [...placed.keys()];
  for (let i = 0; i < ids.length; i += 1) {
    for (const other of ids.slice(i + 1)) {
      assert.ok(!overlaps(placed.get(ids[i]), placed.get(other)), `${ids[i]} and ${other} overlap`);
    }
    for (const thing of items) {
      if (thing.id === ids[i]) continue;
      const body = { left: thing.x - BODY_PX, top: thing.y - BODY_PX, width: 2 * BODY_PX, height: 2 * BODY_PX };
      assert.ok(!overlaps(placed.get(ids[i]), body), `the name ${ids[i]} covers ${thing.id}`);
    }
  }
}

test('a lone name goes to its kind\'s favourite place beside its thing', () => {
  const placed = placeLabels([name('scout1', 100, 100)]);
  const box = placed.get('scout1');
  assert.ok(box.left > 100 && box.top + box.height < 100, `above right: ${JSON.stringify(box)}`);
  assert.equal(box.leader, false);
  const group = placeLabels([name('swarm', 100, 100, 'group')]).get('swarm');
  assert.ok(group.left + group.width < 100 && group.top > 100, `below left: ${JSON.stringify(group)}`);
});

test('names of things at one place are not drawn over each other', () => {
  const items = [
    name('scout1', 300, 300),
    name('thermo1', 300, 300, 'sensor'),
    name('swarm', 302, 301, 'group'),
    name('scout2', 304, 300),
  ];
  const placed = placeLabels(items);
  const ids = [...placed.keys()];
  for (let i = 0; i < ids.length; i += 1) {
    for (const other of ids.slice(i + 1)) assert.ok(!overlaps(placed.get(ids[i]), placed.get(other)), `${ids[i]} / ${other}`);
  }
});

test('a row of robots a few pixels apart keeps every name clear of the others and of the robots', () => {
  const items = Array.from({ length: 8 }, (_, i) => name(`robot${i}`, 200 + 18 * i, 200));
  const placed = placeLabels(items);
  assertClear(items, placed);
  assert.ok([...placed.values()].some((p) => p.leader), 'some names set off with a leader line');
});

test('a crowd beyond every free place still gets a place for each name, the least covered', () => {
  const items = Array.from({ length: 60 }, (_, i) => name(`r${i}`, 500, 500));
  const placed = placeLabels(items);
  assert.equal(placed.size, 60);
  for (const p of placed.values()) assert.ok(Math.abs(p.left - 500) < 200 && Math.abs(p.top - 500) < 200 + RINGS * 20);
});

test('a trail keeps points a step apart, at most its bound, and drops the old', () => {
  const trail = new Trail({ points: 50, ageMs: 10000, stepM: 0.05 });
  assert.ok(trail.add(0, 0, 0));
  assert.ok(!trail.add(0.01, 0, 10), 'a centimetre is no new point');
  for (let i = 1; i <= 200; i += 1) trail.add(i * 0.1, 0, i * 100);
  assert.equal(trail.length, 50, 'bounded');
  assert.ok(Math.abs(trail.points[0].x - 15.1) < 1e-9, 'the oldest went first');
  trail.prune(20000 + 15000);
  assert.ok(trail.length < 50 && trail.points.every((p) => 35000 - p.t <= 10000));
  trail.prune(10 ** 9);
  assert.equal(trail.length, 0);
});

test('a trail fades with age and is not joined across a gap', () => {
  const trail = new Trail();
  const now = TRAIL_MS;
  for (let i = 0; i < 10; i += 1) trail.add(i, 0, now - TRAIL_MS + (i * TRAIL_MS) / 10);
  const lines = trail.polylines(now);
  assert.ok(lines.length >= 3, JSON.stringify(lines));
  for (let i = 1; i < lines.length; i += 1) {
    assert.ok(lines[i].opacity > lines[i - 1].opacity, 'newer is stronger');
    assert.deepEqual(lines[i].points[0], lines[i - 1].points.at(-1), 'the bands meet');
  }
  trail.add(50, 50, now, true);
  trail.add(51, 50, now);
  const after = trail.polylines(now);
  const last = after.at(-1);
  assert.deepEqual(last.points, [[50, 50], [51, 50]], 'the part after the gap stands alone');
});
