// What a new user of the console asked for: times instead of raw Unix seconds, long texts in a
// text area, a question before an action that removes something, and the joystick's knob
// following the keys.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import '../../gateway/console/js/builtin_widgets.js';
import { knobForKeys, Teleop } from '../../gateway/console/js/teleop.js';
import { formatTime } from '../../gateway/console/js/values.js';
import { displayValue, needsConfirmation, widgetFor } from '../../gateway/console/js/widgets.js';

test('Unix seconds show as the local date and time', () => {
  const seconds = Date.UTC(2026, 10, 23, 1, 50, 3) / 1000;
  const local = new Date(seconds * 1000);
  const two = (n) => String(n).padStart(2, '0');
  const expected =
    `${local.getFullYear()}-${two(local.getMonth() + 1)}-${two(local.getDate())} ` +
    `${two(local.getHours())}:${two(local.getMinutes())}:${two(local.getSeconds())}`;
  assert.equal(formatTime(`${seconds}.25`), expected);
  assert.equal(formatTime(''), null);
  assert.equal(formatTime('soon'), null);
  assert.equal(formatTime('1e300'), null);
});

test('a `.gui` time shows a time, the number in its tooltip; other values stay as they are', () => {
  const lastSeen = { name: 'services.scout1.last_seen', type: 'number', access: 'read', gui: 'time' };
  const shown = displayValue(lastSeen, '1763862603.5');
  assert.match(shown.text, /^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d$/);
  assert.equal(shown.title, '1763862603.5 (Unix seconds)');
  assert.deepEqual(displayValue(lastSeen, 'never'), { text: 'never', title: 'never' });
  const speed = { name: 'speed', type: 'number', access: 'read-write', gui: 'slider' };
  assert.deepEqual(displayValue(speed, '0.5'), { text: '0.5', title: '0.5' });
});

test('long texts get a text area; a time its own widget', () => {
  const named = (prop) => widgetFor(prop).name;
  const text = { name: 'patrol.definition', type: 'text', access: 'read-write' };
  assert.equal(named({ ...text, gui: 'code' }), 'textAreaWidget');
  assert.equal(named({ ...text, gui: 'text-area' }), 'textAreaWidget');
  assert.equal(named({ ...text, gui: '' }), 'textWidget');
  assert.equal(named({ name: 'last_seen', type: 'number', access: 'read', gui: 'time' }), 'timeWidget');
});

test('actions that remove something ask first, by their name or a `.gui` confirm', () => {
  const action = (name, gui = 'button') => ({ name, type: 'none', access: 'action', gui });
  assert.ok(needsConfirmation(action('patrol.remove')));
  assert.ok(needsConfirmation(action('delete')));
  assert.ok(needsConfirmation(action('robots.stop-all')));
  assert.ok(needsConfirmation(action('behaviors.moveto', 'confirm')));
  assert.ok(!needsConfirmation(action('patrol.start')));
  assert.ok(!needsConfirmation(action('behaviors.stop')));
  assert.ok(!needsConfirmation({ name: 'remove', type: 'text', access: 'read-write', gui: 'text' }));
  // An action with `.gui` confirm is still a button.
  assert.equal(widgetFor(action('x', 'confirm')).name, 'buttonWidget');
});

test('the knob stands where the keys drive', () => {
  assert.deepEqual(knobForKeys(new Set()), [0, 0]);
  assert.deepEqual(knobForKeys(new Set(['forward'])), [0, -1]);
  assert.deepEqual(knobForKeys(new Set(['back', 'left'])).map((x) => x.toFixed(3)), ['-0.707', '0.707']);
  assert.deepEqual(knobForKeys(new Set(['forward', 'back'])), [0, 0]);
});

class Listeners {
  constructor() {
    this.handlers = {};
  }
  addEventListener(type, f) {
    (this.handlers[type] ??= []).push(f);
  }
  fire(type, event = {}) {
    for (const f of this.handlers[type] ?? []) f({ preventDefault() {}, ...event });
  }
}

test('driving with the keys moves the knob, and letting go brings it back', async () => {
  const element = (extra = {}) =>
    Object.assign(new Listeners(), { classList: { toggle() {}, add() {}, remove() {} }, style: {} }, extra);
  const page = new Listeners();
  page.document = Object.assign(new Listeners(), { visibilityState: 'visible' });
  const els = {
    root: element(),
    joystick: element({ getBoundingClientRect: () => ({ left: 0, top: 0, width: 100, height: 100 }) }),
    knob: element(),
    status: element({ textContent: '' }),
    speed: { value: '0.5' },
    turn: { value: '1' },
    mode: { value: 'heading' },
    stop: element(),
    target: { textContent: '' },
  };
  const teleop = new Teleop(els, {
    selected: () => ({ name: 'scout1', type: 'mobile_robot' }),
    poseOf: () => [0, 0, 0, 0, 0, 0],
    setVelocity: () => Promise.resolve(),
    page,
  });
  teleop.selectionChanged();
  assert.equal(els.knob.style.transform, '');
  page.fire('keydown', { key: 'w', target: {} });
  assert.equal(els.knob.style.transform, 'translate(0px, -30px)');
  page.fire('keydown', { key: 'ArrowRight', target: {} });
  assert.match(els.knob.style.transform, /^translate\(21\.2\d*px, -21\.2\d*px\)$/);
  page.fire('keyup', { key: 'w', target: {} });
  assert.equal(els.knob.style.transform, 'translate(30px, 0px)');
  page.fire('keyup', { key: 'ArrowRight', target: {} });
  assert.equal(els.knob.style.transform, '');
  page.fire('keydown', { key: 's', target: {} });
  page.fire('blur');
  assert.equal(els.knob.style.transform, '', 'losing the page centres the knob');
  teleop.release();
});
