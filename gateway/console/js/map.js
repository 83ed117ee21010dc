// The map (#map): an SVG of the plane in metres (north = +y), with a grid, every robot as a
// triangle pointing along its heading with its name, sensors and group centroids, markers
// (the targets sent from here and every marker-typed property of the services), zoom (wheel),
// pan (drag) and click-to-go: a click on the plane sends behaviors.moveto to the selected robot
// or group (groups with the formation and spacing chosen beside the map). For a fleet: each
// robot's recent path as a fading trail (js/trails.js), its target (a click-to-go, or a property
// of its own that says where it is sent, below) as a mark with a line from the robot, a floor plan
// or an environment model's grid under everything (js/map_background.js), and names placed clear
// of each other (js/labels.js).

import { describe, setProperty } from './api.js';
import { clear, svg } from './dom.js';
import { placeLabels } from './labels.js';
import { MapBackground } from './map_background.js';
import { Trail } from './trails.js';
import { findMarkers, markerAt, markerLocation, parseMarker, parseVector } from './values.js';

/** Services whose models the map reads for marker properties; a larger system keeps the first. */
const MAX_DESCRIBED = 64;
/** Marker properties the map follows at most. */
const MAX_MARKER_PROPERTIES = 32;
/** A pointer that moved further than this (px) between down and up dragged the map, not clicked. */
const CLICK_SLOP_PX = 5;
/** A target counts as reached within this distance (m); its marker then goes. */
const ARRIVED_M = 0.05;
/** A target not reached in this long (a group's centroid need not land on it) is no longer drawn. */
const TARGET_TTL_MS = 120000;
const MOVABLE_TYPES = new Set(['mobile_robot', 'group']);
/** Types that have a location by their standard property set, even before the registry saw one. */
const LOCATED_TYPES = new Set(['mobile_robot', 'group', 'sensor']);
/** Words that make a readable property a service's goal: where it is sent (a marker or x y). */
const GOAL_WORDS = new Set(['goal', 'target']);
/** Pixels of a name's height on the map (12 px text), and from its top to its baseline. */
const LABEL_HEIGHT_PX = 15;
const LABEL_BASELINE_PX = 11;
/** Pixels within which a marker named like a thing (or another marker) stands where it does. */
const SAME_PLACE_PX = 24;
/** Seconds between redraws of the trails' fading while nothing moves. */
const TRAIL_FADE_MS = 1000;

/** A goal property's value as a point [x, y]: a marker with a location, or a vector; else null. */
export function goalPoint(text) {
  if (!text || !text.trim()) return null;
  try {
    const marker = parseMarker(text);
    const location = markerLocation(marker);
    return location && location.length >= 2 ? [location[0], location[1]] : null;
  } catch {
    // not a marker: x y ...
  }
  try {
    const v = parseVector(text);
    return v.length >= 2 ? [v[0], v[1]] : null;
  } catch {
    return null;
  }
}

/** Whether a property of a model names where its service is sent (`goal`, `behaviors.target`, `.gui` goal). */
export function isGoalProperty(prop) {
  const last = String(prop.name ?? '').split('.').at(-1);
  const readable = ['read', 'read-write'].includes(prop.access);
  const shaped = ['marker', 'vector'].includes(prop.type) || ['marker', 'pose', 'vector', 'goal', 'target'].includes(prop.gui);
  return readable && shaped && (GOAL_WORDS.has(last) || GOAL_WORDS.has(prop.gui));
}

function colorOf(text) {
  try {
    const rgb = parseVector(text);
    if (rgb.length >= 3) return `rgb(${rgb.slice(0, 3).map((c) => Math.round(Math.min(1, Math.max(0, c)) * 255)).join(' ')})`;
  } catch {
    // not a colour vector: the default colour
  }
  return null;
}

