// What the map draws under the robots: a floor plan the gateway's config names (`[console]
// map_image` and `map_extent`, served at /console/floor-plan), or a layer of an environment
// model's grid (docs/environment.md: `grid.LAYER.image`, a heat map north up, placed by
// `grid.LAYER.info`'s origin, cell and shape). `#map-background` picks one; by default the floor
// plan when there is one, else the first environment model's `occupancy`.
//
// A grid layer is read again when its `.info` changes (it counts what was added), at most once
// every GRID_REFRESH_MS: the picture is a few kilobytes, its changes many. A layer of means (a
// temperature) is the model's own heat map, empty cells clear. A layer of hit counts (the
// occupancy) is drawn here from its numbers (`grid.LAYER`, a numpy array): the heat map would
// paint every cell never seen in the coldest colour over the whole floor, where an occupancy map
// leaves it clear and darkens a cell the more often something was seen there.

import { propertyUrl, token } from './api.js';
import { svg } from './dom.js';
import { parseList, parseNames } from './values.js';

/** Where the gateway says which floor plan it serves: {"image": URL or null, "extent": [x0, y0, x1, y1]}. */
export const FLOOR_PLAN_URL = '/console/floor-plan.json';
/** Milliseconds between two reads of a grid layer's picture at most. */
export const GRID_REFRESH_MS = 2000;
/** The resource type of an environment model (docs/environment.md). */
const ENVIRONMENT = 'environment_model';
/** Environment models whose layers are offered at most. */
const MAX_MODELS = 8;
export const FLOOR_PLAN = 'floor-plan';
export const NONE = 'none';

/** Cells a grid layer has at most (the environment model's own bound). */
export const MAX_CELLS = 1000000;

/**
 * The plane a grid layer covers, from its `.info` text ("((kind hits) (origin (x0 y0)) (cell m)
 * (shape (rows cols)) ...)"): {extent: [x0, y0, x1, y1] in metres, kind}, or null when the text
 * says no grid.
 */
export function gridInfo(info) {
  let fields;
  try {
    fields = new Map(parseList(info).filter((f) => Array.isArray(f) && f.length >= 2).map(([k, v]) => [k, v]));
  } catch {
    return null;
  }
  const origin = fields.get('origin');
  const shape = fields.get('shape');
  const cell = Number(fields.get('cell'));
  if (!Array.isArray(origin) || !Array.isArray(shape) || origin.length < 2 || shape.length < 2) return null;
  const [x0, y0] = origin.map(Number);
  const [rows, cols] = shape.map(Number);
  if (![x0, y0, rows, cols, cell].every(Number.isFinite) || cell <= 0 || rows <= 0 || cols <= 0) return null;
  return { extent: [x0, y0, x0 + cols * cell, y0 + rows * cell], kind: String(fields.get('kind') ?? '') };
}

/**
 * A 2-D array of numbers as `numpy.save` writes it (format 1.0 to 3.0, little-endian float32 or
 * float64, C order): {rows, cols, values}. Throws an Error saying what it is not.
 */
export function parseNpy(buffer) {
  const bytes = new Uint8Array(buffer);
  const magic = [0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59]; // \x93NUMPY
  if (bytes.length < 10 || magic.some((b, i) => bytes[i] !== b)) throw new Error('not a numpy array (.npy)');
  const view = new DataView(buffer);
  const major = bytes[6];
  const start = major === 1 ? 10 : 12;
  const length = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
  if (start + length > bytes.length) throw new Error('a numpy header longer than the file');
  const header = new TextDecoder('latin1').decode(bytes.subarray(start, start + length));
  const descr = /'descr':\s*'([<|]?)f([48])'/.exec(header);
  const shape = /'shape':\s*\((\d+),\s*(\d+),?\)/.exec(header);
  if (!descr) throw new Error('not a little-endian float array');
  if (/'fortran_order':\s*True/.test(header)) throw new Error('a Fortran-ordered array');
  if (!shape) throw new Error('not a 2-D array');
  const [rows, cols] = [Number(shape[1]), Number(shape[2])];
  const size = Number(descr[2]);
  if (rows * cols > MAX_CELLS) throw new Error(`more than ${MAX_CELLS} cells`);
  const data = buffer.slice(start + length, start + length + rows * cols * size);
  if (data.byteLength !== rows * cols * size) throw new Error('a numpy array shorter than its shape');
  const values = size === 4 ? new Float32Array(data) : new Float64Array(data);
  return { rows, cols, values };
}

