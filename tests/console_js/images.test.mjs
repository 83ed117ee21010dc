// Binary values in the console: the multipart reader of the live image route, the stream that
// feeds an image widget (with a stand-in fetch), which widget a binary property gets, and how a
// binary value shows as text.
import assert from 'node:assert/strict';
import { test } from 'node:test';

import { FrameStream, frameCaption, rawUrl, streamUrl, uploadType } from '../../gateway/console/js/image_widget.js';
import {
  MultipartError,
  MultipartReader,
  boundaryOf,
  formatSize,
  isImageType,
} from '../../gateway/console/js/multipart.js';
import { base64Size, shownValue } from '../../gateway/console/js/values.js';

const enc = new TextEncoder();

function concat(...chunks) {
  const all = new Uint8Array(chunks.reduce((n, c) => n + c.length, 0));
  let at = 0;
  for (const c of chunks) {
    all.set(c, at);
    at += c.length;
  }
  return all;
}

/** A part as the gateway writes it. */
function part(boundary, type, body, sequence) {
  const head = `--${boundary}\r\nContent-Type: ${type}\r\nContent-Length: ${body.length}\r\nX-Sequence: ${sequence}\r\n\r\n`;
  return concat(enc.encode(head), body, enc.encode('\r\n'));
}

/** Bytes 0..255 and some CRLF and boundary-like runs: what a binary frame may hold. */
function frameBytes(seed, length) {
  const bytes = new Uint8Array(length);
  for (let i = 0; i < length; i += 1) bytes[i] = (i * 31 + seed * 7) & 0xff;
  bytes.set(enc.encode('\r\n--psframe\r\n'), Math.min(5, length - 13));
  return bytes;
}

test('the boundary is read from the content type, quoted or not', () => {
  assert.equal(boundaryOf('multipart/x-mixed-replace; boundary=psframe'), 'psframe');
  assert.equal(boundaryOf('multipart/x-mixed-replace;boundary="a b"'), 'a b');
  assert.equal(boundaryOf('image/png'), null);
  assert.equal(boundaryOf(null), null);
});

test('parts come out byte for byte however the body is cut, and the closing boundary ends it', () => {
  const frames = [frameBytes(1, 300), frameBytes(2, 17), new Uint8Array(0), frameBytes(3, 1000)];
  const body = concat(
    ...frames.map((f, i) => part('psframe', 'image/png', f, i + 1)),
    enc.encode('--psframe--\r\n'),
    enc.encode('ignored after the end'),
  );
  for (const size of [1, 2, 7, 64, body.length]) {
    const reader = new MultipartReader('psframe');
    const got = [];
    for (let at = 0; at < body.length; at += size) got.push(...reader.push(body.subarray(at, at + size)));
    assert.equal(got.length, frames.length, `cut every ${size} bytes`);
    got.forEach((p, i) => {
      assert.deepEqual(p.body, frames[i]);
      assert.equal(p.type, 'image/png');
      assert.equal(p.headers['x-sequence'], String(i + 1));
    });
    assert.ok(reader.done);
  }
});

test('a part without Content-Length ends at the next boundary (another server\'s MJPEG)', () => {
  const body = enc.encode(
    'preamble\r\n--b\r\nContent-Type: image/jpeg\r\n\r\nAAAA\r\n--b\r\nContent-Type: image/jpeg\r\n\r\nBB\r\n--b--',
  );
  const reader = new MultipartReader('b');
  const parts = reader.push(body);
  assert.deepEqual(
    parts.map((p) => new TextDecoder().decode(p.body)),
    ['AAAA', 'BB'],
  );
  assert.equal(parts[0].type, 'image/jpeg');
  assert.ok(reader.done);
});

test('a part or its headers over the bounds is an error, never a growing buffer', () => {
  const big = new MultipartReader('b', { maxPart: 10 });
  assert.throws(() => big.push(enc.encode('--b\r\nContent-Length: 11\r\n\r\n')), MultipartError);
  const open = new MultipartReader('b', { maxPart: 10 });
  assert.throws(() => open.push(enc.encode(`--b\r\n\r\n${'x'.repeat(20)}`)), /exceeds 10/);
  const headers = new MultipartReader('b', { maxHeaders: 16 });
  assert.throws(() => headers.push(enc.encode(`--b\r\nX-Long: ${'y'.repeat(40)}`)), /headers exceed/);
  assert.throws(() => new MultipartReader('b').push(enc.encode('--b\r\nContent-Length: -1\r\n\r\n')), /not a size/);
  assert.throws(() => new MultipartReader(''), MultipartError);
});

