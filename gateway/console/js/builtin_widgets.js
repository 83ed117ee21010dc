// The built-in widgets, one per `.gui` word the services use (services/kernel/core: number, slider,
// switch, text, vector, pose, gauge, list, marker, button, group; plot, the last minute from the
// history then live, from plot.js; statechart, a state machine's diagram, from statechart.js;
// image and camera, a live image, from image_widget.js)
// and one per data type (bytes: by its media type).
// Every writable widget has one input or select and a button [data-action=set]; an action has
// an input per parameter [data-param=NAME], a value input [data-value] when it takes a value,
// and a button [data-action=invoke]; a property that needs parameters to be read, a form of them.

import { bytesWidget, imageWidget } from './image_widget.js';
import {
  needsConfirmation,
  registerAddressedWidget,
  registerBuiltin,
  registerMediaWidget,
  registerTypeWidget,
} from './widgets.js';
import { plotWidget } from './plot.js';
import { statechartWidget } from './statechart.js';
import {
  decimalsFor,
  decimalsOf,
  findMarkers,
  formatMeasure,
  formatNumber,
  markerFromInput,
  parseVector,
  roundedText,
  sliderSpan,
  unitOf,
  valueFromInput,
} from './values.js';

const POSE_AXES = ['x', 'y', 'z', 'roll', 'pitch', 'yaw'];

function finite(x) {
  return typeof x === 'number' && Number.isFinite(x);
}

/**
 * An input and its Set button. `read()` turns the input into value text (throws a
 * ValueFormatError for a malformed one, shown as INVALID_ARGUMENT); `show(text)` puts a
 * value into the input unless the operator is editing it.
 */
function editor(
  ctx,
  input,
  { read = () => input.value, show = (text) => (input.value = text), whileFocused = false } = {},
) {
  let dirty = false;
  input.addEventListener('input', () => (dirty = true));
  const send = async () => {
    let text;
    try {
      text = read();
    } catch (e) {
      ctx.showError(e);
      return;
    }
    const reply = await ctx.set(text);
    if (reply !== null) dirty = false;
  };
  if (input.tagName === 'INPUT') {
    input.addEventListener('keydown', (e) => {
      if (e.key === 'Enter') send();
    });
  }
  const button = ctx.h('button', { type: 'button', class: 'set', dataset: { action: 'set' }, onclick: send }, 'Set');
  return {
    element: ctx.h('div', { class: 'editor' }, input, button),
    send,
    show(text) {
      if (!dirty && (whileFocused || document.activeElement !== input)) show(text);
    },
  };
}

function choicesSelect(ctx, prop) {
  const select = ctx.h('select', { 'aria-label': prop.name });
  for (const choice of prop.choices) select.append(ctx.h('option', { value: choice }, choice));
  const ed = editor(ctx, select);
  select.addEventListener('change', ed.send);
  return { element: ed.element, update: (text) => ed.show(text) };
}

function textWidget(prop, ctx) {
  if (!ctx.writable) return { element: null };
  if (prop.choices?.length) return choicesSelect(ctx, prop);
  const input = ctx.h('input', { type: 'text', 'aria-label': prop.name, spellcheck: 'false' });
  const ed = editor(ctx, input, { read: () => valueFromInput(prop.type, input.value) });
  return { element: ed.element, update: (text) => ed.show(text) };
}

/** A long text (`.gui` `text-area`, or `code`: a chart, a script): a text area of several lines. */
function textAreaWidget(prop, ctx) {
  if (!ctx.writable) return { element: null };
  const code = prop.gui === 'code';
  const area = ctx.h('textarea', {
    rows: code ? 12 : 6,
    class: code ? 'code' : 'long-text',
    'aria-label': prop.name,
    spellcheck: code ? 'false' : 'true',
    dataset: { value: '' },
  });
  const ed = editor(ctx, area);
  return { element: ed.element, update: (text) => ed.show(text) };
}

/** Unix seconds (`.gui` `time`): `.value` shows the date and time (js/widgets.js displayValue). */
function timeWidget(prop, ctx) {
  return ctx.writable ? numberWidget(prop, ctx) : { element: null };
}