export class RobotMap {
  /**
   * `svgRoot` is the #map <svg>; `services()` the current list; `selected()` the selected
   * service; `onSelect(name)` for a click on a robot; `formation()` gives {formation, spacing}.
   */
  constructor(svgRoot, { mux, services, selected, onSelect, formation, status, onPose = () => {}, backgroundSelect = null }) {
    Object.assign(this, { root: svgRoot, mux, services, selected, onSelect, formation, status, onPose });
    this.poses = new Map(); // service -> [x y z roll pitch yaw]
    this.targets = new Map(); // service -> [x, y] where a click sent it (with .at, ms)
    this.goals = new Map(); // service -> [x, y] its own goal property says
    this.trails = new Map(); // robot -> Trail
    this.markers = new Map(); // "service/path" -> [{location, label, color}]
    this.stale = new Set(); // services shown where last seen: not up, or their Listen failed
    this._locationSubs = new Map(); // service -> unsubscribe
    this._described = new Set();
    this._markerSubs = new Map();
    this.view = { cx: 2, cy: 0, scale: 60 }; // metres at the centre; pixels per metre
    this._drag = null;
    this._userMoved = false; // the operator zoomed or panned: the map no longer fits by itself
    this.layers = {
      background: svg('g', { class: 'background' }),
      grid: svg('g', { class: 'grid' }),
      trails: svg('g', { class: 'trails' }),
      markers: svg('g', { class: 'markers' }),
      targets: svg('g', { class: 'targets' }),
      others: svg('g', { class: 'others' }), // sensors and group centroids, under the robots
      robots: svg('g', { class: 'robots' }),
    };
    this.world = svg('g', { class: 'world' }, ...Object.values(this.layers));
    clear(this.root).append(this.world);
    this._bind();
    new ResizeObserver(() => this.draw()).observe(this.root);
    this._labelWidths = new Map(); // name -> px
    this._labelsQueued = false;
    this.background = backgroundSelect
      ? new MapBackground(this.layers.background, backgroundSelect, { mux, onExtent: () => !this._userMoved && this.fit() })
      : null;
    // The trails fade with time even where nothing moves.
    setInterval(() => this.trails.size && this.drawTrails(), TRAIL_FADE_MS);
  }

  start() {
    this._fitted = false;
    this.background?.start();
  }

  // -- data ----------------------------------------------------------------------------------

  located({ service, value, removed, gap }) {
    let pose = null;
    if (!removed) {
      try {
        pose = parseVector(value);
      } catch {
        pose = null;
      }
    }
    if (pose && pose.length >= 2) this.poses.set(service, pose);
    else this.poses.delete(service);
    this.stale.delete(service);
    const target = this.targets.get(service);
    const arrived = target && pose && Math.hypot(pose[0] - target[0], pose[1] - target[1]) < ARRIVED_M;
    if (target && (arrived || this.clock() - target.at > TARGET_TTL_MS)) this.targets.delete(service);
    if (pose && this.typeOf(service) === 'mobile_robot') {
      let trail = this.trails.get(service);
      if (!trail) this.trails.set(service, (trail = new Trail()));
      if (trail.add(pose[0], pose[1], this.clock(), Boolean(gap))) this.drawTrail(service);
    } else if (!pose && this.trails.delete(service)) {
      this.drawTrail(service);
    }
    this.drawTarget(service);
    this.drawRobot(service);
    this.onPose(service);
  }

  /** The list of services changed: drop the gone, read the models of the new for markers. */
  /**
   * The list of services changed. The map follows `NAME/location` of every service that is up
   * (one selector per service, so that one that goes away costs only its own); one that is not
   * up stays where the registry last saw it, greyed. It drops the gone, and reads the models of
   * the new for marker properties.
   */
  servicesChanged(list) {
    const names = new Set(list.map((s) => s.name));
    const located = list.filter((s) => s.state === 'up' && (s.location !== null || LOCATED_TYPES.has(s.type)));
    // Many services: one wildcard selector instead of one each (the stream's selectors are bounded).
    const many = located.length > Math.floor(this.mux.maxSelectors / 2);
    const follow = new Set(many ? ['*'] : located.map((s) => s.name));
    for (const [name, unsubscribe] of this._locationSubs) {
      if (!follow.has(name)) {
        unsubscribe();
        this._locationSubs.delete(name);
      }
    }
    for (const name of follow) {
      if (this._locationSubs.has(name)) continue;
      this._locationSubs.set(
        name,
        this.mux.subscribe(`${name}/location`, {
          onValue: (event) => this.located(event),
          onSync: () => {
            if (!this._fitted && this.poses.size) this.fit(); // the first snapshot: everyone in sight
            this._fitted = true;
          },
          onError: () => {
            this.stale.add(name);
            this.drawRobot(name);
          },
        }),
      );
    }
    for (const name of [...this.poses.keys()]) if (!names.has(name)) this.poses.delete(name);
    for (const name of [...this.trails.keys()]) if (!names.has(name)) this.trails.delete(name);
    for (const name of [...this.goals.keys()]) if (!names.has(name)) this.goals.delete(name);
    this.background?.servicesChanged(list);
    for (const s of list) {
      if (follow.has(s.name) || (many && s.state === 'up')) continue;
      this.stale.add(s.name);
      if (Array.isArray(s.location) && s.location.length >= 2) this.poses.set(s.name, s.location);
    }
    for (const [selector, unsubscribe] of this._markerSubs) {
      if (!names.has(selector.split('/')[0])) {
        unsubscribe();
        this._markerSubs.delete(selector);
        this.markers.delete(selector);
      }
    }
    // A goal followed of a service that is gone, or not up (its goal is read anew when it is).
    for (const s of list) if (s.state !== 'up') this.goals.delete(s.name);
    this.drawAll();
    // A service that is not up is described again once it is (its model may have changed).
    for (const service of list) if (service.state !== 'up') this._described.delete(service.name);
    this._describeNew(list);
  }