test('sizes, captions, media types and URLs', () => {
  assert.equal(formatSize(512), '512 B');
  assert.equal(formatSize(2048), '2.0 KB');
  assert.equal(formatSize(3 * 1024 * 1024), '3.00 MB');
  assert.ok(isImageType('image/png'));
  assert.ok(isImageType('image/jpeg; quality=80'));
  assert.ok(!isImageType('application/x-npy'));
  assert.ok(!isImageType(''));
  assert.equal(frameCaption({ frames: 3, width: 64, height: 48, bytes: 100, type: 'image/png' }), 'frame 3 · 64×48 · 100 B · image/png');
  assert.equal(frameCaption({ frames: 1, width: 0, height: 0, bytes: 2048, type: 'image/jpeg' }), 'frame 1 · 2.0 KB · image/jpeg');
  assert.equal(streamUrl('cam 1', 'frame'), '/api/v1/services/cam%201/properties/frame/stream');
  assert.equal(rawUrl('env', 'grid.temperature'), '/api/v1/services/env/properties/grid.temperature?raw=1');
});

test('a binary value shows as its size and media type', () => {
  assert.equal(base64Size(''), 0);
  assert.equal(base64Size('AA=='), 1);
  assert.equal(base64Size('AAA='), 2);
  assert.equal(base64Size('AAAA'), 3);
  assert.equal(shownValue({ data: 'iVBORw0KGgo=', media_type: 'image/png' }), '[8 bytes, image/png]');
  assert.equal(shownValue({ data: '' }), '[0 bytes, application/octet-stream]');
  assert.equal(shownValue({ value: '(1 2)' }), '(1 2)');
});

/** A stand-in fetch answering each call with the next of `answers` (a Response or an Error). */
function fakeFetch(answers) {
  const calls = [];
  const impl = async (url, init) => {
    calls.push({ url, init });
    const next = answers.shift();
    if (next instanceof Error) throw next;
    if (next === undefined) throw new Error('no more answers');
    return next;
  };
  return { impl, calls };
}

function streamed(chunks, { status = 200, type = 'multipart/x-mixed-replace; boundary=psframe' } = {}) {
  const body = new ReadableStream({
    start(controller) {
      for (const c of chunks) controller.enqueue(c);
      controller.close();
    },
  });
  return new Response(body, { status, headers: { 'Content-Type': type } });
}

test('the frame stream hands over each frame, and ends when the gateway closes the body', async () => {
  const frames = [frameBytes(4, 50), frameBytes(5, 60)];
  const body = concat(...frames.map((f, i) => part('psframe', 'image/png', f, i + 1)), enc.encode('--psframe--\r\n'));
  const { impl, calls } = fakeFetch([streamed([body.subarray(0, 33), body.subarray(33)])]);
  const got = [];
  const states = [];
  const stream = new FrameStream('/s', { onFrame: (p) => got.push(p.body), onState: (s) => states.push(s), fetchImpl: impl });
  assert.equal(await stream.start().done, 'ended');
  assert.deepEqual(got, frames);
  assert.deepEqual(states, ['live', 'ended']);
  assert.equal(stream.frames, 2);
  assert.equal(calls[0].init.headers.Accept, 'multipart/x-mixed-replace');
});