function numberInput(ctx, prop) {
  return ctx.h('input', {
    type: 'number',
    'aria-label': prop.name,
    // The spinner steps by the model's resolution where it declares one.
    step: prop.type === 'integer' ? '1' : finite(prop.resolution) && prop.resolution > 0 ? prop.resolution : 'any',
    min: finite(prop.minimum) ? prop.minimum : null,
    max: finite(prop.maximum) ? prop.maximum : null,
  });
}

function numberWidget(prop, ctx) {
  if (!ctx.writable) return { element: null };
  if (prop.choices?.length) return choicesSelect(ctx, prop);
  const input = numberInput(ctx, prop);
  const ed = editor(ctx, input, { read: () => valueFromInput(prop.type, input.value) });
  return { element: ed.element, update: (text) => ed.show(text) };
}

/**
 * A slider: a drawn track (not a second <input>, so the number box stays the one input) that
 * moves the number box and sets on release. Its span comes from the model's range, narrowed
 * around the value when that range is far wider than the value needs (values.js sliderSpan: a
 * speed allowed up to 1000 m/s at 0.5 m/s spans 0 … 1 m/s); the scale names the span with its
 * unit, and the model's whole range when the span is narrower. The span follows the value (see
 * `follow`), never while the knob is held.
 */
function sliderWidget(prop, ctx) {
  const unit = prop.unit ?? '';
  const decimals = decimalsFor(prop);
  const fill = ctx.h('div', { class: 'slider-fill' });
  const thumb = ctx.h('div', { class: 'slider-thumb' });
  const track = ctx.h(
    'div',
    { class: 'slider', role: 'slider', tabindex: ctx.writable ? '0' : null, 'aria-label': prop.name },
    fill,
    thumb,
  );
  const low = ctx.h('span', { class: 'slider-lo' });
  const high = ctx.h('span', { class: 'slider-hi' });
  const allowed = ctx.h('span', { class: 'slider-range' });
  const scale = ctx.h('div', { class: 'slider-scale' }, low, allowed, high);
  let span = null;
  let shownValue = NaN;
  const spanFor = (x) => {
    span = sliderSpan(prop, x);
    const spanDecimals = Math.max(0, decimalsOf(span.step) ?? 0);
    const end = (edge) => `${roundedText(edge, spanDecimals)}${unit ? ` ${unit}` : ''}`;
    low.textContent = end(span.lo);
    high.textContent = end(span.hi);
    const declared = finite(prop.minimum) && finite(prop.maximum);
    allowed.textContent = span.zoomed && declared ? `allowed ${formatNumber(prop.minimum)} … ${formatNumber(prop.maximum)}` : '';
    track.setAttribute('aria-valuemin', String(span.lo));
    track.setAttribute('aria-valuemax', String(span.hi));
    track.dataset.zoomed = String(span.zoomed);
  };
  const place = (x) => {
    const f = Math.min(1, Math.max(0, (x - span.lo) / (span.hi - span.lo)));
    fill.style.width = `${f * 100}%`;
    thumb.style.left = `${f * 100}%`;
    track.setAttribute('aria-valuenow', String(x));
    track.setAttribute('aria-valuetext', formatMeasure(x, decimals, unit));
  };
  let pointer = null;
  const follow = (x) => {
    const first = !finite(shownValue);
    shownValue = x;
    // The first value, one out of the span, in its last tenth (no room to drag up) or its first
    // twentieth (the knob at the far left): a span that fits the value.
    const f = (x - span.lo) / (span.hi - span.lo);
    if (pointer === null && (first || f < 0.05 || f > 0.9)) spanFor(x);
    place(x);
  };
  spanFor(undefined);
  if (!ctx.writable) {
    return {
      element: ctx.h('div', { class: 'slider-box' }, track, scale),
      update(text) {
        const x = Number(text);
        if (text.trim() !== '' && finite(x)) follow(x);
      },
    };
  }
  const input = numberInput(ctx, prop);
  const ed = editor(ctx, input, { read: () => valueFromInput(prop.type, input.value) });
  const clamp = (x) => {
    const lo = finite(prop.minimum) ? Math.max(span.lo, prop.minimum) : span.lo;
    const hi = finite(prop.maximum) ? Math.min(span.hi, prop.maximum) : span.hi;
    return Number(Math.min(hi, Math.max(lo, x)).toPrecision(12));
  };
  const at = (clientX) => {
    const rect = track.getBoundingClientRect();
    const f = Math.min(1, Math.max(0, (clientX - rect.left) / rect.width));
    return clamp(Math.round((span.lo + f * (span.hi - span.lo)) / span.step) * span.step);
  };
  const move = (x) => {
    input.value = roundedText(x, Math.max(decimals, decimalsOf(span.step) ?? 0));
    input.dispatchEvent(new Event('input'));
    place(x);
  };
  track.addEventListener('pointerdown', (e) => {
    pointer = e.pointerId;
    try {
      track.setPointerCapture(e.pointerId);
    } catch {
      // a synthetic pointer: followed while it stays over the track
    }
    move(at(e.clientX));
  });
  track.addEventListener('pointermove', (e) => {
    if (e.pointerId === pointer) move(at(e.clientX));
  });
  const release = (e) => {
    if (e.pointerId !== pointer) return;
    pointer = null;
    if (e.type === 'pointerup') ed.send();
  };
  track.addEventListener('pointerup', release);
  track.addEventListener('pointercancel', release);
  track.addEventListener('keydown', (e) => {
    const delta = { ArrowRight: 1, ArrowUp: 1, ArrowLeft: -1, ArrowDown: -1 }[e.key];
    if (delta === undefined) return;
    e.preventDefault();
    // The arrows move the knob, not the robot: the page's driving keys never hear them.
    e.stopPropagation();
    const now = Number(input.value);
    const from = finite(now) && input.value.trim() !== '' ? now : finite(shownValue) ? shownValue : span.lo;
    move(clamp(Math.round((from + delta * span.step) / span.step) * span.step));
    ed.send();
  });
  track.addEventListener('keyup', (e) => {
    if (e.key.startsWith('Arrow')) e.stopPropagation();
  });
  return {
    element: ctx.h('div', { class: 'slider-box' }, track, scale, ed.element),
    update(text) {
      ed.show(text);
      const x = Number(text);
      if (text.trim() !== '' && finite(x)) follow(x);
    },
  };
}

