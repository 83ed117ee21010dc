// Widgets that fit the data: numbers read to the precision the model implies, sliders that span
// what the value needs, type names for people, doc strings rendered safely, the heat map's axes
// and legend, and several signals in one plot.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { poseText } from '../../gateway/console/js/builtin_widgets.js';
import { MAX_DOC_LENGTH, parseDoc, plainDoc, renderDoc } from '../../gateway/console/js/doc_text.js';
import {
  HEAT_RAMP,
  axisTicks,
  heatMapBase,
  heatMapInfo,
  rampGradient,
  scaleLength,
} from '../../gateway/console/js/image_widget.js';
import { MAX_SIGNALS, PlotSeries, addableSignal, sharedRanges } from '../../gateway/console/js/plot.js';
import { pluralOf, typeTitle } from '../../gateway/console/js/service_list.js';
import {
  decimalsFor,
  decimalsOf,
  formatMeasure,
  niceCeil,
  roundedValue,
  sliderSpan,
} from '../../gateway/console/js/values.js';
import { displayValue } from '../../gateway/console/js/widgets.js';

const SPEED = { name: 'speed', type: 'number', access: 'read-write', unit: 'm/s', minimum: 0, maximum: 1000, gui: 'slider' };
const LOCATION = { name: 'location', type: 'vector', access: 'read', unit: 'm, rad', length: 6, gui: 'pose' };

test('a resolution says how many decimals a number shows', () => {
  assert.equal(decimalsOf(0.01), 2);
  assert.equal(decimalsOf(0.5), 1);
  assert.equal(decimalsOf(0.25), 2);
  assert.equal(decimalsOf(5), 0);
  assert.equal(decimalsOf(0), null);
  assert.equal(decimalsOf(undefined), null);
  const temperature = { type: 'number', unit: 'degC', resolution: 0.01 };
  assert.equal(decimalsFor(temperature), 2, 'the declared resolution wins over the unit');
  assert.equal(formatMeasure(20.76571, decimalsFor(temperature), 'degC'), '20.77 degC');
  assert.equal(formatMeasure(-0.001, 2, 'm'), '0.00 m', 'never "-0.00"');
  assert.equal(decimalsFor({ type: 'integer', unit: 'm' }), 0);
  assert.equal(decimalsFor({ type: 'number', unit: 'degC' }), 1, 'no resolution: the unit tells');
  assert.equal(decimalsFor({ type: 'number' }), 3, 'nothing known: three decimals');
});

test('a location reads x, y and heading rounded, without sixteen digits', () => {
  const sent = '(1.2345678901234567 -0.50000000000001 0 0 0 0.7853981633974483)';
  assert.equal(roundedValue(LOCATION, sent), '(1.23 -0.5 0 0 0 0.79)');
  const shown = displayValue(LOCATION, sent);
  assert.equal(shown.text, '(1.23 -0.5 0 0 0 0.79)');
  assert.ok(shown.title.startsWith(sent), 'the tooltip keeps every digit the service sent');
  assert.equal(poseText(LOCATION, [1.2345678901234567, -0.5, 0, 0, 0, Math.PI / 4]), 'x 1.23 m  y -0.50 m  heading 45.0°');
  assert.equal(poseText({ name: 'centroid', type: 'vector', gui: 'pose' }, [3, 1.5]), 'x 3.00 m  y 1.50 m');
  // A short value stays as it was sent, and text that is not a number is left alone.
  assert.equal(displayValue(SPEED, '0.75').text, '0.75');
  assert.equal(displayValue(SPEED, 'fast').text, 'fast');
  assert.equal(displayValue({ type: 'number', resolution: 0.01 }, '20.76571').text, '20.77');
});

