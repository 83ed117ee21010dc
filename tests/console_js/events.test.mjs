// The page's one event stream: selectors, dispatch, reopening on a change, errors, backoff.
// EventSource and the timers are stand-ins driven by the test (node has neither a browser's
// EventSource nor a clock the test can step).
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { Backoff } from '../../gateway/console/js/backoff.js';
import {
  EventMux,
  MAX_SUBSCRIPTIONS,
  eventsUrl,
  namedSelectors,
  namesIn,
  selectorMatches,
  splitSelector,
} from '../../gateway/console/js/events.js';

class ManualTimers {
  constructor() {
    this.now = 0;
    this.pending = new Map();
    this.nextId = 1;
  }
  setTimeout(f, ms) {
    const id = this.nextId++;
    this.pending.set(id, { at: this.now + ms, f });
    return id;
  }
  clearTimeout(id) {
    this.pending.delete(id);
  }
  /** Run every timer due within `ms` from now, in time order. */
  advance(ms) {
    const end = this.now + ms;
    for (;;) {
      const due = [...this.pending].filter(([, t]) => t.at <= end).sort((a, b) => a[1].at - b[1].at)[0];
      if (!due) break;
      this.pending.delete(due[0]);
      this.now = due[1].at;
      due[1].f();
    }
    this.now = end;
  }
}

class StreamStandIn {
  static made = [];
  constructor(url) {
    this.url = url;
    this.readyState = 0;
    this.listeners = {};
    this.closed = false;
    StreamStandIn.made.push(this);
  }
  addEventListener(type, f) {
    (this.listeners[type] ??= []).push(f);
  }
  close() {
    this.closed = true;
    this.readyState = 2;
  }
  emit(type, data) {
    if (type === 'open') this.readyState = 1;
    for (const f of this.listeners[type] ?? []) f(data === undefined ? {} : { data: JSON.stringify(data) });
  }
  selectors() {
    return new URL(this.url, 'http://x').searchParams.getAll('sel');
  }
}

function mux(options = {}) {
  StreamStandIn.made = [];
  const timers = new ManualTimers();
  const states = [];
  const m = new EventMux({
    EventSourceImpl: StreamStandIn,
    fetchImpl: null,
    timers,
    clock: () => timers.now,
    debounceMs: 50,
    backoff: new Backoff({ initial: 500, max: 4000, random: () => 0.5 }),
    onState: (state, detail) => states.push([state, detail?.retryInSeconds ?? null]),
    ...options,
  });
  return { m, timers, states, last: () => StreamStandIn.made.at(-1) };
}

test('selectors split at the first slash and match one segment per star', () => {
  assert.deepEqual(splitSelector('swarm/robots.scout1.location'), ['swarm', 'robots.scout1.location']);
  assert.throws(() => splitSelector('location'), /SERVICE\/PATH/);
  assert.throws(() => splitSelector('/location'), /SERVICE\/PATH/);
  assert.ok(selectorMatches('*/location', 'scout1', 'location'));
  assert.ok(!selectorMatches('*/location', 'scout1', 'location.x'));
  assert.ok(selectorMatches('swarm/robots.*.location', 'swarm', 'robots.rover2.location'));
  assert.ok(!selectorMatches('swarm/robots.*.location', 'swarm', 'robots.rover2.sensors.location'));
  assert.ok(selectorMatches('scout1/*', 'scout1', 'speed'));
  assert.ok(!selectorMatches('scout1/*', 'scout2', 'speed'));
  assert.equal(eventsUrl(['b/y', 'a/*']), '/api/v1/events?sel=a%2F*&sel=b%2Fy');
});