function switchWidget(prop, ctx) {
  const box = ctx.h('input', {
    type: 'checkbox',
    role: 'switch',
    class: 'switch',
    'aria-label': prop.name,
    disabled: !ctx.writable,
  });
  const show = (text) => {
    box.checked = ['true', '1', 'on', 'yes'].includes(text.trim().toLowerCase());
  };
  if (!ctx.writable) return { element: box, update: show };
  const ed = editor(ctx, box, { read: () => (box.checked ? 'true' : 'false'), show, whileFocused: true });
  // A switch acts when flipped; the Set button sends the state shown again.
  box.addEventListener('change', ed.send);
  return { element: ed.element, update: (text) => ed.show(text) };
}

function elementNames(prop, n) {
  if (n === 6 && (prop.gui === 'pose' || prop.name.endsWith('location'))) return POSE_AXES;
  if (n === 6 && prop.name.endsWith('velocity')) return ['vx', 'vy', 'vz', 'wx', 'wy', 'wz'];
  return Array.from({ length: n }, (_, i) => String(i));
}

function vectorTable(ctx, prop) {
  const table = ctx.h('div', { class: 'vector' });
  return {
    table,
    show(text) {
      let numbers;
      try {
        numbers = parseVector(text);
      } catch {
        table.replaceChildren();
        return;
      }
      const names = elementNames(prop, numbers.length);
      table.replaceChildren(
        ...numbers.map((x, i) =>
          ctx.h(
            'span',
            { class: 'cell', title: formatNumber(x) },
            ctx.h('small', {}, names[i]),
            ctx.h('span', {}, roundedText(x, decimalsFor(prop, i, numbers.length))),
          ),
        ),
      );
    },
  };
}

function vectorWidget(prop, ctx) {
  const view = vectorTable(ctx, prop);
  if (!ctx.writable) return { element: view.table, update: view.show };
  const input = ctx.h('input', {
    type: 'text',
    'aria-label': prop.name,
    spellcheck: 'false',
    placeholder: prop.length ? `(${Array(prop.length).fill('0').join(' ')})` : '(1 2 3)',
  });
  const ed = editor(ctx, input, { read: () => valueFromInput('vector', input.value) });
  return {
    element: ctx.h('div', {}, view.table, ed.element),
    update(text) {
      view.show(text);
      ed.show(text);
    },
  };
}