test('a dropped connection is tried again after a backoff; a refusal is final', async () => {
  const frame = frameBytes(6, 40);
  const sleeps = [];
  const { impl, calls } = fakeFetch([
    new TypeError('connection refused'),
    streamed([part('psframe', 'image/png', frame, 1)]), // cut off: no closing boundary
    streamed([enc.encode('--psframe--')]),
  ]);
  const states = [];
  const got = [];
  const stream = new FrameStream('/s', {
    onFrame: (p) => got.push(p.body),
    onState: (s) => states.push(s),
    fetchImpl: impl,
    sleep: async (ms) => sleeps.push(ms),
  });
  assert.equal(await stream.start().done, 'ended');
  assert.equal(calls.length, 3);
  assert.equal(sleeps.length, 2);
  assert.deepEqual(got, [frame]);
  assert.deepEqual(states, ['retrying', 'live', 'retrying', 'live', 'ended']);

  const error = { error: { code: 'INVALID_ARGUMENT', message: 'location is not a binary property' } };
  const refused = fakeFetch([new Response(JSON.stringify(error), { status: 400, headers: { 'Content-Type': 'application/json' } })]);
  const failures = [];
  const final = new FrameStream('/s', {
    onFrame: () => assert.fail('no frame'),
    onState: (s, e) => failures.push([s, e]),
    fetchImpl: refused.impl,
  });
  assert.equal(await final.start().done, 'failed');
  assert.deepEqual(failures, [['failed', { code: 'INVALID_ARGUMENT', message: 'location is not a binary property' }]]);
});

test('stop() ends a stream for good', async () => {
  let release;
  const hanging = new ReadableStream({
    start(controller) {
      controller.enqueue(enc.encode('--psframe\r\n'));
      release = () => controller.error(new DOMException('aborted', 'AbortError'));
    },
  });
  const { impl } = fakeFetch([new Response(hanging, { headers: { 'Content-Type': 'multipart/x-mixed-replace; boundary=psframe' } })]);
  const stream = new FrameStream('/s', { onFrame: () => {}, fetchImpl: impl, sleep: async () => assert.fail('no retry') });
  stream.start();
  await new Promise((resolve) => setTimeout(resolve, 10));
  stream.stop();
  release();
  assert.equal(await stream.done, 'stopped');
});

test('a binary property gets the image widget by media type or gui, other bytes the bytes widget', async () => {
  await import('../../gateway/console/js/builtin_widgets.js');
  const { followedOnStream, mediaWidgetFor, registerMediaWidget, widgetFor } = await import('../../gateway/console/js/widgets.js');
  const named = (prop) => widgetFor(prop).name;
  assert.equal(named({ name: 'frame', type: 'bytes', access: 'read', gui: '', media_type: 'image/jpeg' }), 'imageWidget');
  assert.equal(named({ name: 'grid.temperature.image', type: 'bytes', access: 'read', gui: '', media_type: 'image/png' }), 'imageWidget');
  assert.equal(named({ name: 'frame', type: 'bytes', access: 'read', gui: 'camera', media_type: '' }), 'imageWidget');
  assert.equal(named({ name: 'snapshot', type: 'bytes', access: 'read', gui: 'image' }), 'imageWidget');
  assert.equal(named({ name: 'grid.temperature', type: 'bytes', access: 'read', gui: '', media_type: 'application/x-npy' }), 'bytesWidget');
  // A text property whose gui is not an image keeps its widget whatever else it says.
  assert.equal(named({ name: 'note', type: 'text', access: 'read-write', gui: 'text', media_type: 'image/png' }), 'textWidget');
  assert.equal(mediaWidgetFor('IMAGE/PNG; x=1').name, 'imageWidget');
  assert.equal(mediaWidgetFor('application/x-npy'), undefined);
  assert.equal(mediaWidgetFor(''), undefined);
  function npyWidget() {
    return { element: null };
  }
  registerMediaWidget('application/x-npy', npyWidget);
  assert.equal(named({ name: 'grid.t', type: 'bytes', access: 'read', gui: '', media_type: 'application/x-npy' }), 'npyWidget');
  assert.throws(() => registerMediaWidget('png', npyWidget), /TYPE\/SUBTYPE/);
  assert.ok(!followedOnStream({ name: 'frame', type: 'bytes' }));
  assert.ok(followedOnStream({ name: 'location', type: 'vector' }));
});

test('a file is sent with the property\'s media type when it has that type, else as octet-stream', () => {
  assert.equal(uploadType({ media_type: 'image/png' }, 'image/png'), 'image/png');
  assert.equal(uploadType({ media_type: 'image/png; x=1' }, 'IMAGE/PNG'), 'image/png');
  assert.equal(uploadType({ media_type: 'image/png' }, 'image/jpeg'), 'application/octet-stream');
  assert.equal(uploadType({ media_type: '' }, ''), 'application/octet-stream');
  assert.equal(uploadType({}, 'image/png'), 'application/octet-stream');
});