test('one stream carries every subscription, and a burst of changes reopens it once', () => {
  const { m, timers, last } = mux();
  const seen = [];
  m.subscribe('*/location', { onValue: (e) => seen.push(['map', e.service]) });
  const stopSpeed = m.subscribe('scout1/speed', { onValue: (e) => seen.push(['speed', e.value]) });
  assert.equal(StreamStandIn.made.length, 0, 'debounced: nothing opened yet');
  timers.advance(50);
  assert.equal(StreamStandIn.made.length, 1);
  assert.deepEqual(last().selectors(), ['*/location', 'scout1/speed']);
  last().emit('open');
  assert.equal(m.state, 'open');
  last().emit('value', { service: 'scout1', path: 'location', value: '(0 0 0 0 0 0)' });
  last().emit('value', { service: 'scout1', path: 'speed', value: '0.5' });
  last().emit('value', { service: 'thermo1', path: 'data', value: '20' }); // nobody's
  assert.deepEqual(seen, [['map', 'scout1'], ['speed', '0.5']]);

  stopSpeed();
  m.subscribe('scout2/speed', {});
  m.subscribe('scout2/speed', {}); // a second subscriber of the same selector
  timers.advance(50);
  assert.equal(StreamStandIn.made.length, 2, 'one reopen for the whole burst');
  const [first, second] = StreamStandIn.made;
  assert.deepEqual(second.selectors(), ['*/location', 'scout2/speed']);
  // Make before break: the first stream delivers until the second is open, and the page stays live.
  assert.ok(!first.closed);
  assert.equal(m.state, 'open');
  first.emit('value', { service: 'scout2', path: 'location', value: '(1 0 0 0 0 0)' });
  assert.deepEqual(seen.at(-1), ['map', 'scout2']);
  second.emit('open');
  assert.ok(first.closed);
  first.emit('value', { service: 'scout3', path: 'location', value: '(1 0 0 0 0 0)' });
  assert.deepEqual(seen.at(-1), ['map', 'scout2'], 'a replaced stream is heard no more');
  second.emit('value', { service: 'scout1', path: 'speed', value: '0.7' });
  assert.equal(seen.length, 3, 'an unsubscribed handler hears nothing more');
});

test('a replacement that fails closes the stream it was replacing too', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  timers.advance(50);
  const first = last();
  first.emit('open');
  m.subscribe('b/y', {});
  timers.advance(50);
  const second = last();
  second.readyState = 2;
  second.emit('error'); // refused: no fetchImpl to ask why, so a plain retry after the backoff
  assert.ok(first.closed && second.closed);
  assert.equal(m.state, 'closed');
});

test('a subscription set that ends where it began does not reopen the stream', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  timers.advance(50);
  last().emit('open');
  const stop = m.subscribe('b/y', {});
  stop();
  timers.advance(50);
  assert.equal(StreamStandIn.made.length, 1);
});

test('a Listen error drops the selectors added since the last good snapshot, and the rest go on', () => {
  const { m, timers, last } = mux();
  const errors = [];
  m.subscribe('*/location', { onError: (e) => errors.push(['map', e.code]) });
  timers.advance(50);
  last().emit('open');
  last().emit('sync', {});
  m.subscribe('nosuch/thing', { onError: (e) => errors.push(['inspector', e.code]) });
  timers.advance(50);
  last().emit('error', { code: 'NOT_FOUND', message: 'no service nosuch' });
  assert.deepEqual(errors, [['inspector', 'NOT_FOUND']]);
  timers.advance(0);
  assert.deepEqual(last().selectors(), ['*/location'], 'reopened at once without the bad one');
  assert.ok(!m.subscriptions.has('nosuch/thing'));
});

test('an error with no new selector reaches everyone and the retry backs off', () => {
  const { m, timers, states, last } = mux();
  const errors = [];
  m.subscribe('scout1/speed', { onError: (e) => errors.push(e.code) });
  timers.advance(50);
  last().emit('open');
  last().emit('sync', {});
  last().emit('error', { code: 'UNAVAILABLE', message: 'gone' });
  assert.deepEqual(errors, ['UNAVAILABLE']);
  assert.deepEqual(states.at(-1), ['closed', 1]);
  const before = StreamStandIn.made.length;
  timers.advance(499);
  assert.equal(StreamStandIn.made.length, before, 'not before the backoff delay');
  timers.advance(1);
  assert.equal(StreamStandIn.made.length, before + 1);
});