test('a speed allowed up to 1000 m/s is slid over what its value needs', () => {
  assert.deepEqual(sliderSpan(SPEED, 0.5), { lo: 0, hi: 1, step: 0.01, zoomed: true });
  assert.deepEqual(sliderSpan(SPEED, 3), { lo: 0, hi: 10, step: 0.1, zoomed: true });
  // A range that fits the value is taken as the model gives it.
  const battery = { type: 'number', minimum: 0, maximum: 1 };
  assert.deepEqual(sliderSpan(battery, 0.8), { lo: 0, hi: 1, step: 0.01, zoomed: false });
  // No range at all: a round span around the value, never 0 … 1000.
  assert.deepEqual(sliderSpan({ type: 'number', unit: 'm/s' }, 0.3), { lo: 0, hi: 1, step: 0.01, zoomed: true });
  assert.deepEqual(sliderSpan({ type: 'number' }, undefined), { lo: 0, hi: 1, step: 0.01, zoomed: true });
  const both = sliderSpan({ type: 'number', minimum: -1000, maximum: 1000 }, -3);
  assert.ok(both.lo <= -3 && both.hi >= 3 && both.hi - both.lo <= 20, JSON.stringify(both));
  // The declared resolution is the step; an integer steps by one; the span stays in the range.
  assert.equal(sliderSpan({ ...SPEED, resolution: 0.05 }, 0.5).step, 0.05);
  assert.equal(sliderSpan({ type: 'integer', minimum: 0, maximum: 100000 }, 12).step, 1);
  const narrow = sliderSpan({ type: 'number', minimum: 0.05, maximum: 60 }, 0.5);
  assert.ok(narrow.lo >= 0.05 && narrow.hi <= 60 && narrow.hi >= 0.5, JSON.stringify(narrow));
  assert.deepEqual([niceCeil(0.7), niceCeil(3), niceCeil(20), niceCeil(0)], [1, 5, 20, 1]);
});

test('group headings name the types for people, with a count', () => {
  assert.equal(typeTitle('environment_model', 1), 'Environment model (1)');
  assert.equal(typeTitle('mobile_robot', 4), 'Robots (4)');
  assert.equal(typeTitle('statemachine', 2), 'State machines (2)');
  assert.equal(typeTitle('registry', 1), 'Registry (1)');
  assert.equal(typeTitle('registry', 2), 'Registries (2)');
  assert.equal(typeTitle('camera', 2), 'Cameras (2)');
  assert.equal(typeTitle('state-machine', 3), 'State machines (3)');
  assert.equal(typeTitle('', 2), 'Others (2)');
  assert.deepEqual(['box', 'switch', 'person', 'key'].map(pluralOf), ['boxes', 'switches', 'people', 'keys']);
});

test('a doc string is read as its small reST subset', () => {
  const [first, second] = parseDoc(
    'A camera (see ``docs/vision.md``) that\nuses *numpy*, **fast**; :class:`Foo` and `x`.\n\n' +
      'Not markup: 2*3*4, snake_case_names.',
  );
  assert.deepEqual(first, [
    { kind: 'text', text: 'A camera (see ' },
    { kind: 'path', text: 'docs/vision.md' },
    { kind: 'text', text: ') that uses ' },
    { kind: 'emphasis', text: 'numpy' },
    { kind: 'text', text: ', ' },
    { kind: 'strong', text: 'fast' },
    { kind: 'text', text: '; ' },
    { kind: 'code', text: 'Foo' },
    { kind: 'text', text: ' and ' },
    { kind: 'code', text: 'x' },
    { kind: 'text', text: '.' },
  ]);
  assert.deepEqual(second, [{ kind: 'text', text: 'Not markup: 2*3*4, snake_case_names.' }]);
  assert.deepEqual(parseDoc('see docs/recording.md#history.')[0][1], { kind: 'path', text: 'docs/recording.md#history' });
  assert.equal(plainDoc('see ``docs/vision.md``'), 'see docs/vision.md');
  assert.equal(parseDoc('x'.repeat(MAX_DOC_LENGTH * 2))[0][0].text.length, MAX_DOC_LENGTH);
});

/** A stand-in for dom.js's h(): elements as plain objects, text kept as text. */
function fakeH(tag, attrs = {}, ...children) {
  return { tag, attrs, children: children.flat().filter((c) => c !== null && c !== undefined) };
}

function tagsOf(node, found = new Set()) {
  if (typeof node === 'string') return found;
  found.add(node.tag);
  for (const child of node.children) tagsOf(child, found);
  return found;
}

