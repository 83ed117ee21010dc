// Teleoperation's safety rules, with the page, the elements and the gateway stood in for:
// a held key sends at once and every 100 ms, releasing sends zeros at once, a command still
// on its way when the operator lets go is followed by another stop, losing the page stops
// only a robot this page drives.
import assert from 'node:assert/strict';
import { mock, test } from 'node:test';

import { SEND_PERIOD_MS, Teleop } from '../../gateway/console/js/teleop.js';

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

function element(extra = {}) {
  return Object.assign(new Listeners(), { classList: { toggle() {}, add() {}, remove() {} }, style: {} }, extra);
}

function setup({ pending = false } = {}) {
  const page = new Listeners();
  page.document = Object.assign(new Listeners(), { visibilityState: 'visible' });
  const sent = [];
  const waiting = [];
  const setVelocity = (name, text, keepalive) => {
    sent.push([name, text, keepalive]);
    if (pending && text !== '(0 0 0 0 0 0)') return new Promise((resolve) => waiting.push(resolve));
    return Promise.resolve();
  };
  const els = {
    root: element(),
    joystick: element(),
    knob: element(),
    status: element({ textContent: '' }),
    speed: { value: '0.5' },
    turn: { value: '1' },
    mode: { value: 'heading' },
    stop: element(),
    target: { textContent: '' },
  };
  let selected = { name: 'scout2', type: 'mobile_robot' };
  const teleop = new Teleop(els, {
    selected: () => selected,
    poseOf: () => [0, 0, 0, 0, 0, 0],
    setVelocity,
    page,
  });
  teleop.selectionChanged();
  return { teleop, page, sent, waiting, els, select: (s) => (selected = s) };
}

const settle = () => new Promise((resolve) => setImmediate(resolve));
const key = (k, target = {}) => ({ key: k, target });

test('a held key drives at once and every period; releasing stops at once and for good', async () => {
  mock.timers.enable({ apis: ['setInterval'] });
  try {
    const { page, sent } = setup();
    page.fire('keydown', key('w'));
    assert.deepEqual(sent, [['scout2', '(0.5 0 0 0 0 0)', false]]);
    page.fire('keydown', key('w')); // the key's auto-repeat adds nothing
    await settle();
    for (let i = 0; i < 3; i += 1) {
      mock.timers.tick(SEND_PERIOD_MS);
      await settle();
    }
    assert.equal(sent.length, 4);
    page.fire('keyup', key('w'));
    assert.deepEqual(sent.at(-1), ['scout2', '(0 0 0 0 0 0)', false]);
    mock.timers.tick(SEND_PERIOD_MS * 10);
    await settle();
    assert.equal(sent.length, 5, 'nothing after the stop');
  } finally {
    mock.timers.reset();
  }
});

test('a command still on its way when the key is released is followed by another stop', async () => {
  mock.timers.enable({ apis: ['setInterval'] });
  try {
    const { page, sent, waiting } = setup({ pending: true });
    page.fire('keydown', key('ArrowLeft'));
    mock.timers.tick(SEND_PERIOD_MS * 3);
    await settle();
    assert.deepEqual(sent, [['scout2', '(0 0 0 0 0 1)', false]], 'one request at a time, never a queue');
    page.fire('keyup', key('ArrowLeft'));
    assert.deepEqual(sent.at(-1), ['scout2', '(0 0 0 0 0 0)', false], 'the stop does not wait');
    waiting[0]();
    await settle();
    assert.deepEqual(sent.at(-1), ['scout2', '(0 0 0 0 0 0)', false]);
    assert.equal(sent.length, 3, 'the late command is followed by a second stop');
  } finally {
    mock.timers.reset();
  }
});

test('losing the page stops the robot this page drives, with a request that outlives the page', async () => {
  mock.timers.enable({ apis: ['setInterval'] });
  try {
    const { page, sent } = setup();
    page.fire('blur');
    assert.deepEqual(sent, [], 'a robot this page does not drive is left alone (its moveto goes on)');
    page.fire('keydown', key('s'));
    await settle();
    page.document.visibilityState = 'hidden';
    page.document.fire('visibilitychange');
    assert.deepEqual(sent.at(-1), ['scout2', '(0 0 0 0 0 0)', true]);
    mock.timers.tick(SEND_PERIOD_MS * 5);
    await settle();
    assert.equal(sent.length, 2, 'and the held key counts no more');
  } finally {
    mock.timers.reset();
  }
});

test('keys do nothing while a text box has the focus, or with nothing to drive', () => {
  const { page, sent, select } = setup();
  page.fire('keydown', key('w', { tagName: 'INPUT' }));
  assert.deepEqual(sent, []);
  select({ name: 'thermo1', type: 'sensor' });
  page.fire('keydown', key('w'));
  assert.deepEqual(sent, []);
});