  async _describeNew(list) {
    for (const service of list) {
      // Only a service that is up can describe itself; one that fails is asked again after it
      // was down and is up again, never with every change of the list.
      if (service.state !== 'up') continue;
      if (this._described.has(service.name) || this._described.size >= MAX_DESCRIBED) continue;
      this._described.add(service.name);
      let model;
      try {
        model = await describe(service.name);
      } catch {
        continue;
      }
      for (const prop of model.properties ?? []) {
        if (isGoalProperty(prop) && this._markerSubs.size < MAX_MARKER_PROPERTIES) {
          const selector = `${service.name}/${prop.name}`;
          const name = service.name;
          this._markerSubs.set(
            selector,
            this.mux.subscribe(selector, {
              onValue: ({ value, removed }) => {
                const point = removed ? null : goalPoint(value);
                if (point) this.goals.set(name, point);
                else this.goals.delete(name);
                this.drawTarget(name);
              },
            }),
          );
          continue;
        }
        const isMarker = prop.type === 'marker' || prop.gui === 'marker' || prop.gui === 'markers';
        if (!isMarker || !['read', 'read-write'].includes(prop.access)) continue;
        if (this._markerSubs.size >= MAX_MARKER_PROPERTIES) return;
        const selector = `${service.name}/${prop.name}`;
        this._markerSubs.set(
          selector,
          this.mux.subscribe(selector, { onValue: (event) => this.markerChanged(selector, event) }),
        );
      }
    }
  }

  markerChanged(selector, { value, removed }) {
    const found = removed ? [] : findMarkers(value, 200);
    const shown = [];
    for (const marker of found) {
      const location = markerLocation(marker);
      if (!location || location.length < 2) continue;
      const f = marker.fields;
      const label = typeof f.name === 'string' ? f.name : typeof f.label === 'string' ? f.label : typeof f.id === 'string' ? f.id : '';
      shown.push({ location, label, color: typeof f.color === 'string' ? colorOf(f.color) : null });
    }
    const first = !this.markers.has(selector);
    this.markers.set(selector, shown);
    if (first && shown.length && !this._userMoved) this.fit(); // new things to see, and nobody chose a view
    else this.drawMarkers();
  }

  clock() {
    return Date.now();
  }

  /** `name` is driven by hand now: its click-to-go target is over. */
  forgetTarget(name) {
    if (this.targets.delete(name)) this.drawTarget(name);
  }

  typeOf(name) {
    return this.services().find((s) => s.name === name)?.type ?? '';
  }

  // -- coordinates ---------------------------------------------------------------------------

  size() {
    const rect = this.root.getBoundingClientRect();
    return { width: rect.width || 600, height: rect.height || 400 };
  }

  /** The world point (m) under a client point (px). */
  toWorld(clientX, clientY) {
    const rect = this.root.getBoundingClientRect();
    const { width, height } = this.size();
    return [
      this.view.cx + (clientX - rect.left - width / 2) / this.view.scale,
      this.view.cy - (clientY - rect.top - height / 2) / this.view.scale,
    ];
  }