/** Colour of an occupied cell (the console's ink); its opacity grows with its hits. */
const OCCUPIED = [36, 41, 47];

/**
 * RGBA pixels (one a cell, row 0 at the top: north up) of a grid of hit counts whose row 0 is at
 * the south: a cell never hit is clear, a hit one from faint to dark on a log scale of the most hits.
 */
export function occupancyPixels({ rows, cols, values }) {
  let most = 0;
  for (const v of values) if (v > most && Number.isFinite(v)) most = v;
  const pixels = new Uint8ClampedArray(rows * cols * 4);
  for (let r = 0; r < rows; r += 1) {
    const top = rows - 1 - r;
    for (let c = 0; c < cols; c += 1) {
      const v = values[r * cols + c];
      if (!(v > 0) || !Number.isFinite(v)) continue;
      const at = (top * cols + c) * 4;
      pixels.set(OCCUPIED, at);
      pixels[at + 3] = 70 + Math.round((185 * Math.log1p(v)) / Math.log1p(most));
    }
  }
  return pixels;
}

/** Whether `extent` is four finite numbers with x1 > x0 and y1 > y0. */
export function isExtent(extent) {
  return Array.isArray(extent) && extent.length === 4 && extent.every(Number.isFinite) && extent[2] > extent[0] && extent[3] > extent[1];
}

export class MapBackground {
  /**
   * `layer` is the map's <g> under everything; `select` the #map-background <select>;
   * `mux` the page's stream; `onExtent()` hears when the floor plan's extent becomes known.
   */
  constructor(layer, select, { mux, fetcher = (...args) => fetch(...args), onExtent = () => {} }) {
    Object.assign(this, { layer, select, mux, fetcher, onExtent });
    this.floorPlan = null; // {image, extent}
    this.models = new Map(); // environment model -> its layer names
    this.choice = null; // what is drawn: FLOOR_PLAN, NONE or "SERVICE/grid.LAYER"
    this.chosenByOperator = false;
    this._info = null; // {selector, unsubscribe, extent, loadedAt, timer}
    this._blobUrl = null;
    this._layerSubs = new Map();
    select.addEventListener('change', () => {
      this.chosenByOperator = true;
      this.show(select.value);
    });
  }

  /** Ask the gateway for its floor plan (none: the answer says so, or the route is not there). */
  async start() {
    try {
      const response = await this.fetcher(FLOOR_PLAN_URL, { credentials: 'same-origin', signal: AbortSignal.timeout(10000) });
      const plan = response.ok ? await response.json() : null;
      if (plan?.image && isExtent(plan.extent)) this.floorPlan = { image: String(plan.image), extent: plan.extent };
    } catch {
      this.floorPlan = null; // an older gateway, or none reachable: no floor plan
    }
    this.fillChoices();
    if (this.floorPlan) this.onExtent(this.floorPlan.extent);
  }

  /** The services changed: follow the layer names of each environment model that is up. */
  servicesChanged(list) {
    const models = list.filter((s) => s.type === ENVIRONMENT && s.state === 'up').slice(0, MAX_MODELS).map((s) => s.name);
    for (const [name, unsubscribe] of this._layerSubs) {
      if (!models.includes(name)) {
        unsubscribe();
        this._layerSubs.delete(name);
        this.models.delete(name);
      }
    }
    for (const name of models) {
      if (this._layerSubs.has(name)) continue;
      this.models.set(name, []);
      this._layerSubs.set(
        name,
        this.mux.subscribe(`${name}/grid`, {
          onValue: ({ value, removed }) => {
            let layers = [];
            try {
              layers = removed ? [] : parseNames(value).slice(0, 32);
            } catch {
              layers = [];
            }
            this.models.set(name, layers);
            this.fillChoices();
          },
        }),
      );
    }
    this.fillChoices();
  }

  choices() {
    const out = [[NONE, 'no background']];
    if (this.floorPlan) out.push([FLOOR_PLAN, 'floor plan']);
    for (const [name, layers] of this.models) for (const layer of layers) out.push([`${name}/grid.${layer}`, `${name} ${layer}`]);
    return out;
  }

