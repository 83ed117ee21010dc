// The statechart widget: the diagram as an <img> of a data: URL (never markup in the page),
// the active states named beside it, and the machine's start, stop and event controls as Sets.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { activeStates, machineOf, statechartWidget, svgDataUrl } from '../../gateway/console/js/statechart.js';

const SVG =
  '<svg xmlns="http://www.w3.org/2000/svg" width="10" height="10"><title>p</title>' +
  '<g class="state compound active" data-state="patrol"><rect/></g>' +
  '<g class="state atomic active" data-state="goto"><rect/></g>' +
  '<g class="state atomic" data-state="wait"><rect/></g></svg>';

/** A stand-in for ctx.h: plain objects that keep what the widget does to them. */
function fakeElement(tag, attrs = {}, ...children) {
  const el = {
    tag,
    attributes: {},
    listeners: {},
    dataset: {},
    children: children.flat().filter((c) => c !== null && c !== undefined),
    hidden: false,
    textContent: '',
    value: '',
    setAttribute(name, value) {
      this.attributes[name] = String(value);
    },
    removeAttribute(name) {
      delete this.attributes[name];
    },
    addEventListener(type, f) {
      this.listeners[type] = f;
    },
  };
  for (const [name, value] of Object.entries(attrs)) {
    if (name === 'dataset') Object.assign(el.dataset, value);
    else if (name === 'hidden') el.hidden = Boolean(value);
    else if (name.startsWith('on') && typeof value === 'function') el.listeners[name.slice(2)] = value;
    else el.attributes[name] = String(value);
  }
  return el;
}

function find(el, pred) {
  if (pred(el)) return el;
  for (const child of el.children ?? []) {
    if (typeof child === 'object') {
      const found = find(child, pred);
      if (found) return found;
    }
  }
  return null;
}

function widgetFor(path) {
  const sets = [];
  const ctx = {
    service: 'missions',
    path,
    writable: false,
    h: fakeElement,
    setPath: async (p, text, parameters = {}) => {
      sets.push([p, text, parameters]);
      return '';
    },
  };
  return { widget: statechartWidget({ name: path, type: 'text', access: 'read', gui: 'statechart' }, ctx), sets };
}

test('the SVG becomes a data: URL of its own text, and nothing else does', () => {
  const url = svgDataUrl(SVG);
  assert.ok(url.startsWith('data:image/svg+xml;charset=utf-8,%3Csvg'));
  assert.equal(decodeURIComponent(url.split(',', 2)[1]), SVG);
  assert.ok(svgDataUrl('<?xml version="1.0"?>\n' + SVG).startsWith('data:image/svg+xml'));
  assert.equal(svgDataUrl(''), null);
  assert.equal(svgDataUrl('<script>alert(1)</script>'), null);
  assert.equal(svgDataUrl('<svgx/>'), null);
  assert.equal(svgDataUrl('<svg>' + 'x'.repeat(70000) + '</svg>'), null);
  assert.equal(svgDataUrl(null), null);
});

test('a diagram path names its machine; the active states are read from the groups', () => {
  assert.equal(machineOf('patrol.diagram'), 'patrol');
  assert.equal(machineOf('fleet.a.diagram'), 'fleet.a');
  assert.equal(machineOf('patrol.state'), null);
  assert.deepEqual(activeStates(SVG), ['patrol', 'goto']);
  assert.deepEqual(activeStates(''), []);
});

test('the widget shows each new diagram as an image and names the active states', () => {
  const { widget } = widgetFor('patrol.diagram');
  assert.equal(widget.hidesValue, true);
  const img = find(widget.element, (el) => el.tag === 'img');
  const active = find(widget.element, (el) => el.tag === 'output');
  assert.equal(img.hidden, true);
  widget.update(SVG);
  assert.equal(img.hidden, false);
  assert.equal(img.attributes.src, svgDataUrl(SVG));
  assert.equal(active.textContent, 'active: patrol goto');
  const next = SVG.replace('class="state atomic active" data-state="goto"', 'class="state atomic" data-state="goto"')
    .replace('class="state atomic" data-state="wait"', 'class="state atomic active" data-state="wait"');
  widget.update(next);
  assert.equal(img.attributes.src, svgDataUrl(next));
  assert.equal(active.textContent, 'active: patrol wait');
  widget.update(''); // the chart was removed
  assert.equal(img.hidden, true);
  assert.equal(img.attributes.src, undefined);
  assert.equal(active.textContent, '');
});

test('its buttons start, stop and send events to the machine the diagram belongs to', async () => {
  const { widget, sets } = widgetFor('patrol.diagram');
  const button = (action) => find(widget.element, (el) => el.tag === 'button' && el.dataset.action === action);
  button('start').listeners.click();
  button('stop').listeners.click();
  const input = find(widget.element, (el) => el.tag === 'input');
  input.value = '  threshold ';
  button('send').listeners.click();
  input.value = '';
  button('send').listeners.click(); // nothing to send
  input.value = 'go';
  input.listeners.keydown({ key: 'Enter' });
  assert.deepEqual(sets, [
    ['patrol.start', '', {}],
    ['patrol.stop', '', {}],
    ['patrol.events', 'threshold', {}],
    ['patrol.events', 'go', {}],
  ]);
});

test('a statechart gui on a property that is no machine diagram shows the image only', () => {
  const { widget } = widgetFor('overview');
  assert.equal(find(widget.element, (el) => el.tag === 'button'), null);
});