  /** Zoom and pan so that every robot and marker is in sight. */
  fit() {
    const points = [...this.poses.values(), ...[...this.markers.values()].flat().map((m) => m.location)];
    const plan = this.background?.choice === 'floor-plan' ? this.background.floorPlan?.extent : null;
    if (plan) points.push([plan[0], plan[1]], [plan[2], plan[3]]);
    if (!points.length) return;
    const xs = points.map((p) => p[0]);
    const ys = points.map((p) => p[1]);
    const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    const { width, height } = this.size();
    this.view.cx = (x0 + x1) / 2;
    this.view.cy = (y0 + y1) / 2;
    this.view.scale = Math.min(200, Math.max(5, Math.min(width / (x1 - x0 + 3), height / (y1 - y0 + 3))));
    this.draw();
  }

  // -- input ---------------------------------------------------------------------------------

  _bind() {
    this.root.addEventListener('wheel', (e) => {
      e.preventDefault();
      this._userMoved = true;
      const before = this.toWorld(e.clientX, e.clientY);
      this.view.scale = Math.min(400, Math.max(2, this.view.scale * (e.deltaY < 0 ? 1.2 : 1 / 1.2)));
      const after = this.toWorld(e.clientX, e.clientY);
      this.view.cx += before[0] - after[0];
      this.view.cy += before[1] - after[1];
      this.draw();
    }, { passive: false });
    this.root.addEventListener('pointerdown', (e) => {
      if (e.button !== 0) return;
      this._drag = { x: e.clientX, y: e.clientY, cx: this.view.cx, cy: this.view.cy, moved: false, id: e.pointerId };
    });
    this.root.addEventListener('pointermove', (e) => {
      const d = this._drag;
      if (!d || d.id !== e.pointerId) return;
      if (!d.moved && Math.hypot(e.clientX - d.x, e.clientY - d.y) > CLICK_SLOP_PX) {
        d.moved = true;
        this._userMoved = true;
        try {
          this.root.setPointerCapture(e.pointerId);
        } catch {
          // a synthetic pointer: the drag goes on while it stays over the map
        }
        this.root.classList.add('panning');
      }
      if (d.moved) {
        this.view.cx = d.cx - (e.clientX - d.x) / this.view.scale;
        this.view.cy = d.cy + (e.clientY - d.y) / this.view.scale;
        this.draw();
      }
    });
    const end = (e) => {
      const d = this._drag;
      this._drag = null;
      this.root.classList.remove('panning');
      if (!d || d.id !== e.pointerId || d.moved || e.type === 'pointercancel') return;
      const robot = e.target.closest?.('[data-robot], [data-group]');
      if (robot) this.onSelect(robot.dataset.robot ?? robot.dataset.group);
      else this.clickToGo(this.toWorld(e.clientX, e.clientY));
    };
    this.root.addEventListener('pointerup', end);
    this.root.addEventListener('pointercancel', end);
  }

  /** Send the selected robot or group to `point` (world metres). */
  async clickToGo([x, y]) {
    const name = this.selected();
    const type = this.typeOf(name);
    if (!name || !MOVABLE_TYPES.has(type)) {
      this.status('Select a robot or a group first: a click on the map sends it there.');
      return;
    }
    const target = Object.assign([Number(x.toFixed(2)), Number(y.toFixed(2))], { at: this.clock() });
    const parameters = {};
    if (type === 'group') {
      const { formation, spacing } = this.formation();
      parameters.formation = formation;
      if (spacing) parameters.spacing = spacing;
    }
    this.targets.set(name, target);
    this.drawTarget(name);
    this.status(`${name}: moving to (${target.join(' ')})…`);
    try {
      const reply = await setProperty(name, 'behaviors.moveto', markerAt(target), parameters);
      const members = reply?.value ? ` ${reply.value}` : '';
      this.status(`${name}: behaviors.moveto (${target.join(' ')}) accepted${members}`);
    } catch (e) {
      this.targets.delete(name);
      this.drawTarget(name);
      this.status(`${name}: ${e.code}: ${e.message}`, true);
    }
  }

  // -- drawing -------------------------------------------------------------------------------

  draw() {
    const { width, height } = this.size();
    const { cx, cy, scale } = this.view;
    this.root.setAttribute('viewBox', `0 0 ${width} ${height}`);
    // World metres to pixels: x right, y up.
    this.world.setAttribute(
      'transform',
      `translate(${width / 2 - cx * scale} ${height / 2 + cy * scale}) scale(${scale} ${-scale})`,
    );
    this.drawGrid(width, height);
    this.drawAll();
  }