/**
 * A pose read by people: x and y in metres and the heading in degrees, each to the precision the
 * model implies (a pose with no unit or resolution is read to the centimetre), e.g.
 * "x 1.23 m  y -0.50 m  heading 45.0°"; a vector of two to five numbers has no heading.
 */
export function poseText(prop, v) {
  const n = v.length;
  const model = prop.unit || finite(prop.resolution) ? prop : { ...prop, unit: 'm, rad' };
  const metres = unitOf(model, 0, n) || 'm';
  const places = decimalsFor(model, 0, n);
  const parts = [`x ${formatMeasure(v[0], places, metres)}`, `y ${formatMeasure(v[1], places, metres)}`];
  if (n >= 6) {
    // Radians read to 0.01 are about half a degree: degrees get one decimal.
    parts.push(`heading ${formatMeasure((v[5] * 180) / Math.PI, 1)}°`);
  }
  return parts.join('  ');
}

function formatVectorText(v) {
  return `(${v.map(formatNumber).join(' ')})`;
}

/** A pose: x, y and the heading in degrees, with a compass needle. */
function poseWidget(prop, ctx) {
  const needle = ctx.svg('path', { d: 'M0,-9 L5,6 L0,3 L-5,6 Z', class: 'needle' });
  const compass = ctx.svg(
    'svg',
    { viewBox: '-12 -12 24 24', class: 'compass', 'aria-hidden': 'true' },
    ctx.svg('circle', { r: 11 }),
    needle,
  );
  const text = ctx.h('span', { class: 'pose-text' });
  const box = ctx.h('div', { class: 'pose' }, compass, text);
  const rest = ctx.writable ? vectorWidget(prop, ctx) : null;
  return {
    element: rest ? ctx.h('div', {}, box, rest.element) : box,
    update(value) {
      rest?.update(value);
      let v;
      try {
        v = parseVector(value);
      } catch {
        text.textContent = '';
        return;
      }
      if (v.length < 2) {
        text.textContent = 'nowhere';
        return;
      }
      const yaw = v.length >= 6 ? v[5] : 0;
      // Map north is +y; the needle points along the heading (counter-clockwise from +x).
      needle.setAttribute('transform', `rotate(${90 - (yaw * 180) / Math.PI})`);
      text.textContent = poseText(prop, v);
      text.title = formatVectorText(v);
    },
  };
}

function gaugeWidget(prop, ctx) {
  const lo = finite(prop.minimum) ? prop.minimum : 0;
  const hi = finite(prop.maximum) && prop.maximum > lo ? prop.maximum : 1;
  const bar = ctx.h('div', { class: 'gauge-bar' });
  const label = ctx.h('span', { class: 'gauge-label' });
  const gauge = ctx.h('div', { class: 'gauge', role: 'meter', 'aria-valuemin': lo, 'aria-valuemax': hi }, bar, label);
  const rest = ctx.writable ? numberWidget(prop, ctx) : null;
  return {
    element: rest ? ctx.h('div', {}, gauge, rest.element) : gauge,
    update(text) {
      rest?.update(text);
      const x = Number(text);
      if (!finite(x)) return;
      const f = Math.min(1, Math.max(0, (x - lo) / (hi - lo)));
      bar.style.width = `${f * 100}%`;
      gauge.classList.toggle('low', f < 0.2);
      gauge.setAttribute('aria-valuenow', String(x));
      label.textContent = `${Math.round(f * 100)} %`;
    },
  };
}

function listWidget(prop, ctx) {
  // Read-only, `.value` shows it (its title holds the whole text when it is clipped).
  if (!ctx.writable) return { element: null };
  const area = ctx.h('textarea', { rows: 2, 'aria-label': prop.name, spellcheck: 'false' });
  const ed = editor(ctx, area);
  return {
    element: ctx.h('div', {}, ed.element),
    update: (text) => ed.show(text),
  };
}

function markerFields(ctx, marker) {
  return ctx.h(
    'dl',
    { class: 'marker' },
    Object.entries(marker.fields).flatMap(([name, value]) => [
      ctx.h('dt', {}, name),
      ctx.h('dd', {}, typeof value === 'string' ? value : '<…>'),
    ]),
  );
}

