// Binary properties: a live image (`image/*` media type, or `.gui` `image` / `camera`) fed by the
// gateway's stream route, and a plain widget for other bytes (a numpy grid) with a link to the raw
// value. Neither follows its property on the page's event stream: a frame is read once, as bytes,
// on its own connection, never as base64 text through the shared stream.

import { API_BASE, setPropertyBytes, token } from './api.js';
import { Backoff } from './backoff.js';
import { MultipartReader, boundaryOf, formatSize, isImageType } from './multipart.js';
import { decimalsFor, formatMeasure, niceCeil, parseList } from './values.js';

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
  // A grid layer's heat map (`grid.LAYER.image` beside `grid.LAYER.info`) gets axes, a scale and
  // a colour legend, drawn from the info of the layer, read again after each frame.
  const heat = heatMapBase(prop.name) && ctx.readPath ? heatMapLegend(ctx, img, `${heatMapBase(prop.name)}.info`) : null;
  const element = ctx.h(
    'figure',
    { class: 'image-view', dataset: { frames: '0', state: 'connecting' } },
    heat ? heat.element : img,
    caption,
  );
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
      heat?.frameShown();
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

// -- a grid layer's heat map: axes, scale and colour legend -------------------------------------

/** The colour ramp of the gateway's heat maps, low to high (services/apps/environment/heatmap.py). */
export const HEAT_RAMP = [
  [48, 18, 160],
  [30, 150, 220],
  [60, 190, 90],
  [245, 210, 40],
  [200, 30, 30],
];
/** Labels an axis carries at most. */
const AXIS_LABELS = 5;

/** "grid.temperature" for "grid.temperature.image" (a grid layer's heat map), else null. */
export function heatMapBase(path) {
  const m = /^(grid\.[^.]+)\.image$/.exec(String(path));
  return m ? m[1] : null;
}

/**
 * A layer's `grid.LAYER.info` ("((kind mean) (origin (-10 -10)) (cell 0.5) (shape (40 40))
 * (min 20.5) (max 27.7) … (unit degC))") as {origin: [x0, y0], cell, rows, cols, min, max, unit};
 * min and max are null while nothing is filled, unit "" for none ("-"). Null for any other text.
 */
export function heatMapInfo(text) {
  let items;
  try {
    items = parseList(String(text));
  } catch {
    return null;
  }
  const fields = new Map();
  for (const item of items) if (Array.isArray(item) && item.length === 2 && typeof item[0] === 'string') fields.set(item[0], item[1]);
  const number = (x) => (typeof x === 'string' && x.trim() !== '' && Number.isFinite(Number(x)) ? Number(x) : null);
  const pair = (x) => (Array.isArray(x) && x.length === 2 ? x.map(number) : [null, null]);
  const origin = pair(fields.get('origin'));
  const [rows, cols] = pair(fields.get('shape'));
  const cell = number(fields.get('cell'));
  if (origin.includes(null) || !(rows > 0) || !(cols > 0) || !(cell > 0)) return null;
  const unit = typeof fields.get('unit') === 'string' && fields.get('unit') !== '-' ? fields.get('unit') : '';
  return { origin, cell, rows, cols, min: number(fields.get('min')), max: number(fields.get('max')), unit };
}

/** Round coordinates between lo and hi for an axis: at most `count` of them, 1, 2 or 5 apart. */
export function axisTicks(lo, hi, count = AXIS_LABELS) {
  if (!(hi > lo)) return [lo];
  const step = niceCeil((hi - lo) / Math.max(1, count - 1));
  const ticks = [];
  for (let k = Math.ceil(lo / step - 1e-9); k * step <= hi + step * 1e-9; k += 1) {
    ticks.push(Number((k * step).toPrecision(12)));
  }
  return ticks;
}

/** The length of a scale bar for a picture `width` metres wide: the round length at most a quarter of it. */
export function scaleLength(width) {
  const quarter = width / 4;
  if (!(quarter > 0) || !Number.isFinite(quarter)) return 1;
  const power = 10 ** Math.floor(Math.log10(quarter));
  const lead = [5, 2, 1].find((m) => m * power <= quarter * (1 + 1e-9)) ?? 1;
  return Number((lead * power).toPrecision(12));
}

/** A CSS gradient of the heat maps' colour ramp, left (lowest) to right (highest). */
export function rampGradient() {
  const stops = HEAT_RAMP.map(([r, g, b], i) => `rgb(${r}, ${g}, ${b}) ${(i / (HEAT_RAMP.length - 1)) * 100}%`);
  return `linear-gradient(to right, ${stops.join(', ')})`;
}