  drawAll() {
    this.drawMarkers();
    this.drawTargets();
    this.drawTrails();
    for (const layer of [this.layers.robots, this.layers.others]) {
      for (const g of [...layer.children]) if (!this.poses.has(g.dataset.service)) g.remove();
    }
    for (const name of this.poses.keys()) this.drawRobot(name);
    this.scheduleLabels();
  }

  drawGrid(width, height) {
    const { cx, cy, scale } = this.view;
    // A step of 1, 2 or 5 times a power of ten that leaves at least 40 px between lines.
    const raw = 40 / scale;
    const power = 10 ** Math.floor(Math.log10(raw));
    const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
    const [x0, x1] = [cx - width / 2 / scale, cx + width / 2 / scale];
    const [y0, y1] = [cy - height / 2 / scale, cy + height / 2 / scale];
    const lines = [];
    const px = 1 / scale; // one pixel, in metres
    // The x labels run along the bottom edge and the y labels up the left one: each leaves the
    // bottom-left corner to the other (a label is at most about 30 px wide and 14 px high).
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      lines.push(svg('line', { x1: x, y1: y0, x2: x, y2: y1, class: Math.abs(x) < step / 2 ? 'axis' : '', 'stroke-width': px }));
      if (x - x0 >= 32 * px) lines.push(this.label(`${Number(x.toFixed(6))}`, x + 3 * px, y0 + 4 * px, 'grid-label'));
    }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      lines.push(svg('line', { x1: x0, y1: y, x2: x1, y2: y, class: Math.abs(y) < step / 2 ? 'axis' : '', 'stroke-width': px }));
      if (y - y0 >= 18 * px) lines.push(this.label(`${Number(y.toFixed(6))}`, x0 + 3 * px, y + 3 * px, 'grid-label'));
    }
    this.layers.grid.replaceChildren(...lines);
  }

  /** Text at world (x, y), upright and of a constant size in pixels. */
  label(text, x, y, cls = 'label') {
    const s = 1 / this.view.scale;
    return svg('text', { class: cls, transform: `translate(${x} ${y}) scale(${s} ${-s})` }, text);
  }

  /** Draw `name` at its pose: its <g> is kept and moved (a script holding it sees it move). */
  drawRobot(name) {
    const selector = `[data-service="${CSS.escape(name)}"]`;
    let g = this.layers.robots.querySelector(selector) ?? this.layers.others.querySelector(selector);
    const pose = this.poses.get(name);
    if (!pose) {
      g?.remove();
      return;
    }
    const type = this.typeOf(name) || 'unknown';
    if (g && g.dataset.kind !== type) {
      g.remove(); // its type became known: drawn anew as what it is
      g = null;
    }
    if (!g) {
      g = this.robotShape(name, type);
      (type === 'mobile_robot' ? this.layers.robots : this.layers.others).append(g);
    }
    const [x, y] = pose;
    const yaw = pose.length >= 6 ? pose[5] : 0;
    const s = 1 / this.view.scale; // shapes keep their size in pixels when zooming
    g.setAttribute('transform', `translate(${x} ${y})`);
    g.classList.toggle('selected', name === this.selected());
    g.classList.toggle('stale', this.stale.has(name));
    g.querySelector('title').textContent = `${name} (${type}) at x ${x.toFixed(2)} y ${y.toFixed(2)}`;
    g.querySelector('.shape').setAttribute('transform', `scale(${s}) rotate(${(yaw * 180) / Math.PI})`);
    this.scheduleLabels();
  }

  // -- names ---------------------------------------------------------------------------------

  /** Lay the names out again at the next frame: many moves in one frame cost one layout. */
  scheduleLabels() {
    if (this._labelsQueued) return;
    this._labelsQueued = true;
    const run = () => {
      this._labelsQueued = false;
      this.layoutLabels();
    };
    if (typeof requestAnimationFrame === 'function') requestAnimationFrame(run);
    else setTimeout(run, 16);
  }

  labelWidth(words, text) {
    let width = this._labelWidths.get(words);
    if (!width) {
      width = text.getComputedTextLength?.() || 0;
      if (!width) return 7 * words.length; // not laid out yet (hidden): a guess, measured next time
      this._labelWidths.set(words, width);
      if (this._labelWidths.size > 4096) this._labelWidths.delete(this._labelWidths.keys().next().value);
    }
    return width;
  }

  /** Every name on the map: {id, g, text, at: [x, y] (m), kind}, things first, then targets and markers. */
  *labelled() {
    for (const g of [...this.layers.robots.children, ...this.layers.others.children]) {
      const at = this.poses.get(g.dataset.service);
      if (at) yield { id: g.dataset.service, g, at, kind: g.dataset.kind };
    }
    for (const g of this.layers.targets.children) if (g.placedAt) yield { id: `→ ${g.dataset.target}`, g, at: g.placedAt, kind: 'target' };
    let i = 0;
    for (const g of this.layers.markers.children) if (g.placedAt) yield { id: `marker ${(i += 1)}`, g, at: g.placedAt, kind: 'marker' };
  }

  /** Place every name in sight clear of the others and of the things (js/labels.js). */
  layoutLabels() {
    const { width, height } = this.size();
    const { cx, cy, scale } = this.view;
    const s = 1 / scale;
    const items = [];
    const found = new Map();
    const selected = this.selected();
    // The selected thing's name chooses first, then robots, groups, the rest, targets and markers.
    const RANK = { mobile_robot: 1, group: 2, target: 4, marker: 5 };
    const shown = new Map(); // name text -> the places (px) it is shown at
    for (const entry of this.labelled()) {
      const text = entry.g.querySelector(':scope > text');
      if (!text) continue;
      const x = width / 2 + (entry.at[0] - cx) * scale;
      const y = height / 2 - (entry.at[1] - cy) * scale;
      if (x < -200 || y < -200 || x > width + 200 || y > height + 200) continue; // out of sight
      // A marker of a thing where that thing stands (an environment model's marker of a robot,
      // a camera's sighting of it) says its name a second time: the name shows once.
      const words = text.textContent;
      const twice = entry.kind === 'marker' && (shown.get(words) ?? []).some(([u, v]) => Math.hypot(u - x, v - y) < SAME_PLACE_PX);
      text.setAttribute('display', twice ? 'none' : 'inline');
      if (twice) {
        entry.g.querySelector(':scope > line.leader')?.remove();
        continue;
      }
      if (!shown.has(words)) shown.set(words, []);
      shown.get(words).push([x, y]);
      const item = { id: entry.id, x, y, width: this.labelWidth(text.textContent, text), height: LABEL_HEIGHT_PX, kind: entry.kind };
      item.rank = entry.id === selected ? 0 : RANK[entry.kind] ?? 3;
      items.push(item);
      found.set(entry.id, { g: entry.g, text, item });
    }
    items.sort((a, b) => a.rank - b.rank || (a.id < b.id ? -1 : a.id > b.id ? 1 : 0));
    for (const [id, box] of placeLabels(items)) {
      const { g, text, item } = found.get(id);
      text.setAttribute('display', box.hidden ? 'none' : 'inline');
      if (box.hidden) {
        g.querySelector(':scope > line.leader')?.remove();
        continue;
      }
      const dx = box.left - item.x;
      const dy = box.top + LABEL_BASELINE_PX - item.y;
      text.setAttribute('transform', `translate(${dx * s} ${-dy * s}) scale(${s} ${-s})`);
      let leader = g.querySelector(':scope > line.leader');
      if (box.leader) {
        // From the thing's edge to the nearest point of its name's box.
        const nx = Math.max(box.left, Math.min(item.x, box.left + box.width)) - item.x;
        const ny = Math.max(box.top, Math.min(item.y, box.top + box.height)) - item.y;
        if (!leader) g.append((leader = svg('line', { class: 'leader' })));
        const length = Math.hypot(nx, ny) || 1;
        const from = Math.min(8, length) / length;
        Object.entries({ x1: nx * from * s, y1: -ny * from * s, x2: nx * s, y2: -ny * s, 'stroke-width': s }).forEach(([k, v]) => leader.setAttribute(k, v));
      } else {
        leader?.remove();
      }
    }
  }

  // -- trails --------------------------------------------------------------------------------

  drawTrails() {
    const now = this.clock();
    for (const [name, trail] of this.trails) {
      trail.prune(now);
      if (!trail.length || !this.poses.has(name)) this.trails.delete(name);
    }
    for (const g of [...this.layers.trails.children]) if (!this.trails.has(g.dataset.trail)) g.remove();
    for (const name of this.trails.keys()) this.drawTrail(name);
  }

  /** The trail of `name`: a <g data-trail=NAME> of polylines, the older the fainter. */
  drawTrail(name) {
    let g = this.layers.trails.querySelector(`[data-trail="${CSS.escape(name)}"]`);
    const trail = this.trails.get(name);
    if (!trail) {
      g?.remove();
      return;
    }
    if (!g) this.layers.trails.append((g = svg('g', { class: 'trail', dataset: { trail: name } })));
    const px = 1 / this.view.scale;
    g.dataset.points = String(trail.length);
    g.replaceChildren(
      ...trail.polylines(this.clock()).map(({ points, opacity }) =>
        svg('polyline', { points: points.map((p) => p.join(',')).join(' '), 'stroke-opacity': opacity, 'stroke-width': 2 * px }),
      ),
    );
  }

  robotShape(name, type) {
    const attrs = { class: `thing ${type}`, dataset: { service: name, kind: type } };
    let body;
    if (type === 'mobile_robot') {
      attrs.dataset.robot = name;
      body = svg('path', { d: 'M14,0 L-9,8 L-5,0 L-9,-8 Z', class: 'robot-body' });
    } else if (type === 'group') {
      attrs.dataset.group = name;
      body = svg('path', { d: 'M0,10 L10,0 L0,-10 L-10,0 Z', class: 'group-body' });
    } else {
      body = svg('circle', { r: 6, class: 'sensor-body' });
    }
    const label = this.label(name, 0, 0); // placed by layoutLabels
    return svg('g', attrs, svg('title', {}), svg('g', { class: 'shape' }, body), label);
  }

  drawTargets() {
    const names = new Set([...this.targets.keys(), ...this.goals.keys()]);
    for (const g of [...this.layers.targets.children]) if (!names.has(g.dataset.target)) g.remove();
    for (const name of names) this.drawTarget(name);
  }

  /**
   * Where `name` is sent, a <g data-target=NAME> (class `goal` when its own property says it, which
   * wins over a click): a cross in a circle, its name, and a line from the robot while it is on
   * its way (gone once it is there).
   */
  drawTarget(name) {
    let g = this.layers.targets.querySelector(`[data-target="${CSS.escape(name)}"]`);
    const goal = this.goals.get(name);
    const point = goal ?? this.targets.get(name);
    const pose = this.poses.get(name);
    if (!point || (goal && pose && Math.hypot(pose[0] - goal[0], pose[1] - goal[1]) < ARRIVED_M)) {
      g?.remove();
      return;
    }
    const s = 1 / this.view.scale;
    const [x, y] = point;
    if (!g) {
      g = svg(
        'g',
        { class: 'target', dataset: { target: name } },
        svg('line', { class: 'target-line' }),
        svg('g', { class: 'target-mark' }, svg('circle', { r: 8 }), svg('path', { d: 'M-12,0 H12 M0,-12 V12' })),
        this.label(`→ ${name}`, 10 * s, -16 * s, 'label target-label'), // placed by layoutLabels
      );
      this.layers.targets.append(g);
    }
    g.classList.toggle('goal', Boolean(goal));
    g.setAttribute('transform', `translate(${x} ${y})`);
    if (!g.placedAt || g.placedAt[0] !== x || g.placedAt[1] !== y) this.scheduleLabels();
    g.placedAt = point;
    g.querySelector('.target-mark').setAttribute('transform', `scale(${s})`);
    const line = g.querySelector('.target-line');
    line.setAttribute('display', pose ? 'inline' : 'none');
    if (pose) {
      Object.entries({ x1: pose[0] - x, y1: pose[1] - y, x2: 0, y2: 0, 'stroke-width': 1.5 * s }).forEach(([k, v]) => line.setAttribute(k, v));
    }
  }

  drawMarkers() {
    const s = 1 / this.view.scale;
    const shapes = [];
    for (const [selector, markers] of this.markers) {
      for (const { location, label, color } of markers) {
        const shape = svg(
          'g',
          { class: 'marker', dataset: { marker: selector }, transform: `translate(${location[0]} ${location[1]})` },
          svg('title', {}, `${selector}${label ? `: ${label}` : ''}`),
          svg('g', { transform: `scale(${s})` }, svg('rect', { x: -5, y: -5, width: 10, height: 10, style: color ? `fill: ${color}` : null })),
          label ? this.label(label, 8 * s, 8 * s) : null,
        );
        shape.placedAt = location; // its name is placed by layoutLabels
        shapes.push(shape);
      }
    }
    this.layers.markers.replaceChildren(...shapes);
    this.scheduleLabels();
  }
}
