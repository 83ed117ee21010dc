// The selected service (#service-view): its properties laid out by their model (`.gui`, type,
// access, unit, range), grouped by namespace, each following its value through the page's one
// event stream. A change of the service's `properties` list loads the model again.

import { describe, getHistory, getProperty, setProperty } from './api.js';
import { h } from './dom.js';
import { plainDoc, renderDoc } from './doc_text.js';
import { MAX_SUBSCRIPTIONS } from './events.js';
import { followedOnStream, needsParameters, propertyView } from './widgets.js';

/** Wildcard Gets one view sends to read what it does not follow. */
const MAX_READ_PATTERNS = 32;
const LISTENABLE = new Set(['read', 'read-write', 'unknown']);

function namespaceOf(path) {
  const dot = path.lastIndexOf('.');
  return dot < 0 ? '' : path.slice(0, dot);
}

export class ServiceView {
  constructor(root, { mux, describe: describeService = describe }) {
    Object.assign(this, { root, mux, describe: describeService });
    this._waiting = false; // its model could not be read: built again when the registry says up
    this.service = null;
    this._views = new Map(); // path -> property view
    this._unsubscribe = [];
    this._generation = 0;
    this._reloadTimer = null;
    this._propertiesText = null;
  }

  /** Show `service` ({name, type, state, address}), or nothing for null. */
  async show(service, { fresh = false } = {}) {
    this._close();
    const generation = ++this._generation;
    this.service = service;
    if (!service) {
      this.root.replaceChildren(h('p', { class: 'muted' }, 'Select a service to see its properties.'));
      return;
    }
    if (service.state !== 'up') {
      // A service that is not up cannot describe itself; its view is built when it comes up.
      this.root.replaceChildren(
        this.header(service),
        h('p', { class: 'muted notice' }, `${service.name} is ${service.state ?? 'unknown'}: its properties show when it is up.`),
      );
      return;
    }
    this.root.replaceChildren(this.header(service), h('p', { class: 'muted' }, 'Loading the model…'));
    let model;
    try {
      model = await this.describe(service.name, { fresh });
    } catch (e) {
      if (generation !== this._generation) return;
      if (e.code === 'UNAVAILABLE') {
        // Listed as up but not answering (the registry has not noticed yet): no retries here;
        // the view is built once the registry says it is up again (updateState).
        this._waiting = true;
        this.root.replaceChildren(
          this.header(service),
          h('p', { class: 'muted notice' }, `${service.name} does not answer (${e.message}): its properties show when it is up again.`),
        );
        return;
      }
      this.root.replaceChildren(this.header(service), h('div', { class: 'error' }, `${e.code}: ${e.message}`));
      return;
    }
    if (generation !== this._generation) return; // another service was selected meanwhile
    this.render(service, model);
  }

  header(service) {
    return h(
      'header',
      { class: 'view-head' },
      h('h2', {}, service.name),
      h('span', { class: 'badge', dataset: { state: service.state ?? 'unknown' } }, service.state ?? 'unknown'),
      h('span', { class: 'muted' }, `${service.type ?? ''}${service.address ? ` · ${service.address}` : ''}`),
    );
  }

  render(service, model) {
    const all = (model?.properties ?? []).filter((p) => p.name !== 'properties');
    // A namespace (actuators, robots.scout1) is a box of its properties and of the namespaces
    // under it; one the model lists is itself [data-property=NAME], like every property.
    const listed = new Set(all.filter((p) => p.type === 'namespace').map((p) => p.name));
    const boxes = new Map([['', { leaves: [], subs: [] }]]);
    const box = (ns) => {
      if (!boxes.has(ns)) {
        boxes.set(ns, { leaves: [], subs: [] });
        box(namespaceOf(ns)).subs.push(ns);
      }
      return boxes.get(ns);
    };
    for (const ns of listed) box(ns);
    for (const prop of all) if (prop.type !== 'namespace') box(namespaceOf(prop.name)).leaves.push(prop);

    // What is shown gets an update function; which of them are followed live is decided after.
    const targets = new Map(); // path -> {update(event), error(e)}
    const leafView = (ns, prop) => {
      const view = propertyView(service.name, prop, {
        setProperty,
        getProperty,
        getHistory,
        describe: (name) => this.describe(name),
        subscribe: (selector, handlers) => this.mux.subscribe(selector, handlers),
        label: ns ? prop.name.slice(ns.length + 1) : prop.name,
      });
      this._views.set(prop.name, view);
      // One that needs a parameter (a file's name) cannot be followed: its form reads it.
      // A binary one (a camera's frame) is read by its widget, on a connection of its own.
      if (LISTENABLE.has(prop.access) && !needsParameters(prop) && followedOnStream(prop)) {
        targets.set(prop.name, leafTarget(view));
      } else if (!followedOnStream(prop)) {
        // Nor may a wildcard of the page's stream bring its values (base64 frames) beside the rest.
        this._unsubscribe.push(this.mux.avoid(`${service.name}/${prop.name}`));
      }
      return view.element;
    };
    const byName = new Map(all.map((p) => [p.name, p]));
    const fieldset = (ns, parent) => {
      const { leaves, subs } = boxes.get(ns);
      const attrs = { class: 'namespace', dataset: { namespace: ns } };
      let value = null;
      if (listed.has(ns)) {
        // A namespace has a value of its own too (its children's names, a registry entry's URL).
        const prop = byName.get(ns);
        Object.assign(attrs.dataset, { property: ns, type: 'namespace', access: prop.access ?? '' });
        value = h('output', { class: 'value ns-value' });
        if (LISTENABLE.has(prop.access)) targets.set(ns, outputTarget(value));
      }
      return h(
        'fieldset',
        attrs,
        h('legend', { title: plainDoc(byName.get(ns)?.doc) || ns }, parent ? ns.slice(parent.length + 1) : ns, value),
        leaves.map((prop) => leafView(ns, prop)),
        subs.sort().map((sub) => fieldset(sub, ns)),
      );
    };
    const top = boxes.get('');
    const sections = [];
    if (top.leaves.length) {
      sections.push(
        h(
          'fieldset',
          { class: 'namespace', dataset: { namespace: '' } },
          h('legend', {}, 'properties'),
          top.leaves.map((prop) => leafView('', prop)),
        ),
      );
    }
    for (const ns of top.subs.sort()) sections.push(fieldset(ns, ''));
    // Every property is followed live, one exact selector each: the page's stream covers them
    // with a few wildcards when they are more than one Listen may name (js/selector_cover.js).
    // Only beyond what the page subscribes to at all (thousands: a registry of hundreds of
    // services) are the deepest read once instead.
    const order = [...targets.keys()].sort((a, b) => a.split('.').length - b.split('.').length);
    const rest = [];
    for (const path of order) {
      if (rest.length || !this.follow(`${service.name}/${path}`, targets.get(path))) rest.push(path);
    }
    let note = null;
    if (rest.length) {
      const refresh = () => this.readOnce(service.name, rest, targets);
      note = h(
        'p',
        { class: 'muted notice' },
        `${rest.length} deeper properties are read once, not followed live (the page follows at most ${MAX_SUBSCRIPTIONS} properties). `,
        h('button', { type: 'button', dataset: { action: 'refresh' }, onclick: refresh }, 'Read again'),
      );
      refresh();
    }
    // replaceChildren, unlike h(), writes a null as the text "null": leave the absent ones out.
    const parts = [
      this.header(service),
      model?.doc ? renderDoc(model.doc, { h }) : null,
      note,
      h('div', { class: 'namespaces' }, sections),
    ];
    this.root.replaceChildren(...parts.filter((part) => part !== null));
    this.follow(`${service.name}/properties`, {
      update: (event) => this.propertiesChanged(event.value),
      error: () => {},
    });
  }

