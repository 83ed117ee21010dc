// Binary properties: a live image (`image/*` media type, or `.gui` `image` / `camera`) fed by the
// gateway's stream route, and a plain widget for other bytes (a numpy grid) with a link to the raw
// value. Neither follows its property on the page's event stream: a frame is read once, as bytes,
// on its own connection, never as base64 text through the shared stream.

import { API_BASE, setPropertyBytes, token } from './api.js';
import { Backoff } from './backoff.js';
import { MultipartReader, boundaryOf, formatSize, isImageType } from './multipart.js';

/** "/api/v1/services/cam1/properties/frame/stream": the live multipart stream of a property. */
export function streamUrl(service, path) {
  return `${API_BASE}/services/${encodeURIComponent(service)}/properties/${encodeURIComponent(path)}/stream`;
}

/** "/api/v1/services/env/properties/grid.temperature?raw=1": the value as its own bytes. */
export function rawUrl(service, path) {
  return `${API_BASE}/services/${encodeURIComponent(service)}/properties/${encodeURIComponent(path)}?raw=1`;
}

/** Pictures narrower than this many pixels are drawn larger, pixel for pixel (class `small`). */
export const SMALL_WIDTH = 160;

/** HTTP statuses after which trying again is pointless (the request itself is wrong or refused). */
const FINAL_STATUSES = new Set([400, 401, 403, 404, 405, 413]);

/**
 * One live stream of parts: `onFrame(part)` for each, `onState(state, detail)` with `live`,
 * `retrying` (a dropped connection; tried again after a backoff), `ended` (the property went
 * away: the gateway closed the body) or `failed` (an error answer that another try would not
 * change: {code, message}). `stop()` ends it for good.
 */
export class FrameStream {
  constructor(url, { onFrame, onState = () => {}, fetchImpl = (...a) => fetch(...a), backoff = new Backoff(), sleep } = {}) {
    Object.assign(this, { url, onFrame, onState, fetchImpl, backoff });
    this.sleep = sleep ?? ((ms) => new Promise((resolve) => setTimeout(resolve, ms)));
    this.controller = null;
    this.stopped = false;
    this.frames = 0;
  }

  start() {
    this.done = this._run();
    return this;
  }

  stop() {
    this.stopped = true;
    this.controller?.abort();
  }

  async _run() {
    while (!this.stopped) {
      const outcome = await this._once();
      if (outcome === 'ended' || outcome === 'failed' || this.stopped) return outcome;
      this.onState('retrying');
      await this.sleep(this.backoff.next());
    }
    return 'stopped';
  }

  async _once() {
    this.controller = new AbortController();
    const headers = { Accept: 'multipart/x-mixed-replace' };
    const bearer = token();
    if (bearer) headers.Authorization = `Bearer ${bearer}`;
    try {
      const response = await this.fetchImpl(this.url, { headers, signal: this.controller.signal, credentials: 'same-origin' });
      if (!response.ok) {
        const error = await errorBody(response);
        if (FINAL_STATUSES.has(response.status)) {
          this.onState('failed', error);
          return 'failed';
        }
        return 'retry';
      }
      const boundary = boundaryOf(response.headers.get('content-type'));
      if (!boundary) {
        this.onState('failed', { code: 'INTERNAL', message: `not a multipart answer: ${response.headers.get('content-type')}` });
        return 'failed';
      }
      const parser = new MultipartReader(boundary);
      const reader = response.body.getReader();
      this.onState('live');
      for (;;) {
        const { value, done } = await reader.read();
        if (done) return parser.done ? 'ended' : 'retry';
        for (const part of parser.push(value)) {
          this.frames += 1;
          this.backoff.reset(); // a frame arrived: the connection works
          this.onFrame(part);
        }
        if (parser.done) {
          reader.cancel().catch(() => {});
          this.onState('ended');
          return 'ended';
        }
      }
    } catch (e) {
      if (this.stopped) return 'stopped';
      if (e?.name === 'MultipartError') {
        this.onState('failed', { code: 'DATA_LOSS', message: e.message });
        return 'failed';
      }
      return 'retry';
    }
  }
}

async function errorBody(response) {
  try {
    const body = await response.json();
    if (body?.error?.code) return { code: body.error.code, message: String(body.error.message ?? '') };
  } catch {
    // not JSON: named by its status
  }
  return { code: 'UNKNOWN', message: `HTTP ${response.status}` };
}

