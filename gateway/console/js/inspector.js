// The property inspector (#inspector): raw Get, Set and Listen on any service and path, with
// optional request parameters ("frame=robot&x=1"), the answer in #inspector-output and the
// events of a Listen in #inspector-log, one <li> each, newest first.

import { describe, getProperty, setProperty } from './api.js';
import { h } from './dom.js';
import { splitSelector } from './events.js';
import { shownValue } from './values.js';

/** Events the log keeps; older ones are dropped from the bottom. */
export const LOG_LIMIT = 200;

function timeOf(seconds) {
  const date = Number.isFinite(seconds) ? new Date(seconds * 1000) : new Date();
  return date.toISOString().slice(11, 23);
}

/** "a=1&b=(1 2)" -> {a: "1", b: "(1 2)"}; throws for a pair without "=". */
export function parseParameters(text) {
  const parameters = {};
  for (const pair of text.split('&').map((p) => p.trim()).filter(Boolean)) {
    const eq = pair.indexOf('=');
    if (eq <= 0) throw Object.assign(new Error(`a parameter is NAME=VALUE, got ${JSON.stringify(pair)}`), { code: 'INVALID_ARGUMENT' });
    parameters[pair.slice(0, eq).trim()] = pair.slice(eq + 1).trim();
  }
  return parameters;
}

export class Inspector {
  /** `els`: {service, path, value, params, get, set, listen, output, log, paths (a datalist)}. */
  constructor(els, { mux, isUp = () => true }) {
    Object.assign(this, { els, mux, isUp });
    this.unlisten = null;
    this.listening = null;
    this._listen = null; // the current Listen's own token
    this._described = null;
    els.get.addEventListener('click', () => this.get());
    els.set.addEventListener('click', () => this.set());
    els.listen.addEventListener('click', () => (this.unlisten ? this.stopListening() : this.listen()));
    els.service.addEventListener('change', () => this.suggestPaths());
    for (const input of [els.service, els.path, els.params]) {
      input.addEventListener('keydown', (e) => e.key === 'Enter' && this.get());
    }
    els.value.addEventListener('keydown', (e) => e.key === 'Enter' && this.set());
  }

  /** Fill the inspector with a service (and a path), as a click elsewhere on the page does. */
  use(service, path = '') {
    this.els.service.value = service;
    if (path) this.els.path.value = path;
    this.suggestPaths();
  }

  fields() {
    const service = this.els.service.value.trim();
    const path = this.els.path.value.trim();
    if (!service || !path) throw Object.assign(new Error('name a service and a property path'), { code: 'INVALID_ARGUMENT' });
    return { service, path, parameters: parseParameters(this.els.params.value) };
  }

  show(text, isError = false) {
    this.els.output.textContent = text;
    this.els.output.classList.toggle('error-text', isError);
  }

  showError(e) {
    this.show(`${e.code ?? 'UNKNOWN'}: ${e.message}`, true);
  }

  async get() {
    try {
      const { service, path, parameters } = this.fields();
      this.show('…');
      const answer = await getProperty(service, path, parameters);
      if (Array.isArray(answer.values)) {
        this.show(answer.values.map((v) => `${v.path} = ${shownValue(v)}`).join('\n') || '(no property matches)');
      } else {
        this.show(shownValue(answer));
      }
    } catch (e) {
      this.showError(e);
    }
  }

  async set() {
    try {
      const { service, path, parameters } = this.fields();
      this.show('…');
      const answer = await setProperty(service, path, this.els.value.value, parameters);
      this.show(`Set ${service}/${path}: ${shownValue(answer) === '' ? 'done' : shownValue(answer)}`);
    } catch (e) {
      this.showError(e);
    }
  }

  listen() {
    let selector;
    try {
      const { service, path } = this.fields();
      selector = `${service}/${path}`;
      splitSelector(selector);
      // Each Listen is its own: what its subscription hears after it was stopped (a replay
      // queued before, a stream still delivering) is not logged.
      const listen = {};
      const current = () => this._listen === listen;
      this.unlisten = this.mux.subscribe(selector, {
        onValue: (event) => current() && this.logEvent(event),
        onSync: () => current() && this.logLine('sync', 'snapshot complete; changes follow'),
        onError: (e, { dropped = false } = {}) => {
          if (!current()) return;
          this.logLine('error', `${e.code}: ${e.message}${dropped ? '' : ' (tried again shortly)'}`);
          if (dropped) this.stopListening();
        },
      });
      this._listen = listen;
    } catch (e) {
      this.showError(e);
      return;
    }
    this.listening = selector;
    this.els.listen.textContent = 'Stop listening';
    this.els.listen.setAttribute('aria-pressed', 'true');
    this.els.log.replaceChildren();
    this.show(`Listening to ${selector}`);
  }

  stopListening() {
    // Always ended at the multiplexer too: a subscription it dropped is gone already (a no-op),
    // and one it kept (an error it tries again after) must not go on logging.
    this.unlisten?.();
    this.unlisten = null;
    this._listen = null;
    if (this.listening) this.show(`Stopped listening to ${this.listening}`);
    this.listening = null;
    this.els.listen.textContent = 'Listen';
    this.els.listen.setAttribute('aria-pressed', 'false');
  }

  logEvent(event) {
    const flags = [event.gap && 'gap', event.removed && 'removed'].filter(Boolean);
    const li = h(
      'li',
      { class: flags.join(' '), dataset: { service: event.service, path: event.path } },
      h('time', {}, timeOf(event.time)),
      h('span', { class: 'log-path' }, `${event.service}/${event.path}`),
      h('span', { class: 'log-value' }, event.removed ? '(removed)' : shownValue(event)),
      flags.length ? h('small', {}, ` ${flags.join(' ')}`) : null,
    );
    this.prepend(li);
  }

  logLine(kind, text) {
    this.prepend(h('li', { class: kind }, h('time', {}, timeOf()), h('span', {}, text)));
  }

  prepend(li) {
    const log = this.els.log;
    log.prepend(li);
    while (log.children.length > LOG_LIMIT) log.lastElementChild.remove();
  }

  /** Offer the service's property names in the path field. */
  async suggestPaths() {
    const service = this.els.service.value.trim();
    if (!service || service === this._described || service.includes('*')) return;
    if (!this.isUp(service)) return; // suggested when it is up (main.js calls again)
    this._described = service;
    try {
      const model = await describe(service);
      this.els.paths.replaceChildren(...(model.properties ?? []).map((p) => h('option', { value: p.name }, p.access)));
    } catch {
      this._described = null;
      this.els.paths.replaceChildren();
    }
  }
}