function markerWidget(prop, ctx) {
  const view = ctx.h('div', { class: 'markers' });
  const show = (text) => view.replaceChildren(...findMarkers(text, 20).map((m) => markerFields(ctx, m)));
  if (!ctx.writable) return { element: view, update: show };
  const area = ctx.h('textarea', {
    rows: 2,
    'aria-label': prop.name,
    spellcheck: 'false',
    placeholder: '<marker><location>(1 2)</location></marker>',
  });
  const ed = editor(ctx, area, { read: () => markerFromInput(area.value) });
  return {
    element: ctx.h('div', {}, view, ed.element),
    update(text) {
      show(text);
      ed.show(text);
    },
  };
}

function valueReader(type, input) {
  if (type === 'marker') return () => markerFromInput(input.value);
  if (type === 'number' || type === 'integer' || type === 'boolean' || type === 'vector') {
    return () => (input.value.trim() === '' ? '' : valueFromInput(type, input.value));
  }
  return () => input.value;
}

const PLACEHOLDERS = {
  marker: 'x y  or  <marker><location>(x y)</location></marker>',
  vector: '(1 2 3)',
  number: '0.5',
  integer: '42',
  boolean: 'true',
  list: '((1 2) (a b))',
  names: '(a b)',
  vectors: '((1 0) (2 1))',
};

/** The inputs of a request's parameters: one [data-param=NAME] each, default as placeholder. */
function parameterInputs(ctx, prop) {
  const inputs = new Map();
  const rows = (prop.parameters ?? []).map((p) => {
    const input = ctx.h('input', {
      type: 'text',
      spellcheck: 'false',
      dataset: { param: p.name },
      'aria-label': `${prop.name} ${p.name}`,
      placeholder: p.default ? `${p.default} (default)` : (PLACEHOLDERS[p.type] ?? p.type ?? ''),
      required: p.required && !p.default,
    });
    inputs.set(p.name, input);
    return ctx.h(
      'label',
      { class: 'param', title: p.doc || p.name },
      ctx.h('span', {}, p.name, p.type ? ctx.h('small', {}, ` ${p.type}`) : null),
      input,
    );
  });
  const read = () => {
    const parameters = {};
    for (const [name, input] of inputs) if (input.value.trim() !== '') parameters[name] = input.value.trim();
    return parameters;
  };
  return { rows, read };
}

/**
 * An action: a form with its value (typed by `prop.value.type` when the model names it; an
 * action whose model says `value: null` takes none) and its parameters, and an Invoke button.
 * The reply of the Set shows in `.value`.
 */
function buttonWidget(prop, ctx) {
  const valueModel = prop.value;
  const takesValue = valueModel !== null;
  const valueType = valueModel?.type ?? '';
  let valueInput = null;
  const rows = [];
  if (takesValue) {
    valueInput = ctx.h('input', {
      type: 'text',
      spellcheck: 'false',
      dataset: { value: '' },
      'aria-label': `${prop.name} value`,
      placeholder: PLACEHOLDERS[valueType] ?? (valueType ? valueType : 'value (empty: none)'),
    });
    rows.push(
      ctx.h(
        'label',
        { class: 'param' },
        ctx.h('span', {}, valueModel?.name ?? 'value', valueType ? ctx.h('small', {}, ` ${valueType}`) : null),
        valueInput,
      ),
    );
  }
  const params = parameterInputs(ctx, prop);
  const readValue = valueInput ? valueReader(valueType, valueInput) : () => '';
  const invoke = async () => {
    let text;
    try {
      text = readValue();
    } catch (e) {
      ctx.showError(e);
      return;
    }
    if (needsConfirmation(prop)) {
      const ask = ctx.confirm ?? ((question) => globalThis.confirm(question));
      if (!ask(`${prop.name} of ${ctx.service}: ${prop.doc || 'invoke it'}. Go ahead?`)) return;
    }
    const reply = await ctx.set(text, params.read());
    if (reply !== null) ctx.showValue(reply === '' ? 'done' : reply);
  };
  valueInput?.addEventListener('keydown', (e) => e.key === 'Enter' && invoke());
  const button = ctx.h(
    'button',
    { type: 'button', class: 'invoke', dataset: { action: 'invoke' }, onclick: invoke },
    prop.name.split('.').pop(),
  );
  return { element: ctx.h('div', { class: 'action-form' }, rows, params.rows, button) };
}

