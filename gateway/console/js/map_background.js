// What the map draws under the robots: a floor plan the gateway's config names (`[console]
// map_image` and `map_extent`, served at /console/floor-plan), or a layer of an environment
// model's grid (docs/environment.md: `grid.LAYER.image`, a heat map north up, placed by
// `grid.LAYER.info`'s origin, cell and shape). `#map-background` picks one; by default the floor
// plan when there is one, else the first environment model's `occupancy`.
//
// A grid layer is read again when its `.info` changes (it counts what was added), at most once
// every GRID_REFRESH_MS: the picture is a few kilobytes, its changes many.

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

/**
 * The plane a grid layer covers, from its `.info` text ("((kind hits) (origin (x0 y0)) (cell m)
 * (shape (rows cols)) ...)"): [x0, y0, x1, y1] in metres, or null when the text says no grid.
 */
export function gridExtent(info) {
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
  return [x0, y0, x0 + cols * cell, y0 + rows * cell];
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
        info.extent = removed ? null : gridExtent(value);
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
    let blob;
    try {
      const response = await this.fetcher(`${propertyUrl(service, `${path}.image`)}?raw=1`, {
        headers,
        credentials: 'same-origin',
        signal: AbortSignal.timeout(10000),
      });
      if (!response.ok) return;
      blob = await response.blob();
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
