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

test('past the most names one layout places, the rest are hidden, the first placed', () => {
  const items = Array.from({ length: 12 }, (_, i) => name(`r${i}`, 100 + 40 * i, 100));
  const placed = placeLabels(items, 10);
  assert.equal(placed.size, 12);
  assert.ok(!placed.get('r9').hidden && placed.get('r9').width > 0);
  assert.deepEqual([placed.get('r10'), placed.get('r11')], [{ hidden: true }, { hidden: true }]);
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

// -- the map's background -------------------------------------------------------------------------

const { gridInfo, isExtent, occupancyPixels, parseNpy } = await import('../../gateway/console/js/map_background.js');
const { goalPoint, isGoalProperty } = await import('../../gateway/console/js/map.js');

/** A 2-D float32 array as numpy.save writes it (format 1.0). */
function npy(rows, cols, numbers, descr = '<f4') {
  let header = `{'descr': '${descr}', 'fortran_order': False, 'shape': (${rows}, ${cols}), }`;
  header += ' '.repeat(64 - ((10 + header.length + 1) % 64)) + '\n';
  const data = descr === '<f8' ? new Float64Array(numbers) : new Float32Array(numbers);
  const out = new Uint8Array(10 + header.length + data.byteLength);
  out.set([0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59, 1, 0], 0);
  new DataView(out.buffer).setUint16(8, header.length, true);
  out.set(new TextEncoder().encode(header), 10);
  out.set(new Uint8Array(data.buffer), 10 + header.length);
  return out.buffer;
}

test('a grid layer\'s info places it on the plane', () => {
  const info = '((kind hits) (origin (-2 -1)) (cell 0.5) (shape (10 16)) (min 0) (max 3) (filled 4) (total 7) (outside 0) (unit ()))';
  assert.deepEqual(gridInfo(info), { extent: [-2, -1, 6, 4], kind: 'hits' });
  assert.equal(gridInfo('((kind mean) (origin (0 0)) (cell 0) (shape (2 2)))'), null, 'no cell size');
  assert.equal(gridInfo('not a list'), null);
  assert.ok(isExtent([-3, -2, 7, 5.5]));
  assert.ok(!isExtent([1, 0, 0, 1]) && !isExtent([0, 0, 1]) && !isExtent(null));
});

test('a numpy array of hit counts reads back with its shape', () => {
  const grid = parseNpy(npy(2, 3, [0, 1, 2, 0, 0, 7]));
  assert.deepEqual([grid.rows, grid.cols, [...grid.values]], [2, 3, [0, 1, 2, 0, 0, 7]]);
  const wide = parseNpy(npy(1, 2, [0.5, 1.5], '<f8'));
  assert.deepEqual([...wide.values], [0.5, 1.5]);
  assert.throws(() => parseNpy(new Uint8Array([1, 2, 3]).buffer), /not a numpy array/);
  assert.throws(() => parseNpy(npy(2, 3, [1, 2, 3, 4, 5, 6]).slice(0, 140)), /shorter than its shape/);
  assert.throws(() => parseNpy(npy(2, 3, [0, 0, 0, 0, 0, 0], '>f4')), /little-endian float/);
});

test('an occupancy grid is drawn north up, clear where nothing was seen, darker where more was', () => {
  // Row 0 is the south: (row 0, col 1) one hit, (row 1, col 2) seven.
  const pixels = occupancyPixels({ rows: 2, cols: 3, values: [0, 1, 0, 0, 0, 7] });
  const alpha = (top, col) => pixels[(top * 3 + col) * 4 + 3];
  assert.equal(alpha(1, 0), 0, 'never seen: clear');
  assert.ok(alpha(1, 1) > 0, 'the south row is the bottom of the picture');
  assert.ok(alpha(0, 2) > alpha(1, 1), 'seven hits darker than one');
  assert.equal(alpha(0, 2), 255);
});

test('a goal property says where its service is sent, as a marker or x y', () => {
  assert.deepEqual(goalPoint('<marker><location>(4 4 0)</location></marker>'), [4, 4]);
  assert.deepEqual(goalPoint('(1.5 -2)'), [1.5, -2]);
  assert.equal(goalPoint('<marker></marker>'), null, 'an empty marker: sent nowhere');
  assert.equal(goalPoint(''), null);
  assert.ok(isGoalProperty({ name: 'goal', type: 'marker', access: 'read-write' }));
  assert.ok(isGoalProperty({ name: 'behaviors.target', type: 'vector', access: 'read' }));
  assert.ok(isGoalProperty({ name: 'destination', type: 'marker', gui: 'goal', access: 'read' }));
  assert.ok(!isGoalProperty({ name: 'goal', type: 'marker', access: 'write' }), 'not readable');
  assert.ok(!isGoalProperty({ name: 'goal', type: 'string', access: 'read' }), 'not a place');
  assert.ok(!isGoalProperty({ name: 'location', type: 'vector', access: 'read' }));
});
