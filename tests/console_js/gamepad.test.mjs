// Gamepad driving's dead-man, with the pad, the page and the teleop stood in for: the stick
// drives only while the dead-man button is held and outside the dead zone; the centre, the
// button let go, a disconnect and a lost page each stop it, and a lost page drives again only
// after the button was let go.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { DEADMAN_BUTTON, Deadman, GamepadDriver, POLL_MS, stickCommand } from '../../gateway/console/js/gamepad.js';

function pad({ x = 0, y = 0, deadman = true, index = 0 } = {}) {
  const buttons = Array.from({ length: 16 }, () => ({ pressed: false, value: 0 }));
  buttons[DEADMAN_BUTTON] = { pressed: deadman, value: deadman ? 1 : 0 };
  return { id: 'stand-in pad', index, connected: true, mapping: 'standard', axes: [x, y, 0, 0], buttons };
}

class Listeners {
  constructor() {
    this.handlers = {};
  }
  addEventListener(type, f) {
    (this.handlers[type] ??= []).push(f);
  }
  fire(type, event = {}) {
    for (const f of this.handlers[type] ?? []) f(event);
  }
}

function page(pads) {
  const p = new Listeners();
  p.navigator = { getGamepads: () => pads };
  p.document = Object.assign(new Listeners(), { visibilityState: 'visible' });
  return p;
}

test('the stick pushed up with the dead-man held drives forward', () => {
  assert.deepEqual(stickCommand(pad({ y: -1 })), { forward: 1, turn: 0 });
  assert.deepEqual(stickCommand(pad({ x: 1 })), { forward: 0, turn: -1 });
});

test('the stick inside the dead zone or without the dead-man asks for nothing', () => {
  assert.equal(stickCommand(pad({ y: -0.1, x: 0.05 })), null);
  assert.equal(stickCommand(pad({ y: -1, deadman: false })), null);
  assert.equal(stickCommand(null), null);
  assert.equal(stickCommand({ ...pad({ y: -1 }), connected: false }), null);
});

test('driving starts from zero at the edge of the dead zone', () => {
  const just = stickCommand(pad({ y: -0.16 }));
  assert.ok(just.forward > 0 && just.forward < 0.02, JSON.stringify(just));
  const half = stickCommand(pad({ y: -(0.15 + 0.85 / 2) }));
  assert.ok(Math.abs(half.forward - 0.5) < 0.01, JSON.stringify(half));
});

test('after a lost page the pad drives again only once the dead-man was let go', () => {
  const d = new Deadman();
  assert.deepEqual(d.read(pad({ y: -1 }), true), { forward: 1, turn: 0 });
  assert.equal(d.read(pad({ y: -1 }), false), null, 'the page lost: stop');
  assert.equal(d.read(pad({ y: -1 }), true), null, 'back, still held: no driving');
  assert.equal(d.read(pad({ y: -1, deadman: false }), true), null);
  assert.deepEqual(d.read(pad({ y: -1 }), true), { forward: 1, turn: 0 }, 'pressed anew: drives');
});

function driver(pads) {
  const p = page(pads);
  const drives = [];
  const d = new GamepadDriver({ drive: (stick) => drives.push(stick), page: p });
  return { p, d, drives };
}

test('a connected pad is read and only its changes reach the teleop', (t) => {
  t.mock.timers.enable({ apis: ['setInterval'] });
  const pads = [pad({ deadman: false })];
  const { p, d, drives } = driver(pads);
  p.fire('gamepadconnected', { gamepad: pads[0] });
  pads[0] = pad({ y: -1 });
  t.mock.timers.tick(POLL_MS * 3);
  assert.deepEqual(drives, [{ forward: 1, turn: 0 }], 'one command for three readings of a held stick');
  pads[0] = pad({ y: 0 });
  t.mock.timers.tick(POLL_MS);
  assert.deepEqual(drives.at(-1), null, 'the stick at the centre lets go');
  d.disconnected(pads[0]);
});

for (const [how, act] of [
  ['the dead-man let go', (pads) => { pads[0] = pad({ y: -1, deadman: false }); }],
  ['the pad disconnected', (pads, p) => { const gone = pads[0]; pads[0] = null; p.fire('gamepaddisconnected', { gamepad: gone }); }],
  ['the page blurred', (pads, p) => p.fire('blur')],
  ['the page hidden', (pads, p) => { p.document.visibilityState = 'hidden'; p.document.fire('visibilitychange'); }],
]) {
  test(`driving stops when ${how}`, (t) => {
    t.mock.timers.enable({ apis: ['setInterval'] });
    const pads = [pad({ y: -1 })];
    const { p, d, drives } = driver(pads); // connected before the page loaded: found at once
    assert.deepEqual(drives, [{ forward: 1, turn: 0 }]);
    act(pads, p);
    t.mock.timers.tick(POLL_MS * 2);
    assert.equal(drives.at(-1), null, `${how}: the teleop let go`);
    assert.equal(drives.length, 2, `${how}: nothing drives again while the stick is still pushed`);
    if (d.timer !== null) d.disconnected(pads[0] ?? { index: 0 });
  });
}

test('the teleop drives what the pad holds and sends zeros when it lets go', async (t) => {
  const { Teleop, SEND_PERIOD_MS } = await import('../../gateway/console/js/teleop.js');
  t.mock.timers.enable({ apis: ['setInterval'] });
  const el = () => Object.assign(new Listeners(), { classList: { toggle() {}, add() {}, remove() {} }, style: {}, textContent: '' });
  const els = { root: el(), joystick: el(), knob: el(), status: el(), stop: el(), target: el() };
  Object.assign(els, { speed: { value: '0.5' }, turn: { value: '1' }, mode: { value: 'heading' } });
  const sent = [];
  const p = page([]);
  const teleop = new Teleop(els, {
    selected: () => ({ name: 'scout2', type: 'mobile_robot' }),
    poseOf: () => [0, 0, 0, 0, 0, 0],
    setVelocity: (name, text) => {
      sent.push([name, text]);
      return Promise.resolve();
    },
    page: p,
  });
  teleop.selectionChanged();
  teleop.gamepad({ forward: 1, turn: 0 });
  assert.deepEqual(sent, [['scout2', '(0.5 0 0 0 0 0)']]);
  await new Promise((resolve) => setImmediate(resolve));
  t.mock.timers.tick(SEND_PERIOD_MS);
  assert.equal(sent.length, 2, 'a held pad is renewed as a held key is');
  teleop.gamepad(null);
  assert.deepEqual(sent.at(-1), ['scout2', '(0 0 0 0 0 0)']);
  t.mock.timers.tick(SEND_PERIOD_MS * 5);
  assert.equal(sent.length, 3, 'nothing after the stop');
});