/** A coordinate in metres with the decimals it needs: 2.5 -> "2.5", -10 -> "-10". */
function metres(x) {
  let places = 0;
  while (places < 3 && Math.abs(x * 10 ** places - Math.round(x * 10 ** places)) > 1e-6) places += 1;
  return formatMeasure(x, places);
}

/** An element placed along an axis (CSSOM, not a style attribute). */
function placed(ctx, side, percent, text) {
  const tick = ctx.h('span', { class: 'tick' }, text);
  tick.style[side] = `${percent}%`;
  return tick;
}

/**
 * The axes (x east along the bottom, y north up the left, in metres), a scale bar and the colour
 * legend (the layer's value range with its unit) around the heat map `img`. `frameShown()` reads
 * the info again; one read at a time, and one more when frames came meanwhile.
 */
function heatMapLegend(ctx, img, infoPath) {
  const yAxis = ctx.h('div', { class: 'heat-axis heat-axis-y', 'aria-hidden': 'true' });
  const xAxis = ctx.h('div', { class: 'heat-axis heat-axis-x', 'aria-hidden': 'true' });
  const bar = ctx.h('span', { class: 'heat-scale-bar' });
  const barLabel = ctx.h('span', { class: 'heat-scale-label' });
  const scale = ctx.h('div', { class: 'heat-scale' }, bar, barLabel);
  const low = ctx.h('span', { class: 'heat-low' });
  const high = ctx.h('span', { class: 'heat-high' });
  const ramp = ctx.h('span', { class: 'heat-ramp' });
  ramp.style.background = rampGradient();
  const legend = ctx.h('div', { class: 'heat-legend', role: 'img', hidden: true }, low, ramp, high);
  const map = ctx.h(
    'div',
    { class: 'heat-map', dataset: { legend: 'waiting' } },
    yAxis,
    img,
    ctx.h('span', { class: 'heat-corner muted' }, 'm'),
    xAxis,
    ctx.h('span', {}),
    scale,
  );
  const element = ctx.h('div', { class: 'heat-view' }, map, legend);
  let reading = false;
  let again = false;
  let drawnInfo = '';

  const draw = (info) => {
    const [x0, y0] = info.origin;
    const x1 = x0 + info.cols * info.cell;
    const y1 = y0 + info.rows * info.cell;
    xAxis.replaceChildren(
      ...axisTicks(x0, x1).map((x) => placed(ctx, 'left', ((x - x0) / (x1 - x0)) * 100, metres(x))),
    );
    // North up: the top of the picture is the grid's largest y.
    yAxis.replaceChildren(
      ...axisTicks(y0, y1).map((y) => placed(ctx, 'top', ((y1 - y) / (y1 - y0)) * 100, metres(y))),
    );
    const length = scaleLength(x1 - x0);
    bar.style.width = `${(length / (x1 - x0)) * 100}%`;
    barLabel.textContent = `${metres(length)} m`;
    const unit = info.unit;
    const places = decimalsFor({ unit });
    if (info.min === null || info.max === null) {
      low.textContent = 'no values yet';
      high.textContent = '';
    } else {
      low.textContent = formatMeasure(info.min, places, unit);
      high.textContent = formatMeasure(info.max, places, unit);
    }
    legend.setAttribute(
      'aria-label',
      info.min === null ? 'no values yet' : `colours from ${low.textContent} (blue) to ${high.textContent} (red)`,
    );
    legend.hidden = false;
    map.dataset.legend = 'drawn';
    Object.assign(map.dataset, { x0: String(x0), x1: String(x1), y0: String(y0), y1: String(y1) });
    Object.assign(legend.dataset, { min: String(info.min ?? ''), max: String(info.max ?? ''), unit });
  };

  const read = async () => {
    if (reading) {
      again = true;
      return;
    }
    reading = true;
    try {
      do {
        again = false;
        let text;
        try {
          text = await ctx.readPath(infoPath);
        } catch {
          // No info beside it (or not readable by this token): the picture without a legend.
          map.dataset.legend = 'none';
          return;
        }
        if (text === drawnInfo) continue;
        const info = heatMapInfo(text);
        if (info === null) {
          map.dataset.legend = 'none';
          return;
        }
        drawnInfo = text;
        draw(info);
      } while (again);
    } finally {
      reading = false;
    }
  };
  return { element, frameShown: read };
}