/** A query: its parameters and a Get button; the answer shows in `.value`. */
function queryWidget(prop, ctx) {
  const params = parameterInputs(ctx, prop);
  const ask = async () => {
    const answer = await ctx.get(params.read());
    if (answer !== null) ctx.showValue(answer);
  };
  const button = ctx.h('button', { type: 'button', dataset: { action: 'get' }, onclick: ask }, 'Get');
  return { element: ctx.h('div', { class: 'action-form' }, params.rows, button) };
}

/**
 * A readable or writable property that needs request parameters to be read (a storage
 * service's `file` and its `name`): an input per parameter, a Get button when it can be read,
 * a text area [data-value] and a Set button when it can be written. It is not followed live
 * (nothing says which parameters to follow it with); the value read, or the reply of a Set,
 * shows in `.value`.
 */
function addressedWidget(prop, ctx) {
  const params = parameterInputs(ctx, prop);
  const readable = ['read', 'read-write', 'unknown'].includes(prop.access);
  const valueType = prop.value?.type ?? prop.type ?? '';
  let area = null;
  const rows = [];
  if (ctx.writable) {
    area = ctx.h('textarea', {
      rows: 3,
      spellcheck: 'false',
      dataset: { value: '' },
      'aria-label': `${prop.name} value`,
      placeholder: PLACEHOLDERS[valueType] ?? (valueType || 'value'),
    });
    rows.push(
      ctx.h(
        'label',
        { class: 'param', title: prop.value?.doc || '' },
        ctx.h('span', {}, prop.value?.name ?? 'value', valueType ? ctx.h('small', {}, ` ${valueType}`) : null),
        area,
      ),
    );
  }
  const readValue = area ? valueReader(valueType, area) : () => '';
  const get = async () => {
    const answer = await ctx.get(params.read());
    if (answer === null) return;
    ctx.showValue(answer);
    if (area) area.value = answer;
  };
  const set = async () => {
    let text;
    try {
      text = readValue();
    } catch (e) {
      ctx.showError(e);
      return;
    }
    const reply = await ctx.set(text, params.read());
    if (reply !== null) ctx.showValue(reply === '' ? 'done' : reply);
  };
  const buttons = ctx.h(
    'div',
    { class: 'editor' },
    readable ? ctx.h('button', { type: 'button', dataset: { action: 'get' }, onclick: get }, 'Get') : null,
    area ? ctx.h('button', { type: 'button', class: 'set', dataset: { action: 'set' }, onclick: set }, 'Set') : null,
  );
  return { element: ctx.h('div', { class: 'action-form' }, params.rows, rows, buttons) };
}

function namespaceWidget() {
  return { element: null };
}

registerBuiltin('text', textWidget);
registerBuiltin('number', numberWidget);
registerBuiltin('slider', sliderWidget);
registerBuiltin('switch', switchWidget);
registerBuiltin('vector', vectorWidget);
registerBuiltin('pose', poseWidget);
registerBuiltin('gauge', gaugeWidget);
registerBuiltin('plot', plotWidget);
registerBuiltin('list', listWidget);
registerBuiltin('marker', markerWidget);
registerBuiltin('button', buttonWidget);
registerBuiltin('query', queryWidget);
registerBuiltin('group', namespaceWidget);
registerBuiltin('statechart', statechartWidget);
registerBuiltin('text-area', textAreaWidget);
registerBuiltin('code', textAreaWidget);
registerBuiltin('time', timeWidget);
// Binary values: a live image by `.gui` or by media type (a camera's `frame`, a grid layer's PNG);
// other bytes (a numpy grid) show their media type and a link to the raw value.
registerBuiltin('image', imageWidget);
registerBuiltin('camera', imageWidget);
registerMediaWidget('image/*', imageWidget);
registerAddressedWidget(addressedWidget);

registerTypeWidget('number', numberWidget);
registerTypeWidget('integer', numberWidget);
registerTypeWidget('boolean', switchWidget);
registerTypeWidget('text', textWidget);
registerTypeWidget('vector', vectorWidget);
registerTypeWidget('marker', markerWidget);
registerTypeWidget('list', listWidget);
registerTypeWidget('names', listWidget);
registerTypeWidget('vectors', listWidget);
registerTypeWidget('namespace', namespaceWidget);
registerTypeWidget('bytes', bytesWidget);