  /** Follow `selector` into `target`; false when the page follows as many as it may already. */
  follow(selector, target) {
    try {
      this._unsubscribe.push(
        this.mux.subscribe(selector, {
          onValue: (event) => target.update(event),
          onError: (e) => target.error(e),
        }),
      );
      return true;
    } catch {
      return false;
    }
  }

  /** Read `paths` once with a wildcard Get per namespace (a few requests, not one per property). */
  async readOnce(service, paths, targets) {
    const generation = this._generation;
    const patterns = [...new Set(paths.map((p) => (namespaceOf(p) ? `${namespaceOf(p)}.*` : '*')))];
    for (const pattern of patterns.slice(0, MAX_READ_PATTERNS)) {
      let answer;
      try {
        answer = await getProperty(service, pattern);
      } catch (e) {
        for (const path of paths) if (namespaceOf(path) === namespaceOf(`${pattern}`)) targets.get(path)?.error(e);
        continue;
      }
      if (generation !== this._generation) return;
      for (const { path, value } of answer.values ?? []) {
        if (paths.includes(path)) targets.get(path)?.update({ service, path, value });
      }
    }
  }

  /**
   * The service's `properties` list: the first value is the list the model was read with; a
   * different one later (a tool plugged in) loads the model again.
   */
  propertiesChanged(value) {
    if (this._propertiesText === null) {
      this._propertiesText = value;
      return;
    }
    if (value === this._propertiesText || this._reloadTimer !== null) return;
    this._reloadTimer = setTimeout(() => {
      this._reloadTimer = null;
      if (this.service) this.show(this.service, { fresh: true }); // the model changed: read it anew
    }, 300);
  }

  /** The service's state changed in the list. */
  updateState(service) {
    if (!this.service || service?.name !== this.service.name) return;
    const was = this.service.state;
    this.service = service;
    this.root.classList.toggle('service-down', service.state !== 'up');
    if (this._waiting && service.state !== 'up') this._waiting = 'down'; // the registry noticed
    if (service.state === 'up' && (was !== 'up' || this._waiting === 'down')) {
      this.show(service); // back: its model and values anew, read once
      return;
    }
    const badge = this.root.querySelector('.view-head .badge');
    if (badge) {
      badge.dataset.state = service.state ?? 'unknown';
      badge.textContent = service.state ?? 'unknown';
    }
  }

  _close() {
    this._waiting = false;
    for (const unsubscribe of this._unsubscribe) unsubscribe();
    this._unsubscribe = [];
    for (const view of this._views.values()) view.dispose();
    this._views.clear();
    if (this._reloadTimer !== null) clearTimeout(this._reloadTimer);
    this._reloadTimer = null;
    this._propertiesText = null;
  }
}

/** What a property view does with an event of its path, or with a failure to follow it. */
function leafTarget(view) {
  return {
    update(event) {
      if (view.element.classList.contains('unfollowed')) {
        view.element.classList.remove('unfollowed'); // followed again after a failure
        view.element.querySelector('.error').hidden = true;
      }
      if (event.removed) view.removed();
      else view.update(event.value, event);
    },
    error(e) {
      view.element.classList.add('unfollowed');
      showListenError(view, e);
    },
  };
}

/** The same for a namespace's own value, shown in its legend. */
function outputTarget(output) {
  return {
    update(event) {
      output.textContent = event.removed ? '' : event.value;
      output.title = output.textContent;
      output.classList.remove('unfollowed');
    },
    error() {
      output.classList.add('unfollowed');
    },
  };
}

function showListenError(view, e) {
  const error = view.element.querySelector('.error');
  if (error) {
    error.textContent = `${e.code}: ${e.message}`;
    error.hidden = false;
  }
}
