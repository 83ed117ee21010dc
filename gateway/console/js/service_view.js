// The selected service (#service-view): its properties laid out by their model (`.gui`, type,
// access, unit, range), grouped by namespace, each following its value through the page's one
// event stream. A change of the service's `properties` list loads the model again.

import { describe, getProperty, setProperty } from './api.js';
import { h } from './dom.js';
import { propertyView } from './widgets.js';

/** Properties one view follows at most; the rest show a note (a group of many robots is big). */
export const MAX_FOLLOWED = 150;
const LISTENABLE = new Set(['read', 'read-write', 'unknown']);

function namespaceOf(path) {
  const dot = path.lastIndexOf('.');
  return dot < 0 ? '' : path.slice(0, dot);
}

export class ServiceView {
  constructor(root, { mux }) {
    Object.assign(this, { root, mux });
    this.service = null;
    this._views = new Map(); // path -> property view
    this._unsubscribe = [];
    this._generation = 0;
    this._reloadTimer = null;
    this._propertiesText = null;
  }

  /** Show `service` ({name, type, state, address}), or nothing for null. */
  async show(service) {
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
      model = await describe(service.name);
    } catch (e) {
      if (generation !== this._generation) return;
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

    let followed = 0;
    const skipped = [];
    const leafView = (ns, prop) => {
      const view = propertyView(service.name, prop, {
        setProperty,
        getProperty,
        label: ns ? prop.name.slice(ns.length + 1) : prop.name,
      });
      this._views.set(prop.name, view);
      if (LISTENABLE.has(prop.access)) {
        if (followed < MAX_FOLLOWED) {
          followed += 1;
          this.follow(`${service.name}/${prop.name}`, view);
        } else {
          skipped.push(prop.name);
        }
      }
      return view.element;
    };
    const fieldset = (ns, parent) => {
      const { leaves, subs } = boxes.get(ns);
      const attrs = { class: 'namespace', dataset: { namespace: ns } };
      if (listed.has(ns)) Object.assign(attrs.dataset, { property: ns, type: 'namespace' });
      return h(
        'fieldset',
        attrs,
        h('legend', {}, parent ? ns.slice(parent.length + 1) : ns),
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
    const note = skipped.length
      ? h('p', { class: 'muted' }, `${skipped.length} more properties are not followed live (limit ${MAX_FOLLOWED}).`)
      : null;
    // replaceChildren, unlike h(), writes a null as the text "null": leave the absent ones out.
    const parts = [
      this.header(service),
      model?.doc ? h('p', { class: 'doc' }, model.doc) : null,
      note,
      h('div', { class: 'namespaces' }, sections),
    ];
    this.root.replaceChildren(...parts.filter((part) => part !== null));
    this._unsubscribe.push(
      this.mux.subscribe(`${service.name}/properties`, {
        onValue: (event) => this.propertiesChanged(event.value),
      }),
    );
  }

  follow(selector, view) {
    this._unsubscribe.push(
      this.mux.subscribe(selector, {
        onValue: (event) => {
          if (view.element.classList.contains('unfollowed')) {
            view.element.classList.remove('unfollowed'); // followed again after a failure
            view.element.querySelector('.error').hidden = true;
          }
          if (event.removed) view.removed();
          else view.update(event.value, event);
        },
        onError: (e) => {
          view.element.classList.add('unfollowed');
          showListenError(view, e);
        },
      }),
    );
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
      if (this.service) this.show(this.service);
    }, 300);
  }

  /** The service's state changed in the list. */
  updateState(service) {
    if (!this.service || service?.name !== this.service.name) return;
    const was = this.service.state;
    this.service = service;
    this.root.classList.toggle('service-down', service.state !== 'up');
    if (was !== 'up' && service.state === 'up') {
      this.show(service); // back: its model and values anew
      return;
    }
    const badge = this.root.querySelector('.view-head .badge');
    if (badge) {
      badge.dataset.state = service.state ?? 'unknown';
      badge.textContent = service.state ?? 'unknown';
    }
  }

  _close() {
    for (const unsubscribe of this._unsubscribe) unsubscribe();
    this._unsubscribe = [];
    for (const view of this._views.values()) view.dispose();
    this._views.clear();
    if (this._reloadTimer !== null) clearTimeout(this._reloadTimer);
    this._reloadTimer = null;
    this._propertiesText = null;
  }
}

function showListenError(view, e) {
  const error = view.element.querySelector('.error');
  if (error) {
    error.textContent = `${e.code}: ${e.message}`;
    error.hidden = false;
  }
}