test('repeated connection errors replace the browser retry with a growing backoff, reset by a sync', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  timers.advance(50);
  const delays = [];
  for (let i = 0; i < 4; i += 1) {
    const stream = last();
    stream.emit('error'); // the browser retries by itself ...
    stream.emit('error');
    stream.emit('error'); // ... until the third failure in a row
    assert.ok(stream.closed);
    const start = timers.now;
    while (last() === stream) timers.advance(100);
    delays.push(timers.now - start);
  }
  assert.deepEqual(delays, [500, 1000, 2000, 4000]);
  last().emit('open');
  last().emit('sync', {});
  assert.equal(m.backoff.attempts, 0);
});

test('a stream the browser gave up on is reopened after the backoff', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  timers.advance(50);
  const stream = last();
  stream.emit('open');
  stream.readyState = 2; // closed by the browser (an HTTP error on its own reconnect)
  stream.emit('error');
  timers.advance(500);
  assert.notEqual(last(), stream);
  assert.equal(m.state, 'connecting');
});

test('a stream that never opens is replaced by the watchdog', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  timers.advance(50);
  const stream = last();
  timers.advance(20000);
  assert.ok(stream.closed);
  timers.advance(500);
  assert.notEqual(last(), stream);
});

test('more selectors than the stream may name are covered by a wildcard, and the rest thrown away', () => {
  const { m, timers, last } = mux({ maxSelectors: 2 });
  const heard = [];
  m.subscribe('registry/revision', {});
  for (const robot of ['scout1', 'scout2', 'scout3']) {
    m.subscribe(`swarm/robots.${robot}.location`, { onValue: (e) => heard.push(e.path) });
  }
  timers.advance(100);
  assert.deepEqual(last().selectors(), ['registry/revision', 'swarm/robots.*.location']);
  last().emit('open');
  for (const robot of ['scout1', 'scout4']) {
    last().emit('value', { service: 'swarm', path: `robots.${robot}.location`, value: '(0 0)' });
  }
  assert.deepEqual(heard, ['robots.scout1.location'], 'scout4 is not subscribed to: its event is dropped');
  assert.deepEqual(m.stats().received, 2);
  assert.deepEqual(m.stats().unwanted, 1);
});

test('the number of subscriptions is bounded', () => {
  const { m } = mux();
  for (let i = 0; i < MAX_SUBSCRIPTIONS; i += 1) m.subscribe(`a/p${i}`, {});
  m.subscribe('a/p0', {}); // the same selector again costs nothing
  assert.throws(() => m.subscribe('a/z', {}), new RegExp(`follows ${MAX_SUBSCRIPTIONS} selectors already`));
});

test('a handler that throws does not stop the others', () => {
  const { m } = mux();
  const heard = [];
  const quiet = console.error;
  console.error = () => {};
  try {
    m.subscribe('a/x', { onValue: () => { throw new Error('broken widget'); } });
    m.subscribe('*/x', { onValue: (e) => heard.push(e.value) });
    m.dispatch({ service: 'a', path: 'x', value: '1' });
  } finally {
    console.error = quiet;
  }
  assert.deepEqual(heard, ['1']);
});

test('a suspended page keeps its subscriptions and follows them all again when shown', () => {
  const { m, timers, last } = mux();
  m.subscribe('a/x', {});
  m.subscribe('b/y', {});
  timers.advance(50);
  const before = last();
  m.suspend();
  assert.ok(before.closed);
  assert.equal(m.state, 'closed');
  timers.advance(60000);
  assert.equal(last(), before, 'nothing reopens while suspended');
  m.reconnect();
  timers.advance(0);
  assert.notEqual(last(), before);
  assert.deepEqual(last().selectors(), ['a/x', 'b/y']);
});

test('a subscriber joining a selector the stream follows gets its latest values at once', () => {
  const { m, timers, last } = mux();
  const first = [];
  m.subscribe('scout1/speed', { onValue: (e) => first.push(e.value) });
  timers.advance(50);
  last().emit('open');
  last().emit('value', { service: 'scout1', path: 'speed', value: '0.5' });
  last().emit('sync', {});
  last().emit('value', { service: 'scout1', path: 'speed', value: '0.8' });
  const joined = [];
  let synced = false;
  m.subscribe('scout1/speed', { onValue: (e) => joined.push(e.value), onSync: () => (synced = true) });
  timers.advance(0);
  assert.equal(StreamStandIn.made.length, 1, 'no reopen: the selector was followed already');
  assert.deepEqual(joined, ['0.8'], 'the latest value, not the whole history');
  assert.ok(synced);
  assert.deepEqual(first, ['0.5', '0.8'], 'the first subscriber hears nothing twice');
});

