// Stop all (js/teleop.js): which services it reaches, how many requests at once, and its report.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { STOP_ALL_AT_ONCE, drivableNames, stopAllReport, stopEvery } from '../../gateway/console/js/teleop.js';

test('Stop all reaches every robot and group, and nothing else', () => {
  const services = [
    { name: 'scout10', type: 'mobile_robot' },
    { name: 'thermo1', type: 'sensor' },
    { name: 'swarm', type: 'group' },
    { name: 'scout2', type: 'mobile_robot' },
    { name: 'registry', type: 'registry' },
  ];
  assert.deepEqual(drivableNames(services), ['scout2', 'scout10', 'swarm']);
});

test('every robot gets zeros, a few at a time, and the report says who did not answer', async () => {
  const names = Array.from({ length: 40 }, (_, i) => `scout${i + 1}`);
  let inFlight = 0;
  let most = 0;
  const sent = [];
  const setVelocity = async (name, text) => {
    inFlight += 1;
    most = Math.max(most, inFlight);
    await new Promise((resolve) => setTimeout(resolve, 1));
    inFlight -= 1;
    sent.push([name, text]);
    if (name === 'scout7') throw Object.assign(new Error('device scout7 is not connected'), { code: 'UNAVAILABLE' });
  };
  const result = await stopEvery(names, { setVelocity });
  assert.equal(sent.length, 40);
  assert.ok(sent.every(([, text]) => text === '(0 0 0 0 0 0)'), 'zeros only');
  assert.ok(most <= STOP_ALL_AT_ONCE, `${most} requests at once`);
  assert.equal(result.stopped.length, 39);
  assert.deepEqual(result.stopped.slice(0, 7), ['scout1', 'scout2', 'scout3', 'scout4', 'scout5', 'scout6', 'scout8']);
  assert.deepEqual(result.failed.map((f) => f.name), ['scout7']);
  const text = stopAllReport(result);
  assert.match(text, /^Stop all: 39 of 40 stopped; stopped scout1, scout2/);
  assert.match(text, /no answer from scout7 \(UNAVAILABLE: device scout7 is not connected\)$/);
});

test('Stop all of nothing sends nothing', async () => {
  const result = await stopEvery([], { setVelocity: () => assert.fail('nothing to send') });
  assert.deepEqual(result, { stopped: [], failed: [] });
});
