// The service list (#services): every service the registry knows, grouped by type or by
// location, with its live state. It follows the registry's `revision` (which counts joins,
// leaves and changes of state) and asks GET /api/v1/services again when it moves.
//
// While the gateway cannot be reached (the list cannot be read, or the page's stream is down
// and a read of the list fails), nobody knows the services' states: each shows as unknown,
// grey, until the gateway answers again and the list is read anew.

import { listServices } from './api.js';
import { h } from './dom.js';

/** Side of the squares the location grouping uses, in metres. */
const AREA_M = 5;
/** Refetches of the list coalesce: a burst of registry changes costs one request. */
const REFRESH_DEBOUNCE_MS = 150;

/** The word people use for a standard type whose name qualifies it (the map, too, says robot). */
const SHORT_NAMES = { mobile_robot: 'robot', statemachine: 'state machine' };
/** Plurals that no rule below makes. */
const IRREGULAR_PLURALS = { person: 'people', child: 'children', mouse: 'mice', status: 'statuses', series: 'series' };

/** The plural of an English noun: registry -> registries, box -> boxes, camera -> cameras. */
export function pluralOf(word) {
  if (word in IRREGULAR_PLURALS) return IRREGULAR_PLURALS[word];
  if (/[^aeiou]y$/.test(word)) return `${word.slice(0, -1)}ies`;
  if (/(s|x|z|ch|sh)$/.test(word)) return `${word}es`;
  return `${word}s`;
}

/**
 * A group heading for people, from the type name and how many services have it:
 * ("environment_model", 1) -> "Environment model (1)", ("mobile_robot", 4) -> "Robots (4)",
 * ("registry", 2) -> "Registries (2)"; an empty type is "Other".
 */
export function typeTitle(type, count) {
  const raw = String(type ?? '').trim();
  const words = (SHORT_NAMES[raw] ?? raw)
    .replace(/([a-z0-9])([A-Z])/g, '$1 $2') // camelCase too
    .split(/[\s_.-]+/)
    .filter(Boolean)
    .map((w) => w.toLowerCase());
  if (!words.length) words.push('other');
  if (count !== 1) words[words.length - 1] = pluralOf(words[words.length - 1]);
  const text = words.join(' ');
  return `${text[0].toUpperCase()}${text.slice(1)} (${count})`;
}

/** The area a location falls in, as a title ("x 0…5 m, y -5…0 m"), or "No location". */
export function areaOf(location) {
  if (!Array.isArray(location) || location.length < 2 || !location.slice(0, 2).every(Number.isFinite)) {
    return 'No location';
  }
  const [x, y] = location.map((v) => Math.floor(v / AREA_M) * AREA_M);
  return `x ${x}…${x + AREA_M} m, y ${y}…${y + AREA_M} m`;
}

export class ServiceList {
  /**
   * `root` is #services; `mux` the event multiplexer; `onSelect(name)` hears a click;
   * `onChange(services)` hears every new list; `locationOf(name)` gives a live location.
   */
  constructor(root, { mux, onSelect, onChange = () => {}, onReachable = () => {}, locationOf = () => null, status }) {
    Object.assign(this, { root, mux, onSelect, onChange, onReachable, locationOf, status });
    /** Whether the last read of the list succeeded: the states shown are the gateway's. */
    this.reachable = true;
    this.services = [];
    this.selected = null;
    this.groupBy = 'type';
    this.registry = 'registry';
    this._timer = null;
    this._inFlight = false;
    this._again = false;
    this._unsubscribe = null;
  }

  start() {
    this.follow(this.registry);
    this.refresh();
  }

  /** Follow the `revision` of the registry named `name`. */
  follow(name) {
    this._unsubscribe?.();
    this.registry = name;
    this._unsubscribe = this.mux.subscribe(`${name}/revision`, {
      onValue: () => this.refreshSoon(),
      onSync: () => this.refreshSoon(), // after a reconnect: what changed meanwhile
      onError: (e) => {
        this.status(`cannot follow the registry: ${e.code}: ${e.message}`);
        this.refreshSoon(); // what changed may be why: a service that went away
      },
    });
  }

  refreshSoon() {
    if (this._timer !== null) return;
    this._timer = setTimeout(() => {
      this._timer = null;
      this.refresh();
    }, REFRESH_DEBOUNCE_MS);
  }