test('the latest values are bounded and forget what nobody follows', () => {
  const { m, timers, last } = mux();
  const stop = m.subscribe('*/x', {});
  m.subscribe('keep/y', {});
  timers.advance(50);
  last().emit('open');
  for (let i = 0; i < 5000; i += 1) last().emit('value', { service: `s${i}`, path: 'x', value: String(i) });
  last().emit('value', { service: 'keep', path: 'y', value: 'kept' });
  assert.ok(m._latest.size <= 4096);
  stop();
  timers.advance(50);
  assert.deepEqual([...m._latest.values()].map((e) => e.value), ['kept']);
});

test('the names an error message points at', () => {
  const unplugged = "device rover1 at tcp://127.0.0.1:44061 is not connected (cannot connect: [Errno 111])";
  assert.ok(namesIn(unplugged).has('rover1'));
  assert.ok(namesIn("service 'rover1' is down: it missed 3 liveness checks").has('rover1'));
  const selectors = ['rover1/speed', 'scout1/speed', 'swarm/robots.rover1.location', '*/location'];
  assert.deepEqual(namedSelectors(unplugged, selectors), ['rover1/speed', 'swarm/robots.rover1.location']);
  assert.deepEqual(namedSelectors('the gateway is shutting down', selectors), []);
  // rover1 is named by no selector but the wildcard service reached it.
  assert.deepEqual(namedSelectors(unplugged, ['scout1/speed', '*/location']), ['*/location']);
});

test('a service that goes away is left out for a growing while, and the rest of the page stays live', () => {
  const { m, timers, last } = mux();
  const errors = [];
  m.subscribe('scout1/speed', { onError: (e) => errors.push(['scout1', e.code]) });
  m.subscribe('rover1/speed', { onError: (e) => errors.push(['rover1', e.code]) });
  timers.advance(50);
  last().emit('open');
  last().emit('sync', {});
  const gone = { code: 'UNAVAILABLE', message: "service 'rover1' is down: it missed 3 liveness checks" };
  last().emit('error', gone);
  assert.deepEqual(errors, [['rover1', 'UNAVAILABLE']], 'only the subscribers of the service that went away hear it');
  timers.advance(0);
  assert.deepEqual(last().selectors(), ['scout1/speed']);
  last().emit('open');
  assert.equal(m.state, 'open');
  const reopened = StreamStandIn.made.length;
  timers.advance(4999);
  assert.equal(StreamStandIn.made.length, reopened, 'left out for 5 s');
  timers.advance(1);
  assert.deepEqual(last().selectors(), ['rover1/speed', 'scout1/speed'], 'then tried again');
  last().emit('error', gone); // still away: twice as long
  timers.advance(0);
  last().emit('open');
  const again = StreamStandIn.made.length;
  timers.advance(9999);
  assert.equal(StreamStandIn.made.length, again);
  timers.advance(1);
  assert.deepEqual(last().selectors(), ['rover1/speed', 'scout1/speed']);
  last().emit('open');
  last().emit('sync', {}); // back: a later failure starts from 5 s again
  assert.equal(m._quarantine.size, 0);
  assert.equal(m.subscriptions.size, 2, 'nobody lost a subscription');
});

test('a gateway that allows fewer selectors says so, and the page covers them with fewer', () => {
  let told = null;
  const { m, timers, last } = mux({ onLimit: (n) => (told = n) });
  m.subscribe('a/x', {});
  timers.advance(50);
  last().emit('open');
  last().emit('sync', {});
  const refused = [];
  m.subscribe('a/y', { onError: (e) => refused.push(e.code) });
  m.subscribe('a/z', { onError: (e) => refused.push(e.code) });
  timers.advance(50);
  last().emit('error', { code: 'RESOURCE_EXHAUSTED', message: 'a Listen may have at most 2 selectors, this one has 3' });
  assert.equal(m.maxSelectors, 2);
  assert.equal(told, 2);
  assert.deepEqual(refused, [], 'nobody lost a subscription');
  timers.advance(0);
  assert.deepEqual(last().selectors(), ['a/*']);
  assert.equal(m.subscriptions.size, 3);
});

