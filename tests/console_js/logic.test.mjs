// Pure pieces of the views: teleop velocities, inspector parameters, location areas.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { parseParameters } from '../../gateway/console/js/inspector.js';
import { areaOf } from '../../gateway/console/js/service_list.js';
import { SEND_PERIOD_MS, velocityFor } from '../../gateway/console/js/teleop.js';

test('the stick drives along the heading, or as drawn on the map', () => {
  const base = { speed: 0.5, turnRate: 1 };
  assert.deepEqual(velocityFor({ ...base, forward: 1, turn: 0, mode: 'heading', yaw: 0 }), [0.5, 0, 0, 0, 0, 0]);
  assert.deepEqual(velocityFor({ ...base, forward: 1, turn: 0, mode: 'heading', yaw: Math.PI / 2 }), [0, 0.5, 0, 0, 0, 0]);
  assert.deepEqual(velocityFor({ ...base, forward: 0, turn: 1, mode: 'heading', yaw: 1 }), [0, 0, 0, 0, 0, 1]);
  assert.deepEqual(velocityFor({ ...base, forward: 1, turn: 0, mode: 'map', yaw: 2 }), [0, 0.5, 0, 0, 0, 0]);
  assert.deepEqual(velocityFor({ ...base, forward: 0, turn: -1, mode: 'map' }), [0.5, 0, 0, 0, 0, 0]);
  assert.deepEqual(velocityFor({ ...base, forward: 0, turn: 0, mode: 'heading' }), [0, 0, 0, 0, 0, 0]);
  assert.ok(velocityFor({ ...base, forward: -1, turn: 0, mode: 'heading', yaw: 0 }).every((v) => !Object.is(v, -0)));
});

test('commands are renewed well within the default velocity timeout', () => {
  assert.ok(SEND_PERIOD_MS * 3 <= 500);
});

test('inspector parameters are NAME=VALUE pairs joined by &', () => {
  assert.deepEqual(parseParameters('frame=robot & spacing=1.5'), { frame: 'robot', spacing: '1.5' });
  assert.deepEqual(parseParameters(''), {});
  assert.deepEqual(parseParameters('near=(5 5 0)'), { near: '(5 5 0)' });
  assert.throws(() => parseParameters('frame'), /NAME=VALUE/);
});

test('services are grouped by the 5 m square they stand in', () => {
  assert.equal(areaOf([1, 2, 0]), 'x 0…5 m, y 0…5 m');
  assert.equal(areaOf([-0.5, 7]), 'x -5…0 m, y 5…10 m');
  assert.equal(areaOf(null), 'No location');
  assert.equal(areaOf([]), 'No location');
});

test('a property gets the widget of its .gui, else of its access and type, and a registered one wins', async () => {
  await import('../../gateway/console/js/builtin_widgets.js');
  const { registerWidget, widgetFor, widgetNames } = await import('../../gateway/console/js/widgets.js');
  const named = (prop) => widgetFor(prop).name;
  assert.equal(named({ name: 'speed', type: 'number', access: 'read-write', gui: 'slider' }), 'sliderWidget');
  assert.equal(named({ name: 'data', type: 'number', access: 'read', gui: 'plot' }), 'plotWidget');
  assert.equal(named({ name: 'led', type: 'boolean', access: 'read-write', gui: '' }), 'switchWidget');
  assert.equal(named({ name: 'x', type: 'vectors', access: 'read', gui: 'nosuch' }), 'listWidget');
  assert.equal(named({ name: 'odd', type: 'bytes', access: 'read', gui: '' }), 'bytesWidget');
  assert.equal(named({ name: 'behaviors.moveto', type: 'none', access: 'action', gui: 'button' }), 'buttonWidget');
  assert.equal(named({ name: 'find', type: 'names', access: 'query', gui: 'names' }), 'queryWidget');
  assert.equal(named({ name: 'patrol.diagram', type: 'text', access: 'read', gui: 'statechart' }), 'statechartWidget');
  // A property that cannot be read without a parameter (a storage service's file and its name)
  // is a form of its parameters; a parameter with a default, or an optional one, does not count.
  const name = { name: 'name', type: 'text', required: true, default: null };
  assert.equal(named({ name: 'file', type: 'text', access: 'read-write', gui: 'text', parameters: [name] }), 'addressedWidget');
  assert.equal(named({ name: 'file', type: 'text', access: 'read', gui: 'text', parameters: [name] }), 'addressedWidget');
  assert.equal(
    named({ name: 'file', type: 'text', access: 'read', gui: 'text', parameters: [{ ...name, default: 'a' }] }),
    'textWidget',
  );
  assert.equal(
    named({ name: 'info', type: 'marker', access: 'read', gui: 'text', parameters: [{ ...name, required: false }] }),
    'textWidget',
  );
  function cameraWidget() {
    return { element: null };
  }
  registerWidget('camera', cameraWidget);
  assert.equal(named({ name: 'frame', type: 'bytes', access: 'read', gui: 'camera' }), 'cameraWidget');
  registerWidget('pose', cameraWidget); // a registered widget replaces the built-in one
  assert.equal(named({ name: 'location', type: 'vector', access: 'read', gui: 'pose' }), 'cameraWidget');
  assert.ok(widgetNames().includes('camera'));
  assert.throws(() => registerWidget('bad name', cameraWidget), /1 to 64 letters/);
  assert.throws(() => registerWidget('x', 'not a function'), /must be a function/);
});