/** The caption under a live image: "frame 12 · 64×48 · 1.2 KB · image/png". */
export function frameCaption({ frames, width, height, bytes, type }) {
  const parts = [`frame ${frames}`];
  if (width && height) parts.push(`${width}×${height}`);
  parts.push(formatSize(bytes), type);
  return parts.join(' · ');
}

/**
 * The live image of a binary property: an `<img>` whose source is each new part as a blob URL
 * (the previous one is released at once, so a long-running view holds one frame), a caption with
 * the frame count, pixel size and bytes, and `data-frames` / `data-bytes` for scripts and tests.
 */
export function imageWidget(prop, ctx) {
  const img = ctx.h('img', { class: 'live-image', alt: `${ctx.service} ${prop.name}` });
  const caption = ctx.h('div', { class: 'image-caption muted' }, 'waiting for the first frame…');
  const element = ctx.h('figure', { class: 'image-view', dataset: { frames: '0', state: 'connecting' } }, img, caption);
  let current = null;
  let last = { frames: 0, bytes: 0, type: '' };
  const show = () => {
    caption.textContent = frameCaption({ ...last, width: img.naturalWidth, height: img.naturalHeight });
    // A small picture (a grid layer's heat map, a cell a pixel) is drawn larger, cells kept sharp.
    img.classList.toggle('small', img.naturalWidth > 0 && img.naturalWidth < SMALL_WIDTH);
  };
  img.addEventListener('load', show);
  const stream = new FrameStream(streamUrl(ctx.service, prop.name), {
    onFrame(part) {
      const url = URL.createObjectURL(new Blob([part.body], { type: part.type }));
      img.src = url;
      if (current) URL.revokeObjectURL(current);
      current = url;
      last = { frames: stream.frames, bytes: part.body.length, type: part.type };
      element.dataset.frames = String(stream.frames);
      element.dataset.bytes = String(part.body.length);
      show();
    },
    onState(state, error) {
      element.dataset.state = state;
      if (state === 'failed') ctx.showError(error);
      else if (state === 'ended') caption.textContent = `${caption.textContent} · ended`;
      else if (state === 'live') ctx.clearError();
    },
  }).start();
  if (ctx.writable) element.append(uploader(prop, ctx));
  return {
    element,
    hidesValue: true,
    dispose() {
      stream.stop();
      if (current) URL.revokeObjectURL(current);
      current = null;
    },
  };
}

/**
 * The content type a file is sent with to `prop`: the property's media type when the file says it
 * is of that type, else application/octet-stream (the gateway refuses any other label).
 */
export function uploadType(prop, fileType) {
  const own = String(prop.media_type ?? '').split(';')[0].trim().toLowerCase();
  return own && String(fileType ?? '').toLowerCase() === own ? own : 'application/octet-stream';
}

/** A file input that sets a writable binary property to the chosen file's bytes. */
function uploader(prop, ctx) {
  const input = ctx.h('input', {
    type: 'file',
    'aria-label': `a file for ${prop.name}`,
    accept: prop.media_type || null,
    dataset: { action: 'upload' },
  });
  input.addEventListener('change', async () => {
    const file = input.files?.[0];
    if (!file) return;
    ctx.clearError();
    if (prop.max_size && file.size > prop.max_size) {
      ctx.showError({ code: 'RESOURCE_EXHAUSTED', message: `${file.name} is ${formatSize(file.size)}, more than ${formatSize(prop.max_size)}` });
      return;
    }
    try {
      await setPropertyBytes(ctx.service, prop.name, file, uploadType(prop, file.type));
    } catch (e) {
      ctx.showError(e);
    } finally {
      input.value = '';
    }
  });
  return ctx.h('label', { class: 'upload' }, 'Set from a file: ', input);
}

/** Any other binary property: what it holds and a link to its raw bytes (not followed live). */
export function bytesWidget(prop, ctx) {
  if (isImageType(prop.media_type)) return imageWidget(prop, ctx);
  const what = prop.media_type || 'application/octet-stream';
  const limit = prop.max_size ? ` · at most ${formatSize(prop.max_size)}` : '';
  const link = ctx.h('a', { href: rawUrl(ctx.service, prop.name), target: '_blank', rel: 'noopener', dataset: { action: 'raw' } }, 'raw bytes');
  const element = ctx.h('div', { class: 'bytes-view muted' }, `${what}${limit} · `, link);
  if (ctx.writable) element.append(uploader(prop, ctx));
  return { element, hidesValue: true };
}