  async refresh() {
    if (this._inFlight) {
      this._again = true; // one more after this one: never two at once, never a lost change
      return;
    }
    this._inFlight = true;
    try {
      const answer = await listServices();
      this.services = Array.isArray(answer?.services) ? answer.services : [];
      const registry = this.services.find((s) => s.type === 'registry');
      if (registry && registry.name !== this.registry) this.follow(registry.name);
      this.reachable = true;
      this.render();
      this.status('');
      this.onChange(this.services);
      this.onReachable(true);
    } catch (e) {
      this.status(`cannot list the services: ${e.code}: ${e.message}`);
      this.unreachable();
    } finally {
      this._inFlight = false;
      if (this._again) {
        this._again = false;
        this.refreshSoon();
      }
    }
  }

  /**
   * Hear the page's stream state: when it is not open, the list is read (the states may have
   * changed, or the gateway may be gone, and then they are unknown). Open again, its `sync`
   * reads the list anyway.
   */
  connectionChanged(state) {
    if (state !== 'open') this.refreshSoon();
  }

  /** The gateway does not answer: every state shown becomes unknown (the list itself stays). */
  unreachable() {
    if (!this.reachable) return;
    this.reachable = false;
    this.render();
    this.onReachable(false);
  }

  /** The state to show: the gateway's, or unknown while it cannot be reached. */
  stateOf(service) {
    return this.reachable ? (service.state ?? 'unknown') : 'unknown';
  }

  byName(name) {
    return this.services.find((s) => s.name === name) ?? null;
  }

  select(name) {
    this.selected = name;
    for (const item of this.root.querySelectorAll('[data-service]')) {
      const on = item.dataset.service === name;
      item.classList.toggle('selected', on);
      item.setAttribute('aria-selected', String(on));
    }
  }

  setGrouping(groupBy) {
    this.groupBy = groupBy;
    this.render();
  }

  /** Re-group by location when a service moved into another area. */
  moved(name) {
    if (this.groupBy !== 'location') return;
    const item = this.root.querySelector(`[data-service="${CSS.escape(name)}"]`);
    if (item && item.dataset.area !== areaOf(this.locationOf(name))) this.render();
  }

  render() {
    const groups = new Map();
    for (const service of this.services) {
      const key = this.groupBy === 'location' ? areaOf(this.locationOf(service.name) ?? service.location) : service.type;
      if (!groups.has(key)) groups.set(key, []);
      groups.get(key).push(service);
    }
    const keys = [...groups.keys()].sort((a, b) => {
      if (a === 'No location') return 1;
      if (b === 'No location') return -1;
      return a.localeCompare(b);
    });
    const sections = keys.map((key) =>
      h(
        'section',
        { class: 'service-group' },
        h(
          'h3',
          { class: this.groupBy === 'type' ? 'by-type' : 'by-area' },
          this.groupBy === 'type' ? typeTitle(key, groups.get(key).length) : key,
          this.groupBy === 'type' ? null : h('small', {}, ` ${groups.get(key).length}`),
        ),
        h(
          'ul',
          { role: 'listbox', 'aria-label': key },
          groups
            .get(key)
            .sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }))
            .map((s) => this.item(s)),
        ),
      ),
    );
    if (!sections.length) sections.push(h('p', { class: 'muted' }, 'No services yet.'));
    this.root.replaceChildren(...sections);
  }

  item(service) {
    const selected = service.name === this.selected;
    return h(
      'li',
      {
        class: `service${selected ? ' selected' : ''}`,
        role: 'option',
        tabindex: '0',
        'aria-selected': String(selected),
        title: service.address ? `${service.name} at ${service.address}` : service.name,
        dataset: {
          service: service.name,
          state: this.stateOf(service),
          type: service.type ?? '',
          area: areaOf(this.locationOf(service.name) ?? service.location),
        },
        onclick: () => this.onSelect(service.name),
        onkeydown: (e) => {
          if (e.key === 'Enter' || e.key === ' ') {
            e.preventDefault();
            this.onSelect(service.name);
          }
        },
      },
      h('span', { class: 'state-dot', title: this.reachable ? this.stateOf(service) : 'unknown: the gateway cannot be reached' }),
      h('span', { class: 'service-name' }, service.name),
      h('span', { class: 'service-type' }, service.type ?? ''),
      h('span', { class: 'service-state' }, this.stateOf(service)),
    );
  }
}
