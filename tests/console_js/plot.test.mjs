// The plot's series: numbers and vectors over the last minute, the history put before what came
// live, points out of the window dropped, one scale for every line.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { PlotSeries, plotNumbers } from '../../gateway/console/js/plot.js';

test('a number is one element and a vector is each of its elements', () => {
  assert.deepEqual(plotNumbers('0.5'), [0.5]);
  assert.deepEqual(plotNumbers('(1 2 0 0 0 0.5)'), [1, 2, 0, 0, 0, 0.5]);
  assert.deepEqual(plotNumbers('hello'), []);
  assert.deepEqual(plotNumbers(''), []);
});

test('points older than the window go, and every line shares one scale', () => {
  const plot = new PlotSeries({ windowMs: 60000 });
  plot.add(0, [1, 10]);
  plot.add(30000, [2, 20]);
  plot.add(61000, [3, 30]);
  const { lines, lo, hi } = plot.lines(90000);
  assert.equal(lines.length, 2);
  assert.equal(lines[0].split(' ').length, 2, 'the point at 0 s fell out of the minute before 90 s');
  assert.deepEqual([lo, hi], [2, 30]);
});

test('the history goes before the live values that came first, without repeating one', () => {
  const plot = new PlotSeries();
  plot.add(5000, [7]);
  const kept = new PlotSeries();
  for (const t of [1000, 2000, 5000]) kept.add(t, [t / 1000]);
  plot.takeOlder(kept);
  assert.deepEqual(plot.series[0], [[1000, 1], [2000, 2], [5000, 7]]);
  assert.equal(plot.count, 3);
});

test('a point no newer than the last is dropped', () => {
  const plot = new PlotSeries();
  plot.add(2000, [1]);
  plot.add(1000, [2]);
  assert.equal(plot.count, 1);
});