  /** The background a page gets before the operator picks one. */
  preferred() {
    if (this.floorPlan) return FLOOR_PLAN;
    for (const [name, layers] of this.models) if (layers.includes('occupancy')) return `${name}/grid.occupancy`;
    return NONE;
  }

  fillChoices() {
    const choices = this.choices();
    const values = choices.map(([value]) => value);
    if (this.select.options.length !== choices.length || [...this.select.options].some((o, i) => o.value !== values[i])) {
      this.select.replaceChildren(...choices.map(([value, text]) => Object.assign(document.createElement('option'), { value, textContent: text })));
    }
    const wanted = this.chosenByOperator && values.includes(this.choice) ? this.choice : this.preferred();
    this.select.value = wanted;
    if (wanted !== this.choice) this.show(wanted);
  }

  show(choice) {
    this.choice = choice;
    this._stopGrid();
    this.layer.dataset.background = choice;
    if (choice === FLOOR_PLAN && this.floorPlan) {
      this.draw(this.floorPlan.image, this.floorPlan.extent, 'floor-plan');
    } else if (choice !== NONE && choice.includes('/grid.')) {
      this._followGrid(choice);
    } else {
      this.layer.replaceChildren();
    }
  }

  /** `href` drawn over `extent` ([x0, y0, x1, y1], m) in the map's world (y up, so flipped back). */
  draw(href, [x0, y0, x1, y1], kind) {
    const image = svg('image', { href, x: 0, y: 0, width: x1 - x0, height: y1 - y0, preserveAspectRatio: 'none', class: kind });
    this.layer.replaceChildren(svg('g', { transform: `translate(${x0} ${y1}) scale(1 -1)` }, image));
  }

  _followGrid(selector) {
    const [service, path] = [selector.slice(0, selector.indexOf('/')), selector.slice(selector.indexOf('/') + 1)];
    const info = { selector, extent: null, loadedAt: 0, timer: null, unsubscribe: null };
    this._info = info;
    info.unsubscribe = this.mux.subscribe(`${service}/${path}.info`, {
      onValue: ({ value, removed }) => {
        const known = removed ? null : gridInfo(value);
        info.extent = known?.extent ?? null;
        info.kind = known?.kind ?? '';
        if (!info.extent) return;
        const wait = info.loadedAt + GRID_REFRESH_MS - Date.now();
        if (wait <= 0) this._loadGrid(info, service, path);
        else info.timer ??= setTimeout(() => this._loadGrid(info, service, path), wait);
      },
    });
  }

  async _loadGrid(info, service, path) {
    info.timer = null;
    info.loadedAt = Date.now();
    const headers = {};
    if (token()) headers.Authorization = `Bearer ${token()}`;
    const hits = info.kind === 'hits';
    let blob;
    try {
      const response = await this.fetcher(`${propertyUrl(service, hits ? path : `${path}.image`)}?raw=1`, {
        headers,
        credentials: 'same-origin',
        signal: AbortSignal.timeout(10000),
      });
      if (!response.ok) return;
      blob = hits ? await occupancyPicture(parseNpy(await response.arrayBuffer())) : await response.blob();
    } catch {
      return; // tried again with the next change of the layer
    }
    if (this._info !== info || !info.extent) return; // another background was chosen meanwhile
    if (this._blobUrl) URL.revokeObjectURL(this._blobUrl);
    this._blobUrl = URL.createObjectURL(blob);
    this.draw(this._blobUrl, info.extent, 'grid-layer');
  }

  _stopGrid() {
    const info = this._info;
    this._info = null;
    if (info) {
      info.unsubscribe?.();
      clearTimeout(info.timer);
    }
    if (this._blobUrl) {
      URL.revokeObjectURL(this._blobUrl);
      this._blobUrl = null;
    }
  }
}

/** A grid of hit counts as a PNG blob, a pixel a cell (drawn in a canvas of the page). */
function occupancyPicture(grid) {
  const canvas = document.createElement('canvas');
  canvas.width = grid.cols;
  canvas.height = grid.rows;
  canvas.getContext('2d').putImageData(new ImageData(occupancyPixels(grid), grid.cols, grid.rows), 0, 0);
  return new Promise((resolve, reject) => canvas.toBlob((b) => (b ? resolve(b) : reject(new Error('no picture'))), 'image/png'));
}