test('a doc is built as elements, and markup in it stays text', () => {
  const hostile = 'Look ``<img src=x onerror=alert(1)>`` and <script>alert(2)</script> in docs/vision.md';
  const tree = renderDoc(hostile, { h: fakeH });
  assert.deepEqual([...tagsOf(tree)].sort(), ['code', 'div', 'p']);
  const paragraph = tree.children[0];
  assert.equal(paragraph.children[1].children[0], '<img src=x onerror=alert(1)>');
  assert.ok(paragraph.children.includes(' and <script>alert(2)</script> in '));
  // With the guides served, a path becomes a link into them; a path with ".." never does.
  const linked = renderDoc('see ``docs/vision.md#frames``', { h: fakeH, docsBase: '/docs/' });
  const link = linked.children[0].children[1];
  assert.equal(link.tag, 'a');
  assert.equal(link.attrs.href, '/docs/vision.md#frames');
  const escaping = renderDoc('``docs/../../etc/passwd.md``', { h: fakeH, docsBase: '/docs/' });
  assert.equal(escaping.children[0].children[0].tag, 'code');
});

test("a grid layer's info gives the heat map's axes, scale and legend", () => {
  assert.equal(heatMapBase('grid.temperature.image'), 'grid.temperature');
  assert.equal(heatMapBase('frame'), null);
  const info = heatMapInfo(
    '((kind mean) (origin (-10 -10)) (cell 0.5) (shape (40 30)) (min 20.76571) (max 27.72667) ' +
      '(filled 19) (total 95) (outside 0) (unit degC))',
  );
  assert.deepEqual(info, { origin: [-10, -10], cell: 0.5, rows: 40, cols: 30, min: 20.76571, max: 27.72667, unit: 'degC' });
  const empty = heatMapInfo('((kind hits) (origin (0 0)) (cell 1) (shape (4 4)) (min ()) (max ()) (unit -))');
  assert.deepEqual([empty.min, empty.max, empty.unit], [null, null, '']);
  assert.equal(heatMapInfo('(a b)'), null);
  assert.equal(heatMapInfo('not a list'), null);
  assert.deepEqual(axisTicks(-10, 10), [-10, -5, 0, 5, 10]);
  assert.deepEqual(axisTicks(-10, 5), [-10, -5, 0, 5]);
  assert.deepEqual(axisTicks(0, 3), [0, 1, 2, 3]);
  assert.deepEqual([scaleLength(20), scaleLength(15), scaleLength(8), scaleLength(3)], [5, 2, 2, 0.5]);
  // The legend's ramp is the gateway's: blue through cyan, green, yellow to red.
  assert.equal(HEAT_RAMP.length, 5);
  assert.match(rampGradient(), /^linear-gradient\(to right, rgb\(48, 18, 160\) 0%, .* rgb\(200, 30, 30\) 100%\)$/);
});

test('signals of one unit share a scale and others keep their own', () => {
  const ranges = sharedRanges([
    { unit: 'm/s', lo: 0, hi: 1 },
    { unit: 'degC', lo: 20, hi: 22 },
    { unit: 'm/s', lo: 0.5, hi: 2 },
  ]);
  assert.deepEqual(ranges, [
    { lo: 0, hi: 2 },
    { lo: 20, hi: 22 },
    { lo: 0, hi: 2 },
  ]);
  const series = new PlotSeries();
  series.add(0, [1]);
  series.add(1000, [2]);
  const own = series.lines(1000);
  const shared = series.lines(1000, { lo: 0, hi: 4 });
  assert.deepEqual([own.lo, own.hi, shared.lo, shared.hi], [1, 2, 0, 4]);
  assert.notEqual(own.lines[0], shared.lines[0], 'the shared scale moves the line');
  assert.equal(MAX_SIGNALS, 3);
  assert.ok(addableSignal({ type: 'number', access: 'read-write' }));
  assert.ok(!addableSignal({ type: 'vector', access: 'read' }), 'a further signal is a number');
  assert.ok(!addableSignal({ type: 'number', access: 'action' }));
});