test('a property the page reads on its own route is never covered by a wildcard', () => {
  const { m, timers, last } = mux({ maxSelectors: 2 });
  m.avoid('camera1/frame');
  for (const path of ['data', 'rate_hz', 'location']) m.subscribe(`camera1/${path}`, {});
  m.subscribe('registry/revision', {});
  timers.advance(100);
  const named = last().selectors();
  assert.ok(!named.includes('camera1/*'), `camera1/* would carry its frames: ${named}`);
});

test('a subscription the limit cannot cover hears so and is not dropped', () => {
  const { m, timers, last } = mux({ maxSelectors: 1 });
  const errors = [];
  m.subscribe('a/x', {});
  m.subscribe('b/y.z', { onError: (e, detail) => errors.push([e.code, detail.dropped]) });
  timers.advance(100);
  assert.equal(last().selectors().length, 1);
  assert.deepEqual(errors, [['RESOURCE_EXHAUSTED', false]]);
  assert.equal(m.subscriptions.size, 2);
});

test('of many new selectors only the one the error names is left out', () => {
  const { m, timers, last } = mux();
  m.subscribe('registry/revision', {});
  timers.advance(50);
  last().emit('open');
  last().emit('sync', {});
  const errors = [];
  for (const path of ['location', 'robots.scout1', 'robots.rover1', 'robots.scout1.location']) {
    m.subscribe(`swarm/${path}`, { onError: (e) => errors.push([path, e.code]) });
  }
  timers.advance(50);
  last().emit('error', { code: 'UNAVAILABLE', message: 'device rover1 at tcp://127.0.0.1:1 is not connected' });
  assert.deepEqual(errors, [['robots.rover1', 'UNAVAILABLE']]);
  timers.advance(0);
  assert.deepEqual(last().selectors(), [
    'registry/revision',
    'swarm/location',
    'swarm/robots.scout1',
    'swarm/robots.scout1.location',
  ]);
  assert.ok(m.subscriptions.has('swarm/robots.rover1'), 'kept, to be tried again');
});

test('a property that does not exist is dropped by the path its error names', () => {
  const { m, timers, last } = mux();
  const errors = [];
  m.subscribe('swarm/sensors', { onError: (e) => errors.push(['sensors', e.code]) });
  m.subscribe('swarm/sensors.battery', { onError: (e) => errors.push(['battery', e.code]) });
  timers.advance(50);
  last().emit('error', { code: 'NOT_FOUND', message: 'unknown property `sensors.battery`: `sensors` has no `battery`' });
  assert.deepEqual(errors, [['battery', 'NOT_FOUND']]);
  assert.ok(!m.subscriptions.has('swarm/sensors.battery'));
  assert.ok(m.subscriptions.has('swarm/sensors'));
});

test('a subscription the synced stream already covers hears its latest value and the sync at once', () => {
  const { m, timers, last } = mux({ maxSelectors: 1 });
  m.subscribe('swarm/robots.scout1.location', {});
  m.subscribe('swarm/robots.scout2.location', {});
  timers.advance(100);
  assert.deepEqual(last().selectors(), ['swarm/robots.*.location']);
  last().emit('open');
  last().emit('value', { service: 'swarm', path: 'robots.scout3.location', value: '(3 0)' });
  last().emit('sync', {});
  const heard = [];
  m.subscribe('swarm/robots.scout3.location', { onValue: (e) => heard.push(e.value), onSync: () => heard.push('sync') });
  const streams = StreamStandIn.made.length;
  timers.advance(100);
  assert.deepEqual(heard, ['(3 0)', 'sync']);
  assert.equal(StreamStandIn.made.length, streams, 'the same cover: no new stream');
  assert.equal(m.stats().unwanted, 1, 'scout3 was nobody\'s when it arrived');
});
